"""soft-twin-sim dynamics (issue 15, items 4 and 5): CSV and JSON carry the
same fields with the same shapes, times are exact multiples of dt, failures
exit non-zero with the reason, impossible durations are refused, progress
excludes compilation, the t = 0 row includes inertia; scenario numbers are
parsed like the robot files' numbers."""
import csv
import io
import json
import os
import re
from decimal import Decimal

import numpy as np
import pytest

from soft_twin_core import cli
from soft_twin_core.files import runs as runner, scenario as scenario_mod
from soft_twin_core.files.scenario import ScenarioError, load_scenario, run_dynamics, scenario_from_dict
from soft_twin_core.reference import dynamics as dy
from soft_twin_core.robot import model as model_mod
from soft_twin_core.robot.model import ModelError, model_from_dict, benchmark_cantilever_dict
from soft_twin_core.solve import constrained

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(HERE, "..", "..", "config")
DYN = os.path.join(CONFIG, "scenarios", "tendon_arm_dynamics.yaml")
ARM = os.path.join(CONFIG, "robots", "tendon_arm.yaml")


def run_cli(args, capsys):
    code = cli.main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def read_csv(text):
    rows = list(csv.reader(io.StringIO(text)))
    return rows[0], rows[1:]


def columns_of(header, rows, field):
    """The CSV columns of a JSON field (``field`` or ``field_<labels>``) as
    a (rows, columns) array of strings."""
    idx = [i for i, h in enumerate(header) if h == field or
           (h.startswith(field + "_") and not any(h.startswith(g + "_") for g in _LONGER[field]))]
    return np.array([[r[i] for i in idx] for r in rows], dtype=object)


_FIELDS = runner.HISTORY_FIELDS + runner.SAMPLE_FIELDS
_LONGER = {f: [g for g in _FIELDS if g != f and g.startswith(f + "_")] for f in _FIELDS}


# ------------------------------------------------------------------ CSV == JSON

@pytest.mark.parametrize("extra", [[], ["--backbone-every", "4", "--record-every", "3"]])
def test_csv_and_json_carry_the_same_fields_and_values(tmp_path, capsys, extra):
    args = ["dynamics", DYN, "--duration", "0.05", "--dt", "0.005", "--points-per-section", "2"] + extra
    code, _, err = run_cli(args + ["-o", str(tmp_path / "o.json")], capsys)
    assert code == 0, err
    js = json.loads((tmp_path / "o.json").read_text())
    code, _, err = run_cli(args + ["--format", "csv", "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err
    header, rows = read_csv((tmp_path / "o.csv").read_text())
    assert all(len(r) == len(header) for r in rows)
    n = len(js["time"])
    assert len(rows) == n
    fields = [f for f in _FIELDS if f in js]
    for f in ("tip_velocity", "strains", "strain_rates", "base_wrench", "tip_position"):
        assert f in fields
    if extra:
        assert set(runner.SAMPLE_FIELDS) <= set(fields)
    covered = set()
    times = js["time"]
    for f in fields:
        a = np.asarray(js[f], dtype=float)
        cols = columns_of(header, rows, f)
        covered |= {h for h in header if h == f or h.startswith(f + "_")
                    and not any(h.startswith(g + "_") for g in _LONGER[f])}
        if f in runner.SAMPLE_FIELDS:
            sel = [times.index(t) for t in js["members_time"]]
            assert all(all(c == "" for c in cols[i]) for i in range(n) if i not in sel)
            cols = cols[sel]
        got = np.array([[float(c) for c in row] for row in cols])
        assert got.shape == (a.shape[0], int(np.prod(a.shape[1:]))), f
        assert np.array_equal(got, a.reshape(a.shape[0], -1)), f    # exact: shortest repr round-trips
    assert covered == set(header)


def test_shapes_of_the_time_histories(capsys, tmp_path):
    code, _, err = run_cli(["dynamics", DYN, "--duration", "0.04", "--dt", "0.01", "--backbone-every", "2",
                            "-o", str(tmp_path / "o.json")], capsys)
    assert code == 0, err
    r = json.loads((tmp_path / "o.json").read_text())
    n, ns = 5, r["n_sections"]
    assert np.shape(r["strains"]) == (n, ns, 6)
    assert np.shape(r["strain_rates"]) == (n, ns, 6)
    assert np.shape(r["tip_velocity"]) == (n, 3)
    assert np.shape(r["base_wrench"]) == (n, 6)
    # member samples start at t = 0
    assert r["members_time"] == [0.0, 0.02, 0.04]
    P = ns * 10 + 1
    assert np.shape(r["member_positions"]) == (3, P, 3) and np.shape(r["member_velocities"]) == (3, P, 3)
    assert np.shape(r["member_internal_wrenches"]) == (3, P, 6)
    assert len(r["members"][0]["backbone"]["s"]) == P and len(r["member_point_names"]) == P
    # strain rates: the free modes' rates, zero for the fixed modes
    m = load_scenario(DYN).model
    rates = np.array(r["strain_rates"]).reshape(n, -1)
    assert np.all(rates[:, ~m.free_mask.ravel()] == 0.0)
    assert np.any(rates[1:, m.free_mask.ravel()] != 0.0)


def test_times_are_exact_multiples_of_dt():
    sc = load_scenario(DYN)
    out = run_dynamics(sc, 2.0, 0.001, record_every=100)
    assert out["time"][-1] == 2.0
    assert out["time"] == [float(Decimal("0.001") * k) for k in range(0, 2001, 100)]
    out = run_dynamics(sc, 2.0, 0.1)
    assert out["time"] == [k / 10 for k in range(21)]        # 0.7, not 0.7000000000000001
    # a duration that is not a multiple of dt is covered: ceil(duration / dt) steps
    out = run_dynamics(sc, 0.25, 0.1)
    assert out["time"] == [0.0, 0.1, 0.2, 0.3]


# ------------------------------------------------------------------ failures

def _write(tmp_path, text, name="s.yaml"):
    f = tmp_path / name
    f.write_text(text)
    return str(f)


def test_failure_at_the_first_step_exits_nonzero_with_the_reason(tmp_path, capsys):
    sc = _write(tmp_path, f"robot: {ARM}\nactuation: {{tendon_z_pos: 1.0e+300}}\n")
    out_file = tmp_path / "o.json"
    code, _, err = run_cli(["dynamics", sc, "--duration", "0.01", "--dt", "0.005", "-o", str(out_file)], capsys)
    assert code == 3, err
    assert re.search(r"dynamics failed: .*(step 1 |initial)", err), err
    r = json.loads(out_file.read_text())
    assert "error" in r and r["time"] in ([], [0.0])


def test_failure_mid_run_keeps_the_history_up_to_the_last_good_step(tmp_path, capsys):
    sc = _write(tmp_path, f"robot: {ARM}\nloads:\n  - {{s: tip, force: [0, 0, 1], "
                          f"profile: [[0, 0], [0.02, 0], [0.021, 1.0e+300]]}}\n")
    out_file = tmp_path / "o.csv"
    code, _, err = run_cli(["dynamics", sc, "--duration", "0.05", "--dt", "0.005", "--format", "csv",
                            "-o", str(out_file)], capsys)
    assert code == 3, err
    assert "step 5 of 10 (t = 0.02 -> 0.025 s) failed" in err and "history ends at t = 0.02 s" in err, err
    header, rows = read_csv(out_file.read_text())
    assert [float(r[0]) for r in rows] == [0.0, 0.005, 0.01, 0.015, 0.02]


@pytest.mark.parametrize("duration, dt, msg", [
    ("0.2", "1", r"duration: 0.2 s is shorter than one time step"),
    ("0", "0.001", r"duration: expected a positive, finite time"),
    ("-1", "0.001", r"duration: expected a positive, finite time"),
    ("nan", "0.001", r"duration: expected a positive, finite time"),
    ("inf", "0.001", r"duration: expected a positive, finite time"),
    ("1", "0", r"dt: expected a positive, finite time"),
    ("1", "nan", r"dt: expected a positive, finite time"),
])
def test_impossible_durations_are_refused(tmp_path, capsys, duration, dt, msg):
    out_file = tmp_path / "o.json"
    code, out, err = run_cli(["dynamics", DYN, "--duration", duration, "--dt", dt, "-o", str(out_file)], capsys)
    assert code == 2 and re.search(msg, err), err
    assert not out_file.exists()
    with pytest.raises(ScenarioError, match=msg):
        run_dynamics(load_scenario(DYN), float(duration), float(dt))


# ------------------------------------------------------------------ progress

@pytest.mark.quiet
def test_progress_excludes_the_warm_up(monkeypatch, capsys, tmp_path):
    """The first call of a step (where numba compiles, ~45 s without a cache)
    is simulated by a 2 s sleep, each later step by 10 ms: the reported
    elapsed time and the estimate of the time left exclude the 2 s."""
    import time
    real_step = constrained.MechanismSimulator.step
    calls = {"n": 0}

    def slow_step(self, *a, **k):
        calls["n"] += 1
        time.sleep(2.0 if calls["n"] == 1 else 0.01)
        return real_step(self, *a, **k)
    monkeypatch.setattr(constrained.MechanismSimulator, "step", slow_step)
    code, _, err = run_cli(["dynamics", DYN, "--duration", "1.5", "--dt", "0.01", "--record-every", "50",
                            "-o", str(tmp_path / "o.json")], capsys)
    assert code == 0, err
    assert re.search(r"kernels ready and t = 0 evaluated in [2-9]\.\d s", err), err
    lines = [ln for ln in err.splitlines() if "% simulated" in ln]
    assert lines, err
    # the first report comes about a second into the run: its elapsed time would be at least the
    # warm-up's 2 s if it were counted (later ones depend on the machine's load)
    frac, elapsed, left = map(float, re.search(r"([\d.]+) % simulated, ([\d.]+) s elapsed, ~(\d+) s left",
                                               lines[0]).groups())
    assert elapsed < 1.9 and left <= 3 / max(frac / 100, 0.1), lines[0]
    wall = float(re.search(r"simulated 1.5 s in ([\d.]+) s wall time", err).group(1))
    assert 1.0 < wall < 3.5, err


# ------------------------------------------------------------------ t = 0 row

def test_base_wrench_at_t0_includes_inertia():
    """Released straight under gravity, the arm accelerates at once: the
    t = 0 reaction has the inertial part, continuous with the next rows."""
    sc = load_scenario(DYN)
    m = sc.model
    out = run_dynamics(sc, 0.0002, 0.0001)
    W = np.array(out["base_wrench"])
    a0 = dy.forward_dynamics(m, m.q0, np.zeros(m.n_dof), sc.actuation_at(0.0), sc.loads_at(0.0))   # numpy chain
    ref = dy.base_reaction_dynamic(m, m.q0, np.zeros(m.n_dof), a0, sc.actuation_at(0.0), sc.loads_at(0.0))
    static = dy.base_reaction_dynamic(m, m.q0, np.zeros(m.n_dof), np.zeros(m.n_dof), sc.actuation_at(0.0),
                                      sc.loads_at(0.0))
    assert np.allclose(W[0], ref, rtol=1e-9, atol=1e-12)
    jump_static = np.linalg.norm(static - W[1])
    assert np.linalg.norm(static - ref) > 0.05 * np.linalg.norm(static)    # inertia matters here
    assert np.linalg.norm(W[0] - W[1]) < 0.1 * jump_static                  # continuous


# ------------------------------------------------------------------ numbers (item 5)

SPELLINGS = ["1.0e6", "1e6", "1.0e+6", "1E6", "+1e6", "1000000", "1000000.0"]


@pytest.mark.parametrize("text", SPELLINGS)
def test_scenario_numbers_spelled_like_robot_files(tmp_path, text):
    """The same spellings work in a robot file and in a scenario."""
    sc = load_scenario(_write(tmp_path, f"robot: {ARM}\nactuation: {{tendon_z_pos: {text}}}\n"
                                        f"loads:\n  - {{s: 2.0e-1, force: [0, 0, {text}], "
                                        f"profile: [[0, 0], [1.0e-1, 1e0]]}}\n"))
    assert sc.actuation[sc.model.actuator_names.index("tendon_z_pos")] == 1e6
    assert sc.loads[0][0].wrench[2] == 1e6 and sc.loads[0][0].s == 0.2
    assert sc.loads[0][1][0].tolist() == [0.0, 0.1]
    robot = tmp_path / "r.yaml"
    robot.write_text(open(ARM).read().replace("youngs_modulus: 2.0e6", f"youngs_modulus: {text}"))
    m = model_mod.load_model(str(robot))
    assert m.sections[0].K[0, 0] == pytest.approx(1e6 * np.pi * 0.012**2)


@pytest.mark.parametrize("text, msg", [("abc", "expected a number"), (".nan", "must be finite"),
                                       ("1.0e+400", "must be finite"), ("5 N", "expected a number"),
                                       ("true", "expected a number")])
def test_bad_numbers_named_alike(tmp_path, text, msg):
    with pytest.raises(ScenarioError, match=r"scenario\.actuation\.tendon_z_pos: " + msg):
        load_scenario(_write(tmp_path, f"robot: {ARM}\nactuation: {{tendon_z_pos: {text}}}\n"))
    d = benchmark_cantilever_dict()
    import yaml
    d["segments"][0]["material"]["density"] = yaml.safe_load(f"v: {text}")["v"]
    with pytest.raises(ModelError, match=r"material\.density: " + msg):
        model_from_dict(d)


def test_one_number_parser():
    assert scenario_mod.parse_number is model_mod.parse_number


# ------------------------------------------------------------------ by name

def test_scenarios_and_robots_by_name(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert set(model_mod.example_files("scenarios")) >= {"tendon_arm_dynamics", "tendon_arm_statics"}
    for name in model_mod.example_files("scenarios"):
        sc = load_scenario(name)
        # every robot is a mechanism; a segments robot also has its model
        assert len(sc.mech.tree.soft_joints) >= 1
        assert sc.model is None or sc.model.n_sections == len(sc.mech.tree.soft_joints)
    assert {"pan_tilt_arm_dynamics", "fixed_fixed_beam"} <= set(model_mod.example_files("scenarios"))
    sc = scenario_from_dict({"robot": "tendon_arm"}, str(tmp_path))
    assert sc.model.name == "tendon_arm"
    code, out, err = run_cli(["statics", "tendon_arm_statics"], capsys)
    assert code == 0, err
    with pytest.raises(ScenarioError, match=r"scenario 'nope': no such file, nor an example .*tendon_arm_statics"):
        load_scenario("nope")


# ------------------------------------------------------------------ time-varying inputs

def test_a_time_varying_input_converges_at_second_order():
    """The forces of a step are taken at its theta point (the midpoint at
    theta = 1/2), so a tension ramp up and down converges at second order in
    dt: the tip error against dt / 16 falls fourfold per halving (with the
    forces at the step's end it would fall twofold, 25 times larger)."""
    sc = scenario_from_dict({"robot": "tendon_arm", "gravity": False,
                             "actuation_profile": {"tendon_y_pos": [[0, 0], [0.02, 3.0], [0.04, 0.0]]}})
    tip = {dt: np.array(run_dynamics(sc, 0.04, dt)["tip_position"][-1]) for dt in (0.004, 0.002, 0.001, 0.00025)}
    err = [np.linalg.norm(tip[dt] - tip[0.00025]) for dt in (0.004, 0.002, 0.001)]
    assert err[0] / err[1] > 3.5 and err[1] / err[2] > 3.5, err
    assert err[0] < 2e-5, err                  # m, on a tip travel of centimetres
