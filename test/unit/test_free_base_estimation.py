"""The filter on robots whose configuration is not a vector space: ball
(spherical) joints and a floating base, whose quaternions the error-state
filter moves on their groups (``q (+) dq = q exp(dq)``), its covariance
over the errors (nv of them, not nq).

References: the step's group Jacobians against central differences built
on the reference implementation of ``q (+) v`` and its inverse
(soft_twin_core.reference.joints: quaternions and SE(3) matrices, not the
engine's kernels); the filter's Phi against central differences of its own
mean step at rest (where the module docstring says it is exact); tracking
against the engine's simulator from a state the filter does not know."""

import numpy as np
import pytest

from soft_twin_core.engine.integrators import integrate_jacobians, integrate_pass
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.estimation import ekf as ek
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.reference import joints as rj
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator


def robot(base, gravity, ball=True):
    """A hub (the base), a ball joint 2 cm along x (``ball``; else a fixed
    one), a 0.2 m soft arm along x (bending and torsion free) on it."""
    return mechanism_from_dict({"name": "ball_arm", "gravity": list(gravity), "base": {"motion": base}, "bodies": [
        {"name": "hub", "type": "link", "mass": 0.2, "inertia": [2e-4, 2e-4, 2e-4, 0, 0, 0]},
        {"name": "ball_link", "type": "link", "parent": "hub", "mass": 0.05, "com": [0.01, 0, 0],
         "inertia": [1e-5, 1e-5, 1e-5, 0, 0, 0],
         "joint": {"name": "ball", "type": "spherical" if ball else "fixed", "position": [0.02, 0, 0]}},
        {"name": "arm", "type": "member", "parent": "ball_link", "segments": [{
            "length": 0.2, "sections": 3, "cross_section": {"shape": "solid_circle", "radius": 0.005},
            "material": {"youngs_modulus": 2e6, "density": 1100, "viscosity": 5.0},
            "free_modes": "bending_torsion"}]}]})


def test_the_step_jacobians_on_the_joints_groups():
    """``q1 = q (+) h v`` (the integrator's kernel) perturbed as ``q (+) d``
    and ``v + dv``: d1 = E d + h J dv, against central differences measured
    with the reference's group difference, on a free base and a ball joint
    at a random configuration and velocity (E far from the identity)."""
    tree = robot("floating", (0, 0, 0)).tree
    assert (tree.nq, tree.nv) == (7 + 4 + 9, 6 + 3 + 9)
    rng = np.random.default_rng(1)
    q, v, h = rj.random_configuration(tree, rng, 0.3), rng.normal(size=tree.nv), 0.05
    ws = Workspace(tree)

    def step(q, v):
        out = np.empty(tree.nq)
        integrate_pass(ws.m, np.ascontiguousarray(q), np.ascontiguousarray(v), h, out)
        return out
    E, J = integrate_jacobians(tree, v, h)
    assert np.allclose(rj.difference(tree, q, step(q, v)), h * v)        # the kernel is the reference's q (+) h v
    eps = 1e-6
    for i in range(tree.nv):
        d = np.zeros(tree.nv)
        d[i] = eps
        dE = rj.difference(tree, step(rj.integrate(tree, q, -d), v), step(rj.integrate(tree, q, d), v)) / (2 * eps)
        dJ = rj.difference(tree, step(q, v - d), step(q, v + d)) / (2 * eps * h)
        assert np.abs(dE - E[:, i]).max() < 1e-8 and np.abs(dJ - J[:, i]).max() < 1e-7, i
    assert np.abs(E - np.eye(tree.nv)).max() > 0.05        # the groups' turn is seen


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_the_filter_linearisation_of_a_free_flyer_at_rest(theta):
    """Zero gravity, at rest: the filter's step keeps the state, and its
    analytic Phi (over the 18 errors, not the 20 coordinates) is the central
    difference of its mean step, perturbed and compared on the groups."""
    mech = robot("floating", (0, 0, 0))
    tree = mech.tree
    f = ek.EKF(mech, [sn.PoseSensor("tip", 1e-3, 1e-2, frame="arm_tip")], dt=0.01, theta=theta, q_init=tree.q0)
    n, nq = f.n, f.nq
    x0 = f.x.copy()
    Phi, _ = f.linearisation()
    assert Phi.shape == (2 * n, 2 * n) and f.P.shape == Phi.shape and len(x0) == nq + n

    def plus(x, d):
        y = x.copy()
        y[:nq] = rj.integrate(tree, x[:nq], d[:n])
        y[nq:] += d[n:]
        return y

    def step(x):
        f.x, f.a = x.copy(), np.zeros(n)
        assert f.predict()
        return f.x.copy()
    y0 = step(x0)
    assert np.abs(y0 - x0).max() < 1e-12
    eps = 1e-6
    fd = np.zeros_like(Phi)
    for i in range(2 * n):
        d = np.zeros(2 * n)
        d[i] = eps
        yp, ym = step(plus(x0, d)), step(plus(x0, -d))
        fd[:, i] = np.concatenate([rj.difference(tree, ym[:nq], yp[:nq]), yp[nq:] - ym[nq:]]) / (2 * eps)
    assert np.abs(Phi - fd).max() <= 1e-6 * np.abs(fd).max()


def _track(mech, q_start, v_start, sensors, seconds=2.0, with_nees=False):
    """The filter (from the robot's reference state at rest) on 100 Hz
    readings of the simulated robot (1 ms steps) started elsewhere: the tip
    errors [m] and the tip-position NEES at each update, and the filter."""
    tree = mech.tree
    sim = MechanismSimulator(mech, 1e-3, q=q_start, v=v_start)
    f = ek.EKF(mech, sensors, dt=0.01, q_init=tree.q0, sigma_joint0=0.5, sigma_v0=2.0)
    ws, rng, errors, nees = Workspace(tree), np.random.default_rng(0), [], []
    for _ in range(int(round(seconds / 0.01))):
        sim.step(n=10)
        truth = sn.predict_readings(ws, sim.q, sensors, f._where)
        f.step({s.name: sn.simulate_measurement(s, truth[s.name], rng) for s in sensors})
        tip = sn.predict_readings(ws, sim.q, [sensors[-1]], {sensors[-1].name: f._where[sensors[-1].name]})
        e = f.tip_pose()[:3, 3] - tip[sensors[-1].name]
        errors.append(np.linalg.norm(e))
        nees.append(ek.nees(e, f.tip_position_cov()) if with_nees else np.nan)
    return np.array(errors), np.array(nees), f


def test_the_filter_follows_an_arm_swinging_on_a_ball_joint():
    """A soft pendulum on a ball joint (gravity along the arm), released
    0.45 rad off its rest: the filter starts at rest, 9 cm off at the tip,
    and follows the tip over the second second (RMS under 2 mm, at most 5
    mm) from two 1 mm
    markers (tip and mid-arm); its quaternion stays a unit one. (Markers on
    the arm's axis cannot see its spin about that axis; and the tip's
    distance to the ball is no state at all, so its covariance is singular
    along the arm: no NEES here.)"""
    mech = robot("fixed", (9.81, 0, 0))
    tree = mech.tree
    ib = tree.idx_v[[j.name for j in tree.joints].index("ball")]
    d = np.zeros(tree.nv)
    d[ib:ib + 3] = [0.0, 0.4, 0.2]
    sensors = [sn.marker("mid", 1e-3, member="arm", s=0.1), sn.marker("tip", 1e-3, frame="arm_tip")]
    errors, _, f = _track(mech, rj.integrate(tree, tree.q0, d), None, sensors)
    assert errors[0] > 0.05 and errors[100:].max() < 5e-3 and np.sqrt(np.mean(errors[100:] ** 2)) < 2e-3
    assert f.health.integrator_failures == 0
    iq = tree.idx_q[[j.name for j in tree.joints].index("ball")]
    assert abs(np.linalg.norm(f.q[iq:iq + 4]) - 1.0) < 1e-12


def test_the_filter_follows_a_tumbling_free_flyer():
    """A free-flying arm (zero gravity) tumbling at about 1 rad/s, which the
    filter believes at rest: from a pose sensor on the hub (1 mm, 0.01 rad)
    and a tip marker it follows the tip over the second second (RMS under 2
    mm, at most 5 mm),
    with a tip-position NEES whose mean over that second (100 samples of 3
    dof) lies in the chi-square band."""
    mech = robot("floating", (0, 0, 0))
    v0 = np.zeros(mech.tree.nv)
    v0[:6] = [0.05, 0.0, 0.02, 0.5, -1.0, 0.3]
    sensors = [sn.PoseSensor("hub", 1e-3, 1e-2, frame="hub"), sn.marker("tip", 1e-3, frame="arm_tip")]
    errors, nees, f = _track(mech, None, v0, sensors, with_nees=True)
    assert errors[100:].max() < 5e-3 and np.sqrt(np.mean(errors[100:] ** 2)) < 2e-3
    assert f.health.integrator_failures == 0
    assert 2.0 < nees[100:].mean() < 4.2          # chi2(300)/100: [2.54, 3.49] (95 %), widened: samples correlate


def _carried(t):
    """The prescribed base's pose at t [s]: 40 mm and 0.3 rad swings at
    0.4 Hz (below the arm's first bending mode, 1.5 Hz: nearer it, the
    filter's 10 ms implicit Euler step damps the resonance that the 1 ms
    truth rings with, and the two part by tens of mm without any sensor)."""
    T = np.eye(4)
    T[1, 3] = 0.04 * np.sin(2 * np.pi * 0.4 * t)
    a = 0.3 * np.sin(2 * np.pi * 0.4 * t)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    return T


def test_the_filter_follows_an_arm_on_a_moving_base_given_its_pose():
    """A soft arm clamped on a prescribed base (an arm carried by a
    manipulator), under gravity, the base swinging 40 mm and 0.3 rad at 1
    Hz: the filter, told the base's pose each step, follows the tip (RMS
    under 2 mm over the second second) from two markers; told nothing (the
    base held where it starts), it cannot (the tip tens of mm off)."""
    mech = robot("prescribed", (0, 0, -9.81), ball=False)
    sensors = [sn.marker("mid", 1e-3, member="arm", s=0.1), sn.marker("tip", 1e-3, frame="arm_tip")]
    tree = mech.tree
    rng, ws = np.random.default_rng(0), Workspace(tree)
    runs = {}
    for told in (True, False):
        sim = MechanismSimulator(mech, 1e-3)
        f = ek.EKF(mech, sensors, dt=0.01, sigma_joint0=0.5, sigma_v0=2.0)
        errors = []
        for k in range(1, 201):
            for i in range(10):
                sim.step(targets=[_carried(sim.t + 1e-3)])
            truth = sn.predict_readings(ws, sim.q, sensors, f._where)
            f.step({s.name: sn.simulate_measurement(s, truth[s.name], rng) for s in sensors},
                   **({"base_pose": _carried(k * 0.01)} if told else {}))
            errors.append(np.linalg.norm(f.tip_pose()[:3, 3] - truth["tip"]))
        runs[told] = np.array(errors)
        if told:
            assert f.health.integrator_failures == 0
            assert np.allclose(f.frame_pose("base"), _carried(2.0), atol=1e-9)      # on its target
    assert np.sqrt(np.mean(runs[True][100:] ** 2)) < 2.5e-3 and runs[True][100:].max() < 6e-3
    assert runs[False][100:].max() > 0.02


def test_a_base_pose_only_for_a_prescribed_base_and_a_rigid_one():
    f = ek.EKF(robot("fixed", (0, 0, -9.81)), [sn.marker("tip", 1e-3, frame="arm_tip")])
    with pytest.raises(ValueError, match="base_pose: only for a prescribed base"):
        f.predict(base_pose=np.eye(4))
    g = ek.EKF(robot("prescribed", (0, 0, -9.81)), [sn.marker("tip", 1e-3, frame="arm_tip")])
    bad = np.eye(4)
    bad[0, 0] = 2.0
    for pose, why in ((bad, "not a rigid transform"), (np.eye(3), "shape"), (np.full((4, 4), np.nan), "non-finite"),
                      ("x", "expected a 4x4")):
        with pytest.raises(ValueError, match=f"base_pose: .*{why}"):
            g.predict(base_pose=pose)


def test_an_encoder_after_a_floating_base_reads_its_joint():
    """A joint's configuration index is not its velocity index after a
    quaternion (7 coordinates, 6 velocities): the encoder reads the joint's
    angle, and its Jacobian picks the joint's velocity."""
    mech = mechanism_from_dict({"name": "flyer", "gravity": [0, 0, 0], "base": {"motion": "floating"}, "bodies": [
        {"name": "hub", "type": "link", "mass": 0.2, "inertia": [2e-4, 2e-4, 2e-4, 0, 0, 0]},
        {"name": "wing", "type": "link", "parent": "hub", "mass": 0.05, "inertia": [1e-5, 1e-5, 1e-5, 0, 0, 0],
         "joint": {"name": "hinge", "type": "revolute", "axis": [0, 0, 1], "position": [0.02, 0, 0]}}]})
    tree = mech.tree
    enc = sn.JointStateSensor("enc", ("hinge",), np.array([1e-3]))
    _, where = sn.check_sensors(mech, [enc])
    q = tree.q0.copy()
    i = [j.name for j in tree.joints].index("hinge")
    q[tree.idx_q[i]] = 0.3
    assert tree.idx_q[i] != tree.idx_v[i]
    ws = Workspace(tree)
    assert sn.predict_readings(ws, q, [enc], where)["enc"] == pytest.approx([0.3])
    e, H = sn.residual_and_jacobian(ws, sn.forward(ws, q), enc, where["enc"], np.array([0.25]))
    assert e == pytest.approx([0.05]) and H[0, tree.idx_v[i]] == 1.0 and H.sum() == 1.0
