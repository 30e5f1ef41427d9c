"""Start numba without importing scipy.linalg.

The first compiled call of a process (even one served from numba's disk
cache) initialises numba's CPU target, which imports
``numba.np.arraymath``; that module probes for a BLAS at import by
importing ``scipy.linalg.cython_blas``, i.e. all of ``scipy.linalg``
(0.3 s on the project machine, a fifth of a new process's first statics
solve and second of dynamics). The engine's kernels use no BLAS. When
scipy is installed (so the probe would succeed anyway), :func:`skip_probe`
imports ``numba.np.arraymath`` with the probe answering "available"
without the import, then puts the real probe back: a kernel that does use
BLAS (``np.dot``, ``np.linalg``) still imports scipy.linalg when it is
compiled, as numba always does there. Pinned numba (requirements): if its
internals differ, nothing is changed.
"""

import importlib.util
import sys


def skip_probe():
    """Import numba.np.arraymath without its scipy.linalg import; True if
    it did (False: already imported, scipy absent, or numba's layout
    differs)."""
    if "numba.np.arraymath" in sys.modules or importlib.util.find_spec("scipy.linalg") is None:
        return False
    try:
        import numba.np.linalg as nb_linalg
        probe = nb_linalg.ensure_blas
    except (ImportError, AttributeError):
        return False
    nb_linalg.ensure_blas = _available
    try:
        import numba.np.arraymath as nb_arraymath
    finally:
        nb_linalg.ensure_blas = probe
    if getattr(nb_arraymath, "ensure_blas", None) is _available:
        nb_arraymath.ensure_blas = probe      # its later callers get the real probe
    return True


def _available():
    """numba's ensure_blas() that succeeds without importing scipy.linalg."""
