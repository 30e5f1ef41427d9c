"""The compiled step of robots with constraint rows (engine.closed_step):
the KKT system of the implicit step solved by its Schur complement on the
constraint rows, against the Python KKT step it replaces (the reference:
``MechanismSimulator(..., compiled=False)``, itself tested against closed
forms, the continuum reference and energy in test_constrained.py and
test_constrained_stability.py).

Robots: a rigid four-bar (a planar loop closed by a 3-D pin: one redundant
row), the fixed-fixed beam (a member clamped at both ends), the planar
parallel robot (two loops, position-controlled joints eliminated), and an
arm on a base clamped to a moving target (a free joint: quaternion
coordinates)."""

import numpy as np
import pytest

from soft_twin_core.engine.closed_step import CLOSED_FIELDS, ClosedArrays, closed_step
from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import find_file
from soft_twin_core.solve.constrained import MechanismSimulator, constraint_rows, make_inputs, solve_equilibrium
from test_constrained import _member, four_bar


def _swing(mech, k, dt):
    """Inputs of step k: position-controlled joints swing, the first tendon pulls."""
    pos = {mech.tree.joints[i].name: 0.2 * np.sin(2 * np.pi * k * dt) for i in mech.joints_with("position")}
    act = {a.name: 1.0 for a in mech.actuators[:1]}
    vel = [0.4 * np.pi * np.cos(2 * np.pi * k * dt) for _ in pos]
    return make_inputs(mech, act, None, pos, vel or None)


def _run_both(mech, dt, steps, reuse, targets=lambda t: None, q=None):
    """The compiled and the Python step side by side, the same inputs."""
    sims = [MechanismSimulator(mech, dt, q=q, compiled=c, reuse_factorisation=reuse) for c in (True, False)]
    assert sims[0]._use_closed_step and not sims[1]._use_closed_step
    for k in range(steps):
        inp = _swing(mech, k, dt)
        for s in sims:
            s.step(inputs=inp, targets=targets(s.t + dt))
    return sims


def _assert_same(a, b, rtol):
    for name in ("q", "v", "lam"):
        x, y = getattr(a, name), getattr(b, name)
        assert np.abs(x - y).max() <= rtol * max(np.abs(y).max(), 1.0), name


def _robots():
    return [("four_bar", four_bar(1.0))] + [(n, load_mechanism(find_file(n, "robots")))
                                            for n in ("fixed_fixed_beam", "planar_parallel_robot")]


@pytest.mark.parametrize("name,mech", _robots(), ids=lambda x: x if isinstance(x, str) else "")
def test_compiled_closed_step_is_the_python_kkt_step(name, mech):
    """With a fresh KKT matrix every step both iterate alike: the same
    states and multipliers to round-off over 60 steps of motion (joints
    swinging, a tendon pulling), every constraint held at the end of each
    step; with the matrix reused across steps, the same to the Newton
    tolerance, with far fewer factorisations."""
    eq = solve_equilibrium(mech)
    fresh = _run_both(mech, 5e-3, 60, reuse=False, q=eq.q)
    _assert_same(*fresh, 1e-9)
    assert fresh[0].factorisations >= 60 and fresh[0]._closed_held is not None     # the compiled path ran
    assert fresh[0].constraint_error() < 1e-10
    reused = _run_both(mech, 5e-3, 60, reuse=True, q=eq.q)
    _assert_same(*reused, 1e-7)
    assert reused[0].factorisations <= 10 and reused[1].factorisations >= 60
    assert reused[0].constraint_error() < 1e-10
    # the efforts of the position-controlled joints (eliminated) are the KKT step's multipliers
    for j, e in fresh[1].joint_efforts().items():
        assert abs(fresh[0].joint_efforts()[j] - e) <= 1e-8 * max(abs(e), 1.0), j


def test_compiled_closed_step_follows_a_moving_clamp_target():
    """A member on a free base clamped to a target that moves (a prescribed
    base: quaternion coordinates, a clamp's rotation rows): as the Python step."""
    mech = mechanism_from_dict({"name": "b", "gravity": [0, 0, -9.81], "base": {"motion": "prescribed"},
                                "bodies": [_member("arm", 0.3, 3, modes="bending_torsion")]})

    def target(t):
        g = np.eye(4)
        g[0, 3] = 0.05 * np.sin(2 * np.pi * t)
        c, s = np.cos(0.3 * t), np.sin(0.3 * t)
        g[:2, :2] = [[c, -s], [s, c]]
        return [g]
    sims = _run_both(mech, 2e-3, 100, reuse=False, targets=target)
    _assert_same(*sims, 1e-9)
    assert sims[0].constraint_error(target(sims[0].t)) < 1e-10


def test_a_failing_compiled_step_falls_back_to_the_python_step(monkeypatch):
    """Told to keep the four-bar's redundant row (the pin's out-of-plane
    one, identically zero), the Schur complement is singular: the compiled
    step reports it, the Python KKT step (which leaves that row out) takes
    the step, and the compiled one resumes with its rows found anew."""
    from soft_twin_core.solve import constrained
    mech = four_bar(1.0)
    sim, ref = (MechanismSimulator(mech, 5e-3, compiled=c, reuse_factorisation=False) for c in (True, False))
    sim.step()
    ref.step()
    _, G = constraint_rows(mech, sim.ws, sim.q)
    assert len(sim._closed_held["rows"]) == 2 and np.abs(G).max(axis=1).min() < 1e-12
    real, calls = constrained.independent_rows, []

    def all_rows_once(G, rtol=1e-10):          # the compiled step's rows: all three, once
        calls.append(len(G))
        return np.arange(len(G)) if len(calls) == 1 else real(G, rtol)
    monkeypatch.setattr(constrained, "independent_rows", all_rows_once)
    sim._closed_held = None
    sim.step()
    ref.step()
    _assert_same(sim, ref, 1e-9)
    assert sim._closed_held is None and len(calls) >= 2          # the Python step's rows after the compiled's
    sim.step()
    ref.step()
    _assert_same(sim, ref, 1e-9)
    assert len(sim._closed_held["rows"]) == 2


def test_closed_step_refuses_factors_of_other_rows():
    """Factors sized for other rows: status 4 before any work (the kernel
    has no bounds checks)."""
    mech = four_bar(1.0)
    sim = MechanismSimulator(mech, 5e-3)
    sim.step()
    held = sim._closed_held
    tree, ws = mech.tree, sim.ws
    inp = make_inputs(mech)
    c = held["arrays"]
    other = ClosedArrays.of(*[np.arange(3) if name == "rows" else getattr(c, name) for name in CLOSED_FIELDS])
    out = closed_step(
        ws.m, ws.w, sim.act, held["loads"], inp.gravity, held["coef"], inp.effort, other, True,
        sim.q, sim.v, 5e-3, 0.5, 1e-10, 1e-14, 10, 1e-12, 0.0, False, sim.v.copy(), sim.lam[:3].copy(),
        np.empty(tree.nq))
    assert out == (0, 4, 0, 0.0)


def test_closed_step_reports_a_step_that_does_not_converge():
    """One Newton iteration allowed: status 1, not a silent wrong state."""
    mech = four_bar(1.0)
    sim = MechanismSimulator(mech, 5e-3, compiled=True)
    sim.step()
    held = sim._closed_held
    tree, ws = mech.tree, sim.ws
    inp = make_inputs(mech)
    q0, v0 = sim.q.copy(), sim.v + 1.0
    v1, q1, lam = v0.copy(), np.empty(tree.nq), sim.lam[:3].copy()
    it, status, _, _ = closed_step(
        ws.m, ws.w, sim.act, held["loads"], inp.gravity, held["coef"], inp.effort, held["arrays"], True,
        q0, v0, 5e-3, 0.5, 1e-10, 1e-14, 1, 1e-12, 0.0, False, v1, lam, q1)
    assert (it, status) == (1, 1)


def test_a_robot_at_rest_steps_in_one_iteration():
    """The rigid four-bar at its static equilibrium: the step's predictor
    already balances the forces to the tolerance of the constraint forces'
    scale, so the compiled step stops after its first residual (no update;
    it took two before), and so does the Python KKT step, which runs the same
    stopping rule. The two keep the robot at rest, and the multipliers' size the kernel hands to
    the next step is that of the multipliers it leaves. (A soft member
    starts from an equilibrium solved to a tolerance: it moves a little, and
    its steps take two iterations after a few.)"""
    mech = four_bar(1.0)
    eq = solve_equilibrium(mech)
    sims = [MechanismSimulator(mech, 5e-3, q=eq.q, compiled=c) for c in (True, False)]
    its = []
    for _ in range(20):
        for s in sims:
            s.step()
        its.append([s.iterations for s in sims])
    assert its[1:] == [[1, 1]] * 19, its           # the Python step too: one stopping rule
    _assert_same(*sims, 1e-9)
    assert np.abs(sims[0].v).max() < 1e-8 and np.abs(sims[0].lam).max() > 0.1
    lam_max, of = sims[0]._closed_held["lam_max"]
    assert of is sims[0].lam and lam_max == np.abs(sims[0].lam).max()


def test_held_joints_at_rest_step_in_one_iteration():
    """The stopping rule of the compiled step for held joints (the contact
    step, eliminating a position-controlled joint) and of the Python KKT
    step (holding it by a multiplier): a rigid double pendulum, its shoulder
    held with the upper link horizontal and the lower one hanging at rest.
    Each step takes one iteration, and both keep the pendulum where it is
    (the shoulder's holding torque is the forces' scale; the elbow's
    residual is its round-off)."""
    link = {"mass": 0.5, "com": [0.15, 0, 0], "inertia": [1e-5, 4e-3, 4e-3, 0, 0, 0]}
    mech = mechanism_from_dict({
        "name": "held_pendulum", "gravity": [0, 0, -9.81],
        "bodies": [
            {"name": "upper", "type": "link", **link,
             "joint": {"name": "shoulder", "type": "revolute", "axis": [0, 1, 0], "control": "position"}},
            {"name": "lower", "type": "link", "parent": "upper", **link,
             "joint": {"name": "elbow", "type": "revolute", "axis": [0, 1, 0], "position": [0.3, 0, 0],
                       "reference": float(np.pi / 2), "control": "passive"}}]})
    inp = make_inputs(mech, positions={"shoulder": 0.0})
    sims = [MechanismSimulator(mech, 5e-3, compiled=c) for c in (True, False)]
    its = []
    for _ in range(20):
        for s in sims:
            s.step(inputs=inp)
        its.append([s.iterations for s in sims])
    assert sims[0]._use_compiled_step and not sims[1]._use_compiled_step
    assert its[1:] == [[1, 1]] * 19, its
    for s in sims:
        assert np.abs(s.v).max() < 1e-10 and np.abs(s.q - mech.tree.q0).max() < 1e-12
