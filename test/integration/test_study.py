"""Design studies (soft_twin_core.studies.study, study_case, study_dask, study_report):
paths, designs, validation, failures, Dask against a serial run, a killed
worker, resuming, the summary; small studies of the default robot."""

import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from soft_twin_core.studies.cluster import StudyInterrupted, read_rows, run_study
from soft_twin_core.studies.study import (CaseValidationError, StudyError, build_scenario, case_documents,
                                          design_matrix, format_path, get_path, make_cases, parse_path,
                                          study_from_dict, validate_cases)
from rod_statics import solve_statics

ROOT = Path(__file__).resolve().parents[2]
META = {"compute_time_s", "started_unix_s", "worker"}


def _study(**kw):
    d = {"name": "t", "scenario": "tendon_arm_statics",
         "parameters": [{"path": "segments[0].material.youngs_modulus", "values": [1.5e6, 3.0e6]},
                        {"path": "scenario.actuation.tendon_y_pos", "range": [0.0, 3.0], "count": 3}],
         "design": {"type": "grid"}, "compute": {"statics": {"points_per_section": 3}}}
    d.update(kw)
    return study_from_dict(d, str(ROOT / "config" / "studies"))


def _same_rows(a, b, tol=1e-12):
    """Row lists equal column by column (numbers within tol, relative to 1)."""
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        ka, kb = set(ra) - META, set(rb) - META
        assert ka == kb, ka ^ kb
        for k in ka:
            x, y = ra[k], rb[k]
            if isinstance(x, float) and isinstance(y, float):
                assert (math.isnan(x) and math.isnan(y)) or abs(x - y) <= tol * max(1.0, abs(x)), (ra["case"], k, x, y)
            else:
                assert x == y, (ra["case"], k, x, y)


# ----------------------------------------------------------------------------
# Paths and designs
# ----------------------------------------------------------------------------

def test_paths_parse_and_address_the_documents():
    assert parse_path("segments[0].material.youngs_modulus") == ("robot", ["segments", 0, "material",
                                                                            "youngs_modulus"])
    assert parse_path("scenario.loads[0].force[2]") == ("scenario", ["loads", 0, "force", 2])
    assert parse_path("robot.actuators[1].offset") == ("robot", ["actuators", 1, "offset"])
    assert format_path(["actuators", 1, "offset", 0]) == "actuators[1].offset[0]"
    for bad in ("", "segments[0]..length", "[0].x", "segments.[0]", "segments[0].", "scenario", "a b"):
        with pytest.raises(StudyError):
            parse_path(bad)
    doc = {"segments": [{"length": 0.1}]}
    assert get_path(doc, ["segments", 0, "length"]) == 0.1
    with pytest.raises(StudyError, match=r"segments\[3\]: out of range"):
        get_path(doc, ["segments", 3, "length"])
    with pytest.raises(StudyError, match=r"parameters\[0\]\.path.*segments\[7\]"):
        _study(parameters=[{"path": "segments[7].length", "values": [0.1]}])
    with pytest.raises(StudyError, match="parameters\\[0\\].path.*not in the robot"):
        _study(parameters=[{"path": "segmentz[0].length", "values": [0.1]}])


def test_case_documents_change_only_the_addressed_fields():
    st = _study(parameters=[{"path": "actuators[1].offset", "values": [[-0.009, 0.001]]},
                            {"path": "segments[2].cross_section.radius", "values": [0.007]},
                            {"path": "scenario.loads[0].force[2]", "values": [-0.2]}])
    robot, scen = case_documents(st, design_matrix(st)[0])
    assert robot["actuators"][1]["offset"] == [-0.009, 0.001]
    assert robot["segments"][2]["cross_section"]["radius"] == 0.007
    assert scen["loads"][0]["force"] == [0.0, 0.0, -0.2]
    assert st.robot_doc["segments"][2]["cross_section"]["radius"] == 0.008     # base untouched
    robot["segments"][2]["cross_section"]["radius"] = 0.008
    robot["actuators"][1]["offset"] = st.robot_doc["actuators"][1]["offset"]
    assert robot == st.robot_doc


def test_designs_grid_random_lhs():
    st = _study()
    m = design_matrix(st)
    assert len(m) == 6 and [c["scenario.actuation.tendon_y_pos"] for c in m[:3]] == [0.0, 1.5, 3.0]
    assert [c["segments[0].material.youngs_modulus"] for c in m] == [1.5e6] * 3 + [3.0e6] * 3
    axes = [{"path": "segments[0].length", "range": [0.1, 0.2]},
            {"path": "segments[1].material.youngs_modulus", "range": [1e5, 1e7], "scale": "log"},
            {"path": "segments[2].cross_section.radius", "normal": {"mean": 0.008, "std": 1e-4}}]
    for kind in ("random", "lhs"):
        a = design_matrix(_study(parameters=axes, design={"type": kind, "samples": 50, "seed": 3}))
        b = design_matrix(_study(parameters=axes, design={"type": kind, "samples": 50, "seed": 3}))
        c = design_matrix(_study(parameters=axes, design={"type": kind, "samples": 50, "seed": 4}))
        assert a == b and a != c
        L = np.array([x["segments[0].length"] for x in a])
        E = np.array([x["segments[1].material.youngs_modulus"] for x in a])
        assert L.min() >= 0.1 and L.max() <= 0.2 and E.min() >= 1e5 and E.max() <= 1e7
        if kind == "lhs":
            # Latin hypercube: exactly one sample in each of the 50 strata of every axis
            assert sorted(np.floor((L - 0.1) / 0.1 * 50).astype(int)) == list(range(50))
            assert sorted(np.floor(np.log(E / 1e5) / np.log(100) * 50).astype(int)) == list(range(50))
    # random: the first samples stay the same when more are asked for (resume reuses them)
    a = design_matrix(_study(parameters=axes[:1], design={"type": "random", "samples": 5, "seed": 1}))
    b = design_matrix(_study(parameters=axes[:1], design={"type": "random", "samples": 9, "seed": 1}))
    assert a == b[:5]
    # normal: the inverse CDF against scipy.stats.norm
    from scipy.stats import norm
    ax = _study(parameters=axes[2:], design={"type": "lhs", "samples": 4}).axes[0]
    assert ax.from_unit([0.5, norm.cdf(1.0), norm.cdf(-2.0)]) == pytest.approx([0.008, 0.0081, 0.0078], rel=1e-12)
    # relative: base * (1 + x)
    ax = _study(parameters=[{"path": "segments[0].length", "range": [-0.1, 0.1], "relative": True}],
                design={"type": "random", "samples": 2}).axes[0]
    assert ax.from_unit([0.0, 1.0]) == pytest.approx([0.135, 0.165], rel=1e-12)


@pytest.mark.parametrize("bad, match", [
    ({"design": {"type": "grid", "samples": 3}}, "design.samples"),
    ({"design": {"type": "lhs"}}, "design.samples: missing"),
    ({"design": {"type": "sobol", "samples": 3}}, "design.type"),
    ({"parameters": [{"path": "segments[0].length", "range": [0.1, 0.2]}]}, r"count"),
    ({"parameters": [{"path": "segments[0].length", "values": [0.1], "range": [0, 1]}]}, "exactly one"),
    ({"compute": {"dynamics": {"duration": 0.001, "dt": 0.01}}}, "shorter than one time step"),
    ({"compute": {"statics": True}, "record": ["settling_time"]}, "record"),
    ({"compute": {"workspace": {"design": "sobol"}}}, r"workspace\.design"),
    ({"paramters": []}, "unknown field"),
])
def test_bad_study_files_name_the_field(bad, match):
    with pytest.raises(StudyError, match=match):
        _study(**bad)


def test_invalid_cases_reported_by_index_and_field_before_anything_runs(tmp_path):
    st = _study(parameters=[{"path": "segments[1].length", "values": [0.15, -0.02, 0.2]},
                            {"path": "actuators[0].offset[0]", "values": [0.007, 1.0]}])
    cases = make_cases(st)
    with pytest.raises(CaseValidationError) as e:
        validate_cases(st, cases)
    bad = dict(e.value.errors)
    assert sorted(bad) == [2, 3]                    # length -0.02 with either offset
    assert "segments[1].length: must be > 0, got -0.02" in bad[2]
    assert "case 2: (segments[1].length = -0.02, actuators[0].offset[0] = 0.007)" in str(e.value)
    with pytest.raises(CaseValidationError):
        run_study(st, tmp_path / "o", serial=True, log=lambda m: None)
    assert not (tmp_path / "o").exists()            # nothing written, nothing run
    # the command: exit 2 and the case and field on stderr
    f = tmp_path / "bad.yaml"
    f.write_text("scenario: tendon_arm_statics\nparameters:\n  - path: segments[0].length\n"
                 "    values: [0.15, -1.0]\ncompute: {statics: true}\n")
    from soft_twin_core.cli import main
    assert main(["study", str(f), "-o", str(tmp_path / "c"), "--serial"]) == 2
    assert not (tmp_path / "c").exists()


def test_failing_case_recorded_with_its_reason_and_the_study_finishes(tmp_path, capsys):
    st = _study(parameters=[{"path": "scenario.actuation.tendon_y_pos", "values": [1.0, 1000.0, 2.0]}])
    res = run_study(st, tmp_path / "o", serial=True, log=lambda m: None)
    assert (res["ok"], res["failed"], res["lost"]) == (2, 1, 0)
    rows = read_rows(tmp_path / "o" / "results.parquet")
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert rows[1]["error"].startswith("StaticsError: statics did not converge")
    assert rows[1]["statics.tip_position_x"] is None and rows[2]["statics.tip_position_x"] is not None
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["failures"][0]["case"] == 1 and "StaticsError" in summary["failures"][0]["error"]
    csv_lines = (tmp_path / "o" / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 4 and ",failed,\"StaticsError" in csv_lines[2]


# ----------------------------------------------------------------------------
# Outputs against direct calls
# ----------------------------------------------------------------------------

def test_rows_equal_direct_statics_and_the_scenario_runner(tmp_path):
    from soft_twin_core.files.scenario import load_scenario
    from soft_twin_core.robot.model import load_model
    st = _study(record=["tip_pose", "base_wrench", "iterations", "strains", "backbone", "internal_wrenches"])
    run_study(st, tmp_path / "o", serial=True, log=lambda m: None)
    rows = read_rows(tmp_path / "o" / "results.parquet")
    sc = load_scenario("tendon_arm_statics")
    for r in rows:
        E = r["segments[0].material.youngs_modulus"]
        d = json.loads(json.dumps(st.robot_doc))
        d["segments"][0]["material"]["youngs_modulus"] = E
        from soft_twin_core.robot.model import model_from_dict
        m = model_from_dict(d)
        u = sc.actuation.copy()                 # the scenario's tendon_z_neg stays
        u[0] = r["scenario.actuation.tendon_y_pos"]
        eq = solve_statics(m, u, sc.loads_at(None))
        assert [r[f"statics.tip_position_{a}"] for a in "xyz"] == pytest.approx(eq.tip_pose[:3, 3], abs=1e-14)
        assert [r[f"statics.base_wrench_{a}"] for a in ("fx", "fy", "fz", "mx", "my", "mz")] == \
            pytest.approx(eq.base_wrench_world, abs=1e-14)
        from scipy.spatial.transform import Rotation
        q = [r[f"statics.tip_quaternion_{a}"] for a in "xyzw"]
        assert Rotation.from_quat(q).as_matrix() == pytest.approx(eq.tip_pose[:3, :3], abs=1e-12)
        assert r["statics.strains_5_bending_z"] == pytest.approx(eq.strains[5, 5], abs=1e-12)
        from soft_twin_core.files.scenario import run_statics
        sc_case = build_scenario(st, {k: r[k] for k in st.parameter_names})
        ref = run_statics(sc_case, 3)          # the runner's own output, every field
        P = np.array(ref["backbone_positions"])
        assert [r[f"statics.backbone_{len(P) - 1}_{a}"] for a in "xyz"] == pytest.approx(P[-1], abs=0)
        assert r["statics.internal_wrenches_0_my"] == ref["internal_wrenches"][0][4]
        assert r[f"statics.backbone_s_{len(P) - 1}"] == pytest.approx(0.45, abs=1e-15)
    assert load_model("tendon_arm").n_sections == 6


def test_max_stress_of_a_cantilever_is_the_beam_formula():
    """A weightless horizontal cantilever with a vertical tip force F: at the
    clamp N = 0, T = 0 and M = F x_tip (the tip's lever arm), so the largest
    stress is sigma = F x_tip r / I, I = pi r^4 / 4 (solid) or
    pi (ro^4 - ri^4) / 4 (tube)."""
    from soft_twin_core.files.scenario import run_statics, scenario_from_dict
    from soft_twin_core.solve.outputs import max_von_mises
    F = 0.05
    for cs, r_out, I in (({"shape": "solid_circle", "radius": 0.01}, 0.01, math.pi * 0.01 ** 4 / 4),
                         ({"shape": "hollow_tube", "outer_radius": 0.01, "inner_radius": 0.006}, 0.01,
                          math.pi * (0.01 ** 4 - 0.006 ** 4) / 4)):
        robot = {"gravity": [0, 0, 0], "segments": [
            {"length": 0.3, "sections": 6, "cross_section": cs,
             "material": {"youngs_modulus": 2e6, "density": 1000}, "free_modes": "bending_torsion"}]}
        sc = scenario_from_dict({"robot": robot, "loads": [{"s": "tip", "force": [0, 0, -F]}]})
        r = run_statics(sc, 5)
        smax, s_at = max_von_mises(sc.mech, r["members"])
        assert s_at == 0.0
        assert smax == pytest.approx(F * r["tip_position"][0] * r_out / I, rel=1e-9)
    # rectangle: M about y with the stress at z = h/2; sectional members: unknown
    from soft_twin_core.robot.stress import section_geometry as _geometry, von_mises
    g = _geometry({"shape": "rectangle", "width": 0.02, "height": 0.01})
    W = np.array([[2.0, 0, 0, 0, 0.3, 0.1]])
    expect = 2.0 / 2e-4 + 0.3 * 0.005 / (0.02 * 0.01 ** 3 / 12) + 0.1 * 0.01 / (0.01 * 0.02 ** 3 / 12)
    assert von_mises(W, g)[0] == pytest.approx(expect, rel=1e-12)
    assert np.isnan(von_mises(W, _geometry({"shape": "explicit", "area": 1})))[0]


def test_settling_time_of_a_first_order_response():
    """p(t) = p_ref (1 - exp(-t / tau)) enters the 2 % band at tau ln 50."""
    from soft_twin_core.studies.case import settling_time
    tau, dt = 0.3, 1e-4
    t = np.arange(0, 3.0, dt)
    p = np.outer(1 - np.exp(-t / tau), [0.1, 0.0, -0.05])
    ts = settling_time(t, p, np.array([0.1, 0.0, -0.05]), 0.02)
    assert ts == pytest.approx(tau * math.log(50), abs=dt)
    assert math.isnan(settling_time(t[:1000], p[:1000], np.array([0.1, 0.0, -0.05]), 0.02))
    assert settling_time(t, np.zeros_like(p) + 1.0, np.ones(3), 0.02) == 0.0


def test_dynamics_case_records_settling_against_the_static_equilibrium(tmp_path):
    st = _study(parameters=[{"path": "scenario.actuation.tendon_y_pos", "values": [2.0]}],
                compute={"dynamics": {"duration": 4.0, "dt": 0.01, "theta": 1.0}},
                record=["tip_pose", "settling_time", "max_tip_speed", "tip_velocity", "strain_rates"])
    res = run_study(st, tmp_path / "o", serial=True, log=lambda m: None)
    r = read_rows(tmp_path / "o" / "results.parquet")[0]
    assert res["ok"] == 1, r["error"]
    # from straight under gravity to the loaded equilibrium: settles within the 4 s
    assert r["dynamics.settled"] and 0.3 < r["dynamics.settling_time_s"] < 4.0
    assert r["dynamics.max_tip_speed_m_s"] > 0.1
    assert abs(r["dynamics.tip_velocity_y"]) < 0.01 and r["dynamics.strain_rates_0_axial"] == 0.0
    from soft_twin_core.files.scenario import load_scenario
    sc = load_scenario("tendon_arm_statics")
    u = sc.actuation.copy()
    u[0] = 2.0
    eq = solve_statics(sc.model, u, sc.loads_at(None))
    band = 0.02 * np.linalg.norm(eq.tip_pose[:3, 3] - [0.45, 0, 0])
    tip = np.array([r[f"dynamics.tip_position_{a}"] for a in "xyz"])
    assert np.linalg.norm(tip - eq.tip_pose[:3, 3]) <= band


def test_sensitivity_against_known_functions():
    from soft_twin_core.studies.report import spearman_matrix, src_matrix
    rng = np.random.default_rng(0)
    a, b = np.meshgrid(np.linspace(0, 1, 7), np.linspace(-1, 1, 5), indexing="ij")
    X = np.column_stack([a.ravel(), b.ravel()])
    Y = np.column_stack([np.exp(3 * X[:, 0]), -X[:, 1] ** 3, 2 * X[:, 0] - X[:, 1]])
    rho = spearman_matrix(X, Y)
    assert rho[0] == pytest.approx([1.0, 0.0], abs=1e-12)         # monotone in a, free of b (full grid)
    assert rho[1] == pytest.approx([0.0, -1.0], abs=1e-12)
    X = rng.random((200, 2))
    Y = (3 * X[:, 0] - 2 * X[:, 1])[:, None]
    src, r2 = src_matrix(X, Y)
    sx, sy = X.std(axis=0), Y[:, 0].std()
    assert src[0] == pytest.approx([3 * sx[0] / sy, -2 * sx[1] / sy], rel=1e-10)
    assert r2[0] == pytest.approx(1.0, abs=1e-12)
    # round-off columns (a force that is zero up to 1e-16) get no sensitivity
    from soft_twin_core.studies.report import numeric_columns
    rows = [{"a": float(i), "f_fx": 1e-16 * (-1) ** i, "f_fz": 1.0 + i, "g": 1e-16 * i} for i in range(5)]
    assert numeric_columns(rows, ["a", "f_fx", "f_fz", "g"]) == ["a", "f_fz", "g"]


# ----------------------------------------------------------------------------
# Dask: equal to a serial run, a killed worker, resuming
# ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def client():
    from soft_twin_core.studies.cluster import start_local_cluster
    cluster, c = start_local_cluster(2)
    yield c
    c.close()
    cluster.close()


def _lhs_study(n):
    return _study(parameters=[{"path": "segments[0].material.youngs_modulus", "range": [1e6, 4e6]},
                              {"path": "actuators[0].offset[0]", "range": [0.004, 0.01]},
                              {"path": "scenario.actuation.tendon_y_pos", "range": [0.0, 4.0]}],
                  design={"type": "lhs", "samples": n, "seed": 2})


def test_dask_results_equal_a_serial_run_case_by_case(client, tmp_path):
    st = _lhs_study(16)
    run_study(st, tmp_path / "serial", serial=True, log=lambda m: None, summary=False)
    res = run_study(st, tmp_path / "dask", client=client, chunk_size=3, log=lambda m: None)
    assert res["ok"] == 16 and res["computed"] == 16
    a, b = read_rows(tmp_path / "serial" / "results.parquet"), read_rows(tmp_path / "dask" / "results.parquet")
    _same_rows(a, b)
    assert len({r["worker"] for r in b}) == 2                       # both workers took cases
    assert (tmp_path / "dask" / "plots" / "sensitivity.png").stat().st_size > 10_000
    summary = json.loads((tmp_path / "dask" / "summary.json").read_text())
    # no compiling per case: a worker's first case costs about what the later ones do
    assert max(summary["timing"]["first_case_s_per_worker"]) < 0.3
    assert not (tmp_path / "dask" / "parts").exists()


def test_a_killed_worker_process_loses_no_case(client, tmp_path):
    st = _lhs_study(24)
    run_study(st, tmp_path / "serial", serial=True, log=lambda m: None, summary=False)
    pids = client.run(os.getpid)
    killed = {}

    def kill_one(done, total):
        if done >= 2 and not killed:
            pid = sorted(pids.values())[0]
            os.kill(pid, signal.SIGKILL)
            killed["pid"] = pid
    res = run_study(st, tmp_path / "dask", client=client, chunk_size=2, log=lambda m: None, summary=False,
                    on_progress=kill_one)
    assert killed
    assert (res["ok"], res["failed"], res["lost"]) == (24, 0, 0)
    b = read_rows(tmp_path / "dask" / "results.parquet")
    _same_rows(read_rows(tmp_path / "serial" / "results.parquet"), b)
    assert [r["case"] for r in b] == list(range(24))
    client.wait_for_workers(2, timeout=60)                        # the nanny restarted it
    assert killed["pid"] not in client.run(os.getpid).values()


def test_a_task_whose_worker_keeps_dying_is_recorded_lost_and_rerun_by_resume(tmp_path):
    """With no retries allowed (distributed.scheduler.allowed-failures = 0)
    a task whose worker dies under it fails (KilledWorker): its cases are
    recorded lost, the others finish, and a resume computes just those. The
    worker dies in its first case, whatever the machine's speed: its
    process is set to kill itself there (``run_case`` replaced in that
    process only); the nanny's restarted worker is a fresh process."""
    import dask
    import distributed  # noqa: F401  (loads its config first: set() must not replace it)
    from soft_twin_core.studies.cluster import start_local_cluster
    st = _lhs_study(12)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster, c = start_local_cluster(1)
    try:
        def die_in_the_first_case():         # runs in the worker's process (pickled by value: a closure)
            import os as os_
            import signal as signal_
            import soft_twin_core.studies.case as case
            case.run_case = lambda *args: os_.kill(os_.getpid(), signal_.SIGKILL)
            return os_.getpid()
        doomed = set(c.run(die_in_the_first_case).values())
        res = run_study(st, tmp_path / "o", client=c, chunk_size=12, log=lambda m: None, summary=False)
        assert (res["ok"], res["lost"]) == (0, 12)
        rows = read_rows(tmp_path / "o" / "results.parquet")
        assert all(r["status"] == "lost" and "KilledWorker" in r["error"] for r in rows)
        c.wait_for_workers(1, timeout=60)
        assert not doomed & set(c.run(os.getpid).values())          # the nanny started a new process
        res = run_study(st, tmp_path / "o", client=c, chunk_size=12, log=lambda m: None, summary=False)
        assert (res["computed"], res["ok"]) == (12, 12)
    finally:
        c.close()
        cluster.close()


def test_an_interrupted_study_resumes_computing_only_the_missing_cases(client, tmp_path):
    st = _lhs_study(20)

    def interrupt(done, total):
        if done >= 8:
            raise KeyboardInterrupt
    with pytest.raises(StudyInterrupted, match="run the same command again"):
        run_study(st, tmp_path / "o", client=client, chunk_size=2, flush_seconds=0.0, log=lambda m: None,
                  on_progress=interrupt)
    saved = {r["case_key"] for f in (tmp_path / "o" / "parts").glob("part-*.parquet") for r in read_rows(f)}
    assert 8 <= len(saved) < 20
    res = run_study(st, tmp_path / "o", client=client, chunk_size=2, log=lambda m: None, summary=False)
    assert res["reused"] == len(saved) and res["computed"] == 20 - len(saved) and res["ok"] == 20
    rows = read_rows(tmp_path / "o" / "results.parquet")
    assert [r["case"] for r in rows] == list(range(20)) and len({r["case_key"] for r in rows}) == 20
    run_study(st, tmp_path / "serial", serial=True, log=lambda m: None, summary=False)
    _same_rows(read_rows(tmp_path / "serial" / "results.parquet"), rows)
    # a finished study computes nothing; another study refuses the folder
    assert run_study(st, tmp_path / "o", client=client, log=lambda m: None, summary=False)["computed"] == 0
    with pytest.raises(StudyError, match="another study"):
        run_study(_study(), tmp_path / "o", serial=True, log=lambda m: None)


def _sigint_default():
    """In the child: SIGINT at its default, as under a terminal. A suite run
    as a background job of a non-interactive shell (``make test &``) starts
    with SIGINT ignored; Python then installs no KeyboardInterrupt handler,
    and the study ran to its end through the signal (seen once)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _sync_interrupted_before_the_loop_starts(loop):
    """Ctrl-C in ``distributed.utils.sync`` while the event loop is busy (so
    the awaited call has not started): the condition of distributed's
    ``cancel`` bug. True when the interrupt came inside ``sync`` (it can come
    just before, on a stalled machine: then the caller tries again)."""
    import asyncio
    import threading
    from distributed.utils import sync
    started, release = threading.Event(), threading.Event()
    loop.add_callback(lambda: (started.set(), release.wait(30)))      # the loop is busy until released
    assert started.wait(30)
    main = threading.get_ident()
    threading.Timer(0.05, signal.pthread_kill, (main, signal.SIGINT)).start()
    inside = False
    try:
        sync(loop, asyncio.sleep, 10.0)
    except KeyboardInterrupt as e:
        inside = any(f.f_code.co_name == "wait" for f, _ in __import__("traceback").walk_tb(e.__traceback__))
    finally:
        release.set()
    sync(loop, asyncio.sleep, 0.0)        # the loop runs its callbacks in order: the cancel has run now
    return inside


class _Keep(logging.Handler):
    """A log handler keeping the records it is given."""

    def __init__(self):
        super().__init__()
        self.records = []

    def emit(self, record):
        self.records.append(record)


def test_a_workers_heartbeat_after_the_scheduler_closed_is_dropped_and_nothing_else():
    """After Ctrl-C the study closes the scheduler while its workers still
    beat; the first beat to find it gone logs "Failed to communicate with
    scheduler during heartbeat." with a traceback, which CI saw in an
    interrupted study's stderr. The workers' filter (installed with their
    SIGINT handling) drops that record, with the text the pinned
    distributed writes, and passes every other."""
    import inspect
    import logging
    import distributed.worker
    from soft_twin_core.studies.cluster import _HeartbeatAfterClose
    text = "Failed to communicate with scheduler during heartbeat."
    assert text in inspect.getsource(distributed.worker.Worker.heartbeat)

    logger = logging.getLogger("distributed.worker.heartbeat_test")
    keep = _Keep()
    logger.addHandler(keep)
    logger.addFilter(_HeartbeatAfterClose())
    try:
        try:
            raise OSError("Stream is closed")
        except OSError:
            logger.exception(text)
            logger.exception("Unexpected exception during heartbeat. Closing worker.")
        logger.error("Failed to communicate with scheduler")
        assert [r.msg for r in keep.records] == ["Unexpected exception during heartbeat. Closing worker.",
                                                 "Failed to communicate with scheduler"]
    finally:
        logger.removeHandler(keep)


def test_the_distributed_cancel_bug_traceback_is_dropped_and_nothing_else():
    """distributed 2026.8.0's ``sync`` logs a NameError traceback (through
    tornado) when Ctrl-C comes before the loop started the call; CI saw it
    in an interrupted study's stderr. Reproduced here with a real loop: the
    record exists without the filter, is dropped with it; another error
    logged on the same logger still passes."""
    import logging
    from distributed.utils import LoopRunner
    from soft_twin_core.studies.cluster import _SyncCancelBug, install_sync_cancel_filter

    logger = logging.getLogger("tornado.application")
    saved_filters = list(logger.filters)
    for f in saved_filters:
        logger.removeFilter(f)
    keep = _Keep()
    logger.addHandler(keep)
    runner = LoopRunner(asynchronous=False)
    runner.start()
    # Ctrl-C must raise KeyboardInterrupt here, whatever an earlier test of the
    # session installed (rclpy's init replaces the SIGINT handler)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        def bug_records():
            for _ in range(5):
                keep.records.clear()
                if _sync_interrupted_before_the_loop_starts(runner.loop):
                    return [r for r in keep.records if r.exc_info and isinstance(r.exc_info[1], NameError)]
            raise AssertionError("the interrupt never came inside sync() in 5 tries")
        assert len(bug_records()) == 1                  # the bug is real in the pinned version
        install_sync_cancel_filter()
        install_sync_cancel_filter()                    # once per process
        assert sum(isinstance(f, _SyncCancelBug) for f in logger.filters) == 1
        assert bug_records() == []
        try:
            raise NameError("cannot access free variable 'future' where it is not associated with a value")
        except NameError:
            logger.error("another callback failed", exc_info=True)      # same text, not distributed's cancel
        assert len(keep.records) == 1
    finally:
        signal.signal(signal.SIGINT, previous)
        runner.stop()
        logger.removeHandler(keep)
        for f in list(logger.filters):
            logger.removeFilter(f)
        for f in saved_filters:
            logger.addFilter(f)


def test_command_interrupted_by_sigint_resumes(tmp_path):
    """The command on a local cluster, Ctrl-C in the middle (SIGINT to its
    whole process group, workers included, as a terminal sends it): exit
    130, the rows saved, no traceback, no process left; the same command
    again (here serial) computes only the missing cases. 600 cases, so that
    the study is still running when the signal comes (with 60, a quiet
    machine finished them before the signal arrived)."""
    f = tmp_path / "s.yaml"
    f.write_text(f"scenario: {ROOT}/config/scenarios/tendon_arm_statics.yaml\nparameters:\n"
                 "  - path: scenario.actuation.tendon_y_pos\n    range: [0.0, 4.0]\n"
                 "design: {type: random, samples: 600, seed: 5}\ncompute: {statics: {points_per_section: 2}}\n"
                 "record: [tip_pose]\n")
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "soft_twin_core.cli", "study", str(f), "-o", str(out)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen(cmd + ["--workers", "2", "--flush-seconds", "0", "--chunk-size", "1"], stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                         start_new_session=True, preexec_fn=_sigint_default)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list((out / "parts").glob("part-*"))) < 5:
            time.sleep(0.05)
        os.killpg(p.pid, signal.SIGINT)
        err = p.communicate(timeout=60)[1]
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, err
    assert "interrupted" in err and "run the same command again" in err and "Traceback" not in err
    deadline = time.monotonic() + 20                 # nothing of the group is left
    while time.monotonic() < deadline:
        try:
            os.killpg(p.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError(subprocess.run(["ps", "-o", "pid,stat,cmd", "-g", str(p.pid)], capture_output=True,
                                            text=True).stdout)
    saved = {r["case_key"] for g in (out / "parts").glob("part-*.parquet") for r in read_rows(g)}
    assert 5 <= len(saved) < 600
    r = subprocess.run(cmd + ["--serial"], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    assert f"{len(saved)} already in" in r.stderr and f"{600 - len(saved)} to compute" in r.stderr
    rows = read_rows(out / "results.parquet")
    assert len(rows) == 600 and all(x["status"] == "ok" for x in rows)


@pytest.mark.slow
def test_command_on_an_existing_scheduler(tmp_path):
    """`dask scheduler` and `dask worker` processes on this machine (the
    loopback), as on a cluster of machines; the command with --scheduler
    runs the study there and its results equal a serial run."""
    from distributed import Client
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    sched_file = tmp_path / "scheduler.json"
    dask_cli = [sys.executable, "-c", "import sys; from dask.cli import run_cli; sys.argv[0] = 'dask'; run_cli()"]
    procs = [subprocess.Popen(dask_cli + ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                          "--scheduler-file", str(sched_file)],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        # the scheduler writes its file non-atomically: wait until it parses, not until it exists
        deadline, address = time.monotonic() + 60, None
        while address is None and time.monotonic() < deadline:
            try:
                address = json.loads(sched_file.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        assert address, "the dask scheduler wrote no address in 60 s"
        procs.append(subprocess.Popen(dask_cli + ["worker", address, "--nworkers", "2", "--nthreads", "1",
                                                  "--no-dashboard", "--host", "127.0.0.1"],
                                      env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with Client(address, timeout=30) as c:
            c.wait_for_workers(2, timeout=60)
        f = tmp_path / "s.yaml"
        f.write_text(f"scenario: {ROOT}/config/scenarios/tendon_arm_statics.yaml\nparameters:\n"
                     "  - path: segments[1].cross_section.radius\n    values: [0.009, 0.01, 0.011]\n"
                     "  - path: scenario.actuation.tendon_y_pos\n    values: [0.0, 2.0]\n"
                     "compute: {statics: true}\n")
        from soft_twin_core.cli import main
        assert main(["study", str(f), "-o", str(tmp_path / "remote"), "--scheduler", address]) == 0
        assert main(["study", str(f), "-o", str(tmp_path / "serial"), "--serial"]) == 0
        rows = read_rows(tmp_path / "remote" / "results.parquet")
        _same_rows(read_rows(tmp_path / "serial" / "results.parquet"), rows)
        assert len({r["worker"] for r in rows}) >= 1 and all(str(os.getpid()) not in r["worker"] for r in rows)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_example_studies_and_the_documented_study_are_valid():
    import re

    import yaml
    from soft_twin_core.studies.study import load_study
    files = sorted((ROOT / "config" / "studies").glob("*.yaml"))
    assert files
    for f in files:
        st = load_study(f)
        validate_cases(st, make_cases(st))
    text = (ROOT / "docs" / "studies.md").read_text()
    sec = text[text.index("# Design studies"):]
    block = re.search(r"```yaml\n(.*?)```", sec, re.S).group(1)
    st = study_from_dict(yaml.safe_load(block), str(ROOT / "config" / "studies"))
    assert st.parameter_names == load_study(ROOT / "config" / "studies" / "tendon_arm_offsets.yaml").parameter_names


def test_a_statics_study_of_a_tree_robot(tmp_path):
    """Design studies of statics take any robot: the gripper's finger tendon
    swept, each case's tip (the last finger's end) and largest stress
    recorded; more tension bends the finger more and stresses it more; and
    dynamics studies alike."""
    from soft_twin_core.studies.cluster import read_rows, run_study
    from soft_twin_core.studies.study import study_from_dict
    spec = {"name": "grip", "scenario": {"robot": "soft_gripper", "gravity": False, "actuation": {"close_2": 0.0}},
            "parameters": [{"path": "scenario.actuation.close_2", "values": [0.5, 2.0]}],
            "compute": {"statics": {}}, "record": ["tip_pose", "max_stress", "stable"]}
    res = run_study(study_from_dict(spec, str(tmp_path)), tmp_path / "o", serial=True, log=lambda m: None)
    assert res["ok"] == 2
    rows = sorted(read_rows(tmp_path / "o" / "results.parquet"), key=lambda r: r["case"])
    r0, r1 = rows
    assert r0["statics.stable"] and r1["statics.max_stress_pa"] > r0["statics.max_stress_pa"] > 0
    d = [np.hypot(r["statics.tip_position_x"], r["statics.tip_position_y"]) for r in rows]
    assert d[1] < d[0]                                   # the finger closes towards the axis
    # dynamics too: from rest, the finger pulled harder moves faster
    spec["compute"] = {"dynamics": {"duration": 0.02, "dt": 0.005}}
    spec["record"] = ["tip_pose", "max_tip_speed", "base_wrench"]
    res = run_study(study_from_dict(spec, str(tmp_path)), tmp_path / "o2", serial=True, log=lambda m: None)
    assert res["ok"] == 2
    r0, r1 = sorted(read_rows(tmp_path / "o2" / "results.parquet"), key=lambda r: r["case"])
    assert r1["dynamics.max_tip_speed_m_s"] > 2 * r0["dynamics.max_tip_speed_m_s"] > 0
    assert abs(r0["dynamics.tip_quaternion_w"]) <= 1 and np.isfinite(r1["dynamics.base_wrench_fz"])
