"""End to end (issue 13, articulated robots): the node's ~/inverse_kinematics
and ~/plan_path on the pan-tilt arm. The IK answers joint commands and
tendon tensions whose equilibrium, solved independently by the core from
scratch, puts the tool at the target (a position, or a full pose with its
orientation); an unreachable target answered with the closest position the joints and
tendons hold. A planned line executed through the service publishes one
JointState (positions) and one ActuationCommand per sample at its time with
the planned values, and the twin follows them. The node runs in a second
process; this process is a real rclpy client; every wait is for a
condition with a timeout."""

import threading

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import Pose  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from soft_twin.client import TwinClient, start_twin, stop_twin  # noqa: E402
from soft_twin.conversions import matrix_from_pose  # noqa: E402
from soft_twin.msg import ActuationCommand  # noqa: E402
from soft_twin.srv import InverseKinematics, PlanPath  # noqa: E402
from soft_twin_core.engine import algorithms as alg  # noqa: E402
from soft_twin_core.engine.workspace import Workspace  # noqa: E402
from soft_twin_core.robot.mechanism import load_mechanism  # noqa: E402
from soft_twin_core.solve import constrained as cs  # noqa: E402

pytestmark = pytest.mark.ros
JOINTS_OUT = "/plan_art/joint_commands"
ACT_OUT = "/plan_art/actuation"


@pytest.fixture(scope="module")
def mech():
    return load_mechanism("pan_tilt_arm")


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    proc, client = start_twin(
        "twin_art_plan", ["-p", "mode:=quasi_static", "-p", "robot_description_file:=pan_tilt_arm",
                          "-p", "republish_rate_hz:=20.0",
                          "-p", f"plan_output_topic:={ACT_OUT}", "-p", f"plan_joint_output_topic:={JOINTS_OUT}"],
        tmp_path_factory.mktemp("twin_art_plan") / "node.log", TwinClient.TOPICS + ("joint_states",), 120.0,
        ready=lambda c: c.pub_joints.get_subscription_count() > 0)
    yield client
    stop_twin(proc, client)


def tool_position(mech, values, q_init=None):
    """The tool's position at the equilibrium of [pan, tilt, tensions],
    solved by the core (from the reference configuration by default)."""
    eq = cs.solve_equilibrium(mech, actuation=values[2:], positions=values[:2], q_init=q_init)
    ref = mech.frame("tool")
    return alg.point_poses(mech.tree, Workspace(mech.tree), eq.q, [ref.joint], [ref.x])[0][:3, 3]


def _pose(p):
    m = Pose()
    m.position.x, m.position.y, m.position.z = (float(v) for v in p)
    m.orientation.w = 1.0
    return m


def _ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_ik_reaches_positions_with_joints_and_tendons(twin, mech):
    c = twin
    target = tool_position(mech, np.array([0.25, -0.2, 1.0, 0.0, 0.6, 0.0]))
    resp = c.call("inverse_kinematics", InverseKinematics.Request(target=_pose(target), position_only=True,
                                                                  tolerance=1e-7))
    assert resp.success, resp.message
    assert list(resp.actuator_names) == ["pan", "tilt", "tendon_y_pos", "tendon_y_neg", "tendon_z_pos",
                                         "tendon_z_neg"]
    x = np.array(resp.actuator_values)
    assert np.all(x[2:] >= 0) and resp.actuation_found and resp.position_error <= 1e-7
    lo, hi = zip(*(mech.tree.joints[mech.tree.joint_index(n)].limits for n in ("pan", "tilt")))
    assert np.all(x[:2] >= lo) and np.all(x[:2] <= hi)
    # the answer holds: the core's own equilibrium of those commands puts the tool at the target
    np.testing.assert_allclose(tool_position(mech, x), target, rtol=0, atol=1e-6)
    np.testing.assert_allclose(matrix_from_pose(resp.achieved)[:3, 3], target, rtol=0, atol=1e-7)
    assert len(resp.strains) == 6 * len(mech.tree.soft_joints)
    # informative: the angle between the achieved and the requested (identity) orientation
    angle = np.arccos(np.clip(0.5 * (np.trace(matrix_from_pose(resp.achieved)[:3, :3]) - 1.0), -1.0, 1.0))
    assert angle > 1e-3 and resp.orientation_error == pytest.approx(angle, rel=1e-9)


def test_ik_reaches_full_poses_and_flags_unreachable_targets(twin, mech):
    from soft_twin.conversions import pose_msg
    from soft_twin_core import lie
    c = twin
    x_true = np.array([0.3, -0.25, 0.8, 0.0, 0.4, 0.0])
    eq = cs.solve_equilibrium(mech, actuation=x_true[2:], positions=x_true[:2])
    ref = mech.frame("tool")
    pose = alg.point_poses(mech.tree, Workspace(mech.tree), eq.q, [ref.joint], [ref.x])[0]
    full = c.call("inverse_kinematics", InverseKinematics.Request(target=pose_msg(pose), tolerance=1e-7))
    assert full.success, full.message
    assert full.position_error <= 1e-7 and full.orientation_error <= 1e-5
    got = matrix_from_pose(full.achieved)
    assert np.linalg.norm(lie.log_so3(got[:3, :3].T @ pose[:3, :3])) <= 2e-5
    np.testing.assert_allclose(tool_position(mech, np.array(full.actuator_values)), pose[:3, 3], rtol=0, atol=1e-6)
    far = c.call("inverse_kinematics", InverseKinematics.Request(target=_pose([1.5, 0.0, 0.0]),
                                                                position_only=True))
    assert not far.success and "not reached" in far.message and far.actuation_found, far.message
    achieved = matrix_from_pose(far.achieved)[:3, 3]
    assert far.position_error == pytest.approx(np.linalg.norm(achieved - [1.5, 0.0, 0.0]), rel=1e-9)
    assert far.position_error > 0.5
    # the closest position is one the returned commands actually hold
    np.testing.assert_allclose(tool_position(mech, np.array(far.actuator_values)), achieved, rtol=0, atol=1e-6)


def test_plan_executes_joint_commands_and_actuation(twin, mech):
    c = twin
    got = {"joints": [], "act": []}
    cond = threading.Condition()

    def keep(key):
        def cb(msg):
            with cond:
                got[key].append(msg)
                cond.notify_all()
        return cb
    sj = c.node.create_subscription(JointState, JOINTS_OUT, keep("joints"), 100)
    sa = c.node.create_subscription(ActuationCommand, ACT_OUT, keep("act"), 100)
    assert c.wait_until(lambda: sj.get_publisher_count() > 0 and sa.get_publisher_count() > 0, 20.0)
    assert c.wait_until(lambda: c.tip_pose is not None, 10.0)
    p0 = matrix_from_pose(c.tip_pose.pose)[:3, 3]
    path = {"type": "line", "start": p0.tolist(), "end": (p0 + [0.0, 0.03, 0.02]).tolist(), "duration": 1.0,
            "sample_period": 0.25}
    resp = c.call("plan_path", PlanPath.Request(path_yaml=yaml.safe_dump(path), tolerance=1e-7, execute=True))
    assert resp.success and resp.executing, resp.message
    names = list(resp.actuator_names)
    assert names[:2] == ["pan", "tilt"] and len(names) == 6
    n = len(resp.times)
    X = np.reshape(resp.values, (n, len(names)))
    assert n == 5 and np.all(X[:, 2:] >= 0) and all(resp.reached)
    with cond:
        assert cond.wait_for(lambda: len(got["joints"]) >= n and len(got["act"]) >= n, timeout=20.0), \
            {k: len(v) for k, v in got.items()}
    start = _ns(resp.start_stamp)
    for k in range(n):
        js, ac = got["joints"][k], got["act"][k]
        assert list(js.name) == ["pan", "tilt"] and list(js.position) == list(X[k, :2])
        assert list(ac.names) == names[2:] and list(ac.values) == list(X[k, 2:])
        for m in (js, ac):
            assert _ns(m.header.stamp) - start == pytest.approx(resp.times[k] * 1e9, abs=1.0)
    # each planned sample holds its predicted tip (the core, independently)
    tips = np.reshape(resp.predicted_tip, (n, 3))
    np.testing.assert_allclose(tool_position(mech, X[-1]), tips[-1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(tips[-1], path["end"], rtol=0, atol=1e-6)
    # the twin follows: its joint states reach the last commands, its tool the path's end
    last = X[-1, :2]
    assert c.wait_until(lambda: c.joint_states is not None
                        and np.allclose(c.joint_states.position, last, rtol=0, atol=1e-9), 15.0)

    def at_end():
        return np.linalg.norm(matrix_from_pose(c.tip_pose.pose)[:3, 3] - path["end"]) < 1e-5
    assert c.wait_until(at_end, 15.0), matrix_from_pose(c.tip_pose.pose)[:3, 3]
