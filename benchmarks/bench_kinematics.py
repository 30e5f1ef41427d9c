"""Kinematics and IK per-call times (issue 4).

Run: .venv/bin/python benchmarks/bench_kinematics.py [--targets 1000]
"""

import argparse
import time

import numpy as np

from _timing import fmt, machine, per_call
from soft_twin_core.planning import ik
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict


def random_targets(m, n, rng):
    bounds = np.tile([1.0, 2 * np.pi / m.total_length, 2 * np.pi / m.total_length], m.n_sections)
    qs = rng.uniform(-0.5, 0.5, (n, m.n_dof)) * bounds
    return qs, kin.tip_pose(m, qs)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--targets", type=int, default=1000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"machine: {machine()}")
    print(f"{'sections':>8} {'dof':>4} {'backbone 10/sec':>16} {'tip Jacobian':>13} {'IK solve':>10} {'IK iters':>8}")
    for n in (1, 5, 10, 20):
        m = model_from_dict(benchmark_cantilever_dict(n, "bending_torsion"))
        q = m.q0 + 0.3 * rng.normal(size=m.n_dof)
        t_bb = per_call(lambda: kin.backbone(m, q, 10))
        t_j = per_call(lambda: kin.tip_jacobian(m, q))
        _, T = random_targets(m, 5, rng)
        times, its = [], []
        for Ti in T:
            t0 = time.perf_counter()
            r = ik.solve_ik(m, Ti)
            times.append(time.perf_counter() - t0)
            its.append(r.iterations)
        print(f"{n:>8} {m.n_dof:>4} {fmt(t_bb):>16} {fmt(t_j):>13} {fmt(np.median(times)):>10} "
              f"{np.median(its):>8.0f}")
    m = model_from_dict(benchmark_cantilever_dict(3, "bending_torsion"))
    qs, T = random_targets(m, args.targets, rng)
    ok, its, times = 0, [], []
    for Ti in T:
        t0 = time.perf_counter()
        r = ik.solve_ik(m, Ti)
        times.append(time.perf_counter() - t0)
        ok += r.success
        its.append(r.iterations)
    print(f"\nIK, 3 sections (bending + torsion), {args.targets} random reachable full-pose targets "
          f"from straight: {100 * ok / args.targets:.1f} % within 1e-8 m / 1e-8 rad, median "
          f"{np.median(its):.0f} iterations, median {fmt(np.median(times))}, max {fmt(np.max(times))}")


if __name__ == "__main__":
    main()
