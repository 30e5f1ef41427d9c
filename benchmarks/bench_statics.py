"""Statics: solve times (issue 5) and the common benchmark case (DESIGN.md).

Run: .venv/bin/python benchmarks/bench_statics.py
"""


import numpy as np

from _timing import best_of, fmt, machine
from soft_twin_core.engine import loads as ld
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import solve_equilibrium


def main():
    print(f"machine: {machine()}")
    # 10-section arm, gravity + tip load + two tendons (issue 5 benchmark)
    for free in ("bending_torsion", "all"):
        d = benchmark_cantilever_dict(10, free)
        d["segments"][0]["material"]["youngs_modulus"] = 5e6
        d["actuators"] = [{"name": "t1", "offset": [0.007, 0.0]},
                          {"name": "t2", "offset": [0.0, -0.007], "end": 0.3}]
        m = model_from_dict(d)
        loads = ld.Loads(point=(ld.tip_load(m, (0.0, 0.05, -0.02)),))
        u = {"t1": 0.8, "t2": 0.4}
        mech = from_robot_model(m)
        solve_equilibrium(mech, u, loads=loads)               # compile
        t_cold, r = best_of(lambda: solve_equilibrium(mech, u, loads=loads))
        u2 = {"t1": 0.85, "t2": 0.4}                           # a new command, warm-started
        t_warm, r2 = best_of(lambda: solve_equilibrium(mech, u2, loads=loads, q_init=r.q))
        print(f"10 sections ({free}, {m.n_dof} dof), gravity + tip load + 2 tendons: cold {fmt(t_cold)} "
              f"({r.iterations} it), warm {fmt(t_warm)} ({r2.iterations} it), residual {r2.residual:.1e}")
    # the common benchmark cantilever under gravity: convergence to the continuum BVP
    from soft_twin_core.reference.continuum import solve_cosserat_statics
    m1 = model_from_dict(benchmark_cantilever_dict(1))
    sec = m1.sections[0]
    ref = solve_cosserat_statics(sec.K, 0.5, distributed_force_world=sec.M[0, 0] * m1.gravity)
    ref = ref.tip_pose()[:3, 3]
    print(f"\nbenchmark cantilever under gravity (all modes); reference: the continuum BVP "
          f"(soft_twin_core.reference.continuum), tip {np.round(ref, 6)} m")
    print(f"{'sections':>8} {'time':>10} {'tip error [m]':>14} {'error / L':>10}")
    for n in (2, 4, 8, 16, 32):
        m = model_from_dict(benchmark_cantilever_dict(n))
        mech = from_robot_model(m)
        solve_equilibrium(mech)
        t, r = best_of(lambda: solve_equilibrium(mech), repeat=3)
        e = np.linalg.norm(kin.tip_pose(m, r.q)[:3, 3] - ref)
        print(f"{n:>8} {fmt(t):>10} {e:>14.3e} {e / 0.5:>10.2e}")


if __name__ == "__main__":
    main()
