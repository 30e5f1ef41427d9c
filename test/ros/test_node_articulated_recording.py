"""MCAP recording of the node running an articulated robot (issue 12), end
to end: the node (pan_tilt_arm) in a second process, this process sets
``record_file`` through the parameter service, drives the joints with
real rclpy publishers, and reads the file back with the mcap libraries:
every topic (joint states, member backbones, /tf, the joint commands),
counts equal to the file's count record and to what was sent, stamps
increasing; figures drawn from the recording equal those drawn from the
messages received live. Every wait is for a condition with a timeout."""
import threading
from collections import defaultdict

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import PoseArray  # noqa: E402
from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from soft_twin.client import TwinClient, stamp_key, start_twin, stop_twin  # noqa: E402
from soft_twin_core.robot.mechanism import load_mechanism  # noqa: E402
from soft_twin_core.robot.model import find_file  # noqa: E402

pytestmark = pytest.mark.ros
NODE = "twin_art_rec"


def _set_string(client, name, value, timeout=20.0):
    cli = client.node.create_client(SetParameters, f"/{NODE}/set_parameters")
    assert cli.wait_for_service(timeout_sec=timeout)
    req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=value))])
    fut = cli.call_async(req)
    done = threading.Event()
    fut.add_done_callback(lambda _: done.set())
    assert done.wait(timeout), "set_parameters: no answer"
    return fut.result().results[0]


def _read_mcap(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    msgs = defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            msgs[channel.topic].append((schema.name, message, decoded))
    return header, meta, msgs


def client_topics_unsubscribed(msgs, ns):
    """The wrench and marker topics were recorded more than once (they come
    at their own rates, not with every state)."""
    return all(len(msgs[f"{ns}/{t}"]) > 1 for t in ("tip_wrench", "base_wrench", "markers", "joint_wrenches/pan"))


def test_recording_of_an_articulated_twin(tmp_path):
    from PIL import Image
    from soft_twin_core import cli
    from soft_twin_core.files.recording import articulated_run_from_messages, read_node_recording
    from soft_twin_core.viz.plots import _save, shapes_figure
    from soft_twin_core.viz.plots import plot_frames, plot_joint_states
    from soft_twin_core.viz.scene import run_snapshots
    # no subscriber of the wrenches or markers: the recording holds them all the same (issue 25, item 4)
    proc, client = start_twin(NODE, ["-p", "robot_description_file:=pan_tilt_arm", "-p", "tf_rate_hz:=50.0"],
                              tmp_path / "node.log", TwinClient.STATE_TOPICS + ("joint_states",), 120.0,
                              ready=lambda c: c.pub_joints.get_subscription_count() > 0)
    live = defaultdict(list)
    lock = threading.Lock()

    def keep(topic):
        def cb(msg):
            with lock:
                live[topic].append(msg)
        return cb
    ns = f"/{NODE}"
    client.node.create_subscription(TFMessage, "/tf", keep("/tf"), 1000)
    client.node.create_subscription(PoseArray, f"{ns}/backbones/arm", keep(f"{ns}/backbones/arm"), 1000)
    try:
        path = tmp_path / "run.mcap"
        res = _set_string(client, "record_file", str(path))
        assert res.successful, res.reason
        # drive the joints while recording: 12 pan/tilt commands, one actuation
        stamps = []
        for k in range(12):
            stamps.append(client.send_joint_command(["pan", "tilt"], positions=[0.05 * k, -0.03 * k]))
            client.wait_until(lambda: False, 0.05)
        sent = [stamp_key(s) for s in stamps]
        client.send_actuation(["tendon_z_pos"], [1.5])
        assert client.wait_until(lambda: client.state_after(stamps[-1]) is not None, 30.0), "commands not applied"
        n = len(client.history["joint_states"])
        assert client.wait_until(lambda: len(client.history["joint_states"]) > n + 20, 30.0)
        with client._cond, lock:
            live[f"{ns}/joint_states"] = [m for _, m in client.history["joint_states"]]
            live_copy = {k: list(v) for k, v in live.items()}
        res = _set_string(client, "record_file", "")
        assert res.successful, res.reason
    finally:
        stop_twin(proc, client)

    header, meta, msgs = _read_mcap(path)
    assert header.profile == "ros2"
    expected = {f"{ns}/joint_states": "sensor_msgs/msg/JointState", f"{ns}/backbones/arm": "geometry_msgs/msg/PoseArray",
                "/tf": "tf2_msgs/msg/TFMessage", f"{ns}/joint_commands": "sensor_msgs/msg/JointState",
                f"{ns}/actuation": "soft_twin/msg/ActuationCommand", f"{ns}/backbone": "geometry_msgs/msg/PoseArray",
                f"{ns}/strains": "soft_twin/msg/Strains", f"{ns}/tip_pose": "geometry_msgs/msg/PoseStamped",
                f"{ns}/tip_wrench": "geometry_msgs/msg/WrenchStamped",
                f"{ns}/base_wrench": "geometry_msgs/msg/WrenchStamped",
                f"{ns}/joint_wrenches/pan": "geometry_msgs/msg/WrenchStamped",
                f"{ns}/joint_wrenches/tilt": "geometry_msgs/msg/WrenchStamped",
                f"{ns}/internal_wrenches/arm": "std_msgs/msg/Float64MultiArray",
                f"{ns}/markers": "visualization_msgs/msg/MarkerArray"}
    assert client_topics_unsubscribed(msgs, ns)
    for topic, type_name in expected.items():
        assert topic in msgs, (topic, sorted(msgs))
        assert {s for s, _, _ in msgs[topic]} == {type_name}, topic
    counts = {k: int(v) for k, v in meta["soft_twin.counts"].items()}
    assert counts == {t: len(v) for t, v in msgs.items()}
    # every joint command received, in order
    assert [stamp_key(d.header.stamp) for _, _, d in msgs[f"{ns}/joint_commands"]] == sent
    # one joint state and one member backbone per state, same stamps, increasing
    js = [stamp_key(d.header.stamp) for _, _, d in msgs[f"{ns}/joint_states"]]
    assert js == [stamp_key(d.header.stamp) for _, _, d in msgs[f"{ns}/backbones/arm"]]
    assert js == [stamp_key(d.header.stamp) for _, _, d in msgs[f"{ns}/strains"]]
    assert len(js) > 20 and all(b > a for a, b in zip(js, js[1:]))           # (43 at a load of 5)
    # what this process received live is in the recording, equal
    rec_js = {stamp_key(d.header.stamp): d for _, _, d in msgs[f"{ns}/joint_states"]}
    both = [m for m in live_copy[f"{ns}/joint_states"] if stamp_key(m.header.stamp) in rec_js]
    assert len(both) > 20
    for m in both:
        d = rec_js[stamp_key(m.header.stamp)]
        assert list(d.name) == list(m.name) == ["pan", "tilt"]
        assert list(d.position) == list(m.position) and list(d.effort) == list(m.effort)
    assert max(d.position[0] for d in rec_js.values()) > 0.3        # the pan joint moved while recording

    # figures drawn from the recording equal those drawn from the live messages (the common states)
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    rec = read_node_recording(str(path), mech)
    def keys(topic, ms):
        return {stamp_key(m.transforms[0].header.stamp) if topic == "/tf" else stamp_key(m.header.stamp) for m in ms}
    common = set.intersection(*(keys(k, v) & keys(k, [d for _, _, d in msgs[k]]) for k, v in live_copy.items()))
    assert len(common) > 10

    def pick(ms, tf=False):
        return [m for m in ms if (stamp_key(m.transforms[0].header.stamp) if tf else stamp_key(m.header.stamp))
                in common]
    live_msgs = {k: pick(v, k == "/tf") for k, v in live_copy.items()}
    rec_msgs = {k: pick([d for _, _, d in msgs[k]], k == "/tf") for k in live_copy}
    out_live = articulated_run_from_messages(live_msgs, mech, ns)
    out_rec = articulated_run_from_messages(rec_msgs, mech, ns)
    assert len(out_live["time"]) == len(common) and np.array_equal(out_live["frame_poses"], out_rec["frame_poses"])
    for name, out in (("live", out_live), ("rec", out_rec)):
        plot_joint_states(out, str(tmp_path / name))
        plot_frames(out, str(tmp_path / name))
        _save(shapes_figure(run_snapshots(out, mech), "twin"), str(tmp_path / name), "backbone_shapes")
    for stem in ("joint_states", "frames", "backbone_shapes"):
        a = np.asarray(Image.open(tmp_path / "live" / f"{stem}.png"))
        b = np.asarray(Image.open(tmp_path / "rec" / f"{stem}.png"))
        assert np.array_equal(a, b), stem
    # the whole recording (its /tf states: tf_rate_hz) and soft-twin-sim renders it
    assert 10 < len(rec["time"]) <= len(js)
    code = cli.main(["render", str(path), "--robot", "pan_tilt_arm", "--plot", str(tmp_path / "cli"),
                     "--animate", str(tmp_path / "rec.gif"), "--fps", "10"])
    assert code == 0
    for stem in ("backbone_shapes", "joint_states", "frames", "strains"):
        with Image.open(tmp_path / "cli" / f"{stem}.png") as im:
            assert im.size[0] >= 600 and np.mean(np.asarray(im.convert("RGB")).min(axis=2) < 200) > 0.01
    with Image.open(tmp_path / "rec.gif") as im:
        assert im.n_frames >= 5 and im.size == (1120, 448)
