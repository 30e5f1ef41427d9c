"""The node in this process (private rclpy Context): parameters validated at
start and on change; a rejected change leaves the running twin untouched."""
import time

import numpy as np

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


# ============================================================================
# issue 15: parameters (item 7), huge inputs (item 1), log lengths (item 8)
# ============================================================================

def _robot_text(limits=None):
    """The default robot's description as inline YAML, its actuator limits
    replaced by ``limits`` ({name: limit}; none declared otherwise)."""
    import yaml
    from soft_twin.config import resolve_robot_file
    d = yaml.safe_load(resolve_robot_file("").read_text())
    for a in d["actuators"]:
        a.pop("limit", None)
        if limits and a["name"] in limits:
            a["limit"] = limits[a["name"]]
    return yaml.safe_dump(d)


def _diagnostics(node):
    out = []
    node._pub_diag.publish = out.append
    node._publish_diagnostics()
    del node._pub_diag.publish
    status = out[0].status[0]
    return status, {kv.key: kv.value for kv in status.values}


@pytest.mark.parametrize("name", ["unknown_param", "step_rate", "Mode"])
def test_an_unknown_parameter_at_start_is_an_error_naming_it(context, name):
    """A misspelt -p name:=value used to be ignored silently (a lab run with
    the default instead); now the node refuses to start (main: exit 2)."""
    with pytest.raises(ConfigError, match="unknown parameter") as exc:
        _node(context, **{name: 1})
    assert repr(name) in str(exc.value)
    if name == "step_rate":
        assert "'step_rate_hz'?" in str(exc.value)        # the nearest name is suggested


def test_an_integer_for_a_float_parameter_keeps_its_type(context):
    node = _node(context, step_rate_hz=100, max_tip_force_n=500)
    try:
        for name, value in (("step_rate_hz", 100.0), ("max_tip_force_n", 500.0)):
            p = node.get_parameter(name)
            assert p.type_ == Parameter.Type.DOUBLE and p.value == value and isinstance(p.value, float)
        res = node.set_parameters([Parameter("step_rate_hz", value=150)])[0]
        assert res.successful, res.reason
        p = node.get_parameter("step_rate_hz")
        assert p.type_ == Parameter.Type.DOUBLE and p.value == 150.0
        assert node.cfg.step_rate_hz == 150.0 and node.twin.settings.dt == pytest.approx(1 / 150)
        # integers stay integers, and a float is no integer
        assert node.set_parameters([Parameter("max_catchup_steps", value=3)])[0].successful
        assert node.get_parameter("max_catchup_steps").type_ == Parameter.Type.INTEGER
        res = node.set_parameters([Parameter("max_catchup_steps", value=3.0)])[0]
        assert not res.successful and "integer" in res.reason
    finally:
        node.destroy_node()


def test_refused_parameter_changes_are_counted_and_named(context):
    from rclpy.exceptions import ParameterNotDeclaredException
    node = _node(context, mode="quasi_static")
    try:
        status, d = _diagnostics(node)
        assert d["rejected_parameter_changes_total"] == "0" and d["last_parameter_rejection"] == ""
        assert not node.set_parameters([Parameter("step_rate_hz", value=-1.0)])[0].successful
        assert not node.set_parameters_atomically([Parameter("mode", value="fast")]).successful
        assert not node.set_parameters([Parameter("actuator_names", value=["x"])])[0].successful
        # an undeclared name: a reason naming it (rclpy's own said "undeclared parameter(s): []")
        with pytest.raises(ParameterNotDeclaredException) as exc:
            node.set_parameters([Parameter("step_rate", value=100.0)])
        assert "'step_rate'" in str(exc.value) and "step_rate_hz" in str(exc.value)
        with pytest.raises(ParameterNotDeclaredException) as exc:
            node.set_parameters_atomically([Parameter("mode", value="dynamic"), Parameter("modes", value="x")])
        assert "'modes'" in str(exc.value) and node.cfg.mode == "quasi_static"
        assert node.set_parameters([Parameter("marker_rate_hz", value=5.0)])[0].successful   # not counted
        status, d = _diagnostics(node)
        assert d["rejected_parameter_changes_total"] == "5", d
        assert "modes" in d["last_parameter_rejection"]
    finally:
        node.destroy_node()


def _take(node, msg):
    """Hand one message to the node's input callback, as the executor would."""
    from soft_twin.msg import ActuationCommand
    if isinstance(msg, ActuationCommand):
        node._on_actuation(msg, None)
    else:
        node._on_tip_wrench(msg, None)


def _command(names, values):
    from soft_twin.msg import ActuationCommand
    msg = ActuationCommand(names=list(names), values=[float(v) for v in values])
    msg.header.stamp.sec = 1
    return msg


def _wrench(fz, frame="base_link"):
    from geometry_msgs.msg import WrenchStamped
    msg = WrenchStamped()
    msg.header.frame_id = frame
    msg.wrench.force.z = float(fz)
    return msg


def test_inputs_beyond_declared_limits_are_rejected_at_the_door(context):
    node = _node(context, mode="dynamic", robot_description=_robot_text({"tendon_y_pos": 40.0}),
                 max_tip_torque_nm=1.0)
    try:
        s = node.stats
        for msg, kind in ((_command(["tendon_y_pos"], [40.5]), "actuation"),
                          (_command(["tendon_y_pos"], [1e300]), "actuation"),
                          (_wrench(1.0e6), "wrench"), (_wrench(-1.0e300), "wrench")):
            _take(node, msg)
        assert s.rejected_by_reason["over_limit"] == 4 and s.totals["rejected_actuation"] == 2
        assert s.totals["rejected_wrench"] == 2 and not np.any(node.twin.u) and not np.any(node.twin.tip_wrench)
        _take(node, _command(["tendon_y_pos"], [40.0]))               # at the limit: fine
        assert node.twin.u[0] == 40.0 and s.totals["commands_applied"] == 1
        status, d = _diagnostics(node)
        assert d["rejected_over_limit_total"] == "4" and "over_limit" in d["last_rejection"]
        # the services refuse the same
        from soft_twin.srv import StaticsQuery
        req = StaticsQuery.Request(actuator_names=["tendon_y_pos"], actuator_values=[50.0])
        resp = node._srv_statics(req, StaticsQuery.Response())
        assert not resp.success and "over_limit" in resp.message
        req = StaticsQuery.Request()
        req.tip_wrench.torque.x = 2.0
        resp = node._srv_statics(req, StaticsQuery.Response())
        assert not resp.success and "max_tip_torque_nm" in resp.message
    finally:
        node.destroy_node()


@pytest.mark.parametrize("magnitude", [1e6, 1e100, 1e300])
def test_a_failing_step_drops_its_input_and_publishing_goes_on(context, magnitude):
    """Dynamic mode, a robot declaring no limits, a huge but finite tension
    (and a tip wrench allowed through by a raised max_tip_force_n): the
    step fails once, within a step period, the input is dropped (counted as
    rejected, solver_failed; not as applied), the last good state is
    published for that tick, and the next tick steps on with the last good
    inputs. (It was: every tick failed with 10 Newton iterations, 64 Hz, the
    command counted as applied; 1e300: 0 Hz.)"""
    node = _node(context, mode="dynamic", robot_description=_robot_text(), max_tip_force_n=1e301,
                 step_on_command=False)       # the ticks are taken here, one by one
    published = []
    node._pub_strains.publish = published.append
    node.listened = lambda pub: True       # no subscriber here: count what each tick publishes

    def take(msg):
        node._anchor = None           # no schedule: the input callback takes no step itself
        _take(node, msg)

    def tick():
        """One timer tick with exactly one step due."""
        node._anchor = time.monotonic() - node.cfg.dt * (node._steps_done + 1)
        node._step_dynamic()
    try:
        s, twin = node.stats, node.twin
        take(_command(["tendon_z_pos"], [0.2]))
        tick()
        good_stamp, t_good = twin.command_stamp, twin.state.t
        assert s.totals["commands_applied"] == 1 and t_good > 0 and len(published) == 1
        costs = []
        for msg, kind in ((_command(["tendon_y_pos"], [magnitude]), "actuation"), (_wrench(-magnitude), "wrench")):
            n_pub, t0 = len(published), twin.state.t
            take(msg)
            assert len(published) == n_pub
            tick()
            assert len(published) == n_pub + 1, "the tick published nothing"
            assert twin.state.t == t0 and s.failures >= 1
            costs.append(s.compute_times[-1])
            # dropped: the inputs are those of the last good state again
            assert twin.command_stamp is good_stamp and twin.u[0] == 0.0 and not np.any(twin.tip_wrench)
            # the next tick steps on (the failed step is caught up)
            tick()
            assert twin.state.t > t0 and len(published) == n_pub + 2
        # (the bound of one step period is checked in test_node_units without this test's overhead)
        assert min(costs) <= 4 * node.cfg.dt, costs
        totals = s.totals
        assert totals["commands_received"] == 2 and totals["commands_applied"] == 1
        assert totals["wrenches_received"] == 1 and totals["wrenches_applied"] == 0
        assert totals["rejected_actuation"] == 1 and totals["rejected_wrench"] == 1
        assert s.rejected_by_reason["solver_failed"] == 2 and totals["solver_failures"] == 2
        assert totals["internal_errors"] == 0
        status, d = _diagnostics(node)
        assert d["rejected_solver_failed_total"] == "2" and "solver_failed" in d["last_rejection"]
        assert d["solver_consecutive_failures"] == "0"
        assert status.level == b"\x01" or status.level == 1       # WARN: dropped, running on
        assert "input dropped" in status.message
    finally:
        node.destroy_node()


def test_a_command_with_10000_names_gives_bounded_logs_and_diagnostics(context, capfd):
    """It produced an 89,077-character log line, repeated in last_rejection
    every second."""
    node = _node(context, mode="quasi_static")
    try:
        capfd.readouterr()
        names = [f"tendon_{k}" for k in range(10000)]
        _take(node, _command(names, [0.1] * 10000))                  # unknown names
        _take(node, _command(["tendon_y_pos"] * 10000, [0.1] * 10000))   # repeated names
        _take(node, _wrench(0.0, frame="f" * 100000))                 # a 100 kB frame id
        assert node.set_parameters([Parameter("base_frame", value="b " * 50000)])[0].successful is False
        with pytest.raises(Exception):
            node.set_parameters([Parameter("x" * 100000, value=1.0)])
        status, d = _diagnostics(node)
        err = capfd.readouterr().err
        assert err.count("rejected") >= 2, err[:2000]       # the log is throttled: 1 a second
        longest = max(len(line) for line in err.splitlines())
        assert longest <= 1000, longest
        assert node.stats.totals["rejected_actuation"] == 2 and node.stats.totals["rejected_wrench"] == 1
        assert max(len(v) for v in d.values()) <= 600, {k: len(v) for k, v in d.items()}
        assert len(status.message) <= 600
        assert "more" in d["last_rejection"] and "more" in d["last_parameter_rejection"]
    finally:
        node.destroy_node()
