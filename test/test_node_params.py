"""The node in this process (private rclpy Context): parameters validated at
start and on change; a rejected change leaves the running twin untouched."""
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
