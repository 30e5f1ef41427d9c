"""Plots and animations of soft-twin-sim runs (issue 12): each file is
opened and checked for what it must show (image size, frame count,
duration, non-blank content, motion), and the drawing helpers are checked
against independent computations."""

import json
import os
import time

import numpy as np
import pytest
from PIL import Image

from soft_twin_core import cli
from soft_twin_core.robot.model import load_model
from soft_twin_core.viz import scene

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(HERE, "..", "..", "config")
FIGURES = ("backbone_shapes", "internal_wrenches_backbone", "tip", "strains", "energies")


def run_cli(args, capsys):
    code = cli.main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def ink(img):
    """Fraction of pixels that are not (near) white: 0 for a blank picture."""
    a = np.asarray(img.convert("RGB"), dtype=float)
    return float(np.mean(a.min(axis=2) < 200))


def check_png(path, min_ink=0.01):
    with Image.open(path) as im:
        assert im.format == "PNG"
        w, h = im.size
        assert w >= 600 and h >= 400, (path, im.size)
        assert ink(im) > min_ink, f"{path} looks blank"
        return im.size


# ---------------------------------------------------------------------------
# scene helpers
# ---------------------------------------------------------------------------

def test_sample_times_plays_in_real_time():
    t = np.arange(0, 101) * 0.01           # samples every 10 ms over 1 s
    idx = scene.sample_times(t, 25)
    assert len(idx) == 26                  # frames at 0, 40, ..., 1000 ms
    assert np.allclose(t[idx], np.arange(26) / 25, atol=1e-12)
    # a run sampled more coarsely than the frame rate holds each sample
    t2 = np.array([0.0, 0.1, 0.2])
    assert scene.sample_times(t2, 20).tolist() == [0, 0, 1, 1, 2]
    with pytest.raises(ValueError, match="fps"):
        scene.sample_times(t2, 0)


def test_bounds_hold_every_point_with_margin():
    a = scene.Snapshot([[[0, 0, 0], [0.1, 0.0, 0.0]]], time=0.0)
    b = scene.Snapshot([[[0, 0, 0], [0.05, 0.02, -0.08]]], links=[[[0, 0, 0], [0, 0, 0.01]]], time=0.1)
    lo, hi = scene.bounds([a, b])
    P = np.concatenate([a.points, b.points])
    assert np.all(lo < P.min(axis=0)) and np.all(hi > P.max(axis=0))
    assert a.caption == "t = 0.00 s"
    with pytest.raises(ValueError, match=r"members\[0\]: expected points of shape \(P, 3\)"):
        scene.Snapshot([[1, 2]])
    with pytest.raises(ValueError, match=r"links\[0\]"):
        scene.Snapshot([[[0, 0, 0]]], links=[[[0, 0, 0]]])


def test_a_member_crosses_its_rigid_offsets():
    """A classic arm with an elbow (a rigid offset between its segments) is
    one member whose samples jump across the offset: the first sample of
    the forearm is where the offset puts it (independent: the rod's chained
    transforms), and the polyline draws the offset as one straight piece."""
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.reference import kinematics as kin
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.solve.outputs import state_shape
    m = load_model(os.path.join(CONFIG, "robots", "elbow_arm.yaml"))
    mech = from_robot_model(m)
    q = m.q0.copy()
    _, members = state_shape(mech, Workspace(mech.tree), q, 5)
    P, s = members["backbone"]
    assert len(P) == 5 * m.n_sections + 1
    T_end = kin.poses(m, q, np.array([0.2 - 1e-12]))[0]
    p_joint = (T_end @ m.offsets[3])[:3, 3]
    k = int(np.flatnonzero(np.isclose(s, 0.2))[-1])           # the forearm's first sample
    assert np.allclose(P[k, :3, 3], p_joint, atol=1e-9)
    assert np.allclose(P[k - 1, :3, 3], kin.poses(m, q, np.array([0.2 - 0.2 / 4 / 5]))[0][:3, 3], atol=1e-9)


def test_energies_from_the_run_equal_the_reference(tmp_path):
    """The energies a run reports at its samples equal the numpy
    reference's energies of the state in its strains and strain rates."""
    from soft_twin_core.files.scenario import load_scenario, run_dynamics
    from soft_twin_core.reference import multibody as reference
    from soft_twin_core.solve.outputs import q_from_section_strains
    sc = load_scenario("tendon_arm_dynamics")
    out = run_dynamics(sc, 0.05, 0.005, backbone_every=5)
    kin_e, ela, grav = np.asarray(out["energies"][-1])
    tree = sc.mech.tree
    k = out["time"].index(out["members_time"][-1])
    q = q_from_section_strains(sc.mech, out["strains"][k], tree.q0)
    R = np.asarray(out["strain_rates"][k])
    v = np.concatenate([R[n, tree.joints[i].section.modes] for n, i in enumerate(tree.soft_joints)])
    assert kin_e == pytest.approx(reference.kinetic_energy(tree, q, v), rel=1e-9)
    assert kin_e > 0
    assert ela + grav == pytest.approx(reference.potential_energy(tree, q), rel=1e-6)


# ---------------------------------------------------------------------------
# soft-twin-sim --plot / --animate / render
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dynamics_run(tmp_path_factory):
    """tendon_arm_dynamics for 0.4 s: figures, a GIF and the JSON of the run."""
    d = tmp_path_factory.mktemp("dyn")
    import io
    import contextlib
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(["dynamics", "tendon_arm_dynamics", "--duration", "0.4", "--dt", "0.002",
                         "--plot", str(d / "fig"), "--animate", str(d / "run.gif"), "-o", str(d / "run.json")])
    assert code == 0, err.getvalue()
    return d, err.getvalue()


def test_dynamics_figures_open_and_show_something(dynamics_run):
    d, err = dynamics_run
    for stem in FIGURES:
        check_png(d / "fig" / f"{stem}.png")
        svg = (d / "fig" / f"{stem}.svg").read_text()
        assert svg.lstrip().startswith("<?xml") and "<svg" in svg and len(svg) > 5000
    assert "wrote 10 figures" in err


def test_gif_plays_the_run_in_real_time(dynamics_run):
    d, err = dynamics_run
    with Image.open(d / "run.gif") as im:
        assert im.size == (1120, 448)
        assert im.n_frames == 11                   # t = 0, 0.04, ..., 0.4 s at 25 fps
        durations, frames = [], []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
            frames.append(np.asarray(im.convert("RGB"), dtype=float))
    assert durations == [40] * 11                  # ms: real time at 25 fps
    assert all(ink(Image.fromarray(f.astype(np.uint8))) > 0.01 for f in frames)
    # the arm moves (tendon ramp + gravity): first and last frames differ
    assert np.mean(np.any(frames[0] != frames[-1], axis=2)) > 0.001
    assert "animation: frame 11/11" in err and "(11 frames at 25 fps, 0.44 s)" in err


def test_run_json_has_backbone_samples_at_the_frame_rate(dynamics_run):
    d, _ = dynamics_run
    out = json.loads((d / "run.json").read_text())
    assert out["members_time"] == pytest.approx(np.arange(11) * 0.04, abs=1e-12)


def test_render_from_the_saved_run_equals_the_live_figures(dynamics_run, capsys):
    d, _ = dynamics_run
    code, _, err = run_cli(["render", str(d / "run.json"), "--scenario", "tendon_arm_dynamics",
                            "--plot", str(d / "again")], capsys)
    assert code == 0, err
    for stem in FIGURES:
        a = np.asarray(Image.open(d / "fig" / f"{stem}.png"))
        b = np.asarray(Image.open(d / "again" / f"{stem}.png"))
        assert a.shape == b.shape and np.array_equal(a, b), stem


def test_mp4_frames_size_rate_and_motion(tmp_path, capsys):
    import imageio.v2 as iio
    path = tmp_path / "run.mp4"
    code, _, err = run_cli(["dynamics", "tendon_arm_dynamics", "--duration", "0.5", "--dt", "0.005",
                            "--animate", str(path), "--fps", "20", "-o", str(tmp_path / "r.json")], capsys)
    assert code == 0, err
    with iio.get_reader(str(path)) as r:
        meta = r.get_meta_data()
        frames = [f for f in r]
    assert meta["fps"] == pytest.approx(20.0)
    assert len(frames) == 11                       # 0.5 s at 20 fps, both ends
    assert frames[0].shape == (448, 1120, 3)
    assert meta["duration"] == pytest.approx(11 / 20, abs=0.051)
    assert all(ink(Image.fromarray(f)) > 0.01 for f in frames)
    assert np.mean(np.abs(frames[0].astype(float) - frames[-1].astype(float)) > 40) > 0.001


def test_princeton_sweep_figures_and_animation(tmp_path, capsys):
    code, out, err = run_cli(["statics", "princeton_beam", "--sections", "4", "--sweep-angle", "0:90:30",
                              "--plot", str(tmp_path / "fig"), "--animate", str(tmp_path / "sweep.gif")], capsys)
    assert code == 0, err
    for stem in ("sweep_tip", "sweep_shapes"):
        check_png(tmp_path / "fig" / f"{stem}.png")
    with Image.open(tmp_path / "sweep.gif") as im:
        assert im.n_frames == 4 and im.info["duration"] == 500       # 2 angles per second
    # the reference drawn is the scenario's (linear beam theory), and the
    # twin's 0 deg tip matches it (small deflection along the stiff axis)
    from soft_twin_core.files.scenario import load_scenario
    ref = load_scenario("princeton_beam").reference
    assert ref["angle_deg"][0] == 0 and "linear" in ref["label"]
    rs = json.loads(out)
    assert rs[0]["tip_position"][1] == pytest.approx(ref["tip_position"][0][1], rel=0.02)


def test_statics_plot_without_sweep(tmp_path, capsys):
    code, _, err = run_cli(["statics", "tendon_arm_statics", "--plot", str(tmp_path)], capsys)
    assert code == 0, err
    check_png(tmp_path / "backbone_shapes.png")
    check_png(tmp_path / "internal_wrenches_backbone.png")          # one figure per member (a rod has one)


@pytest.mark.parametrize("args,msg", [
    (["dynamics", "tendon_arm_dynamics", "--duration", "0.1", "--animate", "x.avi"], "--animate: expected"),
    (["dynamics", "tendon_arm_dynamics", "--duration", "0.1", "--animate", "x.gif", "--fps", "0"], "--fps must"),
    (["render", "nonexistent.json", "--plot", "d"], "No such file"),
])
def test_bad_visual_arguments_are_refused_by_name(args, msg, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)       # restored after the test: a bare os.chdir moved every later test
    code, _, err = run_cli(args, capsys)
    assert code == 2 and msg in err, err
    assert not os.listdir(tmp_path)


def test_render_needs_backbone_samples(tmp_path, capsys):
    run = tmp_path / "r.json"
    code, _, err = run_cli(["dynamics", "tendon_arm_dynamics", "--duration", "0.01", "-o", str(run)], capsys)
    assert code == 0, err
    code, _, err = run_cli(["render", str(run), "--animate", str(tmp_path / "a.gif"), "--robot", "tendon_arm"],
                           capsys)
    assert code == 2 and "--backbone-every" in err


def test_bad_reference_is_named(tmp_path):
    from soft_twin_core.files.scenario import ScenarioError, scenario_from_dict
    d = {"robot": "princeton_beam", "reference": {"angle_deg": [0, 10], "tip_position": [[0, 0, 0]]}}
    with pytest.raises(ScenarioError, match=r"scenario\.reference\.tip_position"):
        scenario_from_dict(d)


def test_view_serves_a_saved_run_in_real_time(dynamics_run):
    """soft-twin-sim view: the page is served (viser's bundled client) and the
    run's states are shown one after the other in real time."""
    import socket
    import threading
    import urllib.request
    from soft_twin_core.viz import render
    d, _ = dynamics_run
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    args = cli._parser().parse_args(["view", str(d / "run.json"), "--scenario", "tendon_arm_dynamics",
                                     "--port", str(port), "--seconds", "2.0"])
    result = {}
    th = threading.Thread(target=lambda: result.setdefault("updates", render.view_main(args)))
    th.start()
    html = None
    end = time.monotonic() + 20
    while html is None and time.monotonic() < end:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                html = r.read().decode("utf-8", "replace")
        except OSError:
            time.sleep(0.1)
    th.join(30)
    assert html is not None and "<html" in html.lower() and len(html) > 100_000   # the whole client, offline
    # 0.4 s of run sampled every 0.04 s, looped for 2 s: about 5 loops of 11 states
    assert 30 <= result["updates"] <= 60, result


def test_view_refuses_bad_port(capsys):
    code, _, err = run_cli(["view", "x.json", "--port", "70000"], capsys)
    assert code == 2 and "--port must lie in 1..65535" in err


def test_dynamics_run_as_mcap_renders_like_the_run(tmp_path, capsys):
    """dynamics --mcap: the node's topics in the ROS 2 bag format; read back,
    its backbone, tip and strains are the run's, and its backbone
    orientations are the model's kinematics of the recorded strains."""
    from soft_twin_core.files import recording
    from soft_twin_core.files.recording import read_node_recording
    from soft_twin_core.files.scenario import load_scenario
    from soft_twin_core.reference import kinematics as kin
    path = tmp_path / "run.mcap"
    code, _, err = run_cli(["dynamics", "tendon_arm_dynamics", "--duration", "0.2", "--dt", "0.005",
                            "--backbone-every", "4", "--mcap", str(path), "-o", str(tmp_path / "run.json")], capsys)
    assert code == 0, err
    out = json.loads((tmp_path / "run.json").read_text())
    sc = load_scenario("tendon_arm_dynamics")
    model = sc.model
    run = read_node_recording(str(path), sc.mech)
    assert run["time"] == pytest.approx(out["members_time"], abs=1e-9)
    assert np.allclose([m["backbone"]["positions"] for m in run["members"]], out["member_positions"], atol=1e-12)
    rows = [out["time"].index(t) for t in out["members_time"]]
    assert np.allclose(run["frame_positions"], np.array(out["tip_position"])[rows][:, None], atol=1e-12)
    assert np.array_equal(np.array(run["strains"]), np.array(out["strains"])[rows])
    # the topics every twin node publishes read back alike
    msgs = recording.read_messages(str(path))
    basic = recording.read_node_run(msgs, "/soft_twin_sim", sc.mech)
    assert np.allclose(basic["tip_position"], np.array(out["tip_position"])[rows], atol=1e-12)
    assert np.allclose(basic["strain_rates"], np.array(out["strain_rates"])[rows], atol=0)
    b = msgs["/soft_twin_sim/backbone"][-1]
    q = model.q_from_strains(np.array(msgs["/soft_twin_sim/strains"][-1].strains).reshape(-1, 6))
    _, T = kin.backbone(model, q, 10)
    from scipy.spatial.transform import Rotation
    o = b.poses[7].orientation
    assert np.allclose(Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix(), T[7, :3, :3], atol=1e-9)
    assert np.allclose([[p.position.x, p.position.y, p.position.z] for p in b.poses], T[:, :3, 3], atol=1e-12)
    code, _, err = run_cli(["render", str(path), "--robot", "tendon_arm", "--plot", str(tmp_path / "fig")], capsys)
    assert code == 0, err
    check_png(tmp_path / "fig" / "backbone_shapes.png")


def test_rviz_config_shows_the_node_topics_and_frames():
    import yaml
    root = os.path.join(HERE, "..", "..")
    cfg = yaml.safe_load(open(os.path.join(root, "config", "soft_twin.rviz")))
    vm = cfg["Visualization Manager"]
    params = yaml.safe_load(open(os.path.join(root, "config", "params.yaml")))["soft_twin"]["ros__parameters"]
    assert vm["Global Options"]["Fixed Frame"] == params["base_frame"]
    displays = {d["Class"]: d for d in vm["Displays"]}
    for cls in ("rviz_default_plugins/MarkerArray", "rviz_default_plugins/TF", "rviz_default_plugins/Wrench",
                "rviz_default_plugins/Pose"):
        assert cls in displays, cls
    topics = {d["Topic"]["Value"] for d in vm["Displays"] if "Topic" in d}
    assert topics == {"/soft_twin/markers", "/soft_twin/tip_pose", "/soft_twin/tip_wrench", "/soft_twin/base_wrench"}
