"""End to end: the node in a second process (python -m soft_twin.node), this
test process as its client over real rclpy (soft_twin.client). Every wait is
for a condition (a matched topic, a service, a message) with a timeout."""
import math
import os
import threading
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import Pose  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from soft_twin.client import NodeProcess, TwinClient, stamp_key, start_twin, stop_twin  # noqa: E402
from soft_twin.config import resolve_robot_file  # noqa: E402
from soft_twin.conversions import matrix_from_pose, pose_msg  # noqa: E402
from soft_twin.srv import ForwardKinematics, InverseKinematics, StaticsQuery  # noqa: E402
from soft_twin_core.engine import loads as ld  # noqa: E402
from soft_twin_core.reference import kinematics as kin  # noqa: E402
from soft_twin_core.reference import statics as st  # noqa: E402
from soft_twin_core.robot.model import load_model  # noqa: E402
from rod_statics import solve_statics

pytestmark = pytest.mark.ros

NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
START_TIMEOUT = 120.0      # a fresh clone compiles the numba kernels first (~10-30 s)


def poses_of(msg):
    """(N, 4, 4) from a PoseArray."""
    return np.array([matrix_from_pose(p) for p in msg.poses])


def q_of(model, strains_msg):
    return model.q_from_strains(np.array(strains_msg.strains).reshape(-1, 6))


@pytest.fixture(scope="module")
def model():
    return load_model(resolve_robot_file(""))


def _start(node_name, ros_args, tmp_path_factory, topics=TwinClient.TOPICS):
    return start_twin(node_name, ros_args, tmp_path_factory.mktemp(node_name) / "node.log", topics, START_TIMEOUT)


def _stop(proc, client):
    stop_twin(proc, client)


# ============================================================================
# quasi-static mode, default robot: exact agreement with the core
# ============================================================================

def unlimited_robot(tmp_path_factory, **material):
    """The default robot without declared actuator limits (huge inputs must
    reach the solver, not the door), its material optionally changed."""
    d = yaml.safe_load(resolve_robot_file("").read_text())
    for a in d["actuators"]:
        a.pop("limit", None)
    for seg in d["segments"]:
        seg["material"].update(material)
    path = tmp_path_factory.mktemp("robots") / ("damped_arm.yaml" if material else "unlimited_arm.yaml")
    path.write_text(yaml.safe_dump(d))
    return path


@pytest.fixture(scope="class")
def qs(tmp_path_factory):
    robot = unlimited_robot(tmp_path_factory)
    proc, client = _start("twin_qs", ["-p", "mode:=quasi_static", "-p", "diagnostics_rate_hz:=20.0",
                                      "-p", "republish_rate_hz:=20.0", "-p", f"robot_description_file:={robot}"],
                          tmp_path_factory)
    yield client, proc
    _stop(proc, client)


class TestQuasiStatic:

    def test_actuation_gives_the_core_statics_backbone(self, qs, model):
        c, _ = qs
        for u in ([0.3, 0.0, 0.0, 0.2], [0.0, 0.6, 0.1, 0.0]):
            q_before = q_of(model, c.strains)
            stamp = c.send_actuation(NAMES, u)
            assert c.wait_until(lambda: c.state_after(stamp), 10.0), "command never applied"
            backbone, strains = c.state_after(stamp)
            ref = solve_statics(model, u, ld.Loads(), q_init=q_before)     # what the node does
            _, P = kin.backbone(model, ref.q)
            got = poses_of(backbone)
            assert backbone.header.frame_id == "base_link" and len(got) == len(P) == 61
            np.testing.assert_allclose(got[:, :3, 3], P[:, :3, 3], rtol=0, atol=1e-9)
            np.testing.assert_allclose(got[:, :3, :3], P[:, :3, :3], rtol=0, atol=1e-9)
            np.testing.assert_allclose(np.reshape(strains.strains, (-1, 6)), ref.strains, rtol=0, atol=1e-9)
            assert c.wait_until(lambda: stamp_key(c.tip_pose.header.stamp) == stamp_key(backbone.header.stamp)
                                or c.counts["tip_pose"] > 0, 5.0)

    def test_partial_command_keeps_the_other_actuators(self, qs, model):
        c, _ = qs
        stamp0 = c.send_actuation(NAMES, [0.2, 0.0, 0.0, 0.0])
        s0 = c.wait_until(lambda: c.applied(stamp0), 10.0)
        q_before = q_of(model, s0)
        stamp = c.send_actuation(["tendon_z_pos"], [0.25])
        assert c.wait_until(lambda: c.state_after(stamp), 10.0)
        _, strains = c.state_after(stamp)
        ref = solve_statics(model, [0.2, 0.0, 0.25, 0.0], ld.Loads(), q_init=q_before)
        np.testing.assert_allclose(np.reshape(strains.strains, (-1, 6)), ref.strains, rtol=0, atol=1e-9)

    def test_tip_wrench_and_base_wrench(self, qs, model):
        c, _ = qs
        u = [0.1, 0.0, 0.0, 0.0]
        stamp = c.send_actuation(NAMES, u)
        q_before = q_of(model, c.wait_until(lambda: c.applied(stamp), 10.0))
        f = [0.0, 0.02, -0.05]
        wstamp = c.send_tip_wrench(f, [0.0, 0.0, 0.001], "base_link")
        # the next state with the load: wait for its base wrench
        loads = ld.Loads(point=(ld.tip_load(model, f, (0.0, 0.0, 0.001)),))
        ref = solve_statics(model, u, loads, q_init=q_before)
        assert c.wait_until(lambda: c.base_wrench is not None and stamp_key(c.base_wrench.header.stamp)
                            >= stamp_key(wstamp) and abs(c.base_wrench.wrench.force.y + 0.02) < 1e-12, 10.0)
        bw = c.base_wrench
        assert bw.header.frame_id == "base_link"
        got = [bw.wrench.force.x, bw.wrench.force.y, bw.wrench.force.z,
               bw.wrench.torque.x, bw.wrench.torque.y, bw.wrench.torque.z]
        np.testing.assert_allclose(got, ref.base_wrench_world, rtol=0, atol=1e-9)
        # the reaction balances gravity and the tip load
        assert got[2] == pytest.approx(model.mass * 9.81 + 0.05, rel=1e-9)
        assert c.wait_until(lambda: c.tip_wrench is not None
                            and stamp_key(c.tip_wrench.header.stamp) == stamp_key(bw.header.stamp), 5.0)
        tw_msg = c.tip_wrench
        assert tw_msg.header.frame_id == "tip_link"
        R = ref.tip_pose[:3, :3]
        tw_got = [tw_msg.wrench.force.x, tw_msg.wrench.force.y, tw_msg.wrench.force.z,
                  tw_msg.wrench.torque.x, tw_msg.wrench.torque.y, tw_msg.wrench.torque.z]
        np.testing.assert_allclose(tw_got[:3], R.T @ f, atol=1e-9)
        np.testing.assert_allclose(tw_got[3:], R.T @ [0.0, 0.0, 0.001], atol=1e-9)
        # a follower load given in the tip frame comes back unchanged
        c.send_tip_wrench([0.0, 0.0, -0.03], [0.0, 0.0, 0.0], "tip_link")
        assert c.wait_until(lambda: abs(c.tip_wrench.wrench.force.z + 0.03) < 1e-12
                            and abs(c.tip_wrench.wrench.force.x) < 1e-12, 10.0)
        c.send_tip_wrench([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "base_link")    # clear it
        assert c.wait_until(lambda: c.tip_wrench.wrench.force.z == 0.0, 10.0)

    def test_a_point_wrench_loads_the_member_where_it_is_named(self, qs, model):
        """Issue 31: ``~/point_wrench_command`` (soft_twin/PointWrench) puts
        a wrench on any point of the robot: 0.05 N down on ``backbone@0.1``
        (the default arm's member, 0.1 m from its base) is carried by the
        base (its vertical reaction is the weight plus the load, exactly)
        and bends the arm down; an unknown point is refused (bad_point),
        counted and never applied; zeros remove the load."""
        c, _ = qs
        stamp = c.send_actuation(NAMES, [0.0, 0.0, 0.0, 0.0])
        assert c.wait_until(lambda: c.applied(stamp), 10.0)
        c.send_tip_wrench([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "base_link")
        weight = model.mass * 9.81
        assert c.wait_until(lambda: c.base_wrench is not None
                            and abs(c.base_wrench.wrench.force.z - weight) < 1e-9, 10.0)
        z0 = c.tip_pose.pose.position.z
        c.send_point_wrench("backbone@0.1", [0.0, 0.0, -0.05], [0.0, 0.0, 0.0], "base_link")
        assert c.wait_until(lambda: abs(c.base_wrench.wrench.force.z - (weight + 0.05)) < 1e-9, 10.0)
        assert c.wait_until(lambda: c.tip_pose.pose.position.z < z0 - 1e-4, 10.0)
        before = int(c.wait_diagnostics(timeout=10.0)["rejected_wrench_total"])
        c.send_point_wrench("nowhere@0.1", [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], "base_link")
        d = c.wait_diagnostics(lambda d: int(d["rejected_wrench_total"]) > before, 10.0)
        assert d is not None and "bad_point" in d["last_rejection"] and "nowhere" in d["last_rejection"]
        assert abs(c.base_wrench.wrench.force.z - (weight + 0.05)) < 1e-9          # not applied
        c.send_point_wrench("backbone@0.1", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "base_link")
        assert c.wait_until(lambda: abs(c.base_wrench.wrench.force.z - weight) < 1e-9, 10.0)

    def test_forward_kinematics_round_trip(self, qs, model):
        c, _ = qs
        shape = solve_statics(model, [0.5, 0.0, 0.2, 0.0])
        resp = c.call("forward_kinematics", ForwardKinematics.Request(strains=shape.strains.ravel().tolist()))
        assert resp.success, resp.message
        _, P = kin.backbone(model, shape.q)
        np.testing.assert_allclose(poses_of(resp.backbone), P, rtol=0, atol=1e-12)
        np.testing.assert_allclose(matrix_from_pose(resp.tip_pose), shape.tip_pose, atol=1e-12)
        np.testing.assert_array_equal(resp.strains, shape.strains.ravel())
        # by actuation: the static shape under gravity (a converged equilibrium)
        resp = c.call("forward_kinematics", ForwardKinematics.Request(
            actuator_names=["tendon_y_pos", "tendon_z_pos"], actuator_values=[0.5, 0.2]))
        assert resp.success, resp.message
        np.testing.assert_allclose(matrix_from_pose(resp.tip_pose), shape.tip_pose, atol=1e-9)
        # nothing given: the twin's current shape
        resp = c.call("forward_kinematics", ForwardKinematics.Request())
        np.testing.assert_allclose(np.reshape(resp.strains, (-1, 6)), np.reshape(c.strains.strains, (-1, 6)),
                                   atol=0)

    def test_inverse_kinematics_round_trip(self, qs, model):
        c, _ = qs
        target = solve_statics(model, [0.0, 0.4, 0.0, 0.3]).tip_pose
        resp = c.call("inverse_kinematics", InverseKinematics.Request(target=pose_msg(target), tolerance=1e-8))
        assert resp.success, resp.message
        assert resp.position_error <= 1e-8 and resp.orientation_error <= 1e-8
        np.testing.assert_allclose(matrix_from_pose(resp.achieved), target, atol=1e-8)
        assert list(resp.actuator_names) == NAMES and min(resp.actuator_values) >= 0.0
        # FK of the IK strains reaches the target
        fk = c.call("forward_kinematics", ForwardKinematics.Request(strains=resp.strains))
        np.testing.assert_allclose(matrix_from_pose(fk.tip_pose), target, atol=1e-8)
        if resp.actuation_found:     # that actuation holds the IK shape
            q_ik = model.q_from_strains(np.reshape(resp.strains, (-1, 6)))
            u, rel = st.actuation_for_shape(model, q_ik)
            assert rel < 1e-6
        # position only: a tip position the tendons can hold (the actuated workspace)
        p = Pose()
        p_t = solve_statics(model, [0.0, 0.0, 0.5, 0.1]).tip_pose[:3, 3]
        p.position.x, p.position.y, p.position.z = (float(v) for v in p_t)
        resp = c.call("inverse_kinematics", InverseKinematics.Request(target=p, position_only=True))
        assert resp.success, resp.message
        a = resp.achieved.position
        assert math.dist((a.x, a.y, a.z), p_t) <= 1e-6
        # unreachable: an answer, not a crash
        p.position.x = 5.0
        resp = c.call("inverse_kinematics", InverseKinematics.Request(target=p, position_only=True))
        assert not resp.success and resp.message

    def test_statics_query_leaves_the_twin_unchanged(self, qs, model):
        c, _ = qs
        stamp = c.send_actuation(NAMES, [0.15, 0.0, 0.0, 0.05])
        s0 = c.wait_until(lambda: c.applied(stamp), 10.0)
        q0, n0 = q_of(model, s0), c.counts["strains"]
        req = StaticsQuery.Request(actuator_names=["tendon_z_pos"], actuator_values=[0.7])
        req.tip_wrench.force.z = -0.02
        resp = c.call("statics_query", req)
        assert resp.success, resp.message
        ref = solve_statics(model, [0.15, 0.0, 0.7, 0.05],
                               ld.Loads(point=(ld.tip_load(model, (0, 0, -0.02)),)), q_init=q0)
        np.testing.assert_allclose(np.reshape(resp.strains, (-1, 6)), ref.strains, atol=1e-9)
        np.testing.assert_allclose([resp.base_wrench.force.z, resp.base_wrench.torque.y],
                                   ref.base_wrench_world[[2, 4]], atol=1e-9)
        assert resp.iterations >= 1 and resp.residual < 1e-8
        assert np.abs(ref.q - q0).max() > 1e-3
        # the twin keeps publishing its own, unchanged state
        assert c.wait_until(lambda: c.counts["strains"] >= n0 + 3, 5.0)
        np.testing.assert_array_equal(q_of(model, c.strains), q0)
        assert stamp_key(c.strains.last_command.stamp) == stamp_key(stamp)

    def test_bad_inputs_are_rejected_and_counted(self, qs, model):
        c, proc = qs
        stamp = c.send_actuation(NAMES, [0.1, 0.1, 0.1, 0.1])
        q_good = q_of(model, c.wait_until(lambda: c.applied(stamp), 10.0))
        cases = [
            ("actuation", (["tendon_y_pos"], [math.nan]), "non_finite"),
            ("actuation", (["tendon_y_pos"], [math.inf]), "non_finite"),
            ("actuation", (["tendon_y_pos", "tendon_z_pos"], [0.1]), "wrong_length"),
            ("actuation", ([], [0.1, 0.2]), "wrong_length"),
            ("actuation", (["tendon_x"], [0.1]), "unknown_name"),
            ("actuation", (["tendon_y_pos", "tendon_y_pos"], [0.1, 0.2]), "duplicate_name"),
            ("actuation", (["tendon_y_neg"], [-0.5]), "negative_tension"),
            ("wrench", ([0.0, math.nan, 0.0], [0.0, 0.0, 0.0], "base_link"), "non_finite"),
            ("wrench", ([0.0, 0.0, 0.1], [0.0, 0.0, 0.0], "map"), "bad_frame"),
            ("wrench", ([0.0, 0.0, 0.1], [0.0, 0.0, 0.0], ""), "bad_frame"),
        ]
        before = c.wait_diagnostics(timeout=5.0)
        assert before is not None
        for kind, args, reason in cases:
            key = f"rejected_{reason}_total"
            n_before = int(c.diagnostics()[key])
            (c.send_actuation if kind == "actuation" else c.send_tip_wrench)(*args)
            d = c.wait_diagnostics(lambda d: int(d[key]) > n_before, timeout=5.0)
            assert d is not None, f"{kind} {args} not counted as {reason}"
            assert int(d[key]) == n_before + 1
            assert reason in d["last_rejection"] or d["last_rejection"]
            n = c.counts["strains"]
            assert c.wait_until(lambda: c.counts["strains"] > n, 5.0), "node stopped publishing"
            np.testing.assert_array_equal(q_of(model, c.strains), q_good)       # never applied
            assert stamp_key(c.strains.last_command.stamp) == stamp_key(stamp)
        d = c.diagnostics()
        assert int(d["rejected_inputs_total"]) >= len(cases)
        assert int(d["rejected_actuation_total"]) >= 7 and int(d["rejected_wrench_total"]) >= 3
        # a good command still works
        stamp = c.send_actuation(["tendon_y_pos"], [0.3])
        assert c.wait_until(lambda: c.applied(stamp), 10.0)
        assert proc.alive()

    def test_service_errors_come_back_as_failures(self, qs, model):
        c, proc = qs
        bad_pose = Pose()
        bad_pose.position.x = math.nan
        zero_q = Pose()
        zero_q.orientation.w = 0.0
        calls = [
            ("forward_kinematics", ForwardKinematics.Request(strains=[0.0] * 7)),
            ("forward_kinematics", ForwardKinematics.Request(strains=[math.nan] * 36)),
            ("forward_kinematics", ForwardKinematics.Request(strains=[0.0] * 36)),   # fixed modes != f0
            ("forward_kinematics", ForwardKinematics.Request(strains=np.tile([1.0, 0, 0, 0, 0, 0], 6).tolist(),
                                                             actuator_names=["tendon_y_pos"],
                                                             actuator_values=[1.0])),
            ("forward_kinematics", ForwardKinematics.Request(actuator_names=["tendon_q"], actuator_values=[1.0])),
            ("statics_query", StaticsQuery.Request(actuator_names=["tendon_y_neg"], actuator_values=[-1.0])),
            ("statics_query", StaticsQuery.Request(actuator_names=["a", "b"], actuator_values=[1.0])),
            ("inverse_kinematics", InverseKinematics.Request(target=bad_pose)),
            ("inverse_kinematics", InverseKinematics.Request(target=zero_q)),
            ("inverse_kinematics", InverseKinematics.Request(tolerance=-1.0)),
        ]
        req = StaticsQuery.Request()
        req.tip_wrench.force.x = math.inf
        calls.append(("statics_query", req))
        for name, request in calls:
            resp = c.call(name, request)
            assert not resp.success and resp.message, (name, request)
        assert proc.alive()
        n = c.counts["strains"]
        assert c.wait_until(lambda: c.counts["strains"] > n, 5.0)

    def test_solver_failure_keeps_the_last_good_state(self, qs, model):
        c, proc = qs
        stamp = c.send_actuation(NAMES, [0.2, 0.0, 0.0, 0.0])
        q_good = q_of(model, c.wait_until(lambda: c.applied(stamp), 10.0))
        before = c.wait_diagnostics(timeout=5.0)
        c.send_actuation(["tendon_z_pos"], [1.0e4])        # valid, but no equilibrium exists
        d = c.wait_diagnostics(lambda d: int(d["solver_consecutive_failures"]) > 0, timeout=10.0)
        assert d is not None and "statics failed" in d["solver_last_message"], d
        assert c.diagnostics()["level"] == 2           # ERROR
        # dropped: counted as rejected (solver_failed), not as applied
        assert int(d["rejected_solver_failed_total"]) == int(before["rejected_solver_failed_total"]) + 1
        assert int(d["commands_applied_total"]) == int(before["commands_applied_total"])
        assert int(d["commands_received_total"]) == int(before["commands_received_total"]) + 1
        n = c.counts["strains"]
        assert c.wait_until(lambda: c.counts["strains"] > n + 2, 5.0), "node stopped publishing"
        np.testing.assert_array_equal(q_of(model, c.strains), q_good)
        assert stamp_key(c.strains.last_command.stamp) == stamp_key(stamp)
        # the failed command was dropped: a partial command starts from the last good inputs
        stamp = c.send_actuation(["tendon_y_neg"], [0.1])
        s = c.wait_until(lambda: c.applied(stamp), 10.0)
        assert s is not None
        ref = solve_statics(model, [0.2, 0.1, 0.0, 0.0], ld.Loads(), q_init=q_good)
        np.testing.assert_allclose(np.reshape(s.strains, (-1, 6)), ref.strains, atol=1e-9)
        d = c.wait_diagnostics(lambda d: d["solver_consecutive_failures"] == "0", timeout=5.0)
        assert d is not None and int(d["solver_failures_total"]) >= 1
        assert proc.alive()

    def test_markers(self, qs, model):
        from visualization_msgs.msg import MarkerArray
        c, _ = qs
        got = []
        c.node.create_subscription(MarkerArray, "/twin_qs/markers", got.append, 5)
        assert c.wait_until(lambda: got, 10.0), "no MarkerArray"
        tube = [m for m in got[-1].markers if m.ns == "tube"]
        assert len(tube) == 60 and all(m.type == m.CYLINDER for m in tube)
        assert tube[0].header.frame_id == "base_link"
        assert tube[0].scale.x == pytest.approx(0.024) and tube[-1].scale.x == pytest.approx(0.016)
        assert [m.ns for m in got[-1].markers].count("tip") == 1

    def test_parameters_over_ros(self, qs):
        from rclpy.parameter import Parameter
        from rclpy.parameter_client import AsyncParameterClient
        c, _ = qs
        params = AsyncParameterClient(c.node, "twin_qs")
        assert params.wait_for_services(timeout_sec=10.0)

        def set_(*ps):
            fut = params.set_parameters(list(ps))
            done = threading.Event()
            fut.add_done_callback(lambda _: done.set())
            assert done.wait(10.0)
            return fut.result().results
        res = set_(Parameter("step_rate_hz", value=-1.0))
        assert not res[0].successful and "step_rate_hz" in res[0].reason
        res = set_(Parameter("robot_description_file", value="no_such_arm.yaml"))
        assert not res[0].successful and "not found" in res[0].reason
        # an undeclared name: the reason names it (it was "undeclared parameter(s): []")
        res = set_(Parameter("republish_rate", value=5.0))
        assert not res[0].successful and "'republish_rate'" in res[0].reason, res[0].reason
        assert "republish_rate_hz" in res[0].reason
        # every refusal counted
        d = c.wait_diagnostics(lambda d: int(d["rejected_parameter_changes_total"]) >= 3, timeout=5.0)
        assert d is not None and "republish_rate" in d["last_parameter_rejection"], c.diagnostics()
        # an integer for a float parameter: accepted, the parameter stays a double
        assert set_(Parameter("republish_rate_hz", value=25))[0].successful
        fut = params.get_parameters(["republish_rate_hz"])
        got = threading.Event()
        fut.add_done_callback(lambda _: got.set())
        assert got.wait(10.0)
        value = fut.result().values[0]
        assert value.type == Parameter.Type.DOUBLE.value and value.double_value == 25.0, value
        assert set_(Parameter("republish_rate_hz", value=20.0))[0].successful
        n = c.counts["backbone"]
        res = set_(Parameter("backbone_points_per_section", value=5))
        assert res[0].successful, res[0].reason
        assert c.wait_until(lambda: c.counts["backbone"] > n and len(c.backbone.poses) == 31, 5.0)
        assert set_(Parameter("backbone_points_per_section", value=10))[0].successful
        assert c.wait_until(lambda: len(c.backbone.poses) == 61, 5.0)

    def test_reset(self, qs, model):
        c, _ = qs
        stamp = c.send_actuation(NAMES, [0.4, 0.0, 0.0, 0.0])
        c.wait_until(lambda: c.applied(stamp), 10.0)
        resp = c.call("reset", Trigger.Request())
        assert resp.success and "reset" in resp.message
        rest = solve_statics(model)
        assert c.wait_until(lambda: stamp_key(c.strains.last_command.stamp) == (0, 0)
                            and np.abs(q_of(model, c.strains) - rest.q).max() < 1e-12, 10.0)


# ============================================================================
# dynamic mode, a well damped robot: the backbone settles onto the statics
# ============================================================================

def damped_robot(tmp_path_factory):
    """The default arm, lighter and strongly damped (first mode near
    critical damping), so it settles in about 2 s; no actuator limits."""
    return unlimited_robot(tmp_path_factory, density=200.0, viscosity=5.0e4)


@pytest.fixture(scope="class")
def dyn(tmp_path_factory):
    robot = damped_robot(tmp_path_factory)
    # implicit Euler (theta = 1): the midpoint rule would let the strongly
    # damped (stiff) modes' rates ring at a fixed shape
    proc, client = _start("twin_dyn", ["-p", f"robot_description_file:={robot}", "-p", "mode:=dynamic",
                                       "-p", "integrator_theta:=1.0", "-p", "diagnostics_rate_hz:=2.0"],
                          tmp_path_factory)
    yield client, proc, load_model(robot)
    _stop(proc, client)


class TestDynamic:

    def test_backbone_settles_onto_the_statics(self, dyn):
        c, _, model = dyn
        # from the rest state, whatever an earlier test of the module left (a tip wrench: in a
        # shuffled run this test came after test_dynamic_tip_wrench and settled elsewhere)
        resp = c.call("reset", Trigger.Request())
        assert resp.success, resp.message
        u = [0.4, 0.0, 0.0, 0.3]
        ref = solve_statics(model, u, ld.Loads(), q_init=solve_statics(model).q)
        _, P = kin.backbone(model, ref.q)
        t0 = time.monotonic()
        stamp = c.send_actuation(NAMES, u)
        assert c.wait_until(lambda: c.state_after(stamp), 5.0), "command never applied"
        b, s = c.state_after(stamp)
        assert np.abs(poses_of(b)[:, :3, 3] - P[:, :3, 3]).max() > 1e-3      # not there yet: it moves

        def settled():
            b = c.backbone
            return (np.abs(poses_of(b)[:, :3, 3] - P[:, :3, 3]).max() < 1e-8
                    and np.abs(c.strains.strain_rates).max() < 1e-6)
        assert c.wait_until(settled, 20.0), "did not settle onto the static equilibrium"
        took = time.monotonic() - t0
        got = poses_of(c.backbone)
        np.testing.assert_allclose(got[:, :3, 3], P[:, :3, 3], atol=1e-8)
        np.testing.assert_allclose(got[:, :3, :3], P[:, :3, :3], atol=1e-7)
        print(f"\nsettled to 1e-8 m in {took:.2f} s")
        assert took < 15.0

    @pytest.mark.quiet
    def test_runs_in_real_time(self, dyn):
        c, _, _ = dyn
        d = c.wait_diagnostics(timeout=5.0)
        d = c.wait_diagnostics(timeout=5.0)
        assert d is not None
        assert abs(float(d["step_rate_hz"]) - 200.0) < 10.0, d
        # (publish_rate_hz is lower on a busy CPU: a late tick takes two steps and
        # publishes the newer state once; 85-195 Hz measured on 2 shared cores)
        assert 0.0 < float(d["publish_rate_hz"]) <= float(d["step_rate_hz"]) + 10.0, d
        assert abs(float(d["real_time_factor"]) - 1.0) < 0.05, d
        assert d["solver_failures_total"] == "0"

    @pytest.mark.quiet
    @pytest.mark.parametrize("magnitude", [1.0e4, 1.0e6, 1.0e100, 1.0e300])
    def test_a_failing_step_drops_the_input_and_publishing_goes_on(self, dyn, magnitude):
        """Valid but huge tensions (the robot declares no limit): the step
        fails, the command is dropped (rejected, solver_failed; not applied),
        the state topics keep coming at the step rate with the last good
        state's command, twin time runs on, and a failing tick costs less
        than a few step periods. (It was: every tick failed, 64 Hz at 1e6,
        0 Hz and ~300 internal errors a second at 1e300, twin time frozen.)"""
        c, proc, model = dyn
        stamp = c.send_actuation(NAMES, [0.2, 0.0, 0.0, 0.0])
        assert c.wait_until(lambda: c.applied(stamp), 10.0)
        before = c.wait_diagnostics(timeout=5.0)
        c.send_actuation(NAMES, [magnitude, 0.0, 0.0, 0.0])
        d = c.wait_diagnostics(lambda d: int(d["rejected_solver_failed_total"])
                               > int(before["rejected_solver_failed_total"]), timeout=10.0)
        assert d is not None, c.diagnostics()
        assert "did not converge" in d["solver_last_message"] and "input dropped" in d["solver_last_message"]
        assert int(d["commands_applied_total"]) == int(before["commands_applied_total"])
        assert int(d["rejected_actuation_total"]) == int(before["rejected_actuation_total"]) + 1
        assert d["internal_errors_total"] == before["internal_errors_total"]
        assert int(d["solver_failures_total"]) == int(before["solver_failures_total"]) + 1   # once
        # the state topics keep coming with the last good command, at the step rate
        # (the node's count: the client may miss some under load); twin time runs on
        n = c.counts["strains"]
        assert c.wait_until(lambda: c.counts["strains"] >= n + 50, 10.0), "node stopped publishing"
        assert stamp_key(c.strains.last_command.stamp) == stamp_key(stamp)
        d1 = c.wait_diagnostics(timeout=5.0)
        d2 = c.wait_diagnostics(timeout=5.0)
        rates = [(float(x["step_rate_hz"]), float(x["publish_rate_hz"])) for x in (d, d1, d2)]
        # every step taken: it was 0 Hz, every tick failing. (States go out at every
        # tick: the in-process test counts them; the publish rate here depends on the
        # CPU: a late tick takes two steps and publishes once, 85-195 Hz measured.)
        assert all(step > 100.0 and publish > 0.0 for step, publish in rates), rates
        assert float(d2["twin_time_s"]) - float(d1["twin_time_s"]) > 0.4       # a 0.5 s period
        # the failing step's cost (it was 25-200 ms) is bounded by the in-process test
        # (test_node_units: the least of five tries within one step period): a wall-clock
        # bound here would measure the other processes of the machine too (53 ms seen once)
        print(f"\n{magnitude:g} N: failing window step time max {d['step_time_max_ms']} ms, step and "
              f"publish rates {rates} Hz")
        # a sane command is applied at once
        stamp = c.send_actuation(NAMES, [0.3, 0.0, 0.0, 0.0])
        assert c.wait_until(lambda: c.applied(stamp), 10.0)
        assert proc.alive()

    def test_dynamic_tip_wrench(self, dyn):
        c, _, model = dyn
        c.send_tip_wrench([0.0, 0.0, 0.0], [0.0, 0.0, -0.002], "tip_link")
        assert c.wait_until(lambda: c.tip_wrench is not None and c.tip_wrench.wrench.torque.z == -0.002
                            and c.tip_wrench.header.frame_id == "tip_link", 10.0)
        assert c.wait_until(lambda: c.base_wrench is not None, 5.0)
        c.send_tip_wrench([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "tip_link")         # clear it for the others


@pytest.mark.parametrize("args, words", [
    (["-p", "mode:=kinematic"], ["mode", "kinematic"]),
    # a misspelt name used to be ignored: the twin ran with the default instead
    (["-p", "unknown_param:=1"], ["unknown parameter", "'unknown_param'"]),
    (["-p", "step_rate:=100.0"], ["unknown parameter", "'step_rate'", "'step_rate_hz'?"]),
])
def test_invalid_start_parameters_exit_with_a_reason(tmp_path, args, words):
    proc = NodeProcess(args, node_name="twin_bad", log_path=tmp_path / "log")
    rc = proc.proc.wait(timeout=60)
    out = proc.output()
    proc.stop()
    assert rc == 2, out
    assert "invalid configuration" in out and all(w in out for w in words), out
    assert "Traceback" not in out


# ============================================================================
# soak: 1 kHz commands for 10 s while services are called
# ============================================================================

@pytest.mark.slow
@pytest.mark.quiet
def test_soak_flood_while_calling_services(tmp_path_factory):
    """Actuation commands at 1 kHz for 10 s while FK and statics queries are
    called back to back: no crash, no solver failure, the step rate within
    2.5 % of 200 Hz over the flood's diagnostics periods and within 10 % in
    each of them, and no command
    lost without being counted: received + lost = published (lost: gaps in
    the publisher's sequence numbers), received = applied + rejected, the
    superseded ones (applied, but no state carries them) at most those no
    state reflected. Nearly every command arrives (one executor dispatch per
    message took 9-34 % here: the queue, keep last 100, overflowed), and the
    states are fresh: a state's command was stamped at most three step
    periods before the state on median (it was ~100 ms, the age of the
    oldest command of a full queue). The last command is applied."""
    proc, c = _start("twin_soak", ["-p", "mode:=dynamic", "-p", "diagnostics_rate_hz:=1.0"], tmp_path_factory,
                     topics=("strains",))
    stop = threading.Event()
    service_results = []

    def call_services():
        reqs = [("forward_kinematics", ForwardKinematics.Request()),
                ("statics_query", StaticsQuery.Request(actuator_names=["tendon_y_pos"], actuator_values=[0.3])),
                ("forward_kinematics", ForwardKinematics.Request(actuator_names=["tendon_z_pos"],
                                                                 actuator_values=[0.2]))]
        k = 0
        while not stop.is_set():
            name, req = reqs[k % len(reqs)]
            t = time.monotonic()
            try:
                ok = c.call(name, req, timeout=10.0).success
            except TimeoutError:
                ok = False
            service_results.append((name, ok, time.monotonic() - t))
            k += 1

    def ns(stamp):
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    try:
        assert c.wait_diagnostics(timeout=5.0) is not None
        # one command first: the node knows this publisher's sequence numbers from then on
        first = c.send_actuation(NAMES, [0.1, 0.0, 0.0, 0.0])
        assert c.wait_until(lambda: c.applied(first), 10.0), "the first command was never applied"
        rng = np.random.default_rng(0)
        services = threading.Thread(target=call_services)
        n_sent, last = 0, None
        t_start = time.monotonic()
        services.start()
        next_t = t_start
        while time.monotonic() - t_start < 10.0:
            last = c.send_actuation(NAMES, rng.uniform(0.0, 0.5, 4))
            n_sent += 1
            next_t += 0.001
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)      # pacing the flood, not waiting for ROS
        t_end = time.monotonic()
        stop.set()
        services.join(timeout=30.0)
        assert c.wait_until(lambda: c.applied(last), 5.0), "the last command was never applied"
        d = c.wait_diagnostics(timeout=5.0)
        assert proc.alive()
    finally:
        _stop(proc, c)
    elapsed = t_end - t_start
    published = n_sent + 1
    # diagnostics periods (1 s each) lying inside the flood
    windows = [w for t, w in c.history["diagnostics"] if t_start + 1.05 <= t <= t_end]
    rates = [float(w["step_rate_hz"]) for w in windows]
    calls = len(service_results)
    # the states of the flood: how old their command was (both stamps from ROS time)
    states = [s for t, s in c.history["strains"] if t_start + 0.5 <= t <= t_end]
    ages = np.array([1e-6 * (ns(s.header.stamp) - ns(s.last_command.stamp)) for s in states])
    reflected = {stamp_key(s.last_command.stamp) for _, s in c.history["strains"]} - {(0, 0)}
    received, lost = int(d["commands_received_total"]), int(d["commands_lost_total"])
    applied, superseded = int(d["commands_applied_total"]), int(d["commands_superseded_total"])
    print(f"\nsoak: {n_sent} commands in {elapsed:.2f} s ({n_sent / elapsed:.0f} Hz), received {received}, "
          f"lost {lost}, superseded {superseded}, queue max {[w['command_queue_max'] for w in windows]}; "
          f"state's command age median {np.median(ages):.1f} ms, p95 {np.percentile(ages, 95):.1f} ms; "
          f"command_to_publish mean {[w['command_to_publish_mean_ms'] for w in windows]} ms; "
          f"{calls} service calls (max {max(r[2] for r in service_results) * 1e3:.0f} ms), step rates {rates}, "
          f"step time max {[w['step_time_max_ms'] for w in windows]} ms, dropped {d['dropped_steps_total']}")
    assert n_sent / elapsed > 900, f"the flood only reached {n_sent / elapsed:.0f} Hz"
    assert calls >= 10 and all(ok for _, ok, _ in service_results), service_results[:5]
    assert d["rejected_actuation_total"] == "0"
    # every command accounted for
    assert received + lost == published, (received, lost, published)
    assert received == applied + int(d["rejected_actuation_total"])
    assert 0 < superseded <= applied - len(reflected), (superseded, applied, len(reflected))
    assert applied - superseded <= int(d["steps_total"])
    # nearly all of them arrive (what is lost depends on the CPU left to the node)
    assert received >= 0.95 * published, (received, lost, published)
    # fresh states: 200 Hz samples of a 1 kHz stream, the command's transport and the
    # node's dispatch; two periods on median on an idle machine, three under load
    assert len(ages) > 500 and np.median(ages) <= 3 * 5.0, (np.median(ages), len(ages))
    assert d["solver_failures_total"] == "0"
    assert len(windows) >= 7, windows
    # the step rate held: within 2.5 % on average over the flood's seconds and
    # within 10 % in every one (alone: every second within 1.7 %; in a full
    # suite run one second fell to 183.8 Hz at the flood's start while the mean
    # was 196.3 Hz: the VM's speed drifts and the suite's other processes run)
    assert abs(np.mean(rates) - 200.0) <= 5.0, rates
    assert all(abs(r - 200.0) <= 20.0 for r in rates), rates


# ============================================================================
# shutdown: SIGINT and SIGTERM at random times, idle, busy, starting
# ============================================================================

SIGNAL_SCENARIOS = [
    # (label, node parameters, what runs while the signal comes)
    ("idle, dynamic", [], None),
    ("idle, quasi-static", ["-p", "mode:=quasi_static", "-p", "republish_rate_hz:=50.0"], None),
    ("idle, 500 Hz, publish every 2nd", ["-p", "step_rate_hz:=500.0", "-p", "publish_every_n_steps:=2"], None),
    ("services back to back", [], "services"),
    ("parameter changes", [], "parameters"),
    ("commands at 500 Hz", ["-p", "mode:=quasi_static"], "inputs"),
    ("during start-up", [], "startup"),
]


def _wait_for_log(path, marker, proc, timeout):
    """Poll the node's log file until it holds ``marker`` (False if the node
    exits or the timeout passes first)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if marker in path.read_text():
                return True
        except FileNotFoundError:
            pass
        if not proc.alive():
            return False
        time.sleep(0.02)
    return False


def _keep_busy(activity, client, node_name, stop):
    """Load the node until ``stop``: service calls, parameter changes or
    commands, each as fast as they go (waiting for each answer)."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    rng = np.random.default_rng(1)
    if activity == "services":
        reqs = [("statics_query", StaticsQuery.Request(actuator_names=["tendon_y_pos"], actuator_values=[0.3])),
                ("forward_kinematics", ForwardKinematics.Request(actuator_names=["tendon_z_pos"],
                                                                 actuator_values=[0.2])),
                ("inverse_kinematics", InverseKinematics.Request(target=pose_msg(np.eye(4)), position_only=True))]
        k = 0
        while not stop.is_set():
            try:
                client.call(*reqs[k % len(reqs)], timeout=2.0)
            except TimeoutError:
                pass
            k += 1
    elif activity == "parameters":
        params = AsyncParameterClient(client.node, node_name)
        params.wait_for_services(timeout_sec=10.0)
        changes = [[Parameter("step_rate_hz", value=150.0)], [Parameter("mode", value="quasi_static")],
                   [Parameter("step_rate_hz", value=200.0), Parameter("mode", value="dynamic")],
                   [Parameter("backbone_points_per_section", value=5)],
                   [Parameter("backbone_points_per_section", value=10)]]
        k = 0
        while not stop.is_set():
            done = threading.Event()
            params.set_parameters(changes[k % len(changes)]).add_done_callback(lambda _: done.set())
            done.wait(2.0)
            k += 1
    elif activity == "inputs":
        while not stop.is_set():
            client.send_actuation(NAMES, rng.uniform(0.0, 0.5, 4))
            time.sleep(0.002)          # pacing the stream, not waiting for ROS


def _signal_run(k, sig, scenario, seed, tmp_path):
    """Start a node, bring it into the scenario, send ``sig`` at a random
    moment; (label, signal name, exit code (None: still running after 60 s),
    seconds from the signal to the exit, the node's output)."""
    import random
    import signal
    import subprocess
    label, args, activity = scenario
    rng = random.Random(seed * 100003 + k)
    name = f"sig{seed}_{k}"
    log = tmp_path / f"{name}.log"
    proc = NodeProcess(args + ["-p", "diagnostics_rate_hz:=5.0"], node_name=name, log_path=log)
    client, stop, worker, rc, took = None, threading.Event(), None, "not started", math.nan
    try:
        marker = "robot 'tendon_arm'" if activity == "startup" else "twin running"
        if _wait_for_log(log, marker, proc, START_TIMEOUT):
            if activity in ("services", "parameters", "inputs"):
                client = TwinClient(name, client_name=f"{name}_client", topics=("strains",))
                client.wait_ready(START_TIMEOUT)
                worker = threading.Thread(target=_keep_busy, args=(activity, client, name, stop), daemon=True)
                worker.start()
            # a random moment: within the start-up (~1 s after its first line), or while running
            time.sleep(rng.uniform(0.0, 1.0 if activity == "startup" else 0.6))
            t0 = time.monotonic()
            proc.proc.send_signal(sig)
            try:
                rc = proc.proc.wait(timeout=60.0)
            except subprocess.TimeoutExpired:
                rc = None                    # ignored: the node kept running
            took = time.monotonic() - t0
    finally:
        stop.set()
        if worker is not None:
            worker.join(timeout=10.0)
        if client is not None:
            client.close()
        proc.stop()
    return label, signal.Signals(sig).name, rc, took, proc.output()


def _signal_storm(n_each, parallel, seed, tmp_path):
    """n_each SIGINTs and n_each SIGTERMs, spread over SIGNAL_SCENARIOS,
    ``parallel`` nodes at a time. Asserts: every one exits with status 0
    within 30 s of the signal (about 2 s here: Python's teardown; 7 ms from
    the signal to "stopped" on an idle machine), without a traceback or an
    rcl error, saying which signal stopped it."""
    import signal
    from concurrent.futures import ThreadPoolExecutor
    jobs = [(k, signal.SIGINT if k % 2 == 0 else signal.SIGTERM, SIGNAL_SCENARIOS[(k // 2) % len(SIGNAL_SCENARIOS)])
            for k in range(2 * n_each)]
    t_start = time.monotonic()
    with ThreadPoolExecutor(parallel) as pool:
        results = list(pool.map(lambda job: _signal_run(*job, seed, tmp_path), jobs))
    bad, rescued = [], []
    for label, sig, rc, took, out in results:
        # a teardown stuck in the middleware is ended by the node's watchdog (a
        # WARN line, still status 0); it happened once in 200 signals in CI
        ended_by_watchdog = "the teardown did not end within" in out
        clean = (rc == 0 and took < 30.0 and (f"{sig}: shutting down" in out or ended_by_watchdog)
                 and not any(w in out for w in ("Traceback", "RCLError", "Failed to publish", "Exception")))
        if not clean:
            bad.append((label, sig, rc, took, out[-2500:]))
        elif ended_by_watchdog:
            rescued.append((label, sig, rc, took, out[-2500:]))
    summary = {s: sum(1 for r in results if r[1] == s and r[2] == 0) for s in ("SIGINT", "SIGTERM")}
    tooks = np.array([r[3] for r in results if r[2] == 0])
    print(f"\nsignals: SIGINT {summary['SIGINT']}/{n_each} exit 0, SIGTERM {summary['SIGTERM']}/{n_each} exit 0; "
          f"exit after the signal median {np.median(tooks):.2f} s, max {tooks.max():.2f} s; "
          f"{len(rescued)} teardowns ended by the watchdog; {len(results)} nodes in {time.monotonic() - t_start:.0f} s")
    assert not bad, "\n\n".join(f"{label} {sig}: exit {rc} after {took:.2f} s\n{out}"
                                for label, sig, rc, took, out in bad[:3]) + f"\n({len(bad)} bad in all)"
    # rare is the middleware; often would be a teardown of ours that hangs
    assert len(rescued) <= max(1, len(results) // 50), "\n\n".join(
        f"{label} {sig}: ended by the watchdog after {took:.2f} s\n{out}" for label, sig, rc, took, out in rescued[:3])


def test_signals_stop_the_node_cleanly(tmp_path):
    """20 SIGINTs and 20 SIGTERMs at random moments (idle in both modes and
    at 500 Hz, during service calls, parameter changes and a command
    stream, during the start-up): exit status 0, no traceback, every time.
    (Before: "RCLError: failed to initialize wait set: the given context is
    not valid", exit 1, in 4 of 28 SIGTERMs and 2 of 38 SIGINTs; a signal
    during the start-up: a traceback or death by the signal.)"""
    _signal_storm(20, 4, 1, tmp_path)


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_signals_stop_the_node_cleanly_10_more_each(tmp_path):
    """10 more SIGINTs and 10 more SIGTERMs at other random moments (seed 2):
    with the 20 each above, 60 signals a suite run. (Issue 9's criterion was
    100 of each, once: this test ran it in every suite run, 215 s of a suite
    that must stay under 15 minutes; 30 each took 57 s; the full storm again:
    SOFT_TWIN_SIGNALS=100 pytest test/ros/test_node_e2e.py -k more_each.)"""
    _signal_storm(int(os.environ.get("SOFT_TWIN_SIGNALS", "10")), 4, 2, tmp_path)



STUCK_TEARDOWN = """\
import sys, threading
sys.path.insert(0, {root!r})          # the sources, as NodeProcess runs them
import rclpy.node
from soft_twin import node as twin_node, shutdown
from soft_twin.executor import TwinExecutor
shutdown.TEARDOWN_TIMEOUT_S = {timeout}
never = lambda *args, **kwargs: threading.Event().wait()
if {stuck!r} == "destroy_node":
    # a middleware teardown that never returns (as a DDS deletion racing its discovery threads can)
    rclpy.node.Node.destroy_node = never
elif {stuck!r} == "executor":
    # a callback that never ends: the executor's shutdown waits for it, the recording is still open
    TwinExecutor.shutdown = never
sys.exit(twin_node.main(sys.argv))
"""


@pytest.mark.parametrize("stuck,when", [("destroy_node", "running"), ("destroy_node", "start-up"),
                                        ("executor", "running"), ("nothing", "running"),
                                        ("nothing", "start-up")])
def test_a_stuck_teardown_is_logged_and_the_node_exits_anyway(tmp_path, stuck, when):
    """A teardown that never returns, in a real node process that records to
    MCAP (rclpy's Node.destroy_node blocking, or the executor's shutdown
    waiting for a callback that never ends), is given TEARDOWN_TIMEOUT_S (2 s
    here): the watchdog logs where the main thread is stuck, closes the
    recording and the process exits with status 0; the recording reads back
    with the mcap library. (A signal test in CI once saw a node stay for 60 s
    after SIGINT during the start-up: 1 of 200.) Without a block the watchdog
    stays silent."""
    import signal
    import subprocess
    import sys
    from mcap.reader import make_reader
    from soft_twin.client import REPO_ROOT
    name = f"stuck_{stuck}_{when.replace('-', '_')}"
    script = tmp_path / "run_node.py"
    script.write_text(STUCK_TEARDOWN.format(root=str(REPO_ROOT), timeout=2.0, stuck=stuck))
    log, mcap_path = tmp_path / "node.log", tmp_path / "run.mcap"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, str(script), "--ros-args", "-r", f"__node:={name}",
                                 "-p", f"record_file:={mcap_path}"], cwd=REPO_ROOT, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        marker = "mode dynamic" if when == "start-up" else "recording every published topic"
        assert _wait_for_log(log, marker, _Alive(proc), START_TIMEOUT), log.read_text()[-2000:]
        if when == "running":
            assert _wait_for_log(log, "twin running", _Alive(proc), 10.0), log.read_text()[-2000:]
            time.sleep(0.3)            # some states recorded (200 Hz), not waiting for ROS
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=30.0)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert rc == 0, text[-2000:]
    assert ("SIGINT: stopping at the end of the start-up step" if when == "start-up"
            else "SIGINT: shutting down") in text, text[-2000:]
    assert "Traceback" not in text and "before the exit" not in text, text[-2000:]
    assert "/.venv/" not in text, "the node ran from the installed copy, not the sources"
    if stuck != "nothing":
        assert "the teardown did not end within 2 s" in text, text[-2000:]
        assert ("destroy_node (node.py" if stuck == "destroy_node" else "main (node.py") in text, text[-2000:]
        assert 2.0 <= took < 10.0, took
        assert "stopped" not in text.splitlines()[-1]
    else:
        assert "teardown did not end" not in text, text[-2000:]
        assert text.rstrip().endswith("stopped"), text[-2000:]
    if when == "running":              # the recording is whole: summary, footer, the states
        with open(mcap_path, "rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            topics = {ch.topic for ch in summary.channels.values()}
            n_backbones = sum(1 for _, ch, _ in reader.iter_messages() if ch.topic == f"/{name}/backbone")
        assert f"/{name}/backbone" in topics and n_backbones >= 10, (topics, n_backbones)
        assert summary.statistics.message_count >= n_backbones


class _Alive:
    """_wait_for_log's view of a plain Popen."""
    def __init__(self, proc):
        self.proc = proc

    def alive(self):
        return self.proc.poll() is None
