"""Where visvec's compiled kernels stand: whether Numba (the ``fast`` extra) is there to
compile them. A module of its own so that any part (the fusion, the detectors, the
estimators) can ask without importing another's kernels.

``VISVEC_PURE=1`` in the environment runs the numpy functions even where Numba is
installed (the path a machine without the extra takes).
"""

from __future__ import annotations

import importlib.util
import os

PURE = os.environ.get("VISVEC_PURE", "").strip() not in ("", "0")
# Numba is imported when a kernel is first called, not here: its import takes 0.2 s,
# which every command line would pay, also those that run no kernel
AVAILABLE = not PURE and importlib.util.find_spec("numba") is not None
