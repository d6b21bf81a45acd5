"""The command line starts quickly: what only some commands need (scipy's fits,
distributions and trees; Numba's compiler) is imported where it is used, not with the
commands (visvec --help took 1.3 s, 0.45 s now)."""

import subprocess
import sys

import pytest
from scipy import stats

from visvec.chi2 import ppf


def test_the_command_line_imports_neither_scipy_nor_numba():
    code = (
        "import sys, visvec.cli.main; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'numba'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("q, dof", [(1 - 1e-6, 3), (0.99, 3), (1 - 1e-4, 6), (0.999, 1),
                                    (0.999, 13), (0.975, 40), (0.025, 40), (0.5, 5),
                                    (0.95, 2.5)])  # fmt: skip
def test_chi2_quantiles_are_scipy_stats_own(q, dof):
    assert ppf(q, dof) == float(stats.chi2.ppf(q, dof))
