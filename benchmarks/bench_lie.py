"""Per-call times of the Lie maps, single and batched (issue 3).

Run: .venv/bin/python benchmarks/bench_lie.py
"""

import numpy as np

from _timing import fmt, machine, per_call
from soft_twin_core import lie


def main():
    rng = np.random.default_rng(0)
    x1 = rng.normal(size=6)
    xb = rng.normal(size=(1000, 6))
    H1, Hb = lie.exp_se3(x1), lie.exp_se3(xb)
    print(f"machine: {machine()}")
    print(f"{'function':<12} {'single':>12} {'batch 1000':>12} {'per element':>12}")
    for name, f1, fb in [
        ("exp_se3", lambda: lie.exp_se3(x1), lambda: lie.exp_se3(xb)),
        ("log_se3", lambda: lie.log_se3(H1), lambda: lie.log_se3(Hb)),
        ("T_se3", lambda: lie.T_se3(x1), lambda: lie.T_se3(xb)),
        ("T_se3_dot", lambda: lie.T_se3_dot(x1, x1), lambda: lie.T_se3_dot(xb, xb)),
        ("cay_se3", lambda: lie.cay_se3(x1), lambda: lie.cay_se3(xb)),
    ]:
        t1, tb = per_call(f1), per_call(fb)
        print(f"{name:<12} {fmt(t1):>12} {fmt(tb):>12} {fmt(tb / 1000):>12}")


if __name__ == "__main__":
    main()
