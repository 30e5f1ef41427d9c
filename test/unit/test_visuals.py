"""Plots and animations of soft-twin-sim runs (issue 12): each file is
opened and checked for what it must show (image size, frame count,
duration, non-blank content, motion), and the drawing helpers are checked
against independent computations."""

import json
import os
import time
from pathlib import Path

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
    # the references drawn are the scenario's (the published large-deflection solution, whose x is not
    # given, and linear beam theory), and the twin's 0 deg tip matches both (small deflection, stiff axis)
    from soft_twin_core.files.scenario import load_scenario
    published, linear = load_scenario("princeton_beam").reference
    assert "Obrezkov" in published["label"] and np.isnan(published["tip_position"][0][0])
    assert linear["angle_deg"][0] == 0 and "linear" in linear["label"]
    rs = json.loads(out)
    for ref in (published, linear):
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
    good = {"angle_deg": [0], "tip_position": [[None, 0.01, 0.0]]}         # null: not given
    d["reference"] = [good, {"angle_deg": [0], "tip_position": [["a", 0, 0]]}]
    with pytest.raises(ScenarioError, match=r"scenario\.reference\[1\]\.tip_position"):
        scenario_from_dict(d)


@pytest.mark.quiet                     # counts the updates of 2 s of real time
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


def _check_ticks_apart_and_legend_off_the_panels(fig, renderer):
    """No two tick labels of an axis of the 2D views overlap; the legend meets no panel."""
    for ax in fig.axes[:2]:
        for labels in (ax.get_xticklabels(), ax.get_yticklabels()):
            boxes = [t.get_window_extent(renderer) for t in labels if t.get_visible() and t.get_text()]
            assert not any(a.overlaps(b) for k, a in enumerate(boxes) for b in boxes[k + 1:]), \
                [t.get_text() for t in labels]
    legend = fig.legends[0].get_window_extent(renderer)
    assert not any(legend.overlaps(ax.get_window_extent(renderer)) for ax in fig.axes)


def test_a_vertical_arms_shapes_figure_has_room_for_its_ticks_and_keeps_the_legend_off_the_axes():
    """Issue 31: a vertical arm (0.3 m tall, 10 mm wide) in the shapes
    figure: its side view is at least 3/4 as wide as tall (it was a
    sliver), no two tick labels of an axis overlap (they ran together as
    ``-0.0250.0000.025``), and the legend sits outside every panel (it
    covered the arm)."""
    from soft_twin_core.viz.plots import shapes_figure
    from soft_twin_core.viz.scene import Snapshot
    z = np.linspace(0.0, 0.3, 20)
    snaps = [Snapshot(members=[np.c_[0.01 * k * np.sin(8 * z), 0.002 * z, z]], time=0.5 * k) for k in range(4)]
    fig = shapes_figure(snaps, "a vertical arm")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    side = fig.axes[0]
    (x0, x1), (z0, z1) = side.get_xlim(), side.get_ylim()
    assert x1 - x0 >= 0.75 * (z1 - z0) - 1e-12
    _check_ticks_apart_and_legend_off_the_panels(fig, renderer)
    assert [t.get_text() for t in fig.legends[0].get_texts()][:2] == ["t = 0.00 s", "t = 0.50 s"]
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_the_workspace_colour_bar_leaves_the_z_label_free():
    """Issue 31: the colour bar of a workspace cloud coloured by an input
    covered the 3-D view's z label; it sits left of the view now."""
    from soft_twin_core.planning.reach import hull_summary
    from soft_twin_core.viz.plots import workspace_figure
    rng = np.random.default_rng(0)
    P = rng.normal(0.0, 0.05, (200, 3))
    fig = workspace_figure(P, hull_summary(P), "cloud", color=P[:, 0] * 10, color_label="tendon_y_pos [N]")
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    ax3, bar = fig.axes[0], [a for a in fig.axes if a.get_label() == "<colorbar>"][0]
    assert not bar.get_window_extent(r).overlaps(ax3.zaxis.label.get_window_extent(r))
    assert bar.get_window_extent(r).x1 <= ax3.get_window_extent(r).x0 + 1
    right = fig.axes[1]                                       # the x-y projection, right of the 3-D view
    assert not ax3.zaxis.label.get_window_extent(r).overlaps(right.yaxis.label.get_window_extent(r))
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_a_plan_that_leaves_x_free_draws_its_target_where_the_arm_puts_x():
    """Issue 31: the tendon arm's circle plan tracks y and z only
    (position_weights [0, 1, 1]); its side view drew the target at its
    nominal x, a vertical line tens of mm from the achieved path that read
    as a large miss. The target is drawn at the achieved x and the views
    that show x say it is free; y and z stay the target's."""
    from soft_twin_core.viz.plan_plots import plan_path_figure
    t = np.linspace(0.0, 2.0, 41)
    target = np.c_[np.full_like(t, 0.25), 0.03 * np.cos(np.pi * t), -0.1 + 0.03 * np.sin(np.pi * t)]
    tip = target + np.c_[-0.04 + 0.01 * np.sin(np.pi * t), np.zeros_like(t), 1e-4 * np.ones_like(t)]
    out = {"time": t.tolist(), "target": target.tolist(), "predicted_tip": tip.tolist(),
           "reached": [True] * len(t), "position_weights": [0.0, 1.0, 1.0], "robot": "tendon_arm",
           "error_m": np.abs(tip[:, 2] - target[:, 2]).tolist(), "summary": {"reached": len(t), "samples": len(t)}}
    fig = plan_path_figure(out)
    top, side, front = fig.axes[:3]
    line = [ln for ln in side.get_lines() if ln.get_label() == "planned (target)"][0]
    np.testing.assert_allclose(line.get_xdata(), tip[:, 0])
    np.testing.assert_allclose(line.get_ydata(), target[:, 2])
    front_line = [ln for ln in front.get_lines() if ln.get_label() == "planned (target)"][0]
    np.testing.assert_allclose(front_line.get_xdata(), target[:, 1])
    assert "x free" in side.get_title() and "x free" in top.get_title() and "free" not in front.get_title()
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_study_axes_carry_units_and_an_si_prefix_instead_of_an_offset():
    """Issue 31: the study scatter plots had no units, and Young's modulus
    (1-4e6 Pa) put a ``1e6`` at the axis' end over its label. Each column
    gets its unit from its name, with a prefix bringing the values into
    [1, 1000); matplotlib then draws no offset."""
    from soft_twin_core.studies.report import column_unit, scaled_axis
    assert column_unit("segments[0].material.youngs_modulus", True) == "Pa"
    assert column_unit("actuators[0].offset[0]", True) == "m"
    assert column_unit("scenario.actuation.tendon_y_pos", True) == "N"
    assert column_unit("statics.tip_position_z", False) == "m"
    assert column_unit("statics.base_wrench_my", False) == "N m"
    assert column_unit("statics.max_stress_pa", False) == "Pa"
    assert column_unit("workspace.volume_m3", False) == "m^3"
    assert column_unit("statics.iterations", False) is None
    v, label = scaled_axis([1.2e6, 3.9e6], "segments[0].material.youngs_modulus", True)
    assert label == "segments[0].material.youngs_modulus [MPa]" and np.allclose(v, [1.2, 3.9])
    v, label = scaled_axis([0.0075, 0.0099], "segments[2].cross_section.radius", True)
    assert label.endswith("[mm]") and np.allclose(v, [7.5, 9.9])
    v, label = scaled_axis([2e-5, 9e-5], "workspace.volume_m3", False)
    assert label == "workspace.volume_m3 [x1e-6 m^3]" and np.allclose(v, [20.0, 90.0])
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(2.6, 2.0))
    x, _ = scaled_axis(np.linspace(1.0e6, 4.0e6, 40), "segments[0].material.youngs_modulus", True)
    ax.scatter(x, x ** 2)
    ax.ticklabel_format(useOffset=False, style="plain")
    fig.canvas.draw()
    assert ax.xaxis.get_offset_text().get_text() == ""
    plt.close(fig)


@pytest.mark.parametrize("style,width_pt", [("paper", 252.0), ("paper-wide", 515.52)])
def test_paper_figures_are_vector_at_a_column_width_in_8_point_type(style, width_pt, tmp_path):
    """Issue 31: ``--style paper`` (3.5 in, a journal's column) and
    ``paper-wide`` (7.16 in): the shapes figure of a vertical arm keeps
    its aspect ratio at that width, every text between 6 and 9 pt, no two
    tick labels of an axis overlapping, the legend off the panels and
    every text inside the page; written as PDF (that width in points,
    TrueType fonts: no Type 3, which publishers refuse), SVG (that width,
    its text as text) and a 300 dpi PNG."""
    import re
    import matplotlib.pyplot as plt
    from matplotlib.text import Text
    from soft_twin_core.viz.plots import shapes_figure
    from soft_twin_core.viz.scene import Snapshot
    from soft_twin_core.viz.style import STYLES, fit_to_width, save_figure
    z = np.linspace(0.0, 0.3, 20)
    snaps = [Snapshot(members=[np.c_[0.01 * k * np.sin(8 * z), 0.002 * z, z]], time=0.5 * k) for k in range(4)]
    fig = shapes_figure(snaps, "a vertical arm")
    w, h = fig.get_size_inches()
    fit_to_width(fig, STYLES[style].width_in)
    assert fig.get_size_inches()[0] == pytest.approx(width_pt / 72)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    page = fig.bbox
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text()]
    assert texts and all(6.0 <= t.get_fontsize() <= 9.0 for t in texts)

    ticks, shown = set(), set()         # (a tick label outside its axis's view limits is kept, not drawn)
    for ax in fig.axes:
        for labels, lim, k in ((ax.get_xticklabels(), ax.get_xlim(), 0), (ax.get_yticklabels(), ax.get_ylim(), 1)):
            lo, hi = sorted(lim)
            ticks |= {id(t) for t in labels}
            shown |= {id(t) for t in labels if ax.name != "3d" and lo - 1e-12 <= t.get_position()[k] <= hi + 1e-12}
        if ax.name == "3d":             # (3D ticks: projected, past the limits too)
            ticks |= {id(t) for t in ax.zaxis.get_ticklabels()}
    for t in (t for t in texts if id(t) not in ticks or id(t) in shown):
        b = t.get_window_extent(renderer)
        assert b.x0 >= page.x0 - 1 and b.x1 <= page.x1 + 1 and b.y0 >= page.y0 - 1 and b.y1 <= page.y1 + 1, \
            t.get_text()
    _check_ticks_apart_and_legend_off_the_panels(fig, renderer)
    paths = save_figure(fig, str(tmp_path), "shapes", STYLES[style])
    assert [os.path.basename(p) for p in paths] == ["shapes.pdf", "shapes.svg", "shapes.png"]
    assert not plt.get_fignums()                                       # closed
    pdf = (tmp_path / "shapes.pdf").read_bytes()
    box = re.search(rb"/MediaBox \[ *0 0 ([\d.]+) ([\d.]+) *\]", pdf)
    assert box and float(box.group(1)) == pytest.approx(width_pt, abs=0.5)
    assert b"/Type3" not in pdf and b"/FontFile2" in pdf                 # TrueType embedded
    svg = (tmp_path / "shapes.svg").read_text()
    assert re.search(r'<svg[^>]* width="([\d.]+)pt"', svg).group(1) == pytest.approx(f"{width_pt:g}", abs=0) \
        or float(re.search(r'<svg[^>]* width="([\d.]+)pt"', svg).group(1)) == pytest.approx(width_pt, abs=0.5)
    assert "<text" in svg and "a vertical arm" in svg                   # text kept as text
    with Image.open(tmp_path / "shapes.png") as im:
        assert im.size[0] == pytest.approx(STYLES[style].width_in * 300, abs=2) and ink(im) > 0.01


def test_the_cli_writes_paper_figures_and_refuses_an_unknown_style(tmp_path, capsys):
    code, _, err = run_cli(["statics", "tendon_arm_statics", "--plot", str(tmp_path), "--style", "paper"], capsys)
    assert code == 0, err
    names = set(os.listdir(tmp_path))
    assert {"backbone_shapes.pdf", "backbone_shapes.svg", "backbone_shapes.png"} <= names
    assert not any(n.endswith(".png") and n[:-4] + ".pdf" not in names for n in names)
    with pytest.raises(SystemExit) as e:
        cli.main(["statics", "tendon_arm_statics", "--plot", str(tmp_path / "x"), "--style", "poster"])
    assert e.value.code == 2 and "poster" in capsys.readouterr().err and not (tmp_path / "x").exists()


def _texts_between_6_and_9_pt_and_on_the_page(fig, renderer):
    """Every drawn text of ``fig`` is 6-9 pt and lies on the page; no two
    tick labels of a 2D axis overlap."""
    from matplotlib.text import Text
    page = fig.bbox
    hidden = set()                       # tick labels of ticks outside the view: not drawn
    for ax in fig.axes:
        for axis, k in ((ax.xaxis, 0), (ax.yaxis, 1)):
            lo, hi = sorted(axis.get_view_interval())
            hidden |= {id(t) for t in axis.get_ticklabels() if not lo - 1e-12 <= t.get_position()[k] <= hi + 1e-12}
    for t in fig.findobj(Text):
        if not (t.get_visible() and t.get_text().strip()) or id(t) in hidden:
            continue
        assert 6.0 <= t.get_fontsize() <= 9.0, (t.get_text(), t.get_fontsize())
        if t.axes is None or t.axes.name != "3d":
            b = t.get_window_extent(renderer)
            assert b.x0 >= page.x0 - 1 and b.x1 <= page.x1 + 1 and b.y0 >= page.y0 - 1 and b.y1 <= page.y1 + 1, \
                t.get_text()
    for ax in fig.axes:
        if ax.name == "3d" or ax.get_label() == "<colorbar>":
            continue
        for labels in (ax.get_xticklabels(), ax.get_yticklabels()):
            boxes = [t.get_window_extent(renderer) for t in labels if t.get_visible() and t.get_text()]
            assert not any(a.overlaps(b) for k, a in enumerate(boxes) for b in boxes[k + 1:]), \
                [t.get_text() for t in labels]


def _pdf_width_pt(path):
    import re
    pdf = path.read_bytes()
    assert b"/Type3" not in pdf and b"/FontFile2" in pdf                 # TrueType embedded
    return float(re.search(rb"/MediaBox \[ *0 0 ([\d.]+) ([\d.]+) *\]", pdf).group(1))


def test_the_workspace_and_study_figures_in_the_paper_styles(tmp_path, capsys):
    """Issue 31: ``--style paper`` / ``paper-wide`` for the workspace
    command and a design study: their figures are drawn at the column's
    (3.5 in = 252 pt) or the page's (7.16 in = 515.5 pt) width in 6-9 pt
    type (viz.style.drawn_size, drawing_rc), every text on the page, no two
    tick labels overlapping, the workspace legend under the panels; written
    as PDF (TrueType), SVG and PNG. The scatter matrix keeps its rows and
    columns, its long labels stacked; summary.md shows the PNGs."""
    import matplotlib.pyplot as plt
    import yaml
    from soft_twin_core.cli import main
    from soft_twin_core.planning.reach import hull_summary
    from soft_twin_core.viz.plots import workspace_figure
    from soft_twin_core.viz.style import figure_style
    rng = np.random.default_rng(0)
    P = rng.normal(0.0, 0.05, (200, 3)) + [0.3, 0.0, -0.3]
    with figure_style("paper"):
        fig = workspace_figure(P, hull_summary(P), "cloud", color=P[:, 0] * 10, color_label="tendon_y_pos [N]",
                               mark=np.arange(200) < 8)
    try:
        assert fig.get_size_inches()[0] == pytest.approx(3.5)
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        _texts_between_6_and_9_pt_and_on_the_page(fig, r)
        legend = fig.legends[0].get_window_extent(r)
        assert not any(legend.overlaps(ax.get_window_extent(r)) for ax in fig.axes)
    finally:
        plt.close(fig)
    out = tmp_path / "ws"
    assert main(["workspace", "tendon_arm", "--limit", "3", "--samples", "8", "--actuators",
                 "tendon_y_pos,tendon_z_neg", "-o", str(out), "--style", "paper"]) == 0
    assert _pdf_width_pt(out / "workspace.pdf") == pytest.approx(252.0, abs=0.5)
    assert (out / "workspace.svg").exists() and (out / "workspace.png").exists()
    assert "workspace.pdf" in capsys.readouterr().err
    scenario = Path(__file__).resolve().parents[2] / "config" / "scenarios" / "tendon_arm_statics.yaml"
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump({"name": "paper", "scenario": str(scenario), "design": {"type": "grid"},
                                 "parameters": [{"path": "actuators[0].offset[0]", "values": [0.005, 0.006, 0.007]},
                                                {"path": "segments[0].material.youngs_modulus",
                                                 "values": [1.0e6, 1.5e6]}],
                                 "compute": {"statics": {}}}))
    assert main(["study", str(f), "-o", str(tmp_path / "st"), "--serial", "--style", "paper-wide"]) == 0
    plots = tmp_path / "st" / "plots"
    for stem in ("sensitivity", "scatter"):
        assert _pdf_width_pt(plots / f"{stem}.pdf") == pytest.approx(515.52, abs=0.5)
        assert (plots / f"{stem}.svg").exists() and (plots / f"{stem}.png").exists()
    md = (tmp_path / "st" / "summary.md").read_text()
    assert "](plots/scatter.png)" in md and ".pdf)" not in md and ".svg)" not in md
    with pytest.raises(SystemExit):                                   # argparse: exit 2, nothing written
        main(["workspace", "tendon_arm", "--limit", "3", "--style", "poster", "-o", str(tmp_path / "p")])
    assert not (tmp_path / "p").exists()
