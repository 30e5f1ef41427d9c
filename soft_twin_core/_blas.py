"""Small dense linear algebra on one BLAS thread, and a block-diagonal
matrix without scipy.linalg (the statics start without importing it).

The solvers factor matrices of tens to a few hundred rows (statics tangents,
IK normal equations): OpenBLAS's threads cost more than they save there (a
240 x 240 solve took 2.4 ms on two threads, 0.74 ms on one, on the 2-core
project machine). ``with one_blas_thread(): ...`` limits BLAS to one thread
for a block (threadpoolctl; about 20 us to enter, nothing when nested in
another such block of the same thread), leaving the user's setting
untouched outside it; it covers every BLAS loaded when the block starts
(scipy's too, which often loads after this module). The processes the twin
owns take one thread for their whole life: :func:`blas_on_one_thread`.
"""

import contextlib
import os
import sys
import threading

import numpy as np

try:
    from threadpoolctl import ThreadpoolController
except ImportError:      # optional: without it, BLAS keeps its own thread count
    ThreadpoolController = None

# The BLAS libraries loaded (threadpoolctl's view), and whether scipy.linalg's was among them: numpy's loads
# with numpy, scipy's only with scipy.linalg (the Python KKT step's factorisations, the compiled kernels'
# LAPACK calls), often after this module; the view is taken again then.
_CONTROLLER, _WITH_SCIPY = None, False


def _controller():
    global _CONTROLLER, _WITH_SCIPY
    if ThreadpoolController is None:
        return None
    scipy = "scipy.linalg" in sys.modules
    if _CONTROLLER is None or (scipy and not _WITH_SCIPY):
        _CONTROLLER, _WITH_SCIPY = ThreadpoolController(), scipy
    return _CONTROLLER


_LOCAL = threading.local()    # blocks this thread has entered: an inner one (a solver called in a loop that
                              # holds one) costs nothing


@contextlib.contextmanager
def one_blas_thread():
    depth = getattr(_LOCAL, "depth", 0)
    _LOCAL.depth = depth + 1
    try:
        controller = None if depth else _controller()
        if controller is None:
            yield
        else:
            with controller.limit(limits=1, user_api="blas"):
                yield
    finally:
        _LOCAL.depth = depth


_PROCESS_LIMIT = []    # the process-wide limits, kept alive (exiting one would restore the old count)
_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def blas_on_one_thread():
    """Limit BLAS to one thread for the rest of the process, unless the user
    chose a count (one of ``_THREAD_VARIABLES`` set): for the entry points
    that own their process (the node, the estimator node, the command line).
    The engine's matrices are small: a second OpenBLAS thread saves nothing
    there and spins on the other core between calls (a step of the planar
    parallel robot: 120 us of wall time either way, 240 us of CPU time on
    two threads). The BLAS libraries loaded now are limited through
    threadpoolctl; the variable covers those loaded later (scipy's, which
    the compiled kernels' LAPACK calls load on first use). Idempotent."""
    if _PROCESS_LIMIT or any(v in os.environ for v in _THREAD_VARIABLES):
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    if ThreadpoolController is not None:
        _PROCESS_LIMIT.append(ThreadpoolController().limit(limits=1, user_api="blas"))


def block_diag(blocks):
    """The block-diagonal matrix of square blocks (scipy.linalg.block_diag
    without importing scipy.linalg)."""
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        k = b.shape[0]
        out[i:i + k, i:i + k] = b
        i += k
    return out
