"""Soft articulated robots (issue "Soft articulated robots end to end"):
cost of a constrained statics solve and of a dynamics step on the example
robots, and of the outputs of one state (joint states, wrenches, stresses).

For each example robot (config/robots: pan_tilt_arm, soft_gripper,
fixed_fixed_beam, planar_parallel_robot) and a rigid four-bar:

* statics from the reference configuration under gravity (cold: a new
  problem each call), best of repeats;
* one dynamics step of ``MechanismSimulator`` (dt = 5 ms, the node's
  default) from the static equilibrium with a small joint or tendon motion,
  per step over 200 steps, best of 3 runs, with Newton iterations per step;
* ``state_outputs`` of one state.

Printed with the machine load (1-minute load average): the project machine
has 2 CPUs shared with other jobs. CPU time (process_time) beside wall time.

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_articulated.py
"""

import os
import sys
import time
from dataclasses import replace

import numpy as np

from _timing import fmt, machine
from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.robot.model import find_file
from soft_twin_core.solve.constrained import MechanismSimulator, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs

_TEST = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "test")
sys.path[:0] = [_TEST, os.path.join(_TEST, "unit")]       # the tests' helpers (rod_statics) and four_bar


def load():
    return f"[load {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs]"


def robots():
    from test_constrained import four_bar
    out = [(n, load_mechanism(find_file(n, "robots"))) for n in
           ("pan_tilt_arm", "soft_gripper", "fixed_fixed_beam", "planar_parallel_robot")]
    return out + [("four_bar (rigid, 1 loop)", four_bar(1.0))]


def inputs_for(mech, k, dt):
    """A gentle motion: position-controlled joints swing, tendons pull."""
    pos = {mech.tree.joints[i].name: 0.2 * np.sin(2 * np.pi * k * dt) for i in mech.joints_with("position")}
    act = {a.name: 1.0 for a in mech.actuators[:1]}
    vel = [0.4 * np.pi * np.cos(2 * np.pi * k * dt) for _ in pos]
    return make_inputs(mech, act, None, pos, vel or None)


def step_time(mech, q, dt, n, **kw):
    """(best wall, best CPU time per step [s], Newton iterations a step) of
    ``MechanismSimulator(mech, dt, q=q, **kw)`` over n gentle steps, best of 3."""
    walls, cpus, its = [], [], 0
    for _ in range(3):
        sim = MechanismSimulator(mech, dt, q=q, **kw)
        inps = [inputs_for(mech, k + 1, dt) for k in range(n)]
        sim.step(inputs=inps[0])
        t, c, it = time.perf_counter(), time.process_time(), 0
        for inp in inps[1:]:
            sim.step(inputs=inp)
            it += sim.iterations
        walls.append((time.perf_counter() - t) / (n - 1))
        cpus.append((time.process_time() - c) / (n - 1))
        its = it / (n - 1)
    return min(walls), min(cpus), its, sim


def main():
    print(f"machine: {machine()}, {os.cpu_count()} CPUs")
    print(load())
    head = f"{'robot':28s} {'dof':>4s} {'constr.':>7s} | {'statics':>10s} {'it':>3s} | {'step wall':>10s} " \
           f"{'step CPU':>10s} {'it/step':>7s} | {'outputs':>10s}"
    print(head)
    print("-" * len(head))
    dt, n = 5e-3, 200
    closed = []
    for name, mech in robots():
        best, eq = np.inf, None
        for _ in range(3):
            t = time.perf_counter()
            eq = solve_equilibrium(mech)
            best = min(best, time.perf_counter() - t)
        wall, cpu, its, sim = step_time(mech, eq.q, dt, n)
        if mech.n_constraint_rows:
            closed.append((name, mech, eq.q, wall))
        t = time.perf_counter()
        for _ in range(20):
            state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a, sim.ws)
        out_t = (time.perf_counter() - t) / 20
        print(f"{name:28s} {mech.tree.nv:4d} {mech.n_constraint_rows:7d} | {fmt(best)} {eq.iterations:3d} | "
              f"{fmt(wall)} {fmt(cpu)} {its:7.2f} | {fmt(out_t)}")
    print(load())
    # constraint rows: the compiled KKT step (engine.closed_step) against the Python one it replaced, and
    # against the same robot with its constraints taken away (an open tree, the same dof and dt)
    print(f"\n{'with constraint rows':28s} | {'compiled':>10s} {'Python KKT':>10s} {'speed-up':>8s} | "
          f"{'open tree':>10s} {'closed/open':>11s}")
    for name, mech, q, wall in closed:
        py = step_time(mech, q, dt, n, compiled=False)[0]
        open_tree = step_time(replace(mech, constraints=()), q, dt, n)[0]
        print(f"{name:28s} | {fmt(wall)} {fmt(py)} {py / wall:7.1f}x | {fmt(open_tree)} {wall / open_tree:10.1f}x")
        if name.startswith("four_bar") and (pin_t := pinocchio_four_bar(dt)) is not None:
            print(f"{'  Pinocchio constraintDynamics':28s} | {fmt(pin_t)} (explicit step; compiled / Pinocchio "
                  f"{wall / pin_t:.1f}x)")
    print(load())


def pinocchio_four_bar(dt, n=2000):
    """Per step [s] of Pinocchio's constrained dynamics on the same four-bar
    (``constraintDynamics`` with the loop as a 3-D point constraint between
    the coupler's and the rocker's ends, then a semi-implicit Euler step:
    explicit, one call a step), or None without the ``pin`` wheel."""
    try:
        import pinocchio as pin
    except ImportError:
        return None
    from test_constrained import A4, B4, C4, D4, MASSES, four_bar_angles

    def rod(m, length):
        return pin.Inertia(m, np.array([length / 2, 0, 0]), np.diag([1e-6, m * length**2 / 12, m * length**2 / 12]))
    model = pin.Model()
    model.gravity.linear[:] = [0, 0, -9.81]
    at = [pin.SE3(np.eye(3), np.array(p, float)) for p in ([0, 0, 0], [A4, 0, 0], [D4, 0, 0], [B4, 0, 0], [C4, 0, 0])]
    j1 = model.addJoint(0, pin.JointModelRY(), at[0], "crank")
    model.appendBodyToJoint(j1, rod(MASSES[0], A4), pin.SE3.Identity())
    j2 = model.addJoint(j1, pin.JointModelRY(), at[1], "knee")
    model.appendBodyToJoint(j2, rod(MASSES[1], B4), pin.SE3.Identity())
    j3 = model.addJoint(0, pin.JointModelRY(), at[2], "rocker")
    model.appendBodyToJoint(j3, rod(MASSES[2], C4), pin.SE3.Identity())
    loop = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, j2, at[3], j3, at[4], pin.ReferenceFrame.LOCAL)
    models, datas = pin.StdVec_RigidConstraintModel(), pin.StdVec_RigidConstraintData()
    models.append(loop)
    datas.append(loop.createData())
    data = model.createData()
    pin.initConstraintDynamics(model, data, models, datas)
    prox = pin.ProximalSettings(1e-12, 1e-12, 10)
    t3, t4 = four_bar_angles(1.0)
    q, v, tau = np.array([1.0, t3 - 1.0, t4]), np.zeros(3), np.zeros(3)
    t = time.perf_counter()
    for _ in range(n):
        v = v + dt * pin.constraintDynamics(model, data, q, v, tau, models, datas, prox)
        q = pin.integrate(model, q, v * dt)
    return (time.perf_counter() - t) / n


if __name__ == "__main__":
    main()
