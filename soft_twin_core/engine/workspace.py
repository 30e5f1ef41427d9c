"""The workspace of a multibody model: every per-call array, allocated once.

>>> ws = Workspace(model)          # one per thread; never shared between callers

Algorithms (:mod:`soft_twin_core.engine.algorithms`) are free functions
``algo(model, ws, q, ...)`` that write into the workspace and return views
of it: copy a result you keep across calls.
"""

import numpy as np

from soft_twin_core.engine.kernels.data import kernel_struct, make_work


class Workspace:
    """Packed model arrays (``arrays``), pass arrays (``work``), their kernel
    views (``m``, ``w``) and result buffers (``tau``, ``M``, ``a``) of one
    model."""

    def __init__(self, model):
        self.model = model
        self.arrays = model.arrays
        self.work = make_work(self.arrays)
        self.m = model.kernel_arrays          # the same arrays as structrefs, for the kernels
        self.w = kernel_struct(self.work)
        self.tau = np.zeros(model.nv)
        self.M = np.zeros((model.nv, model.nv))
        self.a = np.zeros(model.nv)
        self.zeros_v = np.zeros(model.nv)
        self.level = -1            # what the last forward pass computed (0 poses, 1 twists, 2 accelerations)
        # who left the articulated-body factorisation in ``work`` (U, Dinv,
        # Sf, Xf) and for what: an integrator's (token, h) while it may reuse
        # it in its next steps; None after any other factorisation
        self.factor_key = None

    def check(self, model):
        if model is not self.model:
            raise ValueError("workspace: made for another model")


def thread_workspace(model):
    """A workspace of ``model`` private to the calling thread, made on first
    use and kept with the model (convenience functions that take only a
    model use it; algorithms called by several threads never share one)."""
    import threading
    local = model.__dict__.get("_thread_workspaces")
    if local is None:
        local = threading.local()
        object.__setattr__(model, "_thread_workspaces", local)
    ws = getattr(local, "ws", None)
    if ws is None:
        ws = local.ws = Workspace(model)
    return ws
