"""A prescribed base carried at run time (an arm on a manipulator's flange):
the twin's base pose input (:meth:`soft_twin_core.twin.Twin.set_base_pose`,
checked at the door by :func:`soft_twin_core.commands.parse_base_pose`), in
dynamics (statics has no moving base): the base follows the poses, and the
arm's shape relative to it is the still arm's (Galilean invariance)."""

import math

import numpy as np
import pytest

from soft_twin_core import commands as cmd
from soft_twin_core.errors import InputError
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.twin import Twin, TwinSettings

L = 0.2


def _arm(base="prescribed"):
    """A 0.2 m soft arm along x on a base (bending free), gravity -z."""
    return mechanism_from_dict({"name": "carried_arm", "gravity": [0, 0, -9.81], "base": {"motion": base},
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


def test_a_quasi_static_twin_says_statics_has_no_moving_base():
    """Statics refuses a prescribed base (its Newton runs on nq = nv
    coordinates; the base's quaternion is not): the solve fails with the
    reason, the pose is dropped and the state kept."""
    tw = Twin(_arm(), TwinSettings(mode="quasi_static"))
    assert "statics has no moving base" in tw.rest_message
    tw.set_base_pose(_pose(x=0.05))
    info = tw.step()
    assert not info.converged and "base_pose" in info.dropped and "no moving base" in info.message
    assert tw.base_pose is None


def test_a_dynamic_twin_carries_its_base_along_the_stream_of_poses():
    """Poses streamed at every step, the base carried along x at 0.1 m/s:
    the base frame follows them exactly (the clamp's rows), and the arm's
    shape relative to its base is Galilean: the same as a still twin's
    (same start, same time), but for the ringing of the start's jolt (a
    step from rest to 0.1 m/s: 5-25 um over 4 s, where the arm sags 30 mm
    in the first second): within 0.1 mm. A reset puts the base back at
    the robot file's pose."""
    dt, v = 0.005, 0.1
    carried, still = (Twin(_arm(), TwinSettings(mode="dynamic", dt=dt)) for _ in range(2))
    for k in range(1, 201):
        T = _pose(x=v * k * dt)
        carried.set_base_pose(T)
        assert carried.step().converged and still.step().converged
    a, b = carried.outputs().backbone, still.outputs().backbone
    np.testing.assert_allclose(a[0], T, atol=1e-9)
    rel = np.linalg.inv(T) @ a[-1]
    assert b[-1][2, 3] < -0.02
    np.testing.assert_allclose(rel[:3, 3], b[-1][:3, 3], atol=1e-4)
    carried.reset()
    assert carried.base_pose is None
    np.testing.assert_allclose(carried.outputs().backbone[0], np.eye(4), atol=1e-12)


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
