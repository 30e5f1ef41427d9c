"""Scenario runs of soft articulated robots through ``soft-twin-sim``
(statics and dynamics, JSON and CSV alike; errors name the field)."""

import csv
import json

import numpy as np
import pytest

from soft_twin_core.cli import main
from soft_twin_core.robot.model import find_file
from rod_statics import solve_statics


def _run(tmp_path, *args):
    out = tmp_path / "out.txt"
    rc = main([*args, "--output", str(out)])
    return rc, out.read_text() if out.exists() else ""


def test_fixed_fixed_beam_statics_json_balances(tmp_path):
    rc, text = _run(tmp_path, "statics", "fixed_fixed_beam")
    assert rc == 0
    r = json.loads(text)
    clamp = np.array(r["constraint_wrenches"][0])
    base = np.array(r["transmitted_wrenches"][0])
    mid = np.array(r["frame_positions"][r["frame_names"].index("mid")])
    tip = np.array(r["frame_positions"][r["frame_names"].index("beam_tip")])
    weight = 1000.0 * np.pi * 0.01**2 * 1.0 * 9.81
    # vertical forces: the two reactions carry the load and the weight
    assert abs(clamp[2] + base[2] - 50.0 - weight) < 1e-9 * 50
    # moments about the base: the mid load, the clamp and the distributed weight (its centroid, ~mid-span)
    assert r["members"]["beam"]["normal_stress"][0] > 1e6          # Pa, at the clamped root
    # 8 sections sampled at the CLI's 10 points each and the end
    assert len(r["members"]["beam"]["s"]) == 81 and r["members"]["beam"]["s"][-1] == pytest.approx(1.0)
    assert mid[2] < 0 and abs(tip[2]) < 1e-12


def test_pan_tilt_dynamics_csv_equals_json(tmp_path):
    args = ("dynamics", "pan_tilt_arm_dynamics", "--duration", "0.1", "--dt", "0.005", "--record-every", "4")
    rc, js = _run(tmp_path, *args)
    assert rc == 0
    r = json.loads(js)
    rc, cs = _run(tmp_path, *args, "--format", "csv")
    assert rc == 0
    rows = list(csv.DictReader(cs.splitlines()))
    assert len(rows) == len(r["time"]) == 6           # t = 0, 4 steps apart, the last
    assert r["joint_names"] == ["pan", "tilt"]
    for k, row in enumerate(rows):
        assert float(row["time"]) == r["time"][k]
        assert float(row["joint_efforts_tilt"]) == r["joint_efforts"][k][1]
        assert float(row["frame_positions_tool_z"]) == r["frame_positions"][k][r["frame_names"].index("tool")][2]
        assert float(row["peak_normal_stress_arm"]) == r["peak_normal_stress"][k][0]
    # the pan joint follows its spline (at rest at t = 0) and its effort is an output
    assert r["joint_positions"][0][0] == 0.0 and r["joint_positions"][-1][0] > 0.0
    assert all(np.isfinite(e[0]) for e in r["joint_efforts"])
    assert max(r["constraint_error"]) == 0.0          # no constraints on this robot


@pytest.mark.parametrize("patch,field", [
    ({"joint_trajectories": {"elbow": [[0, 0], [1, 1]]}}, "scenario.joint_trajectories"),
    ({"joint_positions": {"tilt": 2.5}}, "outside the joint limits"),
    ({"loads": [{"frame": "nowhere", "force": [0, 0, 1]}]}, "scenario.loads[0].frame"),
    ({"actuation": {"tendon_z_pos": -1.0}}, "tendon_z_pos"),
    ({"joint_trajectories": {"pan": [[1, 0], [0, 1]]}}, "times must increase"),
    ({"base_trajectory": [[0, 0, 0, 0, 0, 0, 0]]}, "scenario.base_trajectory"),
])
def test_articulated_scenario_errors_name_the_field(tmp_path, patch, field, capsys):
    import yaml
    d = {"robot": str(find_file("pan_tilt_arm", "robots")), **patch}
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    rc, text = _run(tmp_path, "statics", str(p))
    assert rc == 2 and text == ""
    assert field in capsys.readouterr().err


def test_prescribed_base_trajectory_moves_the_robot(tmp_path):
    import yaml
    robot = {"name": "carried", "gravity": [0, 0, -9.81], "base": {"motion": "prescribed"},
             "bodies": [{"name": "arm", "type": "member", "segments": [
                 {"name": "arm", "length": 0.3, "sections": 3, "cross_section": {"shape": "solid_circle", "radius": 0.01},
                  "material": {"youngs_modulus": 1e7, "density": 1000.0, "viscosity": 1e4},
                  "free_modes": "bending_torsion"}]}]}
    sc = {"robot": robot, "base_trajectory": [[0.0, 0, 0, 0, 0, 0, 0], [0.5, 0.1, 0, 0.05, 0, 0, 0.3]]}
    p = tmp_path / "carried.yaml"
    p.write_text(yaml.safe_dump(sc))
    rc, text = _run(tmp_path, "dynamics", str(p), "--duration", "0.6", "--dt", "0.005", "--record-every", "20",
                    "--backbone-every", "60")
    assert rc == 0, text
    r = json.loads(text)
    base = np.array([f[r["frame_names"].index("base")] for f in r["frame_positions"]])
    np.testing.assert_allclose(base[-1], [0.1, 0, 0.05], atol=1e-10)      # at rest at the end of the spline
    assert max(r["constraint_error"]) < 1e-10
    # the base's constraint wrench: the support carrying and accelerating the arm
    assert r["constraint_names"] == ["base"] and np.isfinite(r["constraint_wrenches"]).all()
    assert r["members_time"] == [0.0, 0.3, 0.6] and "velocities" in r["members"][-1]["arm"]


def test_articulated_run_animates(tmp_path):
    import imageio.v3 as iio
    gif = tmp_path / "pan_tilt.gif"
    rc, _ = _run(tmp_path, "dynamics", "pan_tilt_arm_dynamics", "--duration", "0.5", "--dt", "0.01",
                 "--animate", str(gif), "--fps", "10")
    assert rc == 0
    frames = iio.imread(gif, index=None)
    assert len(frames) == 6 and frames.shape[1] > 100
    assert np.abs(frames[-1].astype(float) - frames[0].astype(float)).mean() > 0.5     # the arm moved
    rc, _ = _run(tmp_path, "dynamics", "pan_tilt_arm_dynamics", "--duration", "0.1", "--dt", "0.01",
                 "--plot", str(tmp_path / "figs"))
    assert rc == 0 and (tmp_path / "figs" / "joint_states.png").is_file()    # issue 12: test_articulated_visuals


def test_dynamics_histories_carry_transmitted_wrenches_and_strains(tmp_path):
    rc, js = _run(tmp_path, "dynamics", "pan_tilt_arm_dynamics", "--duration", "0.02", "--dt", "0.01")
    r = json.loads(js)
    rc2, cs = _run(tmp_path, "dynamics", "pan_tilt_arm_dynamics", "--duration", "0.02", "--dt", "0.01",
                   "--format", "csv")
    assert rc == rc2 == 0
    rows = list(csv.DictReader(cs.splitlines()))
    assert np.array(r["transmitted_wrenches"]).shape == (3, len(r["transmitted_names"]), 6)
    assert np.array(r["strains"]).shape == (3, 4, 6) and r["section_names"] == ["arm_0", "arm_1", "arm_2", "arm_3"]
    assert float(rows[-1]["transmitted_wrenches_tilt_fz"]) == r["transmitted_wrenches"][-1][1][2]
    assert float(rows[-1]["strains_arm_3_bending_y"]) == r["strains"][-1][3][4]
    # the base's vertical reaction at rest carries the robot's weight
    assert r["transmitted_wrenches"][0][0][2] > 0


def test_gripper_and_parallel_robot_scenarios(tmp_path):
    rc, js = _run(tmp_path, "statics", "planar_parallel_robot")
    assert rc == 0
    r = json.loads(js)
    names = r["transmitted_names"]
    f = np.array(r["transmitted_wrenches"][names.index("rod1_0")]) + np.array(
        r["transmitted_wrenches"][names.index("rod2_0")])
    weight = 9.81 * (0.05 + 2 * 0.4 * 6450.0 * np.pi * 0.002**2)
    assert abs(f[0] + 2.0) < 1e-9 and abs(f[2] - 3.0 - weight) < 1e-6      # balance: load + weight
    rc, js = _run(tmp_path, "dynamics", "soft_gripper_grasp", "--duration", "0.3", "--dt", "0.01",
                  "--record-every", "10")
    assert rc == 0
    r = json.loads(js)
    assert r["joint_names"] == ["wrist"] and r["joint_positions"][-1][0] > 0.05
    tips = np.array(r["frame_positions"][-1])
    rad = [np.hypot(*tips[r["frame_names"].index(f"finger_{k}_tip")][:2]) for k in range(3)]
    assert max(rad) < 0.03 and np.ptp(rad) < 1e-6                # the fingers close alike


def test_member_samples_in_json_and_csv_alike(tmp_path):
    args = ("dynamics", "pan_tilt_arm_dynamics", "--duration", "0.04", "--dt", "0.01", "--backbone-every", "2",
            "--points-per-section", "2")
    rc, js = _run(tmp_path, *args)
    rc2, cs = _run(tmp_path, *args, "--format", "csv")
    assert rc == rc2 == 0
    r = json.loads(js)
    rows = list(csv.DictReader(cs.splitlines()))
    assert r["members_time"] == [0.0, 0.02, 0.04] and r["member_point_names"][-1] == "arm_8"   # 4 sections x 2 + 1
    for k, t in enumerate(r["members_time"]):
        row = rows[r["time"].index(t)]
        assert float(row["member_internal_wrenches_arm_0_my"]) == r["members"][k]["arm"]["internal_wrench"][0][4]
        assert float(row["member_positions_arm_4_z"]) == r["members"][k]["arm"]["positions"][4][2]
    assert rows[1]["member_positions_arm_4_z"] == ""          # not a sample time


# ------------------------------------------------------------------ one schema for every robot (issue 26)

def _scenario(d):
    from soft_twin_core.files.scenario import scenario_from_dict
    return scenario_from_dict(d, ".")


def test_a_tree_robot_takes_loads_on_members_load_steps_and_initial_strains():
    from soft_twin_core.files.scenario import run_dynamics, run_statics
    w = [0.0, 0.05, -0.1]
    base = {"robot": "soft_gripper", "actuation": {"close_1": 1.0}, "gravity": False}
    on_member = run_statics(_scenario({**base, "loads": [{"member": "finger_1", "s": "tip", "force": w}]}))
    on_frame = run_statics(_scenario({**base, "loads": [{"frame": "finger_1_tip", "force": w}]}))
    stepped = run_statics(_scenario({**base, "load_steps": 4,
                                     "loads": [{"member": "finger_1", "s": "tip", "force": w}]}))
    for r in (on_frame, stepped):
        assert np.allclose(r["strains"], on_member["strains"], atol=1e-9)
    assert stepped["iterations"] > on_member["iterations"]            # four warm-started solves
    # a distributed load on one finger bends that finger only
    dist = run_statics(_scenario({**base, "actuation": {}, "loads": [
        {"member": "finger_2", "distributed": True, "force": [0.5, 0.5, 0], "start": 0.02}]}))   # N/m, across it
    rest = run_statics(_scenario({**base, "actuation": {}}))
    moved = {m: np.abs(np.array(dist["members"][m]["strains"]) - rest["members"][m]["strains"]).max()
             for m in ("finger_0", "finger_1", "finger_2")}
    assert moved["finger_2"] > 1e-3 and moved["finger_0"] < 1e-12 and moved["finger_1"] < 1e-12
    # dynamics starts from the given strains (tree order; here finger_0's first section bent)
    sc = _scenario({**base, "actuation": {}, "initial_strains": [[1, 0, 0, 0, 0, 5.0]] + [[1, 0, 0, 0, 0, 0]] * 8})
    start = np.array(run_dynamics(sc, 0.002, 0.001)["strains"][0])
    assert start[0, 5] == pytest.approx(5.0) and np.abs(start[1:, 1:]).max() < 1e-12


def test_a_rod_takes_a_load_on_its_tip_frame_as_on_its_tip():
    from soft_twin_core.files.scenario import run_statics
    base = {"robot": "tendon_arm", "actuation": {"tendon_y_pos": 1.0}}
    a = run_statics(_scenario({**base, "loads": [{"s": "tip", "force": [0.1, 0, -0.2]}]}))
    b = run_statics(_scenario({**base, "loads": [{"frame": "tip", "force": [0.1, 0, -0.2]}]}))
    assert np.allclose(a["tip_position"], b["tip_position"], atol=1e-12)
    assert _scenario(base).mech.members[0].name == "backbone"


@pytest.mark.parametrize("load, text", [
    ({"member": "thumb", "s": 0.01, "force": [0, 0, 1]}, "scenario.loads[0].member: 'thumb' is not a soft member"),
    ({"frame": "nose", "force": [0, 0, 1]}, "scenario.loads[0].frame: 'nose' is not a frame"),
    ({"s": 0.01, "frame": "world", "axes": "body"}, "give the axes once"),
    ({"member": "finger_0", "s": 0.5}, "scenario.loads[0].s: must lie in [0, 0.08] m"),
    ({"force": [0, 0, 1]}, "give s (an arc length on a member), distributed: true, or frame"),
    ({"frame": "palm", "distributed": False, "force": [0, 0, 1]}, "to load the frame 'palm', give no s"),
    ({"member": "finger_0", "force": [0, 0, 1]}, "scenario.loads[0].s: missing"),
])
def test_load_errors_name_the_field(load, text):
    from soft_twin_core.files.scenario import ScenarioError
    with pytest.raises(ScenarioError) as e:
        _scenario({"robot": "soft_gripper", "loads": [load]})
    assert text in str(e.value)


def test_one_statics_runner_for_every_robot():
    """A rod's statics through the one runner equals the rod's own statics
    (tip, strains, support reaction); a tree robot's result has the same
    fields, its support reaction carries the robot's weight (gravity only)."""
    from soft_twin_core.engine.loads import Loads, PointLoad
    from soft_twin_core.files.scenario import run_statics
    sc = _scenario({"robot": "tendon_arm", "actuation": {"tendon_y_pos": 2.0},
                    "loads": [{"s": 0.3, "force": [0, 0.1, -0.1]}]})
    r = run_statics(sc, 4)
    ref = solve_statics(sc.model, sc.actuation, Loads(point=(PointLoad(0.3, (0, 0.1, -0.1, 0, 0, 0)),)))
    assert np.abs(np.array(r["tip_position"]) - ref.tip_pose[:3, 3]).max() < 1e-9
    assert np.abs(np.array(r["strains"]) - ref.strains).max() < 1e-7
    assert np.abs(np.array(r["base_wrench"]) - ref.base_wrench_world).max() < 1e-7
    assert r["stable"] and len(r["backbone_s"]) == 4 * sc.model.n_sections + 1
    tree = run_statics(_scenario({"robot": "soft_gripper"}), 2)
    for key in ("tip_position", "tip_rotation", "base_wrench", "backbone_s", "backbone_positions",
                "internal_wrenches", "strains", "members", "frame_names", "stable"):
        assert key in tree
    mass = _scenario({"robot": "soft_gripper"}).mech.tree.mass_and_size[0]
    assert tree["base_wrench"][2] == pytest.approx(9.81 * mass, rel=1e-9)
    assert np.allclose(tree["base_wrench"][:2], 0.0, atol=1e-9 * mass)
