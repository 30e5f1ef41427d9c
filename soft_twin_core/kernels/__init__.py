"""Compiled passes of the multibody engine (numba)."""
