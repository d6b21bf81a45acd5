"""How the detectors' and estimators' kernels are compiled: through Numba, lazily.

The kernels (visvec._kernels.edge_fit, pixel_fit, rotation, readout) are plain Python
functions written as loops over profiles, pixels or points. Each module names its
kernels with :func:`kernel` (a loop over a frame's pixels with its numpy twin, the
name's function where the kernels are off); with the ``fast`` extra each name first holds a _Lazy
stand-in whose first call imports Numba and puts every kernel's dispatcher in its place
at once (so that a kernel calling another compiles against the other's dispatcher),
compiled on first use and cached on disk after that. Numba has wheels for x86-64 and
aarch64, the flight computers' two architectures.

Without Numba, with ``VISVEC_PURE=1``, or when the kernels do not load
(visvec.detect.warm.warm_up turns :data:`ON` off), the detectors and estimators run
their numpy functions.
"""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager

from visvec._kernels import AVAILABLE

# whether the kernels run: the detectors and estimators look here on every call;
# detect.warm.warm_up turns it off when they do not load
ON = AVAILABLE

# every kernel made so far: (the namespace that holds it, its name there, its _Lazy)
_KERNELS: list = []
_LOADING = threading.Lock()
_failed = False  # Numba did not import: every kernel is its plain function


class _Lazy:
    """A kernel before Numba is loaded: its first call loads every kernel (_load) and
    is passed on to its dispatcher (or, where Numba did not import, to the plain
    function). ``py_func``: the kernel as Python, as a dispatcher's; ``plain``: what
    runs where the kernels are off (py_func, or its numpy twin)."""

    def __init__(self, name, f, plain):
        self.__name__ = name
        self.py_func = f
        self.plain = plain
        self.dispatcher = None

    def __call__(self, *args):
        if self.dispatcher is None:
            _load()
        # (after a Numba that did not import: the plain function)
        return (self.plain if self.dispatcher is None else self.dispatcher)(*args)


def _load():
    """Import Numba and put the dispatcher of every kernel not yet made in its place
    among its module's names, all at once (where nothing else was put there; a module
    imported later has its kernels made on their first call). A Numba that cannot be
    imported turns the kernels off (ON) and leaves the plain functions in their
    places."""
    global ON, _failed
    with _LOADING:
        todo = [e for e in _KERNELS if e[2].dispatcher is None]
        if _failed or not todo:
            return
        made = {}
        try:
            import numba as nb

            for _, _, k in todo:
                if id(k.py_func) not in made:
                    # cache: compiled once per machine, loaded from disk after that;
                    # nogil: the live paths' threads run beside it; no fastmath: sums
                    # taken in the order written
                    made[id(k.py_func)] = nb.njit(cache=True, nogil=True)(k.py_func)
        except Exception as exc:  # a Numba that cannot import here or make them: numpy
            ON = False
            _failed = True
            for names, name, k in _KERNELS:
                if names[name] is k:
                    names[name] = k.plain
            if not isinstance(exc, ImportError):
                raise  # (warm_up says why)
            print(f"visvec: Numba did not import ({exc}); the numpy path runs",
                  file=sys.stderr)  # fmt: skip
            return
        for names, name, k in todo:
            k.dispatcher = made[id(k.py_func)]
            if names[name] is k:
                names[name] = k.dispatcher


def off() -> None:
    """Turn the kernels off (kernels that did not load: warm_up) and put every plain
    function (a loop's numpy twin where it has one) in its name, whatever the name held
    (its stand-in, its dispatcher, one that failed), so that the detectors, which call
    the kernels by name, and a kernel's Python source run as the numpy path call the
    plain functions, never a dispatcher that cannot compile."""
    global ON
    with _LOADING:
        ON = False
        for names, name, k in _KERNELS:
            names[name] = k.plain


@contextmanager
def numpy_path():
    """The numpy path for a while where the kernels are on (tests and benchmarks that
    compare the two paths): ON off, and every kernel's name its plain function, so that
    a kernel's source run as Python calls its numpy twins; both put back after."""
    global ON
    with _LOADING:
        was, swapped = ON, []
        for names, name, k in _KERNELS:
            if names[name] is not k.plain:
                swapped.append((names, name, names[name]))
                names[name] = k.plain
        ON = False
    try:
        yield
    finally:
        with _LOADING:
            for names, name, f in swapped:
                names[name] = f
            ON = was


def kernel(names: dict, name: str, f, numpy=None):
    """The kernel ``f`` known as ``name`` in the module whose globals are ``names``:
    compiled on its first call (with the fast extra), else the plain function: ``f``
    run as Python, or ``numpy``, its twin written with numpy on arrays (a loop over a
    frame's pixels or profiles, which as Python would run several times slower), with
    the same arguments and result. A kernel's Python source that calls ``name`` then
    runs on numpy where the kernels are off, and compiled where they are on."""
    plain = f if numpy is None else numpy
    if not AVAILABLE:
        return plain
    lazy = _Lazy(name, f, plain)
    _KERNELS.append((names, name, lazy))
    return lazy
