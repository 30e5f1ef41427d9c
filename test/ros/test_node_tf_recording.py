"""/tf and MCAP recording of the node (issue 12), end to end: the node in a
second process, this test process subscribing to /tf and the state topics
with real rclpy, setting ``record_file`` through the parameter service and
reading the recording back with the mcap libraries. Every wait is for a
condition with a timeout."""
import threading
import time
from collections import defaultdict

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from soft_twin.client import NodeProcess, TwinClient, stamp_key  # noqa: E402
from soft_twin.config import resolve_robot_file  # noqa: E402
from soft_twin.conversions import matrix_from_pose, matrix_from_quaternion  # noqa: E402
from soft_twin_core.reference import kinematics as kin  # noqa: E402
from soft_twin_core.robot.model import load_model  # noqa: E402

pytestmark = pytest.mark.ros

NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
NODE = "twin_tf_rec"
START_TIMEOUT = 120.0


class Listener:
    """/tf and ~/markers in the client's node: every message kept."""

    def __init__(self, client):
        self.tf, self.markers, self.tips = [], 0, []
        self._client = client
        n = client.node
        n.create_subscription(TFMessage, "/tf", self._on_tf, 1000)
        n.create_subscription(PoseStamped, f"/{NODE}/tip_pose", self.tips.append, 1000)
        n.create_subscription(MarkerArray, f"/{NODE}/markers", self._on_markers, 10)
        self.set_params = n.create_client(SetParameters, f"/{NODE}/set_parameters")

    def _on_tf(self, msg):
        with self._client._cond:
            self.tf.append(msg)
            self._client._cond.notify_all()

    def _on_markers(self, msg):
        self.markers += 1

    def set_string(self, name, value, timeout=20.0):
        assert self.set_params.wait_for_service(timeout_sec=timeout)
        req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=value))])
        fut = self.set_params.call_async(req)
        done = threading.Event()
        fut.add_done_callback(lambda _: done.set())
        assert done.wait(timeout), "set_parameters: no answer"
        return fut.result().results[0]


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    log = tmp_path_factory.mktemp("node") / "node.log"
    proc = NodeProcess(["-p", "wrench_rate_hz:=50.0", "-p", "marker_rate_hz:=10.0"], node_name=NODE, log_path=log)
    client = TwinClient(NODE, client_name=f"{NODE}_test_client")
    listener = Listener(client)
    try:
        client.wait_ready(START_TIMEOUT)
    except Exception:
        client.close()
        proc.stop()
        raise AssertionError(f"node did not come up:\n{proc.output()[-3000:]}")
    yield proc, client, listener
    client.close()
    rc = proc.stop()
    assert rc == 0 and "Traceback" not in proc.output(), proc.output()[-3000:]


def transform_matrix(t):
    T = np.eye(4)
    r, p = t.transform.rotation, t.transform.translation
    T[:3, :3] = matrix_from_quaternion(r.x, r.y, r.z, r.w)
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def test_tf_tip_equals_the_tip_pose_topic(twin):
    proc, client, listener = twin
    client.send_actuation(NAMES, [2.0, 0.0, 5.0, 0.0])
    # every tip pose seen from now on, paired with the /tf message of its stamp
    start = client.counts["tip_pose"]
    assert client.wait_until(lambda: client.counts["tip_pose"] > start + 5, 10.0)
    seen, tip_poses = {}, []

    def have_pairs():
        tp = client.tip_pose
        if tp is not None:
            seen[stamp_key(tp.header.stamp)] = tp
        by_stamp = {stamp_key(m.transforms[0].header.stamp): m for m in listener.tf[-400:]}
        tip_poses[:] = [(seen[k], by_stamp[k]) for k in seen if k in by_stamp]
        return len(tip_poses) >= 10
    assert client.wait_until(have_pairs, 15.0), f"only {len(tip_poses)} tip poses matched a /tf message"
    model = load_model(resolve_robot_file(""))
    for tp, tf in tip_poses:
        tips = [t for t in tf.transforms if t.child_frame_id == "tip_link"]
        assert len(tips) == 1
        t = tips[0]
        assert t.header.frame_id == "base_link" and tp.header.frame_id == "base_link"
        p, r = t.transform.translation, t.transform.rotation
        q = tp.pose.position, tp.pose.orientation
        assert np.allclose([p.x, p.y, p.z], [q[0].x, q[0].y, q[0].z], rtol=0, atol=1e-9)
        assert np.allclose([r.x, r.y, r.z, r.w], [q[1].x, q[1].y, q[1].z, q[1].w], rtol=0, atol=1e-9)
        names = [t.child_frame_id for t in tf.transforms]
        # the robot's named frames (a classic rod's: tip), every section boundary of its member, the tip
        assert names == ([f"{NODE}/tip"] + [f"{NODE}/backbone_{i}" for i in range(model.n_sections + 1)]
                         + ["tip_link"])


def test_tf_section_frames_equal_the_core_kinematics(twin):
    """The member's section-boundary frames equal the rod kinematics' poses
    at the section starts and the tip for the strains published with the
    same stamp (independent of the node's backbone sampling)."""
    proc, client, listener = twin
    model = load_model(resolve_robot_file(""))
    found = {}

    def pair():
        s = client.strains
        if s is None:
            return False
        k = stamp_key(s.header.stamp)
        for m in reversed(listener.tf[-400:]):
            if stamp_key(m.transforms[0].header.stamp) == k:
                found["pair"] = (s, m)
                return True
        return False
    assert client.wait_until(pair, 10.0)
    s, tf = found["pair"]
    q = model.q_from_strains(np.array(s.strains).reshape(-1, 6))
    T_ref = kin.poses(model, q, np.append(model.s_starts, model.total_length))
    boundaries = [t for t in tf.transforms if t.child_frame_id.startswith(f"{NODE}/backbone_")]
    assert len(boundaries) == model.n_sections + 1
    for i, t in enumerate(boundaries):
        assert np.allclose(transform_matrix(t), T_ref[i], atol=1e-9), t.child_frame_id


def test_bad_record_file_is_refused(twin, tmp_path):
    proc, client, listener = twin
    res = listener.set_string("record_file", str(tmp_path / "run.bag"))
    assert not res.successful and "record_file" in res.reason and ".mcap" in res.reason
    res = listener.set_string("record_file", str(tmp_path / "missing" / "run.mcap"))
    assert not res.successful and "does not exist" in res.reason


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


def test_recording_holds_every_topic_and_input(twin, tmp_path):
    proc, client, listener = twin
    model = load_model(resolve_robot_file(""))
    path = tmp_path / "run.mcap"
    res = listener.set_string("record_file", str(path))
    assert res.successful, res.reason
    # drive the twin while recording: 25 commands at ~50 Hz, and a tip wrench
    sent = []
    for k in range(25):
        sent.append(stamp_key(client.send_actuation(NAMES, [0.2 * k, 0.0, 0.4 * k, 0.0])))
        client.wait_until(lambda: False, 0.02)
    client.send_tip_wrench([0.0, 0.0, -0.05], [0.0, 0.0, 0.0], "base_link")
    n_diag = client.counts["diagnostics"]
    assert client.wait_until(lambda: client.counts["diagnostics"] >= n_diag + 2 and listener.markers > 0, 10.0)
    with client._cond:
        live_tips = {stamp_key(m.header.stamp): m for _, m in list(client.history["strains"])}
        live = dict(backbone=[m for _, m in client.history["backbone"]], tip_pose=list(listener.tips),
                    strains=[m for _, m in client.history["strains"]])
    res = listener.set_string("record_file", "")
    assert res.successful, res.reason
    header, meta, msgs = _read_mcap(path)
    assert header.profile == "ros2"
    ns = f"/{NODE}"
    expected = {f"{ns}/backbone": "geometry_msgs/msg/PoseArray", f"{ns}/tip_pose": "geometry_msgs/msg/PoseStamped",
                f"{ns}/strains": "soft_twin/msg/Strains", f"{ns}/tip_wrench": "geometry_msgs/msg/WrenchStamped",
                f"{ns}/base_wrench": "geometry_msgs/msg/WrenchStamped", f"{ns}/markers":
                "visualization_msgs/msg/MarkerArray", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                "/tf": "tf2_msgs/msg/TFMessage", f"{ns}/actuation": "soft_twin/msg/ActuationCommand",
                f"{ns}/tip_wrench_command": "geometry_msgs/msg/WrenchStamped",
                # every robot's joint and member topics (a classic rod: no joints, member "backbone")
                f"{ns}/joint_states": "sensor_msgs/msg/JointState",
                f"{ns}/backbones/backbone": "geometry_msgs/msg/PoseArray",
                f"{ns}/internal_wrenches/backbone": "std_msgs/msg/Float64MultiArray",
                f"{ns}/contacts": "soft_twin/msg/Contacts"}        # empty: the default arm touches nothing
    assert set(msgs) == set(expected), sorted(msgs)
    for topic, type_name in expected.items():
        assert {s for s, _, _ in msgs[topic]} == {type_name}, topic
    # counts: the file's own count record, and what the node published / received
    counts = {k: int(v) for k, v in meta["soft_twin.counts"].items()}
    assert counts == {t: len(v) for t, v in msgs.items()}
    commands = [stamp_key(d.header.stamp) for _, _, d in msgs[f"{ns}/actuation"]]
    assert commands == sent                      # every command received, in order
    assert len(msgs[f"{ns}/tip_wrench_command"]) == 1
    # the states: one backbone, tip pose, strains and /tf message per state, same stamps
    stamps = {t: [stamp_key(d.header.stamp) if t != "/tf" else stamp_key(d.transforms[0].header.stamp)
                  for _, _, d in msgs[t]] for t in (f"{ns}/backbone", f"{ns}/tip_pose", f"{ns}/strains", "/tf")}
    assert stamps[f"{ns}/backbone"] == stamps[f"{ns}/tip_pose"] == stamps[f"{ns}/strains"]
    assert len(stamps[f"{ns}/backbone"]) > 50
    # /tf: the frames of some of those states (tf_rate_hz 50 of the 200 Hz states)
    assert set(stamps["/tf"]) <= set(stamps[f"{ns}/backbone"])
    b = stamps[f"{ns}/backbone"]
    duration = (b[-1][0] - b[0][0]) + 1e-9 * (b[-1][1] - b[0][1])
    assert 0.3 * min(len(b), 50 * duration) <= len(stamps["/tf"]) <= 50 * duration * 1.1 + 2, (len(stamps["/tf"]),
                                                                                                len(b), duration)
    # stamps and log times increase
    st = [s[0] * 10**9 + s[1] for s in stamps[f"{ns}/backbone"]]
    assert all(b > a for a, b in zip(st, st[1:]))
    for topic, rows in msgs.items():
        logs = [m.log_time for _, m, _ in rows]
        assert all(b >= a for a, b in zip(logs, logs[1:])), topic
    # what this process received live is in the recording, equal
    for _, _, d in msgs[f"{ns}/strains"]:
        got = live_tips.get(stamp_key(d.header.stamp))
        if got is not None:
            assert list(got.strains) == list(d.strains)
    assert sum(stamp_key(d.header.stamp) in live_tips for _, _, d in msgs[f"{ns}/strains"]) > 50


    # figures drawn from the recording equal those drawn from the live messages
    from soft_twin_core.files import recording
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.viz.plots import plot_dynamics
    from soft_twin_core.viz.scene import run_snapshots
    from PIL import Image
    mech = from_robot_model(model)
    rec = recording.read_messages(str(path))
    common = (set.intersection(*(set(stamp_key(m.header.stamp) for m in live[k]) for k in live))
              & set(stamp_key(m.header.stamp) for m in rec[f"{ns}/strains"]))
    assert len(common) > 50

    def pick(ms):
        return [m for m in ms if stamp_key(m.header.stamp) in common]
    out_live = recording.run_from_messages(*(pick(live[k]) for k in ("backbone", "tip_pose", "strains")), mech)
    out_rec = recording.run_from_messages(*(pick(rec[f"{ns}/{k}"]) for k in ("backbone", "tip_pose", "strains")),
                                          mech)
    assert out_live == out_rec
    for name, out in (("live", out_live), ("rec", out_rec)):
        plot_dynamics(out, str(tmp_path / name), mech, "twin")
    for stem in ("backbone_shapes", "tip", "strains"):
        a = np.asarray(Image.open(tmp_path / "live" / f"{stem}.png"))
        b = np.asarray(Image.open(tmp_path / "rec" / f"{stem}.png"))
        assert np.array_equal(a, b), stem
    assert len(run_snapshots(out_rec, mech)) == len(common)
    # and soft-twin-sim renders the recording
    from soft_twin_core import cli
    code = cli.main(["render", str(path), "--robot", "tendon_arm", "--plot", str(tmp_path / "cli"),
                     "--animate", str(tmp_path / "rec.gif"), "--fps", "10"])
    assert code == 0
    with Image.open(tmp_path / "rec.gif") as im:
        assert im.n_frames >= 5 and im.size == (1120, 448)
