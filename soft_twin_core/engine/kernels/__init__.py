"""Compiled passes of the multibody engine (numba)."""

from soft_twin_core.engine.kernels._blas_probe import skip_probe
from soft_twin_core.engine.kernels._caches import choose_cpu_target, install_locator

# Before any kernel is compiled or loaded: one CPU target whose caches travel (see _caches), the shipped
# caches served wherever numba caches, and numba's start without scipy.linalg (see _blas_probe).
choose_cpu_target()
install_locator()
skip_probe()
