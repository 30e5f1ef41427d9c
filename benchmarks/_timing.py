"""Tiny timing helper shared by the benchmark scripts (best-of-repeats, per call)."""

import platform
import time
import timeit


def per_call(fn, number=None, repeat=5):
    """Best per-call time in seconds of ``fn()`` over ``repeat`` runs."""
    if number is None:
        number, _ = timeit.Timer(fn).autorange()
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number


def best_of(fn, repeat=5):
    """(best wall time [s] of ``fn()`` over ``repeat`` calls, its last result)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def machine():
    return f"{platform.processor() or platform.machine()}, Python {platform.python_version()}"


def fmt(seconds):
    if seconds < 1e-3:
        return f"{seconds * 1e6:8.1f} us"
    return f"{seconds * 1e3:8.2f} ms"
