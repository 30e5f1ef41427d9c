"""Tiny timing helper shared by the benchmark scripts (best-of-repeats, per call)."""

import platform
import timeit


def per_call(fn, number=None, repeat=5):
    """Best per-call time in seconds of ``fn()`` over ``repeat`` runs."""
    if number is None:
        number, _ = timeit.Timer(fn).autorange()
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number


def machine():
    return f"{platform.processor() or platform.machine()}, Python {platform.python_version()}"


def fmt(seconds):
    if seconds < 1e-3:
        return f"{seconds * 1e6:8.1f} us"
    return f"{seconds * 1e3:8.2f} ms"
