"""End to end (issue 13): the IK service answers honestly (unreachable
targets: success false and the closest pose the tendons can hold; a robot
without actuators: no talk of actuation) and ~/plan_path plans a circle and
executes it: the commands appear on the configured output topic with the
planned values at the planned times, and the twin applies them. The node
runs in a second process; this process is a real rclpy client; every wait
is for a condition with a timeout."""
import math
import threading
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import Pose  # noqa: E402

from soft_twin.client import start_twin, stop_twin  # noqa: E402
from soft_twin.config import resolve_robot_file  # noqa: E402
from soft_twin.conversions import matrix_from_pose  # noqa: E402
from soft_twin.msg import ActuationCommand  # noqa: E402
from soft_twin.srv import InverseKinematics, PlanPath  # noqa: E402
from soft_twin_core.robot.model import load_model  # noqa: E402
from rod_statics import solve_statics

pytestmark = pytest.mark.ros

START_TIMEOUT = 120.0
OUTPUT = "/plan_e2e/commands"


@pytest.fixture(scope="module")
def model():
    return load_model(resolve_robot_file(""))


def _start(node_name, ros_args, tmp_path_factory):
    return start_twin(node_name, ros_args, tmp_path_factory.mktemp(node_name) / "node.log", timeout=START_TIMEOUT)


def _stop(proc, client):
    stop_twin(proc, client)


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    proc, client = _start("twin_plan", ["-p", f"plan_output_topic:={OUTPUT}"], tmp_path_factory)
    yield client, proc
    _stop(proc, client)


def _ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _pose(p):
    m = Pose()
    m.position.x, m.position.y, m.position.z = (float(v) for v in p)
    return m


def test_ik_unreachable_target_gives_the_closest_holdable_pose(twin, model):
    c, _ = twin
    target = (0.3, 0.1, -0.2)             # off the tendons' reachable surface (~5 cm)
    resp = c.call("inverse_kinematics", InverseKinematics.Request(target=_pose(target), position_only=True))
    assert not resp.success
    assert "closest pose" in resp.message and "best" not in resp.message
    assert resp.actuation_found and min(resp.actuator_values) >= 0.0
    assert resp.position_error > 0.01
    # the answer is a pose the tendons actually hold: the statics of those tensions
    q = model.q_from_strains(np.reshape(resp.strains, (-1, 6)))
    eq = solve_statics(model, list(resp.actuator_values), q_init=q)
    np.testing.assert_allclose(eq.tip_pose, matrix_from_pose(resp.achieved), atol=1e-7)
    a = resp.achieved.position
    assert math.dist((a.x, a.y, a.z), target) == pytest.approx(resp.position_error, rel=1e-9)
    # a reachable one: success, within the tolerance; timing reported
    p_t = solve_statics(model, [0.0, 1.0, 0.6, 0.0]).tip_pose[:3, 3]
    times = []
    for _ in range(5):
        t = time.monotonic()
        resp = c.call("inverse_kinematics", InverseKinematics.Request(target=_pose(p_t), position_only=True))
        times.append(time.monotonic() - t)
        assert resp.success, resp.message
        assert resp.position_error <= 1e-6
    print(f"IK round trip through the node: median {1e3 * np.median(times):.1f} ms")


def test_plan_path_executes_on_the_output_topic(twin, model):
    c, _ = twin
    got, cond = [], threading.Condition()

    def on_cmd(msg):
        with cond:
            got.append((c.node.get_clock().now().nanoseconds, msg))
            cond.notify_all()
    # kept until the client closes (destroying it while the client's executor spins can stall that executor)
    sub = c.node.create_subscription(ActuationCommand, OUTPUT, on_cmd, 100)
    # the node makes its output publisher at start: wait for the match
    assert c.wait_until(lambda: sub.get_publisher_count() > 0, 20.0), f"no publisher on {OUTPUT}"
    # plan once without executing: the answer alone
    path = {"type": "circle", "center": [0.38, 0.0, -0.22], "radius": 0.03, "normal": [1, 0, 0],
            "duration": 1.0, "sample_period": 0.1}
    req = PlanPath.Request(path_yaml=yaml.safe_dump(path), position_weights=[0.0, 1.0, 1.0])
    resp = c.call("plan_path", req)
    assert resp.success, resp.message
    assert not resp.executing and len(resp.times) == 11
    names = list(resp.actuator_names)
    U = np.reshape(resp.values, (len(resp.times), len(names)))
    assert np.all(U >= 0) and max(resp.errors) <= 1e-6 and all(resp.reached)
    # execute
    req.execute = True
    t_call = time.monotonic()
    resp = c.call("plan_path", req)
    assert resp.success and resp.executing, resp.message
    U = np.reshape(resp.values, (len(resp.times), len(names)))
    n = len(resp.times)
    with cond:
        ok = cond.wait_for(lambda: len(got) >= n, timeout=20.0)
    assert ok, f"{len(got)} of {n} commands arrived on {OUTPUT}"
    assert len(got) == n
    start = _ns(resp.start_stamp)
    for k, (_, msg) in enumerate(got):
        assert list(msg.names) == names
        assert list(msg.values) == list(U[k])                      # the planned values, exactly
        assert _ns(msg.header.stamp) - start == pytest.approx(resp.times[k] * 1e9, abs=1.0)
    # published at their times: never before its stamp (the node and this process share the
    # system clock), in order. How promptly is the machine's, not the node's, so it is printed, not
    # asserted (alone the maximum is 40-50 ms; stalls of 0.3 and 0.8 s, caught up by the next
    # commands, were seen in full-suite runs on the loaded 2-CPU machine)
    latency = np.array([(a - _ns(m.header.stamp)) * 1e-9 for a, m in got])
    assert latency.min() >= -1e-3, latency
    assert all(a <= b for (a, _), (b, _) in zip(got[:-1], got[1:]))
    print(f"plan execution: command latency median {1e3 * np.median(latency):.1f} ms, "
          f"max {1e3 * latency.max():.1f} ms")
    assert (time.monotonic() - t_call) >= resp.times[-1]
    # the twin applied the same commands: its state reflects the last one
    last = got[-1][1].header.stamp
    assert c.wait_until(lambda: c.applied(last), 10.0), "the twin never applied the last command"
    # and follows: after settling, its tip is at the plan's last predicted tip (y, z)
    tip_last = np.reshape(resp.predicted_tip, (-1, 3))[-1]

    def settled():
        p = c.tip_pose.pose.position
        return math.hypot(p.y - tip_last[1], p.z - tip_last[2]) < 2e-3
    assert c.wait_until(settled, 15.0)


def test_cancel_plan_stops_the_execution(twin):
    """~/cancel_plan (std_srvs/Trigger) stops a running execution: the
    commands published before the answer are all there is (checked once a
    later plan's first command arrived: one publisher, reliable, in order),
    fewer than planned; a second cancel says nothing is executing."""
    from std_srvs.srv import Trigger
    c, _ = twin
    got, cond = [], threading.Condition()

    def on_cmd(msg):
        with cond:
            got.append(msg)
            cond.notify_all()
    sub = c.node.create_subscription(ActuationCommand, OUTPUT, on_cmd, 100)
    assert c.wait_until(lambda: sub.get_publisher_count() > 0, 20.0), f"no publisher on {OUTPUT}"
    assert c.wait_until(lambda: c.clients["cancel_plan"].service_is_ready(), 20.0)
    path = {"type": "circle", "center": [0.38, 0.0, -0.22], "radius": 0.03, "normal": [1, 0, 0],
            "duration": 4.0, "sample_period": 0.1}
    resp = c.call("plan_path", PlanPath.Request(path_yaml=yaml.safe_dump(path), position_weights=[0.0, 1.0, 1.0],
                                                execute=True))
    assert resp.success and resp.executing, resp.message
    n_planned, start = len(resp.times), _ns(resp.start_stamp)
    with cond:
        assert cond.wait_for(lambda: len(got) >= 3, timeout=20.0), f"{len(got)} commands arrived"
    cancel = c.call("cancel_plan", Trigger.Request())
    assert cancel.success, cancel.message
    n_sent = int(cancel.message.split("cancelled after ")[1].split(" of ")[0])
    assert f"of {n_planned} commands" in cancel.message
    assert 3 <= n_sent < n_planned
    again = c.call("cancel_plan", Trigger.Request())
    assert not again.success and "no plan is executing" in again.message
    # a marker: a short plan executed now; its first command comes after every earlier one
    line = {"type": "line", "start": [0.38, 0.0, -0.25], "end": [0.38, 0.0, -0.25], "duration": 0.2,
            "sample_period": 0.1}
    resp2 = c.call("plan_path", PlanPath.Request(path_yaml=yaml.safe_dump(line), position_weights=[0.0, 1.0, 1.0],
                                                 execute=True))
    assert resp2.executing, resp2.message
    start2 = _ns(resp2.start_stamp)
    with cond:
        assert cond.wait_for(lambda: any(_ns(m.header.stamp) >= start2 for m in got), timeout=20.0)
        first = [m for m in got if start <= _ns(m.header.stamp) < start2]
    assert len(first) == n_sent, (len(first), n_sent)
    stamps = [_ns(m.header.stamp) - start for m in first]
    assert stamps == pytest.approx([t * 1e9 for t in resp.times[:n_sent]], abs=1.0)
    with cond:
        assert cond.wait_for(lambda: sum(_ns(m.header.stamp) >= start2 for m in got) >= 3, timeout=20.0)


def test_plan_path_rejects_bad_requests(twin):
    c, _ = twin
    for req, word in [(PlanPath.Request(path_yaml="{type: spiral}"), "path.type"),
                      (PlanPath.Request(path_yaml="[1, 2"), "invalid YAML"),
                      (PlanPath.Request(path_yaml="{type: line, start: [0,0,0], end: [0,0,1], duration: 1}",
                                        max_rate=-1.0), "max_rate"),
                      (PlanPath.Request(path_yaml="{type: line, start: [0,0,0], end: [0,0,1], duration: 1}",
                                        position_weights=[1.0, 1.0]), "position_weights")]:
        resp = c.call("plan_path", req)
        assert not resp.success and word in resp.message, resp.message


def test_ik_without_actuators_speaks_of_shapes_only(tmp_path_factory):
    d = yaml.safe_load(resolve_robot_file("").read_text())
    d.pop("actuators")
    f = tmp_path_factory.mktemp("robots") / "no_actuators.yaml"
    f.write_text(yaml.safe_dump(d))
    proc, c = _start("twin_noact", ["-p", f"robot_description_file:={f}", "-p", "mode:=quasi_static"],
                     tmp_path_factory)
    try:
        m = load_model(str(f))
        target = solve_statics(m, loads=None).tip_pose.copy()
        target[:3, 3] += [0.0, 0.02, 0.03]
        resp = c.call("inverse_kinematics", InverseKinematics.Request(target=_pose(target[:3, 3]),
                                                                       position_only=True))
        assert resp.success, resp.message
        assert "best" not in resp.message and "fit" not in resp.message
        assert not resp.actuation_found and list(resp.actuator_values) == []
        resp = c.call("plan_path", PlanPath.Request(
            path_yaml="{type: line, start: [0.3, 0, -0.2], end: [0.3, 0.1, -0.2], duration: 1}"))
        assert not resp.success and "no actuators" in resp.message
    finally:
        _stop(proc, c)
