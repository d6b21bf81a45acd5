"""Quantiles of the chi-square distribution, for the tests of fits and innovations.

scipy.stats.chi2.ppf's own formula, 2 gammaincinv(dof / 2, q), through scipy.special,
imported on the first call: importing scipy.stats took 0.4 s of every command line's
start, also of the commands that never test a chi-square.
"""

from __future__ import annotations

from functools import cache


@cache
def ppf(q: float, dof: float) -> float:
    """The q-quantile of the chi-square distribution with ``dof`` degrees of freedom."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, q))
