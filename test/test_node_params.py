"""The node in this process (private rclpy Context): parameters validated at
start and on change; a rejected change leaves the running twin untouched."""
import time

import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from rclpy.parameter import Parameter  # noqa: E402

from soft_twin.config import ConfigError  # noqa: E402
from soft_twin.node import SoftTwinNode  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def _node(context, **params):
    return SoftTwinNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


@pytest.mark.parametrize("params, match", [
    ({"mode": "kinematic"}, "mode"),
    ({"step_rate_hz": -1.0}, "step_rate_hz"),
    ({"robot_description_file": "no_such_robot.yaml"}, "not found"),
    ({"robot_description": "segments: 3"}, "segments"),
    ({"actuator_names": ["tendon_y_pos", "chamber_1"]}, "do not match"),
    ({"base_frame": "tip_link"}, "differ"),
])
def test_bad_parameters_at_start_raise(context, params, match):
    with pytest.raises(ConfigError, match=match):
        _node(context, **params)


def test_run_time_changes(context):
    node = _node(context, mode="quasi_static", step_rate_hz=100)       # an int for a rate is fine
    try:
        twin, q = node.twin, node.twin.state.q.copy()
        assert node.cfg.step_rate_hz == 100.0
        bad = [
            [Parameter("mode", value="fast")],
            [Parameter("step_rate_hz", value=0.0)],
            [Parameter("step_rate_hz", value="high")],
            [Parameter("robot_description_file", value="missing.yaml")],
            [Parameter("backbone_points_per_section", value=0)],
            [Parameter("tip_frame", value="base_link")],
            [Parameter("actuator_names", value=["tendon_y_pos"])],
            # one bad value spoils the whole request
            [Parameter("mode", value="dynamic"), Parameter("integrator_theta", value=2.0)],
        ]
        for params in bad:
            res = node.set_parameters_atomically(params)
            assert not res.successful and res.reason, params
            assert node.twin is twin and node.twin.settings.mode == "quasi_static"
            assert (node.twin.state.q == q).all()
            assert node.get_parameter("mode").value == "quasi_static"
        assert node.get_parameter("step_rate_hz").value == 100

        res = node.set_parameters_atomically([Parameter("mode", value="dynamic"),
                                              Parameter("step_rate_hz", value=250.0)])
        assert res.successful, res.reason
        assert node.cfg.mode == "dynamic" and node.twin.settings.mode == "dynamic"
        assert node.twin.settings.dt == pytest.approx(0.004)
        assert node.twin is twin and (node.twin.state.q == q).all()     # same robot, same shape

        res = node.set_parameters([Parameter("robot_description_file", value="pneumatic_arm.yaml")])[0]
        assert res.successful, res.reason
        assert node.twin is not twin and node.twin.model.name == "pneumatic_arm"
        assert node.twin.model.actuator_names[0] == "chamber_1"

        res = node.set_parameters([Parameter("actuator_names", value=["chamber_2"])])[0]
        assert not res.successful and "do not match" in res.reason
    finally:
        node.destroy_node()


def test_unexpected_errors_never_escape_a_callback(context):
    from soft_twin.srv import ForwardKinematics
    node = _node(context)
    try:
        def broken_service(req, resp):
            raise RuntimeError("a bug")
        resp = node._guarded(broken_service)(ForwardKinematics.Request(), ForwardKinematics.Response())
        assert not resp.success and "RuntimeError: a bug" in resp.message
        assert node._guarded(lambda: 1 / 0)() is None
        assert node.stats.totals["internal_errors"] == 2
        assert "ZeroDivisionError" in node.stats.last_internal_error
    finally:
        node.destroy_node()


def test_a_burst_is_drained_in_one_callback_and_its_overflow_counted(context):
    """350 commands published while the node's executor is busy elsewhere
    (not spinning): its queue (keep last 100) keeps the newest 100. One
    callback takes all of them, the 250 the queue dropped are counted as lost
    from the publisher's sequence numbers, the newest one is applied, and
    received + lost = published."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from diagnostic_msgs.msg import DiagnosticStatus
    from soft_twin.msg import ActuationCommand
    node = _node(context, mode="quasi_static", diagnostics_rate_hz=0.01)
    sender = rclpy.create_node("burst_sender", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        pub = sender.create_publisher(ActuationCommand, "/soft_twin/actuation",
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        totals = node.stats.totals

        def spin_until(condition, timeout=10.0):
            end = time.monotonic() + timeout
            while not condition() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
            return condition()

        def send(k):
            msg = ActuationCommand(names=["tendon_y_pos"], values=[k / 1000.0])
            msg.header.stamp = sender.get_clock().now().to_msg()
            pub.publish(msg)
            return msg

        assert spin_until(lambda: pub.get_subscription_count() > 0)
        send(0)                                   # the publisher's first number: the stream is known
        assert spin_until(lambda: totals["commands_received"] == 1)
        batches = len(node.stats.input_batches)
        last = [send(k) for k in range(1, 351)][-1]
        assert spin_until(lambda: totals["commands_received"] + totals["commands_lost"] == 351), totals
        taken = node.stats.input_batches[batches:]
        assert totals["commands_lost"] == 250 and taken == [100], (totals, taken)
        assert totals["commands_applied"] == totals["commands_received"] == 101
        # the 99 older ones of the batch, and the first command unless a solve used it already
        assert 99 <= totals["commands_superseded"] <= 100
        assert node.twin.command_stamp.stamp == last.header.stamp
        assert node.twin.u[node.robot.model.actuator_names.index("tendon_y_pos")] == 0.35
        # the diagnostics say so
        out = []
        node._pub_diag.publish = out.append
        node._publish_diagnostics()
        status = out[0].status[0]
        values = {kv.key: kv.value for kv in status.values}
        assert values["commands_lost_total"] == "250" and values["command_queue_max"] == "100"
        assert status.level == DiagnosticStatus.WARN and "250 input(s) lost" in status.message
    finally:
        executor.shutdown()
        sender.destroy_node()
        node.destroy_node()


def test_command_latency_starts_at_the_command_stamp(context):
    """command_to_publish counts from the command's header.stamp (a command
    stamped 0.5 s ago shows >= 500 ms), command_in_node from the callback
    that took it; a zero stamp counts from the arrival."""
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from soft_twin.msg import ActuationCommand
    node = _node(context, mode="dynamic", diagnostics_rate_hz=0.01)
    sender = rclpy.create_node("stamp_sender", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        pub = sender.create_publisher(ActuationCommand, "/soft_twin/actuation", 10)
        s = node.stats

        def spin_until(condition, timeout=10.0):
            end = time.monotonic() + timeout
            while not condition() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
            return condition()

        assert spin_until(lambda: pub.get_subscription_count() > 0)
        old = ActuationCommand(names=["tendon_z_pos"], values=[0.2])
        old.header.stamp = (sender.get_clock().now() - Duration(seconds=0.5)).to_msg()
        pub.publish(old)
        assert spin_until(lambda: len(s.command_latencies) == 1)
        assert 0.5 <= s.command_latencies[0] < 5.0, s.command_latencies
        assert 0.0 <= s.node_latencies[0] < 0.5, s.node_latencies
        pub.publish(ActuationCommand(names=["tendon_z_pos"], values=[0.3]))     # stamp 0
        assert spin_until(lambda: len(s.command_latencies) == 2)
        assert 0.0 <= s.command_latencies[1] < 0.5, s.command_latencies
        diag = {}
        node._pub_diag.publish = lambda msg: diag.update((kv.key, kv.value) for kv in msg.status[0].values)
        node._publish_diagnostics()
        assert float(diag["command_to_publish_max_ms"]) >= 500.0
        assert float(diag["command_in_node_mean_ms"]) < 500.0
        assert diag["commands_lost_total"] == "0" and diag["commands_received_total"] == "2"
    finally:
        executor.shutdown()
        sender.destroy_node()
        node.destroy_node()
