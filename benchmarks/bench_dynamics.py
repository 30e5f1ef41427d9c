"""Dynamics: simulation speed (issue 6) and the common benchmark case.

Run: .venv/bin/python benchmarks/bench_dynamics.py
"""

import time

import numpy as np

from _timing import fmt, machine
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator


def arm(n, free="bending_torsion", tendons=True):
    d = benchmark_cantilever_dict(n, free)
    d["segments"][0]["material"]["youngs_modulus"] = 5e6
    d["segments"][0]["material"]["viscosity"] = 1e4
    if tendons:
        d["actuators"] = [{"name": "t1", "offset": [0.007, 0.0]},
                          {"name": "t2", "offset": [0.0, -0.007], "end": 0.3}]
    return model_from_dict(d)


def run(m, T, dt, u=None, **kw):
    """(wall time, simulator, Newton iterations a step) of T s stepped one
    step a call, as the node does, with the node's Newton settings."""
    mech = from_robot_model(m)
    kw = {"tol": 1e-4, "max_iterations": 10, **kw}
    MechanismSimulator(mech, dt, **kw).step(u, n=2)  # compile / first Jacobian
    sim = MechanismSimulator(mech, dt, **kw)
    n = int(round(T / dt))
    t0 = time.perf_counter()
    for _ in range(n):
        sim.step(u)
    return time.perf_counter() - t0, sim, sim.newton_iterations / n


def main():
    print(f"machine: {machine()}")
    u = {"t1": 0.5, "t2": 0.3}
    for free in ("bending_torsion", "all"):
        m = arm(5, free)
        wall, sim, it = run(m, 1.0, 1e-3, u)
        print(f"5 sections ({free}, {m.n_dof} dof), gravity + 2 tendons, 1 s at dt = 1 ms: wall {wall:.3f} s "
              f"= {1.0 / wall:.1f}x real time, {it:.2f} Newton it/step, {sim.factorisations} factorisations")
    print(f"\n{'sections':>8} {'dof':>4} {'per step (1 ms)':>16} {'x real time':>12} {'RNEA call':>12}")
    for n in (1, 5, 10, 20):
        m = arm(n)
        wall, sim, it = run(m, 0.2, 1e-3, u)
        q, qd = sim.q, sim.v
        from soft_twin_core.engine import algorithms as alg
        import timeit
        tk = min(timeit.repeat(lambda: alg.rnea(sim.tree, sim.ws, q, qd, None), number=200, repeat=3)) / 200
        print(f"{n:>8} {m.n_dof:>4} {fmt(wall / 200):>16} {1e-3 / (wall / 200):>12.1f} {fmt(tk):>12}")
    # common benchmark case: undamped cantilever released under gravity, 1 s
    print("\nbenchmark cantilever (all modes, undamped) released from straight, 1 s:")
    ref_m = model_from_dict(benchmark_cantilever_dict(24))
    _, ref_sim, _ = run(ref_m, 1.0, 2.5e-4)
    ref = kin.tip_pose(ref_m, ref_sim.q)[:3, 3]
    print(f"  reference: 24 sections, dt = 0.25 ms: tip at t = 1 s {np.round(ref, 5)} m")
    for n, dt in ((5, 1e-3), (10, 1e-3), (10, 5e-4)):
        m = model_from_dict(benchmark_cantilever_dict(n))
        wall, sim, it = run(m, 1.0, dt)
        e = np.linalg.norm(kin.tip_pose(m, sim.q)[:3, 3] - ref)
        print(f"  {n:>2} sections, dt = {dt * 1e3:.2f} ms: wall {wall:.3f} s ({1.0 / wall:.1f}x real time), "
              f"{it:.2f} it/step, tip error {e:.2e} m ({e / 0.5:.1e} L)")


if __name__ == "__main__":
    main()
