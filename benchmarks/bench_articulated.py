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


def main():
    print(f"machine: {machine()}, {os.cpu_count()} CPUs")
    print(load())
    head = f"{'robot':28s} {'dof':>4s} {'constr.':>7s} | {'statics':>10s} {'it':>3s} | {'step wall':>10s} " \
           f"{'step CPU':>10s} {'it/step':>7s} | {'outputs':>10s}"
    print(head)
    print("-" * len(head))
    dt, n = 5e-3, 200
    for name, mech in robots():
        best, eq = np.inf, None
        for _ in range(3):
            t = time.perf_counter()
            eq = solve_equilibrium(mech)
            best = min(best, time.perf_counter() - t)
        walls, cpus, its = [], [], 0
        for _ in range(3):
            sim = MechanismSimulator(mech, dt, q=eq.q)
            inps = [inputs_for(mech, k + 1, dt) for k in range(n)]
            sim.step(inputs=inps[0])
            t, c, it = time.perf_counter(), time.process_time(), 0
            for inp in inps[1:]:
                sim.step(inputs=inp)
                it += sim.iterations
            walls.append((time.perf_counter() - t) / (n - 1))
            cpus.append((time.process_time() - c) / (n - 1))
            its = it / (n - 1)
        t = time.perf_counter()
        for _ in range(20):
            state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a, sim.ws)
        out_t = (time.perf_counter() - t) / 20
        print(f"{name:28s} {mech.tree.nv:4d} {mech.n_constraint_rows:7d} | {fmt(best)} {eq.iterations:3d} | "
              f"{fmt(min(walls))} {fmt(min(cpus))} {its:7.2f} | {fmt(out_t)}")
    print(load())


if __name__ == "__main__":
    main()
