"""What a variable-strain segment costs a dynamic step (issue 28): the
benchmark cantilever (L = 0.5 m, r = 10 mm, E = 1 MPa, bending modes free,
gravity) released from straight, 0.5 s at dt 2.5 ms (implicit midpoint,
Newton tolerance 1e-6), on n sections as PCS (the engine's compiled O(n)
step) and with the robot file's ``strain_basis: {type: legendre, order:
p}`` (reduced_step.ReducedThetaIntegrator: the same residual pass over the
n sections, a dense CRBA and an nz x nz Cholesky a step). Reported: CPU
time a step (median of 3 runs), Newton iterations a step, and the tip's
distance from PCS on the same sections at the end.

Second table: the pan-tilt arm (config/robots/pan_tilt_arm.yaml, its two
joints position-controlled) as the twin steps it: one 5 ms step a call,
the joints following a smooth 1 s move and the tendons pulling, 300 steps;
PCS (the engine's compiled contact step) against Legendre order 2 on each
segment (the reduced step, its joints eliminated). CPU time a step, median
of 3 runs.

Third table: robots with multipliers on Legendre order 2, 200 steps of 2 ms
from rest: the planar parallel robot (a loop's rows, 3 N on its platform)
and the catheter in its vessel (a prescribed base's clamp, contacts), in
the engine's compiled closed-chain and contact steps with the basis's
Galerkin inverse, in the Python KKT step in z (``compiled=False``), and as
PCS. CPU time a step, median of 3 runs.

Run: PYTHONPATH=. .venv/bin/python benchmarks/gvs_dynamics.py
"""

import time

import numpy as np

from soft_twin_core._blas import blas_on_one_thread
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator
from soft_twin_core.solve.outputs import state_outputs
from soft_twin_core.solve.constrained import make_inputs

DT, STEPS = 2.5e-3, 200


def cantilever(n, order=None):
    d = benchmark_cantilever_dict(n, "bending")
    if order is not None:
        d["segments"][0]["strain_basis"] = {"type": "legendre", "order": order}
    return from_robot_model(model_from_dict(d))


def run(mech):
    times, sim = [], None
    for _ in range(3):
        sim = MechanismSimulator(mech, DT, 0.5, tol=1e-6, max_iterations=30)
        sim.step(n=2)                                   # (compiled code loaded)
        t0 = time.process_time()
        sim.step(n=STEPS)
        times.append((time.process_time() - t0) / STEPS)
    tip = state_outputs(mech, sim.q, np.zeros(0), make_inputs(mech)).frames["tip"][:3, 3]
    return np.median(times), sim.newton_iterations / (STEPS + 2), tip


def pan_tilt(sections, order=None):
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    from soft_twin_core.robot.model import find_file, read_yaml_file
    path = find_file("pan_tilt_arm", "robots")
    d = read_yaml_file(path)
    for seg in next(b for b in d["bodies"] if b.get("type") == "member")["segments"]:
        seg["sections"] = sections
        if order is not None:
            seg["strain_basis"] = {"type": "legendre", "order": order}
    return mechanism_from_dict(d, str(path.parent))


def twin_steps(mech, dt=5e-3, steps=300):
    """CPU time a twin step [s] (median of 3 runs) and Newton iterations a step."""
    times = []
    for _ in range(3):
        sim = MechanismSimulator(mech, dt, 0.5)
        sim.step(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.0, "tilt": 0.0})   # (compiled code loaded)
        it0, t0 = sim.newton_iterations, time.process_time()
        for k in range(steps):
            s = min(1.0, (k + 1) * dt)
            s = s * s * (3 - 2 * s)
            sim.step(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4 * s, "tilt": -0.3 * s})
        times.append((time.process_time() - t0) / steps)
    return np.median(times), (sim.newton_iterations - it0) / steps


def with_basis(name, order):
    """Robot file ``name`` with every member's segments on Legendre ``order``."""
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    from soft_twin_core.robot.model import find_file, read_yaml_file
    path = find_file(name, "robots")
    d = read_yaml_file(path)
    if order is not None:
        for b in d["bodies"]:
            for seg in b.get("segments", []) if b.get("type") == "member" else []:
                seg["strain_basis"] = {"type": "legendre", "order": order}
    return mechanism_from_dict(d, str(path.parent))


def multiplier_steps(mech, inputs, compiled, dt=2e-3, steps=200):
    """CPU time a step [s] (median of 3 runs) and Newton iterations a step."""
    times = []
    for _ in range(3):
        sim = MechanismSimulator(mech, dt, 0.5, compiled=compiled, max_iterations=60)
        sim.step(n=2, **inputs)                       # (compiled code loaded)
        it0, t0 = sim.newton_iterations, time.process_time()
        sim.step(n=steps, **inputs)
        times.append((time.process_time() - t0) / steps)
    return np.median(times), (sim.newton_iterations - it0) / steps


def main():
    blas_on_one_thread()             # as the node and the command line run (a second thread spins on the other core)
    print(f"{'sections':>8s} {'model':>12s} {'coords':>6s} {'us/step':>8s} {'it/step':>7s} {'tip vs PCS':>11s}")
    for n in (16, 32, 64):
        t, it, tip_pcs = run(cantilever(n))
        print(f"{n:8d} {'PCS':>12s} {2 * n:6d} {t * 1e6:8.0f} {it:7.2f} {'':>11s}", flush=True)
        for p in (1, 3, 5, 7):
            mech = cantilever(n, p)
            t, it, tip = run(mech)
            print(f"{n:8d} {f'Legendre {p}':>12s} {mech.basis.shape[1]:6d} {t * 1e6:8.0f} {it:7.2f} "
                  f"{np.linalg.norm(tip - tip_pcs):9.2e} m", flush=True)
    print(f"\npan-tilt arm, a twin step of 5 ms a call\n{'sections':>8s} {'model':>12s} {'coords':>6s} "
          f"{'us/step':>8s} {'it/step':>7s}")
    for n in (6, 12):
        for order in (None, 2):
            mech = pan_tilt(n, order)
            t, it = twin_steps(mech)
            print(f"{f'{n} + {n}':>8s} {'PCS' if order is None else f'Legendre {order}':>12s} "
                  f"{mech.tree.nv if order is None else mech.basis.shape[1]:6d} {t * 1e6:8.0f} {it:7.2f}", flush=True)
    from soft_twin_core.solve.constrained import FrameLoad
    print(f"\nrows and contacts, 200 steps of 2 ms\n{'robot':>22s} {'model / step':>24s} {'coords':>6s} "
          f"{'us/step':>8s} {'it/step':>7s}")
    platform = dict(point_loads=(FrameLoad("platform", np.array([2.0, 0.0, -3.0, 0.0, 0.0, 0.0]), "world"),))
    for name, inputs in (("planar_parallel_robot", platform), ("catheter_in_vessel", {})):
        for order, compiled, label in ((None, True, "PCS, compiled"), (2, True, "Legendre 2, compiled"),
                                       (2, False, "Legendre 2, Python KKT")):
            mech = with_basis(name, order)
            t, it = multiplier_steps(mech, inputs, compiled)
            print(f"{name:>22s} {label:>24s} {mech.tree.nv if order is None else mech.basis.shape[1]:6d} "
                  f"{t * 1e6:8.0f} {it:7.2f}", flush=True)


if __name__ == "__main__":
    main()
