"""A prescribed base carried at run time (an arm on a manipulator's flange):
the twin's base pose input (:meth:`soft_twin_core.twin.Twin.set_base_pose`,
checked at the door by :func:`soft_twin_core.commands.parse_base_pose`). In
dynamics the base follows the poses, and the arm's shape relative to it is
the still arm's (Galilean invariance); in statics the base is held where the
pose puts it, and the arm is the arm fixed there."""

import math

import numpy as np
import pytest
from scipy.integrate import simpson
from scipy.spatial.transform import Rotation

from soft_twin_core import commands as cmd
from soft_twin_core.errors import InputError
from soft_twin_core.engine.algorithms import forward_kinematics
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.lie import exp_so3
from soft_twin_core.robot.mechanism import base_targets, mechanism_from_dict
from soft_twin_core.solve import constrained as cs
from soft_twin_core.twin import Twin, TwinSettings

L = 0.2


def _arm(base="prescribed", at=None):
    """A 0.2 m soft arm along x on a base (bending free), gravity -z; ``at``:
    the base's pose in the file (4x4)."""
    where = {}
    if at is not None:
        where = {"position": [float(x) for x in at[:3, 3]],
                 "quaternion": [float(x) for x in Rotation.from_matrix(at[:3, :3]).as_quat()]}
    return mechanism_from_dict({"name": "carried_arm", "gravity": [0, 0, -9.81], "base": {"motion": base, **where},
                                "bodies": [{"name": "arm", "type": "member", "segments": [{
                                    "length": L, "sections": 4,
                                    "cross_section": {"shape": "solid_circle", "radius": 0.005},
                                    "material": {"youngs_modulus": 2e6, "density": 1100, "viscosity": 5.0},
                                    "free_modes": "bending"}]}]})


def _pose(x=0.0, z=0.0, pitch=0.0):
    T = np.eye(4)
    c, s = math.cos(pitch), math.sin(pitch)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, 0.0, z]
    return T


def test_a_base_pose_is_checked_at_the_door_naming_the_reason():
    arm = _arm()
    assert np.array_equal(cmd.parse_base_pose(arm, _pose(0.1), "world", "world"), _pose(0.1))
    bad = _pose()
    bad[0, 0] = 2.0
    nan = _pose()
    nan[0, 3] = np.nan
    for mech, pose, frame, reason in ((_arm("fixed"), _pose(), "world", "wrong_mode"),
                                      (arm, _pose(), "tool", "bad_frame"),
                                      (arm, nan, "world", "non_finite"),
                                      (arm, bad, "world", "bad_pose"),
                                      (arm, np.eye(3), "world", "bad_pose")):
        with pytest.raises(InputError) as e:
            cmd.parse_base_pose(mech, pose, frame, "world")
        assert e.value.reason == reason and reason in cmd.REJECT_REASONS and "base pose" in str(e.value)


def _tilted():
    """A base pose turned about every axis, off the origin."""
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([0.3, -0.7, 0.4]))
    T[:3, 3] = [0.1, -0.05, 0.3]
    return T


@pytest.mark.parametrize("angle, axis", [(0.0, 0), (0.3, 0), (3.1, 0), (3.1, 1), (3.1, 2), (math.pi, 1)])
def test_a_free_joints_coordinates_give_back_the_pose_they_are_made_of(angle, axis):
    """:func:`constrained._free_coordinates` against the rotation matrix of
    the unit quaternion (:func:`constrained._free_pose`), through each of
    Shepperd's four branches (w, x, y or z largest: near pi about each
    axis); the quaternion is unit."""
    w = np.zeros(3)
    w[axis] = angle
    g = np.eye(4)
    g[:3, :3] = exp_so3(w + np.array([0.01, -0.02, 0.015]))
    g[:3, 3] = [0.2, -0.1, 0.3]
    q = cs._free_coordinates(g)
    assert abs(np.linalg.norm(q[3:]) - 1) < 1e-15
    assert np.allclose(cs._free_pose(q), g, rtol=0, atol=1e-14)


def test_statics_holds_a_prescribed_base_where_its_pose_puts_it():
    """The arm on a prescribed base posed at T (turned about every axis)
    is the arm whose file fixes its base at T (no free joint, no clamp):
    the same strains to the Newton tolerance, from the file's pose or from
    a start at another. The clamp's reaction carries the arm: its force is
    the weight rho A L g, and its moment about the base is the weight's,
    -(int (p - p0) ds) x rho A g, integrated along the backbone (Simpson,
    16 points a section)."""
    T = _tilted()
    arm, fixed = _arm(), _arm("fixed", at=T)
    ref = cs.solve_equilibrium(fixed)
    elsewhere = cs.solve_equilibrium(arm, targets=base_targets(arm, _pose(x=0.3, pitch=1.0))).q
    for q_init in (None, elsewhere):
        eq = cs.solve_equilibrium(arm, targets=base_targets(arm, T), q_init=q_init)
        assert eq.stable and eq.constraint_error < 1e-12
        assert np.allclose(eq.q[7:], ref.q, rtol=0, atol=1e-8 * np.abs(ref.q).max())
    tw = Twin(_arm(), TwinSettings(mode="quasi_static", points_per_section=16))
    tw.set_base_pose(T)
    assert tw.step().converged
    snap = tw.outputs()
    P, s = snap.backbone[:, :3, 3], snap.s
    assert np.allclose(P[0], T[:3, 3], rtol=0, atol=1e-15)
    rho_a_g = 1100 * math.pi * 0.005 ** 2 * np.array([0, 0, -9.81])
    f, m = snap.constraint_wrenches["base"][:3], snap.constraint_wrenches["base"][3:]
    assert np.allclose(f, -L * rho_a_g, rtol=0, atol=1e-12)
    moment = -np.cross(simpson(P - P[0], x=s, axis=0), rho_a_g)
    assert np.allclose(m, moment, rtol=0, atol=1e-5 * np.abs(moment).max())


def test_a_quasi_static_twin_carries_its_base_where_the_poses_put_it():
    """Quasi-static: each base pose is solved for (the pose applied, not
    dropped), the shape the fixed arm's at that pose; the support's
    reaction (``base_wrench``, world axes about the world origin) is the
    fixed arm's. A reset puts the base back at the robot file's pose."""
    tw = Twin(_arm(), TwinSettings(mode="quasi_static"))
    assert tw.rest_message == "rest: static equilibrium under gravity"
    rest_tip = tw.outputs().tip_pose
    for T in (_pose(x=0.05), _pose(z=0.1, pitch=math.pi / 2), _tilted()):
        tw.set_base_pose(T)
        info = tw.step()
        assert info.converged and not info.dropped and np.array_equal(tw.base_pose, T)
        fixed = Twin(_arm("fixed", at=T), TwinSettings(mode="quasi_static"))
        fixed.step()
        a, b = tw.outputs(), fixed.outputs()
        assert np.allclose(a.tip_pose, b.tip_pose, rtol=0, atol=1e-9)
        assert np.allclose(a.base_wrench, b.base_wrench, rtol=0, atol=1e-9 * np.abs(b.base_wrench).max())
    tw.reset()
    assert tw.base_pose is None and np.allclose(tw.outputs().tip_pose, rest_tip, rtol=0, atol=1e-9)


def test_a_carried_base_moves_the_arm_as_galilean_invariance_says():
    """The base carried along x at 0.1 m/s from the start, the arm straight
    along x at rest (its reference configuration, inextensible: the jolt
    moves it rigidly), the poses streamed as the twin streams them
    (``carried_secant``): the base frame follows them exactly (the clamp's
    rows), and the arm's shape relative to its base is Galilean, the same
    as a still arm's (same start, same time), where the arm sags more than
    20 mm in the second: within 0.1 mm."""
    from soft_twin_core.solve.constrained import MechanismSimulator
    dt, v = 0.005, 0.1
    mech = _arm()
    carried, still = (MechanismSimulator(mech, dt, 0.5, tol=1e-10, carried_secant=True) for _ in range(2))
    ws = Workspace(mech.tree)
    for k in range(1, 201):
        T = _pose(x=v * k * dt)
        carried.step(targets=base_targets(mech, T))
        still.step()
    a, b = (forward_kinematics(mech.tree, ws, sim.q)[1][-1].copy() for sim in (carried, still))
    base = forward_kinematics(mech.tree, ws, carried.q)[1][0]
    np.testing.assert_allclose(base, T, atol=1e-9)
    rel = np.linalg.inv(T) @ a
    assert b[2, 3] < -0.02
    np.testing.assert_allclose(rel[:3, 3], b[:3, 3], atol=1e-4)


def test_a_dynamic_twin_carries_its_base_along_the_stream_of_poses():
    """A dynamic twin streamed a pose every step (along x at 0.1 m/s from
    its rest): its base frame follows them exactly, every step converges,
    and the arm is carried along (its tip moved with the base, within the
    swing of the jolt). A reset puts the base back at the robot file's pose
    and the arm at its rest."""
    dt, v = 0.005, 0.1
    tw = Twin(_arm(), TwinSettings(mode="dynamic", dt=dt))
    rest = tw.outputs().backbone
    for k in range(1, 201):
        T = _pose(x=v * k * dt)
        tw.set_base_pose(T)
        assert tw.step().converged
    a = tw.outputs().backbone
    np.testing.assert_allclose(a[0], T, atol=1e-9)
    assert abs(a[-1][0, 3] - rest[-1][0, 3] - T[0, 3]) < 0.02
    tw.reset()
    assert tw.base_pose is None
    np.testing.assert_allclose(tw.outputs().backbone, rest, atol=1e-12)


def test_a_base_moved_in_jerks_leaves_each_step_with_the_twist_of_its_motion():
    """Poses 1 mm apart, every other step (moved, held, moved, ...: a
    carrier's stream slower than the twin's steps), midpoint rule: with
    ``carried_secant`` (the twin's) the base leaves each step with the
    twist of its motion over it, 0.2 m/s or 0, and every step converges;
    without (the midpoint rule's v1 = 2 s - v0) the velocity grows in
    alternating signs (0.4, -0.4, 0.8, ... m/s) until Newton fails (341 of
    400 steps at 40 iterations)."""
    from soft_twin_core.robot.mechanism import base_targets
    from soft_twin_core.solve.constrained import MechanismSimulator, StepError
    mech, dt = _arm(), 0.005
    iv = mech.tree.idx_v[mech.constraints[0].a.joint]
    for secant in (True, False):
        sim = MechanismSimulator(mech, dt, 0.5, tol=1e-10, max_iterations=40, carried_secant=secant)
        x, failed = 0.0, 0
        for k in range(200):
            moved = k % 2 == 0
            x += 0.001 if moved else 0.0
            try:
                sim.step(targets=base_targets(mech, _pose(x=x)))
            except StepError:
                failed += 1
                continue
            if secant:
                np.testing.assert_allclose(sim.v[iv:iv + 6], [0.2 if moved else 0.0, 0, 0, 0, 0, 0], atol=1e-9)
        assert (failed == 0) if secant else (failed > 100)


def _tendon_arm(base="prescribed", at=None):
    """A 0.2 m soft arm along x with two tendons (bending up and sideways)
    on a base, gravity -z; ``at``: the base's pose in the file (4x4)."""
    d = {"name": "carried_tendon_arm", "gravity": [0, 0, -9.81], "base": {"motion": base},
         "bodies": [{"name": "arm", "type": "member", "segments": [{
             "length": L, "sections": 4, "cross_section": {"shape": "solid_circle", "radius": 0.008},
             "material": {"youngs_modulus": 2e6, "density": 1100, "viscosity": 5.0},
             "free_modes": "bending_torsion"}],
             "actuators": [{"name": "up", "type": "tendon", "routing": "straight", "offset": [0.0, 0.006],
                            "limit": 20.0},
                           {"name": "side", "type": "tendon", "routing": "straight", "offset": [0.006, 0.0],
                            "limit": 20.0}]}]}
    if at is not None:
        d["base"].update(position=[float(x) for x in at[:3, 3]],
                         quaternion=[float(x) for x in Rotation.from_matrix(at[:3, :3]).as_quat()])
    return mechanism_from_dict(d)


def test_ik_and_planning_hold_a_carried_base_where_the_twin_has_it():
    """IK of a twin whose prescribed base is carried to T, for a target the
    arm reaches from there (its tip under known tensions, solved on the
    robot file that fixes its base at T), finds those tensions and reaches
    it; the plan of a path in the base frame (the twin's options carry
    the base pose) is the fixed arm's plan, sample by sample (its world
    targets, inputs and tip; the samples two tendons cannot reach are the
    same closest points). Planning
    with a base pose is refused, naming it, on a robot whose base is not
    prescribed."""
    from soft_twin_core.planning import planner as pl
    from soft_twin_core.planning.paths import TipPath
    T = _tilted()
    fixed = _tendon_arm("fixed", at=T)
    u_true = np.array([1.2, 0.5])
    goal = cs.solve_equilibrium(fixed, actuation=u_true)
    tip = Twin(fixed, TwinSettings(mode="quasi_static"))
    tip.set_actuation(u_true)
    tip.step()
    target = tip.outputs().tip_pose[:3, 3]
    tw = Twin(_tendon_arm(), TwinSettings(mode="quasi_static"))
    tw.set_base_pose(T)
    assert tw.step().converged
    r = tw.inverse_kinematics(target, tolerance=1e-7)
    assert r.reached and r.names == ("up", "side") and np.allclose(r.values, u_true, rtol=0, atol=1e-4), r
    assert np.allclose(r.q[7:], goal.q, rtol=0, atol=1e-4 * np.abs(goal.q).max())
    # a path in the base frame: the carried arm's plan is the fixed arm's
    base_frame_tip = np.linalg.inv(T) @ np.append(target, 1.0)
    path = TipPath(np.array([0.0, 0.5, 1.0]),
                   base_frame_tip[:3] + np.array([[0, 0, 0], [0, 0.004, 0.004], [0, 0.008, 0.0]]))
    a = pl.plan_path(tw.mech, path, tw.plan_options(tolerance=1e-7))
    b = pl.plan_path(fixed, path, pl.PlanOptions(tolerance=1e-7))
    assert a.reached[0] and list(a.status) == list(b.status)    # two tendons: the later samples off their surface
    assert np.allclose(a.u, b.u, rtol=0, atol=1e-5) and np.allclose(a.tip, b.tip, rtol=0, atol=1e-6)
    assert np.allclose(a.target, b.target, rtol=0, atol=1e-15)
    with pytest.raises(pl.PlanError, match="base_pose"):
        pl.TipSolver(fixed, pl.PlanOptions(base_pose=T))


def test_statics_brings_a_far_base_along_the_geodesic_in_steps():
    """The continuation's targets (:func:`constrained._base_path`): the
    base from where it rests at q_start to its target along ``T0 exp(t
    log(T0^-1 T1))`` (its ends and midpoint against the matrix
    exponential's definition: the midpoint's twice is the whole motion);
    the catheter pushed 50 mm into its vessel (its scenario at t = 1.5 s)
    rests with its base where the trajectory puts it."""
    from soft_twin_core.files.scenario import load_scenario, run_statics
    from soft_twin_core.lie import log_se3
    arm = _arm()
    q0 = cs.carry_base(arm, arm.tree.q0, base_targets(arm, _pose(x=0.1)))
    path = cs._base_path(arm, q0, base_targets(arm, _tilted()))
    assert np.allclose(path(0.0)[0], _pose(x=0.1), atol=1e-14) and np.allclose(path(1.0)[0], _tilted(), atol=1e-12)
    half = np.linalg.inv(_pose(x=0.1)) @ path(0.5)[0]
    assert np.allclose(half @ half, np.linalg.inv(_pose(x=0.1)) @ _tilted(), atol=1e-12)
    assert np.allclose(log_se3(half), 0.5 * log_se3(np.linalg.inv(_pose(x=0.1)) @ _tilted()), atol=1e-12)
    out = run_statics(load_scenario("catheter_in_vessel"), time=1.5)
    base = np.array(out["frame_poses"][out["frame_names"].index("base")])
    assert np.allclose(base[:3, 3], [0.05, 0, 0], atol=1e-9) and out["residual"] < 1e-8
