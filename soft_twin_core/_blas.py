"""Small dense linear algebra on one BLAS thread.

The solvers factor matrices of tens to a few hundred rows (statics tangents,
IK normal equations): OpenBLAS's threads cost more than they save there (a
240 x 240 solve took 2.4 ms on two threads, 0.74 ms on one, on the 2-core
project machine). ``with one_blas_thread(): ...`` limits BLAS to one thread
for a block (threadpoolctl; about 20 us to enter, nothing when nested in
another such block), leaving the user's setting untouched outside it.
"""

import contextlib

try:
    from threadpoolctl import ThreadpoolController
    _CONTROLLER = ThreadpoolController()
except ImportError:      # optional: without it, BLAS keeps its own thread count
    _CONTROLLER = None


_DEPTH = [0]      # blocks entered: an inner block (a solver called in a loop that holds one) costs nothing


@contextlib.contextmanager
def one_blas_thread():
    if _CONTROLLER is None or _DEPTH[0]:
        _DEPTH[0] += 1
        try:
            yield
        finally:
            _DEPTH[0] -= 1
        return
    with _CONTROLLER.limit(limits=1, user_api="blas"):
        _DEPTH[0] += 1
        try:
            yield
        finally:
            _DEPTH[0] -= 1
