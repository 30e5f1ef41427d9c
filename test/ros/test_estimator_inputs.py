"""The estimator's input accounting (issue 25, item 6): readings arriving
faster than the filter steps are merged and counted, bad stamps rejected by
reason, and every message counted as received or lost.

The ledger alone (no ROS), then the node in a second process flooded with
1 kHz pose readings (a 100 Hz filter) plus readings stamped 1970, in the
future and out of order, over real rclpy: sent = received + lost, and
accepted = used + merged + pending. Every wait is for a condition with a
timeout."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from soft_twin.readings import InputLedger, accept_reading, merge_readings


def _stamp(ns):
    return SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


# ---------------------------------------------------------------------------
# the ledger, ROS-free
# ---------------------------------------------------------------------------
def test_merged_pose_is_the_chordal_mean():
    """The merged rotation equals scipy's Rotation.mean (the chordal L2
    mean, computed by its quaternion eigenvector method), the position the
    plain mean; a single reading is returned unchanged."""
    rng = np.random.default_rng(3)
    R0 = Rotation.from_rotvec([0.3, -0.2, 0.9])
    rots = R0 * Rotation.from_rotvec(rng.normal(0.0, 0.05, (7, 3)))
    poses = []
    for R, p in zip(rots, rng.normal(0.0, 1e-3, (7, 3)) + [0.1, 0.2, 0.3]):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.as_matrix(), p
        poses.append(T)
    m = merge_readings(poses)
    np.testing.assert_allclose(m[:3, :3], Rotation.mean(rots).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], np.mean([T[:3, 3] for T in poses], axis=0), atol=1e-15)
    np.testing.assert_allclose(m[3], [0, 0, 0, 1])
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    assert merge_readings(poses[:1]) is poses[0]
    np.testing.assert_allclose(merge_readings([np.array([1.0, 2.0]), np.array([3.0, 6.0])]), [2.0, 4.0])


def test_ledger_counts_every_reading_once():
    now = 1_800_000_000 * 10**9
    led = InputLedger(max_age_s=1.0)
    rejected = []

    def reject(kind, text):
        rejected.append(kind)

    def vector(value):                  # as sensors.measurement_vector: a ValueError for NaN
        if not np.isfinite(value):
            raise ValueError("measurement contains NaN or inf")
        return np.array([value])

    def feed(name, value, t):
        accept_reading(led, reject, name, lambda: vector(value), _stamp(t), now)

    for k in range(5):
        feed("a", k, now - 10_000_000 + k)             # five in one step: one used, four merged
    feed("b", 1.0, 0)                                   # unstamped: taken at arrival
    feed("a", 9.0, now - 20_000_000)                    # older than a's last one
    feed("a", 9.0, 1)                                   # stamped 1970
    feed("a", 9.0, now + 5 * 10**9)                     # 5 s in the future
    feed("b", float("nan"), now)                        # not finite
    assert rejected == ["out_of_order", "stale_stamp", "future_stamp", "non_finite"]
    d = led.diagnostics()
    assert (d["readings_accepted"], d["readings_pending"]) == (6, 6)
    out = led.take()
    assert out["a"] == pytest.approx([2.0]) and out["b"] == pytest.approx([1.0])
    d = led.diagnostics()
    assert (d["readings_used"], d["readings_merged"], d["readings_pending"]) == (2, 4, 0)
    assert d["readings_accepted"] == d["readings_used"] + d["readings_merged"] + d["readings_pending"]
    led.reset()
    assert led.diagnostics()["readings_accepted"] == 0 and led.take() == {}
    feed("a", 1.0, now - 20_000_000)                    # after a reset the stamps start afresh
    assert led.diagnostics()["readings_accepted"] == 1


def test_sequence_gaps_are_counted_per_topic():
    led = InputLedger()
    for seq in (1, 2, 3, 7, 8):                        # 4, 5, 6 lost
        led.message("/est/measurements/pose", {"publication_sequence_number": seq}, 1)
    led.message("/est/measurements/poses", {"publication_sequence_number": 1}, 1)
    d = led.diagnostics()
    assert (d["est_measurements_pose_received"], d["est_measurements_pose_lost"]) == (5, 3)
    assert (d["est_measurements_poses_received"], d["est_measurements_poses_lost"]) == (1, 0)


# ---------------------------------------------------------------------------
# the node, flooded, over real rclpy
# ---------------------------------------------------------------------------
@pytest.mark.ros
@pytest.mark.quiet                     # a 1 kHz flood against a 100 Hz filter: rates
def test_estimator_flood_is_accounted_for(tmp_path):
    rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from soft_twin.client import NodeProcess
    from soft_twin.conversions import pose_msg
    from soft_twin_core.reference import kinematics as kin
    from soft_twin_core.robot.model import load_model

    sensors = [{"name": "tip", "type": "pose", "s": 0.40, "sigma_position": 1.0e-3, "sigma_rotation": 0.01}]
    (tmp_path / "sensors.yaml").write_text(yaml.safe_dump({"sensors": sensors}))
    proc = NodeProcess(["-p", "robot_description_file:=tracked_arm", "-p", f"sensors_file:={tmp_path / 'sensors.yaml'}",
                        "-p", "rate_hz:=100.0"], "est_flood", tmp_path / "node.log", module="soft_twin.estimator")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("est_flood_client", context=ctx)
    pub = node.create_publisher(PoseStamped, "/est_flood/measurements/pose", 1000)
    cond, diag = threading.Condition(), {}

    def on_diag(msg):
        for s in msg.status:
            if s.name == "soft_twin_estimator":
                with cond:
                    diag.clear()
                    diag.update({kv.key: kv.value for kv in s.values})
                    cond.notify_all()
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    model = load_model("tracked_arm")
    T = kin.poses(model, np.zeros(model.n_dof), [0.40])[0]        # the straight arm's sensor pose

    def send(stamp_ns):
        msg = PoseStamped()
        msg.header.frame_id = "tip"
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_ns // 10**9, stamp_ns % 10**9
        msg.pose = pose_msg(T)
        pub.publish(msg)

    try:
        with cond:
            assert cond.wait_for(lambda: pub.get_subscription_count() > 0 and "readings_used" in diag, 120.0), \
                proc.output()[-3000:]
        now = lambda: node.get_clock().now().nanoseconds  # noqa: E731
        send(now())                                    # the node learns this publisher's numbers
        with cond:
            assert cond.wait_for(lambda: diag.get("est_flood_measurements_pose_received") == "1", 20.0), diag
        n, t0 = 0, time.monotonic()
        next_t = t0
        while n < 2000:                                 # 1 kHz for 2 s
            send(now())
            n += 1
            next_t += 0.001
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)                       # pacing the flood, not waiting for ROS
        for _ in range(3):
            send(1_000_000_000)                         # stamped 1970
            send(now() + 10 * 10**9)                    # 10 s in the future
        t = now()
        send(t)
        send(t - 5_000_000)                             # 5 ms before the one just sent
        sent = 1 + n + 6 + 2

        def settled():
            return (int(diag.get("est_flood_measurements_pose_received", 0))
                    + int(diag.get("est_flood_measurements_pose_lost", 0)) == sent
                    and diag.get("readings_pending") == "0")
        with cond:
            assert cond.wait_for(settled, 30.0), diag
            d = dict(diag)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        proc.stop()
    received = int(d["est_flood_measurements_pose_received"])
    rejected = {k: int(d[f"rejected_{k}"]) for k in ("stale_stamp", "future_stamp", "out_of_order")}
    accepted, used, merged = (int(d[k]) for k in ("readings_accepted", "readings_used", "readings_merged"))
    print(f"\nestimator flood: sent {sent}, received {received}, lost {d['est_flood_measurements_pose_lost']}, "
          f"accepted {accepted} = used {used} + merged {merged}; rejected {rejected}")
    assert rejected == {"stale_stamp": 3, "future_stamp": 3, "out_of_order": 1}, d
    assert int(d["measurements_rejected"]) >= 7, d
    assert accepted == used + merged and accepted + 7 == received, d
    # a 100 Hz filter fed at 1 kHz: most readings are merged, each step uses one
    assert merged > used > 0 and used <= int(d["predictions"]), d


# ---------------------------------------------------------------------------
# the node's force_directions parameter (issue 29), in this process
# ---------------------------------------------------------------------------
def test_the_estimator_takes_its_force_directions_parameter(tmp_path):
    rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from rclpy.parameter import Parameter
    from soft_twin.estimator import EstimatorNode
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": [
        {"name": "em", "type": "pose", "s": 0.4, "sigma_position": 1e-3, "sigma_rotation": 0.01}]}))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)

    def node(directions):
        return EstimatorNode("est_dirs", context=ctx, parameter_overrides=[
            Parameter("robot_description_file", value="tracked_arm"),
            Parameter("sensors_file", value=str(tmp_path / "s.yaml")),
            Parameter("wrench", value="force"), Parameter("force_directions", value=directions)])
    try:
        n = node("0,1,0; 0,0,2")
        try:
            assert n.ekf.k == 2 and np.allclose(n.ekf.S[:3].T, [[0, 1, 0], [0, 0, 1]])
        finally:
            n.destroy_node()
        with pytest.raises(ValueError, match="force_directions: expected 'x,y,z'"):
            node("0,1")
    finally:
        rclpy.shutdown(context=ctx)
