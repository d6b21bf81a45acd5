"""The gate both filters put their fixes through: a fix whose innovation is
implausible (chi-square, 3 degrees of freedom, p < NIS_P) is refused; one beyond
BURST_P is taken as a burst the model does not hold (AttitudeModel.update)."""

from __future__ import annotations

from visvec.chi2 import ppf as chi2_ppf

# a fix whose innovation's NIS is this improbable (3 degrees of freedom) is refused
NIS_P = 1e-6
# a fix taken with an innovation beyond this (p = 0.01) found a burst the model does not
# hold (see AttitudeModel.update)
BURST_P = 0.01


def warm_up() -> None:
    """Compute (and cache) the chi-square quantiles the filters use, so that the import
    they take (scipy.special: 0.5 s) does not fall on a live run's first fix; and load
    the 3-D filter's compiled propagation (visvec.fuse.kernels) for the same reason."""
    from visvec.fuse import kernels

    nis_limit()
    chi2_ppf(1.0 - BURST_P, 3)
    kernels.warm_up()


def nis_limit() -> float:
    """The NIS beyond which a fix is refused (p = NIS_P, 3 degrees of freedom)."""
    return chi2_ppf(1.0 - NIS_P, 3)
