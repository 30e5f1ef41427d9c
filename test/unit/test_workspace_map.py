"""Workspaces over the actuation space (soft_twin_core.planning.reach) and
the `soft-twin-sim workspace` command."""

import json
import math

import numpy as np
import pytest

from soft_twin_core.files.scenario import scenario_from_dict
from soft_twin_core.planning.reach import (actuation_ranges, hull_summary, parse_workspace_options,
                                           sample_actuations, workspace_of)
from rod_statics import solve_statics


def test_hull_volume_area_and_degenerate_clouds():
    rng = np.random.default_rng(1)
    cube = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float) * [0.1, 0.2, 0.3]
    P = np.vstack([cube, rng.random((50, 3)) * [0.1, 0.2, 0.3]])
    h = hull_summary(P)
    assert h["dimension"] == 3
    assert h["volume_m3"] == pytest.approx(0.006, rel=1e-12)
    assert h["area_m2"] == pytest.approx(2 * (0.02 + 0.03 + 0.06), rel=1e-12)
    assert sorted(h["boundary"]) == list(range(8))
    assert h["extent_max"] == pytest.approx([0.1, 0.2, 0.3])
    # a sphere: the hull of many points on it tends to 4/3 pi r^3 from below
    v = rng.normal(size=(4000, 3))
    S = 0.2 * v / np.linalg.norm(v, axis=1, keepdims=True)
    hs = hull_summary(S)["volume_m3"]
    assert 0.98 * 4 / 3 * math.pi * 0.2 ** 3 < hs < 4 / 3 * math.pi * 0.2 ** 3
    # planar (a tilted unit square) and a line, NaN rows ignored
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    sq = np.vstack([np.c_[rng.random((30, 2)), np.zeros(30)], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]]) @ R.T
    h = hull_summary(np.vstack([sq, [np.nan] * 3]))
    assert (h["dimension"], h["volume_m3"]) == (2, 0.0) and h["area_m2"] == pytest.approx(1.0, rel=1e-9)
    h = hull_summary(np.outer(np.linspace(0, 2, 9), [0, 0.6, 0.8]))
    assert h["dimension"] == 1 and h["length_m"] == pytest.approx(2.0)


def test_samples_stay_within_the_limits_and_include_the_corners():
    sc = scenario_from_dict({"robot": "tendon_arm"})
    opts = parse_workspace_options({"samples": 30, "actuators": ["tendon_y_pos", "tendon_z_pos"],
                                    "limits": {"tendon_y_pos": 3.0, "tendon_z_pos": [1.0, 5.0]}}, "w")
    U, corner = sample_actuations(sc.model, opts)
    assert U.shape == (34, 4) and corner.sum() == 4
    assert {tuple(u) for u in U[corner]} == {(0, 0, 1, 0), (3, 0, 1, 0), (0, 0, 5, 0), (3, 0, 5, 0)}
    assert np.all(U[:, 1] == 0) and np.all(U[:, 3] == 0)
    assert U[:, 0].min() >= 0 and U[:, 0].max() <= 3 and U[:, 2].min() >= 1 and U[:, 2].max() <= 5
    # no range: the robot's limit, else an error naming the actuator
    with pytest.raises(ValueError, match="tendon_y_pos has no limit"):
        actuation_ranges(sc.model, parse_workspace_options({}, "w"))
    robot = {"segments": [{"length": 0.2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
                           "material": {"youngs_modulus": 1e6, "density": 1000}}],
             "actuators": [{"name": "t", "offset": [0.005, 0], "limit": 2.0}]}
    m = scenario_from_dict({"robot": robot}).model
    assert actuation_ranges(m, parse_workspace_options({}, "w"))[2].tolist() == [2.0]
    with pytest.raises(ValueError, match="exceeds the robot file's limit 2.0"):
        actuation_ranges(m, parse_workspace_options({"limit": 3.0}, "w"))


def test_default_robot_workspace_extent_is_reached_at_the_actuation_limits():
    """The default arm, its +y and +z tendons up to 4 N: the corner samples
    equal direct statics at those inputs, and the cloud's extent in every
    direction is reached at a corner (the inputs at their limits)."""
    sc = scenario_from_dict({"robot": "tendon_arm"})
    opts = parse_workspace_options({"samples": 40, "limit": 4.0, "seed": 3,
                                    "actuators": ["tendon_y_pos", "tendon_z_pos"]}, "w")
    w = workspace_of(sc, opts)
    assert not w["failed"]
    P, c = w["points"], w["corner"]
    direct = np.array([solve_statics(sc.model, u).tip_pose[:3, 3]
                       for u in ([0, 0, 0, 0], [4, 0, 0, 0], [0, 0, 4, 0], [4, 0, 4, 0])])
    assert P[c] == pytest.approx(direct, abs=1e-12)
    h = w["hull"]
    assert h["extent_max"] == pytest.approx(direct.max(axis=0), abs=1e-12)
    assert h["extent_min"] == pytest.approx(direct.min(axis=0), abs=1e-12)
    assert h["dimension"] == 2 or h["volume_m3"] < 1e-4      # two inputs: a (curved) sheet


def test_workspace_command_writes_points_summary_and_plot(tmp_path, capsys):
    from soft_twin_core.cli import main
    from soft_twin_core.studies.cluster import read_rows
    out = tmp_path / "ws"
    rc = main(["workspace", "tendon_arm", "--limit", "3", "--samples", "20", "--actuators",
               "tendon_y_pos,tendon_z_neg", "-o", str(out)])
    assert rc == 0
    s = json.loads((out / "workspace.json").read_text())
    assert s["samples"] == 24 and s["ranges"]["tendon_z_neg"] == [0.0, 3.0] and not s["failed"]
    rows = read_rows(out / "points.parquet")
    assert len(rows) == 24 and sum(r["corner"] for r in rows) == 4
    assert (out / "workspace.png").stat().st_size > 20_000
    assert (out / "points.csv").read_text().count("\n") == 25
    assert json.loads(capsys.readouterr().out)["extent_max_m"] == s["extent_max_m"]
    assert main(["workspace", "tendon_arm", "-o", str(tmp_path / "x")]) == 2      # no limits: refused
    assert "tendon_y_pos has no limit" in capsys.readouterr().err


def test_workspace_per_case_in_a_study(tmp_path):
    from soft_twin_core.studies.cluster import read_rows, run_study
    from soft_twin_core.studies.study import study_from_dict
    stdy = study_from_dict({"name": "ws", "robot": "tendon_arm", "parameters": [
        {"path": "actuators[0].offset[0]", "values": [0.005, 0.009]}],
        "compute": {"workspace": {"samples": 6, "limit": 3.0, "actuators": ["tendon_y_pos", "tendon_z_pos"]}}})
    res = run_study(stdy, tmp_path / "o", serial=True, log=lambda m: None)
    assert res["ok"] == 2
    rows = read_rows(tmp_path / "o" / "results.parquet")
    pts = read_rows(tmp_path / "o" / "points.parquet")
    assert len(pts) == 2 * 10 and {p["case"] for p in pts} == {0, 1}
    # a larger offset bends the arm further towards +y at the same tension
    assert rows[1]["workspace.y_max_m"] > rows[0]["workspace.y_max_m"] > 0
    for r in rows:
        ys = [p["tip_position_y"] for p in pts if p["case"] == r["case"]]
        assert r["workspace.y_max_m"] == max(ys)
    assert (tmp_path / "o" / "plots" / "workspace_clouds.png").exists()
    assert (tmp_path / "o" / "plots" / "workspace_case_1.png").exists()


def test_a_tree_robots_workspace_turns_with_its_pan_joint(tmp_path, capsys):
    """The pan-tilt arm's workspace over two tendons, its joints held by the
    scenario: the tool's cloud with the pan joint at 0.5 rad is the cloud
    at 0 turned by 0.5 rad about the world z axis (gravity along z: the pan
    turns the whole problem), and the command line maps a tree robot too."""
    from soft_twin_core.cli import main
    opts = parse_workspace_options({"samples": 8, "limit": 3.0, "seed": 1,
                                    "actuators": ["tendon_y_pos", "tendon_z_pos"]}, "w")
    clouds = {}
    for pan in (0.0, 0.5):
        sc = scenario_from_dict({"robot": "pan_tilt_arm", "joint_positions": {"pan": pan, "tilt": -0.3}})
        w = workspace_of(sc, opts)
        assert not w["failed"] and len(w["points"]) == 12
        clouds[pan] = w["points"]
    c, s = math.cos(0.5), math.sin(0.5)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert np.abs(clouds[0.5] - clouds[0.0] @ Rz.T).max() < 1e-9
    assert np.ptp(clouds[0.0], axis=0).max() > 0.01                 # the tendons move the tool
    out = tmp_path / "ws"
    assert main(["workspace", "pan_tilt_arm", "--limit", "2", "--samples", "4", "--actuators",
                 "tendon_y_pos", "-o", str(out)]) == 0
    assert json.loads((out / "workspace.json").read_text())["samples"] == 6
