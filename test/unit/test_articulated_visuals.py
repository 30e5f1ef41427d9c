"""Figures, animations and MCAP recordings of soft articulated robots
(issue 12 for tree robot files): soft-twin-sim --plot/--animate/--mcap on
the articulated example scenarios, ``render`` from the JSON and from the
MCAP, each file opened and checked (image size, non-blank content, frame
count and duration, motion); the drawing of links and joints and the
energies against independent computations."""

import contextlib
import io
import json

import numpy as np
import pytest
from PIL import Image

from soft_twin_core import cli
from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import find_file
from soft_twin_core.viz.scene import snapshot, solid_outline

FIGURES = ("backbone_shapes", "tip", "joint_states", "joint_wrenches", "frames", "strains", "internal_wrenches_arm",
           "energies")


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


def run_cli(args):
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = cli.main(args)
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------------------
# links and joints in a snapshot
# ---------------------------------------------------------------------------

def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_box_outline_has_the_corners_of_the_box():
    T = np.eye(4)
    T[:3, :3] = _rot_z(0.3)
    T[:3, 3] = [0.1, -0.2, 0.3]
    vis = {"shape": "box", "size": [0.2, 0.1, 0.04], "position": [0.01, 0.0, 0.0]}
    P = solid_outline(vis, T)
    P = P[np.all(np.isfinite(P), axis=1)]
    # independent: the 8 corners +-size/2 about the shifted centre, rotated about z
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.05, 0.05) for z in (-0.02, 0.02)])
    want = (corners + [0.01, 0, 0]) @ _rot_z(0.3).T + [0.1, -0.2, 0.3]
    got = np.unique(np.round(P, 12), axis=0)
    assert len(got) == 8
    for c in want:
        assert np.min(np.linalg.norm(got - c, axis=1)) < 1e-12


def test_cylinder_outline_lies_on_the_cylinder():
    T = np.eye(4)
    T[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])      # local z along world y
    T[:3, 3] = [0.0, 0.5, 0.0]
    P = solid_outline({"shape": "cylinder", "radius": 0.04, "length": 0.06}, T)
    P = P[np.all(np.isfinite(P), axis=1)] - T[:3, 3]
    assert np.allclose(np.hypot(P[:, 0], P[:, 2]), 0.04, atol=1e-12)       # radius about world y
    assert np.isclose(P[:, 1].min(), -0.03) and np.isclose(P[:, 1].max(), 0.03)


def test_pan_tilt_snapshot_draws_links_joints_and_the_arm():
    from soft_twin_core.solve.constrained import solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    eq = solve_equilibrium(mech, {"tendon_z_pos": 1.0}, None, {"pan": 0.5, "tilt": -0.3})
    o = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    snap = snapshot(mech, {m.name: m.poses[:, :3, 3] for m in o.members}, o.frames, time=0.5)
    assert snap.caption == "t = 0.50 s"
    assert len(snap.members) == 1 and len(snap.solids) == 2 and len(snap.shapes) == 2 and not snap.links
    # joints at the pan axis (origin) and the tilt axis (0.08 m above), axes along z and the turned y
    assert np.allclose(snap.joints, [[0, 0, 0], [0, 0, 0.08]], atol=1e-12)
    ax_pan, ax_tilt = (a[1] - a[0] for a in snap.joint_axes)
    assert np.allclose(ax_pan / np.linalg.norm(ax_pan), [0, 0, 1], atol=1e-12)
    assert np.allclose(ax_tilt / np.linalg.norm(ax_tilt), [-np.sin(0.5), np.cos(0.5), 0], atol=1e-12)
    # the tilt link's box: centred on its frame, turned by pan and tilt
    vis, T = snap.shapes[1]
    assert vis["shape"] == "box" and np.allclose(T, o.frames["tilt_link"], atol=1e-15)
    # the arm starts 0.05 m along the tilt link's x axis
    R = o.frames["tilt_link"][:3, :3]
    assert np.allclose(snap.members[0][0], [0, 0, 0.08] + 0.05 * R[:, 0], atol=1e-12)
    lo, hi = snap.points.min(axis=0), snap.points.max(axis=0)
    assert np.all(np.isfinite(lo)) and hi[2] >= 0.08 + 0.015 - 1e-9     # the box top is in the bounds


def test_the_ghost_of_a_configuration_is_the_snapshot_drawn_from_its_outputs():
    """scene.skeleton (the IK answer's ghost on the live page): at the
    IK's configuration of the pan-tilt arm, its lines are the snapshot's
    (the member's backbone ending at the tool frame, the two links'
    outlines), from kinematics alone; the twin's own state is not touched."""
    from soft_twin_core.twin import Twin, TwinSettings
    from soft_twin_core.viz.scene import skeleton
    from soft_twin_core.robot.model import read_yaml_file
    twin = Twin(mechanism_from_dict(read_yaml_file(find_file("pan_tilt_arm", "robots"))), TwinSettings())
    q_before = twin.state.q.copy()
    target = twin.outputs().tip_pose[:3, 3] + [0.0, 0.02, 0.01]
    r = twin.query_copy().inverse_kinematics(target, 1e-7)
    assert r.reached and np.array_equal(twin.state.q, q_before)
    mech = twin.mech
    lines = skeleton(mech, r.q, points_per_section=4)
    from soft_twin_core.solve.constrained import make_inputs
    from soft_twin_core.solve.outputs import state_outputs
    o = state_outputs(mech, r.q, np.zeros(len(mech.joints_with("position"))), make_inputs(mech), points_per_section=4)
    assert np.allclose(o.frames[twin.tip][:3, 3], r.achieved_pose[:3, 3], atol=1e-12)
    snap = snapshot(mech, {m.name: m.poses[:, :3, 3] for m in o.members}, o.frames)
    expected = snap.members + snap.links + snap.solids
    assert len(lines) == len(expected) == 1 + 2                     # the arm, the two links' outlines
    for got, want in zip(lines, expected):
        assert np.allclose(got, want, atol=1e-12, equal_nan=True)


def test_pendulum_energies_equal_the_closed_form():
    """sample_energies of a rigid pendulum (one revolute joint about y, a
    point-like mass on a 0.2 m arm, a joint spring) against 1/2 I w^2,
    1/2 k q^2 and m g z."""
    from soft_twin_core.engine.loads import Loads
    from soft_twin_core.files.runs import sample_energies
    from soft_twin_core.solve.constrained import MechanismSimulator, make_inputs
    m, L, k, Ic = 0.5, 0.2, 0.7, 1e-4
    d = {"name": "pendulum", "bodies": [
        {"name": "bob", "type": "link", "joint": {"name": "swing", "type": "revolute", "axis": [0, 1, 0],
                                                   "stiffness": k, "control": "passive"},
         "mass": m, "com": [L, 0, 0], "inertia": [Ic, Ic, Ic, 0, 0, 0]}]}
    mech = mechanism_from_dict(d)
    sim = MechanismSimulator(mech, 1e-3)
    q, w = 0.4, -1.3
    sim.q[:] = q
    sim.v[:] = w
    sim.start_multipliers(make_inputs(mech, [], {}, {}, [], Loads(gravity=True), []))
    kin, ela, grav = sample_energies(sim)
    assert kin == pytest.approx(0.5 * (Ic + m * L**2) * w**2, rel=1e-12)
    assert ela == pytest.approx(0.5 * k * q**2, rel=1e-12)
    # rotation q about +y takes the com (L, 0, 0) to (L cos q, 0, -L sin q)
    assert grav == pytest.approx(m * 9.81 * (-L * np.sin(q)), rel=1e-12)


# ---------------------------------------------------------------------------
# soft-twin-sim on the articulated scenarios
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pan_tilt_run(tmp_path_factory):
    """pan_tilt_arm_dynamics for 0.4 s: figures, a GIF, an MCAP and the JSON."""
    d = tmp_path_factory.mktemp("pan_tilt")
    code, _, err = run_cli(["dynamics", "pan_tilt_arm_dynamics", "--duration", "0.4", "--dt", "0.005",
                            "--plot", str(d / "fig"), "--animate", str(d / "run.gif"), "--mcap", str(d / "run.mcap"),
                            "-o", str(d / "run.json")])
    assert code == 0, err
    return d, err


def test_articulated_figures_open_and_show_something(pan_tilt_run):
    d, err = pan_tilt_run
    for stem in FIGURES:
        check_png(d / "fig" / f"{stem}.png")
        svg = (d / "fig" / f"{stem}.svg").read_text()
        assert svg.lstrip().startswith("<?xml") and "<svg" in svg and len(svg) > 5000
    assert f"wrote {2 * len(FIGURES)} figures" in err


def test_articulated_run_samples_frames_and_energies(pan_tilt_run):
    d, _ = pan_tilt_run
    out = json.loads((d / "run.json").read_text())
    assert out["members_time"] == pytest.approx(np.arange(11) * 0.04, abs=1e-12)   # one per frame at 25 fps
    rows = [out["time"].index(t) for t in out["members_time"]]
    P = np.array(out["frame_poses"])[:, :, :3, 3]
    assert np.array_equal(P, np.array(out["frame_positions"])[rows])
    R = np.array(out["frame_poses"])[:, :, :3, :3]
    assert np.allclose(np.einsum("bfij,bfkj->bfik", R, R), np.eye(3), atol=1e-12)
    # the pan link turns by the pan angle about z
    pan = np.array(out["joint_positions"])[rows, 0]
    k = out["frame_names"].index("pan_link")
    assert np.allclose(R[:, k, 0, 0], np.cos(pan), atol=1e-12) and np.allclose(R[:, k, 1, 0], np.sin(pan), atol=1e-12)
    E = np.array(out["energies"])
    assert E.shape == (11, 3) and np.all(E[1:, 0] > 0) and np.all(E[:, 1] >= 0)


def test_articulated_gif_plays_in_real_time_and_moves(pan_tilt_run):
    d, err = pan_tilt_run
    with Image.open(d / "run.gif") as im:
        assert im.size == (1120, 448)
        assert im.n_frames == 11                   # t = 0, 0.04, ..., 0.4 s at 25 fps
        durations, frames = [], []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
            frames.append(np.asarray(im.convert("RGB"), dtype=float))
    assert durations == [40] * 11
    assert all(ink(Image.fromarray(f.astype(np.uint8))) > 0.01 for f in frames)
    assert np.mean(np.any(frames[0] != frames[-1], axis=2)) > 0.001
    assert "animation: frame 11/11" in err and "(11 frames at 25 fps, 0.44 s)" in err


def test_animation_frames_draw_the_links_and_joints():
    """A frame with the links' shapes and joints differs from one without
    them where the shapes are, and the shapes are inside the fixed camera."""
    from soft_twin_core.solve.constrained import solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    from soft_twin_core.viz.animate import FrameDrawer
    from soft_twin_core.viz.scene import Snapshot
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    eq = solve_equilibrium(mech, {}, None, {"pan": 0.3, "tilt": 0.2})
    o = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    full = snapshot(mech, {m.name: m.poses[:, :3, 3] for m in o.members}, o.frames, time=0.0)
    bare = Snapshot(full.members, time=0.0)
    drawer = FrameDrawer([full])
    try:
        a, b = drawer.frame(full).astype(int), drawer.frame(bare).astype(int)
    finally:
        drawer.close()
    assert a.shape == (448, 1120, 3)
    diff = np.any(np.abs(a - b) > 60, axis=2)
    assert diff.sum() > 300                        # the pan cylinder, tilt box and joint markers
    # in all three views (side, top, 3D: thirds of the frame)
    assert all(diff[:, k * 373:(k + 1) * 373].sum() > 50 for k in range(3))


@pytest.mark.parametrize("scenario,members", [("soft_gripper_grasp", 3), ("planar_parallel_robot", 2)])
def test_other_articulated_scenarios_plot_and_animate(scenario, members, tmp_path):
    code, _, err = run_cli(["dynamics", scenario, "--duration", "0.08", "--dt", "0.005", "--plot", str(tmp_path),
                            "--animate", str(tmp_path / "a.gif"), "-o", str(tmp_path / "r.json")])
    assert code == 0, err
    for stem in ("backbone_shapes", "frames", "strains", "energies"):
        check_png(tmp_path / f"{stem}.png")
    out = json.loads((tmp_path / "r.json").read_text())
    assert len(out["members"][0]) == members
    for m in out["members"][0]:
        check_png(tmp_path / f"internal_wrenches_{m}.png")
    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 3 and im.info["duration"] == 40


def test_articulated_mp4_frames_size_rate(tmp_path):
    import imageio.v2 as iio
    path = tmp_path / "run.mp4"
    code, _, err = run_cli(["dynamics", "soft_gripper_grasp", "--duration", "0.25", "--dt", "0.005",
                            "--animate", str(path), "--fps", "20", "-o", str(tmp_path / "r.json")])
    assert code == 0, err
    with iio.get_reader(str(path)) as r:
        meta = r.get_meta_data()
        frames = [f for f in r]
    assert meta["fps"] == pytest.approx(20.0)
    assert len(frames) == 6                        # 0.25 s at 20 fps, both ends
    assert frames[0].shape == (448, 1120, 3)
    assert meta["duration"] == pytest.approx(6 / 20, abs=0.051)
    assert all(ink(Image.fromarray(f)) > 0.01 for f in frames)
    assert np.mean(np.abs(frames[0].astype(float) - frames[-1].astype(float)) > 40) > 0.0005   # fingers close


def test_render_from_the_articulated_json_equals_the_live_figures(pan_tilt_run):
    d, _ = pan_tilt_run
    code, _, err = run_cli(["render", str(d / "run.json"), "--scenario", "pan_tilt_arm_dynamics",
                            "--plot", str(d / "again")])
    assert code == 0, err
    for stem in FIGURES:
        a = np.asarray(Image.open(d / "fig" / f"{stem}.png"))
        b = np.asarray(Image.open(d / "again" / f"{stem}.png"))
        assert a.shape == b.shape and np.array_equal(a, b), stem


def test_render_of_an_articulated_json_needs_its_robot(pan_tilt_run):
    d, _ = pan_tilt_run
    code, _, err = run_cli(["render", str(d / "run.json"), "--plot", str(d / "x")])
    assert code == 2 and "give the run's robot" in err and "--scenario" in err
    code, _, err = run_cli(["render", str(d / "run.json"), "--plot", str(d / "x"), "--robot", "tendon_arm"])
    assert code == 2 and "a run of another robot" in err and "'pan_tilt_arm'" not in err, err


# ---------------------------------------------------------------------------
# MCAP
# ---------------------------------------------------------------------------

def test_articulated_mcap_reads_back_with_the_mcap_libraries(pan_tilt_run):
    """Read with mcap's own reader and decoder: every topic, one message per
    sample, stamps increasing, values those of the run."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    d, err = pan_tilt_run
    out = json.loads((d / "run.json").read_text())
    msgs = {}
    with open(d / "run.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        schemas = {s.name for s in reader.get_summary().schemas.values()}
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert schema.encoding == "ros2msg"
            msgs.setdefault(channel.topic, []).append((message.log_time, decoded))
    ns = "/soft_twin_sim"
    topics = {f"{ns}/joint_states", f"{ns}/backbones/arm", f"{ns}/backbone", f"{ns}/tip_pose", f"{ns}/strains", "/tf",
              f"{ns}/joint_wrenches/pan", f"{ns}/joint_wrenches/tilt"}
    assert set(msgs) == topics
    assert {"sensor_msgs/msg/JointState", "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/PoseArray"} <= schemas
    n = len(out["members_time"])
    assert all(len(v) == n for v in msgs.values())
    for v in msgs.values():
        assert all(b[0] > a[0] for a, b in zip(v, v[1:]))
    rows = [out["time"].index(t) for t in out["members_time"]]
    js = [m for _, m in msgs[f"{ns}/joint_states"]]
    assert list(js[0].name) == ["pan", "tilt"]
    assert np.array_equal([m.position for m in js], np.array(out["joint_positions"])[rows])
    assert np.array_equal([m.effort for m in js], np.array(out["joint_efforts"])[rows])
    bb = [m for _, m in msgs[f"{ns}/backbones/arm"]]
    assert np.array_equal([[[p.position.x, p.position.y, p.position.z] for p in m.poses] for m in bb],
                          [s["arm"]["positions"] for s in out["members"]])
    # ~/backbone: the main member's, as the node publishes it
    assert [list(m.poses) for _, m in msgs[f"{ns}/backbone"]] == [list(m.poses) for m in bb]
    tf = msgs["/tf"][-1][1]
    tilt = next(t for t in tf.transforms if t.child_frame_id == "soft_twin_sim/tilt_link")
    assert tilt.header.frame_id == "base_link"
    assert "wrote" in err and f"({n} states" in err


def test_plots_from_the_mcap_equal_those_of_the_run(tmp_path):
    """Every sample written (--backbone-every 1): the figures drawn from the
    MCAP read back equal, pixel for pixel, those drawn from the run."""
    from soft_twin_core.files.recording import read_node_recording
    code, _, err = run_cli(["dynamics", "pan_tilt_arm_dynamics", "--duration", "0.1", "--dt", "0.005",
                            "--backbone-every", "1", "--plot", str(tmp_path / "live"),
                            "--mcap", str(tmp_path / "run.mcap"), "-o", str(tmp_path / "run.json")])
    assert code == 0, err
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    out = json.loads((tmp_path / "run.json").read_text())
    rec = read_node_recording(str(tmp_path / "run.mcap"), mech)
    assert rec["time"] == pytest.approx(out["time"], abs=1e-9)
    assert np.allclose(rec["frame_poses"], out["frame_poses"], rtol=0, atol=1e-12)
    assert np.array_equal(rec["strains"], out["strains"])
    assert np.allclose(rec["transmitted_wrenches"],
                       np.array(out["transmitted_wrenches"])[:, [out["transmitted_names"].index(j)
                                                                 for j in ("pan", "tilt")]], rtol=0, atol=0)
    code, _, err = run_cli(["render", str(tmp_path / "run.mcap"), "--scenario", "pan_tilt_arm_dynamics",
                            "--plot", str(tmp_path / "rec"), "--animate", str(tmp_path / "rec.gif")])
    assert code == 0, err
    for stem in ("backbone_shapes", "joint_states", "joint_wrenches", "frames", "strains"):
        a = np.asarray(Image.open(tmp_path / "live" / f"{stem}.png"))
        b = np.asarray(Image.open(tmp_path / "rec" / f"{stem}.png"))
        assert a.shape == b.shape and np.array_equal(a, b), stem
    with Image.open(tmp_path / "rec.gif") as im:
        assert im.n_frames == 3                     # 0.1 s at 25 fps


def test_articulated_statics_figures_and_frame(tmp_path):
    code, out, err = run_cli(["statics", "planar_parallel_robot", "--plot", str(tmp_path / "fig"),
                              "--animate", str(tmp_path / "eq.gif")])
    assert code == 0, err
    for stem in ("backbone_shapes", "internal_wrenches_rod1", "internal_wrenches_rod2"):
        check_png(tmp_path / "fig" / f"{stem}.png")
    with Image.open(tmp_path / "eq.gif") as im:
        assert im.n_frames == 1 and im.size == (1120, 448) and ink(im) > 0.01
    r = json.loads(out)
    # the platform's pose in the JSON is its frame's: position equal, rotation orthonormal
    k = r["frame_names"].index("platform")
    T = np.array(r["frame_poses"][k])
    assert np.array_equal(T[:3, 3], r["frame_positions"][k]) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))


def test_view_plays_an_articulated_run(pan_tilt_run):
    """soft-twin-sim view of an articulated run (JSON and MCAP): the page is
    served and the states are shown in real time."""
    import socket
    import threading
    import time
    import urllib.request
    from soft_twin_core.viz import render
    d, _ = pan_tilt_run
    for run in ("run.json", "run.mcap"):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        args = cli._parser().parse_args(["view", str(d / run), "--scenario", "pan_tilt_arm_dynamics",
                                         "--port", str(port), "--seconds", "1.5"])
        result = {}
        th = threading.Thread(target=lambda: result.setdefault("updates", render.view_main(args)))
        th.start()
        html, end = None, time.monotonic() + 20
        while html is None and time.monotonic() < end:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                    html = r.read().decode("utf-8", "replace")
            except OSError:
                time.sleep(0.1)
        th.join(30)
        assert html is not None and "<html" in html.lower()
        # 0.4 s of run sampled every 0.04 s (11 states), looped for 1.5 s: about 3.5 loops (38 states);
        # at least one whole loop on a loaded machine, never faster than real time
        assert 11 <= result["updates"] <= 42, (run, result)


def test_a_tree_robots_statics_sweep_plots_its_tip(tmp_path):
    """One statics renderer for every robot: a sweep of an in-plane force on
    a gripper finger draws its tip frame against the angle and the shapes,
    and the tip moves with the load's direction."""
    scen = tmp_path / "sweep.yaml"
    scen.write_text("robot: soft_gripper\ngravity: false\n"
                    "loads: [{member: finger_2, s: tip, in_plane_force: {magnitude: 0.3, angle_deg: 0}}]\n")
    code, _, err = run_cli(["statics", str(scen), "--sweep-angle", "0:90:45", "--plot", str(tmp_path / "fig"),
                            "-o", str(tmp_path / "r.json")])
    assert code == 0, err
    for stem in ("sweep_tip", "sweep_shapes"):
        check_png(tmp_path / "fig" / f"{stem}.png")
    r = json.loads((tmp_path / "r.json").read_text())
    tips = np.array([x["tip_position"] for x in r])
    assert [x["angle_deg"] for x in r] == [0.0, 45.0, 90.0] and np.ptp(tips[:, 1]) > 1e-4
