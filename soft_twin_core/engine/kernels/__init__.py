"""Compiled passes of the multibody engine (numba)."""

from soft_twin_core.engine.kernels._blas_probe import skip_probe

skip_probe()      # before any kernel is compiled or loaded: numba's start without scipy.linalg (see the module)
