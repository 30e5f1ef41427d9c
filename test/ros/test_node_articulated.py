"""The node with an articulated robot (tree robot file), end to end: the node
in a second process, this process as its client over real rclpy. Joint
commands in (sensor_msgs/JointState), joint states, backbones and wrenches
out, compared with the core for the same inputs; bad joint commands
rejected and counted."""

import math

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import PoseArray, WrenchStamped  # noqa: E402

from soft_twin.client import TwinClient, stamp_key, start_twin, stop_twin  # noqa: E402
from soft_twin.conversions import matrix_from_pose  # noqa: E402
from soft_twin_core.robot.mechanism import load_mechanism  # noqa: E402
from soft_twin_core.robot.model import find_file  # noqa: E402
from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium  # noqa: E402
from soft_twin_core.solve.outputs import state_outputs  # noqa: E402

pytestmark = pytest.mark.ros
START_TIMEOUT = 120.0
PPS = 10               # backbone_points_per_section's default: every member sampled alike
TOPICS = TwinClient.TOPICS + ("joint_states",)


def _start(name, args, tmp_path_factory):
    return start_twin(name, args, tmp_path_factory.mktemp(name) / "node.log", TOPICS, START_TIMEOUT,
                      ready=lambda c: c.pub_joints.get_subscription_count() > 0)


def _stop(proc, client):
    stop_twin(proc, client)


def poses_of(msg):
    return np.array([matrix_from_pose(p) for p in msg.poses])


@pytest.fixture(scope="module")
def pan_tilt_qs(tmp_path_factory):
    proc, client = _start("twin_art_qs", ["-p", "mode:=quasi_static", "-p", "diagnostics_rate_hz:=20.0",
                                          "-p", "republish_rate_hz:=20.0",
                                          "-p", "robot_description_file:=pan_tilt_arm"], tmp_path_factory)
    yield client
    _stop(proc, client)


def test_joint_commands_give_the_core_equilibrium(pan_tilt_qs):
    c = pan_tilt_qs
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    stamp = c.send_actuation(["tendon_z_pos"], [2.0])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0)
    stamp = c.send_joint_command(["pan", "tilt"], positions=[0.4, -0.3])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0), "joint command never applied"
    backbone, strains = c.state_after(stamp)
    ref = solve_equilibrium(mech, {"tendon_z_pos": 2.0}, None, {"pan": 0.4, "tilt": -0.3})
    out = state_outputs(mech, ref.q, ref.lam, ref.inputs, points_per_section=PPS)
    got = poses_of(backbone)
    want = out.members[0].poses
    assert backbone.header.frame_id == "base_link" and len(got) == len(want) == 4 * PPS + 1
    np.testing.assert_allclose(got[:, :3, 3], want[:, :3, 3], rtol=0, atol=1e-9)
    # joint states of that state (same stamp): positions and the inverse-dynamics efforts
    js = c.wait_until(lambda: next((m for _, m in c.history["joint_states"]
                                    if stamp_key(m.header.stamp) == stamp_key(backbone.header.stamp)), None), 5.0)
    assert list(js.name) == ["pan", "tilt"]
    np.testing.assert_allclose(js.position, [0.4, -0.3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(js.effort, [out.efforts["pan"], out.efforts["tilt"]], rtol=0, atol=1e-9)
    assert abs(js.effort[1]) > 0.05              # the tilt joint holds the arm up
    # the base wrench: the support's reaction balances the weight
    assert c.wait_until(lambda: c.base_wrench is not None and stamp_key(c.base_wrench.header.stamp)
                        >= stamp_key(backbone.header.stamp), 10.0)
    weight = 9.81 * (0.40 + 0.15 + 1100.0 * 0.15 * math.pi * (0.012**2 + 0.009**2))
    assert abs(c.base_wrench.wrench.force.z - weight) < 1e-9 * weight


@pytest.mark.parametrize("names,positions,efforts,reason", [
    (["elbow"], [0.1], [], "unknown_name"),
    (["pan"], [float("nan")], [], "non_finite"),
    (["tilt"], [2.0], [], "over_limit"),
    (["pan"], [], [0.3], "wrong_mode"),
    (["pan", "tilt"], [0.1], [], "wrong_length"),
])
def test_bad_joint_commands_are_rejected_and_counted(pan_tilt_qs, names, positions, efforts, reason):
    c = pan_tilt_qs
    before = c.wait_diagnostics(timeout=10.0)
    n0 = int(before[f"rejected_{reason}_total"])
    j0 = int(before["rejected_joint_total"])
    pan0 = c.joint_states.position[0]
    c.send_joint_command(names, positions, efforts)
    d = c.wait_diagnostics(lambda d: int(d[f"rejected_{reason}_total"]) > n0, 10.0)
    assert d is not None, f"rejection {reason} never counted"
    assert int(d["rejected_joint_total"]) == j0 + 1
    assert c.joint_states.position[0] == pan0          # nothing applied


def test_dynamic_joint_motion_and_constraint_wrenches(tmp_path_factory):
    """Dynamic mode: a step command becomes a smooth move within the joint's
    speed bound; the parallel robot's constraint wrench topic matches the core."""
    proc, c = _start("twin_art_dyn", ["-p", "robot_description_file:=pan_tilt_arm"], tmp_path_factory)
    try:
        c.send_joint_command(["pan"], positions=[0.3])
        assert c.wait_until(lambda: c.joint_states is not None and abs(c.joint_states.position[0] - 0.3) < 1e-9,
                            10.0), f"pan never reached 0.3: {c.joint_states}"
        vel = [abs(m.velocity[0]) for _, m in c.history["joint_states"]]
        assert max(vel) <= 1.0 + 1e-9 and max(vel) > 0.3       # moved, within max_velocity 1 rad/s
    finally:
        _stop(proc, c)
    proc, c = _start("twin_art_par", ["-p", "mode:=quasi_static", "-p", "republish_rate_hz:=20.0",
                                      "-p", "robot_description_file:=planar_parallel_robot"], tmp_path_factory)
    try:
        got = c.subscribe(WrenchStamped, "/twin_art_par/constraint_wrenches/rod2_to_platform")
        rods = c.subscribe(PoseArray, "/twin_art_par/backbones/rod2")
        assert c.wait_until(lambda: got and rods, 10.0)
        mech = load_mechanism(find_file("planar_parallel_robot", "robots"))
        ref = solve_equilibrium(mech)
        w = ref.constraint_wrenches["rod2_to_platform"]
        m = got[-1].wrench
        np.testing.assert_allclose([m.force.x, m.force.y, m.force.z, m.torque.x, m.torque.y, m.torque.z], w,
                                   rtol=0, atol=1e-9)
        assert len(rods[-1].poses) == 8 * PPS + 1
    finally:
        _stop(proc, c)


def test_markers_draw_members_and_links(pan_tilt_qs):
    from visualization_msgs.msg import MarkerArray
    c = pan_tilt_qs
    got = c.subscribe(MarkerArray, "/twin_art_qs/markers", depth=5)
    assert c.wait_until(lambda: got, 10.0), "no markers"
    ms = got[-1].markers
    links = {m.id: m for m in ms if m.ns == "links"}
    tubes = [m for m in ms if m.ns == "tube" and m.action == 0]
    assert len(links) == 2 and len(tubes) == 4 * PPS           # pan and tilt links; 4 arm sections
    assert links[0].type == links[0].CYLINDER and links[1].type == links[1].CUBE
    assert abs(links[1].pose.position.z - 0.08) < 1e-12        # the tilt link sits on top of the pan link
    assert abs(tubes[0].scale.x - 0.024) < 1e-12               # the proximal member's diameter


@pytest.mark.parametrize("robot", ["soft_gripper", "fixed_fixed_beam"])
def test_every_example_robot_runs_in_the_node(robot, tmp_path_factory):
    """Dynamic mode at 200 Hz: the node starts, steps without failures and stops cleanly."""
    name = f"twin_ex_{robot}"
    proc, c = _start(name, ["-p", f"robot_description_file:={robot}", "-p", "diagnostics_rate_hz:=5.0"],
                     tmp_path_factory)
    try:
        d = c.wait_diagnostics(lambda d: float(d["twin_time_s"]) > 0.5, 20.0)
        assert d is not None, "the twin did not advance"
        assert d["solver_failures_total"] == "0" and d["internal_errors_total"] == "0", d
    finally:
        _stop(proc, c)


def test_tf_carries_the_articulated_frames(pan_tilt_qs):
    from tf2_msgs.msg import TFMessage
    c = pan_tilt_qs
    got = c.subscribe(TFMessage, "/tf", depth=20)
    assert c.wait_until(lambda: any(t.child_frame_id.endswith("tilt_link") for m in got for t in m.transforms),
                        10.0), "no articulated frames on /tf"
    msg = next(m for m in reversed(got) if any(t.child_frame_id.endswith("tilt_link") for t in m.transforms))
    tf = {t.child_frame_id: t for t in msg.transforms}
    assert abs(tf["twin_art_qs/tilt_link"].transform.translation.z - 0.08) < 1e-12
    assert "tip_link" in tf and "twin_art_qs/arm_0" in tf and "twin_art_qs/arm_4" in tf
    tip = tf["tip_link"].transform.translation
    # the tip frame equals the published tip pose of a state (same stamps)
    same = c.wait_until(lambda: c.tip_pose is not None and stamp_key(c.tip_pose.header.stamp)
                        >= stamp_key(msg.transforms[0].header.stamp), 5.0)
    assert same
    p = c.tip_pose.pose.position
    if stamp_key(c.tip_pose.header.stamp) == stamp_key(msg.transforms[0].header.stamp):
        assert abs(p.x - tip.x) < 1e-12 and abs(p.z - tip.z) < 1e-12


def test_live_view_snapshot_of_an_articulated_robot():
    from soft_twin_core.twin import Twin
    from soft_twin.live_view_out import articulated_view_snapshot
    mech = load_mechanism(find_file("soft_gripper", "robots"))
    twin = Twin(mech)
    snap = twin.outputs()
    shot, radii = articulated_view_snapshot(mech, snap)
    assert len(shot.members) == 3 and [len(r) for r in radii] == [3 * PPS + 1] * 3
    assert np.allclose(radii[0], 0.008)                      # half the 16 mm finger width
    np.testing.assert_allclose(shot.members[1][-1], snap.frames["finger_1_tip"][:3, 3], atol=1e-15)
    # the palm: its visual cylinder (no bar), the wrist joint at the base point with its axis along z
    assert not shot.links and len(shot.shapes) == 1 and shot.shapes[0][0]["shape"] == "cylinder"
    np.testing.assert_allclose(shot.shapes[0][1], snap.frames["palm"], atol=1e-15)
    assert np.allclose(shot.joints, [[0, 0, 0.3]]) and np.allclose(np.diff(shot.joint_axes[0], axis=0), [[0, 0, 0.03]])


def _set_tensions(c, tensions):
    """Every tendon's tension set here (the module's node is shared: a test
    must not rely on what an earlier one left, whatever the order)."""
    names = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
    stamp = c.send_actuation(names, [tensions.get(n, 0.0) for n in names])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0), "actuation not applied"


def test_joint_wrench_topics_carry_the_transmitted_wrenches(pan_tilt_qs):
    c = pan_tilt_qs
    _set_tensions(c, {"tendon_z_pos": 2.0})
    got = c.subscribe(WrenchStamped, "/twin_art_qs/joint_wrenches/pan")
    stamp = c.send_joint_command(["pan", "tilt"], positions=[0.1, -0.2])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0)
    assert c.wait_until(lambda: got, 10.0), "no joint wrench"
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    ref = solve_equilibrium(mech, {"tendon_z_pos": 2.0}, None, {"pan": 0.1, "tilt": -0.2})
    w = state_outputs(mech, ref.q, ref.lam, ref.inputs).joint_wrenches["pan"]
    assert c.wait_until(lambda: abs(got[-1].wrench.force.z - w[2]) < 1e-9, 10.0)
    m = got[-1].wrench
    np.testing.assert_allclose([m.force.x, m.force.y, m.force.z, m.torque.x, m.torque.y, m.torque.z], w,
                               rtol=0, atol=1e-9)


def test_internal_wrench_topic_along_the_member(pan_tilt_qs):
    from std_msgs.msg import Float64MultiArray
    c = pan_tilt_qs
    _set_tensions(c, {"tendon_z_pos": 2.0})
    got = c.subscribe(Float64MultiArray, "/twin_art_qs/internal_wrenches/arm")
    stamp = c.send_joint_command(["pan", "tilt"], positions=[0.2, 0.1])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0)
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    ref = solve_equilibrium(mech, {"tendon_z_pos": 2.0}, None, {"pan": 0.2, "tilt": 0.1})
    want = state_outputs(mech, ref.q, ref.lam, ref.inputs, points_per_section=PPS).members[0].internal_wrench
    assert c.wait_until(lambda: got and np.allclose(np.reshape(got[-1].data, (-1, 6)), want, rtol=0, atol=1e-9),
                        10.0), "internal wrenches differ from the core's"
    assert [d.size for d in got[-1].layout.dim] == [4 * PPS + 1, 6]


def test_forward_kinematics_service_answers_for_a_tree_robot(pan_tilt_qs):
    """~/forward_kinematics of an articulated robot (was refused): the
    current state, the strains of an equilibrium of the core (its tool pose
    back), an actuation (the core's equilibrium with the current joint
    commands), and a wrong strain count named in the answer."""
    from soft_twin.srv import ForwardKinematics
    from soft_twin_core.solve.outputs import section_strains
    c = pan_tilt_qs
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    stamp = c.send_actuation(["tendon_z_pos"], [0.0])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0)
    stamp = c.send_joint_command(["pan", "tilt"], positions=[-0.2, 0.25])
    assert c.wait_until(lambda: c.state_after(stamp), 10.0)
    ref = solve_equilibrium(mech, {"tendon_y_neg": 1.5}, None, {"pan": -0.2, "tilt": 0.25})
    tool = state_outputs(mech, ref.q, ref.lam, ref.inputs).frames["tool"]
    r = c.call("forward_kinematics", ForwardKinematics.Request(strains=section_strains(mech, ref.q).ravel().tolist()))
    assert r.success, r.message
    np.testing.assert_allclose(matrix_from_pose(r.tip_pose), tool, rtol=0, atol=1e-9)
    assert len(r.backbone.poses) == 4 * PPS + 1 and r.backbone.header.frame_id == "base_link"
    r = c.call("forward_kinematics", ForwardKinematics.Request(actuator_names=["tendon_y_neg"],
                                                               actuator_values=[1.5]))
    assert r.success, r.message
    np.testing.assert_allclose(matrix_from_pose(r.tip_pose), tool, rtol=0, atol=1e-8)
    r = c.call("forward_kinematics", ForwardKinematics.Request())
    assert r.success and "current" in r.message
    r = c.call("forward_kinematics", ForwardKinematics.Request(strains=[0.0] * 6))
    assert not r.success and "expected 24 values" in r.message
