"""No silent partial answers (issue 25, items 11 and 12): statics of a
scenario with time-varying inputs says at which time it solved (the end of
the profiles by default, --time T otherwise); a robot name given as a
scenario says so and how to use it; render --plot of a run without backbone
samples names the figures it leaves out; calibrate on a tree robot gives the
reason; a killed Dask worker leaves a trace in the study's output."""
import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def _cli(*args, timeout=300):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "soft_twin_core.cli", *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=timeout)


def test_statics_of_a_profiled_articulated_scenario_solves_where_the_profiles_end():
    """soft_gripper_grasp: the tendons ramp to 3 N by 0.5 s, the wrist to
    0.6 rad by 1 s. Before: solved at t = 0 (fingers open, wrist 0), no word."""
    from soft_twin_core.files.scenario import load_scenario, run_statics
    sc = load_scenario("soft_gripper_grasp")
    end = run_statics(sc)
    assert end["time"] == 1.0 and "joint_trajectories.wrist" in end["time_note"]
    assert end["joint_positions"] == pytest.approx([0.6])
    start = run_statics(sc, time=0.0)
    assert start["time"] == 0.0 and start["joint_positions"] == pytest.approx([0.0])
    # the fingers close: each finger tip moves towards the palm's axis under 3 N
    names = end["frame_names"]
    tips = [i for i, n in enumerate(names) if n.endswith("_tip")]
    r_end = [np.hypot(*np.asarray(end["frame_positions"][i])[:2]) for i in tips]
    r_start = [np.hypot(*np.asarray(start["frame_positions"][i])[:2]) for i in tips]
    assert len(tips) == 3 and all(a < b - 1e-3 for a, b in zip(r_end, r_start)), (r_end, r_start)


def test_statics_of_a_profiled_classic_scenario_and_the_cli_note(tmp_path):
    from soft_twin_core.files.scenario import load_scenario, run_statics
    sc = load_scenario("tendon_arm_dynamics")            # tendon_y_pos: 0 -> 3 N over 0.5 s
    r = run_statics(sc)
    r0 = run_statics(sc, time=0.0)
    assert r["time"] == 0.5 and r0["time"] == 0.0
    assert r["tip_position"][1] > r0["tip_position"][1] + 0.01      # pulled towards +y
    const = run_statics(load_scenario("tendon_arm_statics"))
    assert "time" not in const and "time_note" not in const          # constant inputs: as before
    p = _cli("statics", "soft_gripper_grasp", "--plot", str(tmp_path / "figs"))
    assert p.returncode == 0, p.stderr
    assert ("the scenario's inputs vary in time (actuation_profile.close_0, actuation_profile.close_1, "
            "actuation_profile.close_2, joint_trajectories.wrist): solved at t = 1 s") in p.stderr
    assert json.loads(p.stdout)["time"] == 1.0
    p = _cli("statics", "tendon_arm_dynamics", "--time", "0.25")
    assert p.returncode == 0 and "solved at t = 0.25 s" in p.stderr and json.loads(p.stdout)["time"] == 0.25
    p = _cli("statics", "tendon_arm_dynamics", "--time", "-1")
    assert p.returncode == 2 and "--time" in p.stderr


def test_a_robot_given_as_a_scenario_says_so_and_how_to_use_it():
    for arg in ("tendon_arm", os.path.join("config", "robots", "tendon_arm.yaml")):
        p = _cli("statics", arg)
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
        assert "robot" in p.stderr and "not a scenario" in p.stderr, p.stderr
        assert "soft-twin-sim statics tendon_arm_statics" in p.stderr, p.stderr
        assert "no such file" not in p.stderr


def test_render_plot_without_backbone_samples_names_what_it_leaves_out(tmp_path):
    from soft_twin_core.files.scenario import load_scenario, run_dynamics
    out = run_dynamics(load_scenario("tendon_arm_dynamics"), 0.02, 0.01)
    assert "members" not in out
    run = tmp_path / "run.json"
    run.write_text(json.dumps(out))
    p = _cli("render", str(run), "--plot", str(tmp_path / "figs"), "--scenario", "tendon_arm_dynamics")
    assert p.returncode == 0, p.stderr
    assert ("warning: the run has no member samples, so the backbone_shapes, member internal wrench and energies "
            "figures are left out: run dynamics with --backbone-every K") in p.stderr
    assert (tmp_path / "figs" / "tip.png").exists() and not (tmp_path / "figs" / "backbone_shapes.png").exists()
    p = _cli("render", str(run), "--plot", str(tmp_path / "figs2"))
    assert p.returncode == 2 and "give the run's robot: --scenario S or --robot R" in p.stderr, p.stderr
    p = _cli("render", str(run), "--plot", str(tmp_path / "figs3"), "--robot", "pan_tilt_arm")
    assert p.returncode == 2 and "a run of another robot or discretisation" in p.stderr, p.stderr


def test_calibrate_on_a_tree_robot_gives_the_reason(tmp_path):
    """A tree robot calibrates (it was refused, then it read the file as a
    classic one: "unknown field(s) ['bodies', 'frames']"); a missing file
    is named, without a traceback, for the damping fit too (which takes
    tree robots now)."""
    p = _cli("calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(tmp_path / "d.csv"),
             "--fit", "youngs_modulus")
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert f"sensors file {tmp_path / 's.yaml'}: No such file" in p.stderr and "unknown field" not in p.stderr
    (tmp_path / "s.yaml").write_text("sensors: [{name: t, type: pose, frame: tool, sigma_position: 0.001, "
                                     "sigma_rotation: 0.01}]\n")
    p = _cli("calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(tmp_path / "d.csv"),
             "--fit", "viscosity", "--dynamic")
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert f"data file {tmp_path / 'd.csv'}: No such file" in p.stderr, p.stderr


def test_a_killed_dask_worker_is_named_in_the_study_output(tmp_path):
    """Dask re-runs the chunk of a killed worker elsewhere; before, nothing
    in the log, results or summary said that a worker had died."""
    from soft_twin_core.studies.cluster import run_study, start_local_cluster
    from soft_twin_core.studies.study import study_from_dict
    st = study_from_dict({"name": "kill", "scenario": "tendon_arm_statics",
                          "parameters": [{"path": "scenario.actuation.tendon_y_pos", "range": [0.0, 4.0]}],
                          "design": {"type": "lhs", "samples": 16, "seed": 3}}, ROOT)
    cluster, client = start_local_cluster(2)
    try:
        pids = client.run(os.getpid)
        killed, logs = {}, []

        def kill_one(done, total):
            if done >= 2 and not killed:
                busy = [w for w, tasks in client.processing().items() if tasks]
                if busy:
                    pid = pids[busy[0]]
                    os.kill(pid, signal.SIGKILL)
                    killed.update(pid=pid, worker=busy[0])
        res = run_study(st, tmp_path / "o", client=client, chunk_size=2, log=logs.append, on_progress=kill_one)
        # the scheduler's own record: was a task of ours on the worker when it died?
        under = [m for _, m in client.get_events("all") if isinstance(m, dict)
                 and m.get("action") == "remove-worker" and m.get("processing-tasks")]
    finally:
        client.close()
        cluster.close()
    if not killed or not under:
        pytest.skip("the kill landed between two tasks of the worker (nothing was re-run)")
    assert res["ok"] == 16
    losses = res["worker_losses"]
    assert losses and all(w["worker"] == killed["worker"] and w["rerun"] for w in losses), (losses, killed)
    assert any(f"worker {killed['worker']} died while computing cases" in m and "re-run on another worker" in m
               for m in logs), logs
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["worker_losses"] == losses
    assert "## Workers that died during the run" in (tmp_path / "o" / "summary.md").read_text()
