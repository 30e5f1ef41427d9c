"""Validate once, at the door, and a short path (issue 26): an actuation
command goes from the node's subscription callback to the compiled kernel
through at most 12 Python calls, with one validation (the door's
parse_actuation), for a classic rod and a tree robot, in dynamic and
quasi-static mode. Measured with sys.setprofile on a node in this process
(real rclpy, callbacks invoked directly); the kernels are wrapped so that
their entry shows as a Python frame."""

import sys

import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from rclpy.parameter import Parameter  # noqa: E402

pytestmark = pytest.mark.ros

ENTRIES = ("_on_actuation", "_on_step_tick")
VALIDATORS = {"parse_actuation", "actuation_vector", "check_actuator_input", "make_inputs", "joint_vector",
              "validate_loads", "parse_tip_wrench", "parse_joint_command", "check_joint_position"}
# (check_q, a shape assertion of the algorithms, is not a validation of the command)


def _chain(frame):
    """The functions from the nearest entry callback down to ``frame``."""
    out = []
    while frame is not None:
        out.append(f"{frame.f_code.co_filename.rsplit('/', 1)[-1]}:{frame.f_code.co_name}")
        if frame.f_code.co_name in ENTRIES:
            return out[::-1]
        frame = frame.f_back
    return None


def _trace(fn, stops):
    """(chain to the first call of a function in ``stops``, top-level validator calls) while fn runs."""
    found, checks = {}, []

    def prof(frame, event, arg):
        if event != "call":
            return
        name = frame.f_code.co_name
        if name in stops and name not in found:
            found[name] = _chain(frame)
        if name in VALIDATORS:
            ch = _chain(frame)
            if ch is not None and not any(c.split(":")[1] in VALIDATORS for c in ch[:-1]):
                checks.append(" > ".join(ch))
    sys.setprofile(prof)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return found, checks


@pytest.fixture
def kernels(monkeypatch):
    """The compiled entry points wrapped in a Python function named kernel_entry."""
    from soft_twin_core.engine import integrators
    from soft_twin_core.solve import constrained, equilibrium

    def wrap(module, name):
        real = getattr(module, name)

        def kernel_entry(*a, **k):
            return real(*a, **k)
        monkeypatch.setattr(module, name, kernel_entry)
    wrap(integrators, "run_steps")
    wrap(constrained, "residual_pass")
    wrap(constrained, "contact_step")           # (the compiled step of position-controlled joints and contacts)
    wrap(equilibrium, "static_newton")          # (the name equilibrium calls it by)


@pytest.mark.parametrize("robot", ["tendon_arm", "pan_tilt_arm"])
@pytest.mark.parametrize("mode", ["dynamic", "quasi_static"])
def test_actuation_reaches_the_kernel_in_12_calls_with_one_check(kernels, robot, mode):
    from soft_twin.msg import ActuationCommand
    from soft_twin.node import SoftTwinNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = SoftTwinNode(context=ctx, parameter_overrides=[Parameter("robot_description_file", value=robot),
                                                          Parameter("mode", value=mode),
                                                          Parameter("step_on_command", value=False)])
    try:
        msg = ActuationCommand()
        msg.names, msg.values = [node.twin.model.actuator_names[0]], [1.0]
        msg.header.stamp = node.get_clock().now().to_msg()
        node._anchor = None                                   # a step is due at the tick below
        got, checks_in = _trace(lambda: node._on_actuation(msg), {"parse_actuation", "set_actuation"})
        if mode == "quasi_static":
            node.twin._dirty = True
        node._anchor = -1.0
        ran, checks_step = _trace(node._on_step_tick, {"kernel_entry"})
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    door, store, kernel = got.get("parse_actuation"), got.get("set_actuation"), ran.get("kernel_entry")
    assert door and store and kernel, (got, ran)
    path = list(dict.fromkeys(door + store + kernel[:-1]))      # the calls on the way, the wrapper left out
    assert len(path) <= 12, path
    assert checks_in == [" > ".join(door)] and checks_step == [], (checks_in, checks_step)
