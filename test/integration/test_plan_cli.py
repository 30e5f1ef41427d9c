"""``soft-twin-sim plan``: the files it writes (CSV and JSON agree with the
planner), exit codes, bad fields named, and the shipped example (a 10 cm
circle in 4 s on the default robot, quasi-static error below 1 mm)."""

import csv
import json

import numpy as np
import pytest
import yaml

from soft_twin_core import cli
from soft_twin_core.planning import planner as pl
from soft_twin_core.planning.plan_file import PlanFileError, load_plan_file, plan_from_dict


def _write(tmp_path, d, name="p.yaml"):
    f = tmp_path / name
    f.write_text(yaml.safe_dump(d))
    return str(f)


SMALL = {"robot": "tendon_arm",
         "path": {"type": "circle", "center": [0.38, 0.0, -0.22], "radius": 0.02, "normal": [1, 0, 0],
                  "duration": 1.0, "sample_period": 0.1},
         "tracking": {"position_weights": [0, 1, 1]},
         "actuation": {"pretension": 0.2, "max_rate": 40.0},
         "dynamics": {"dt": 0.01, "compensation_iterations": 1}}


def test_plan_cli_writes_csv_and_json(tmp_path, capsys):
    f = _write(tmp_path, SMALL)
    rc = cli.main(["plan", f, "-o", str(tmp_path / "out")])
    assert rc == 0
    out = json.loads((tmp_path / "out.json").read_text())
    rows = list(csv.DictReader(open(tmp_path / "out.csv")))
    assert len(rows) == len(out["time"]) == 11
    u = np.array([[float(r[f"u_{n}"]) for n in out["actuator_names"]] for r in rows])
    assert np.array_equal(u, np.array(out["actuation"]))
    assert all(r["status"] == "reached" for r in rows)
    assert max(float(r["error_m"]) for r in rows) <= 1e-6
    # the same plan from the core
    model, path, opts, u0, _ = load_plan_file(f)
    plan = pl.plan_path(model, path, opts, start=u0, from_start=u0 is not None)
    assert np.allclose(plan.u, u, rtol=1e-9, atol=1e-9)
    assert u0 is None
    assert np.all(u >= 0.2) and np.all(np.abs(np.diff(u, axis=0)) <= 40.0 * 0.1 * (1 + 1e-12))
    d = out["dynamics"]
    assert set(d) >= {"uncompensated", "compensated", "iterations", "simulated_error_m"}
    assert "sim_error_m" in rows[0] and "u_ff_tendon_y_pos" in rows[0]
    assert "rms tracking error" in capsys.readouterr().err


def test_plan_cli_unreachable_exit_3(tmp_path):
    d = dict(SMALL, actuation={"max_tension": 1.0}, dynamics=None)
    d.pop("dynamics")
    f = _write(tmp_path, d)
    assert cli.main(["plan", f, "-o", str(tmp_path / "o")]) == 3
    out = json.loads((tmp_path / "o.json").read_text())
    assert out["summary"]["unreachable"] > 0
    assert "at_limit" in out["status"]


@pytest.mark.parametrize("patch, match", [
    ({"tracking": {"weights": [1, 1, 1]}}, "tracking.weights"),
    ({"actuation": {"max_rate": -2}}, "max_rate"),
    ({"actuation": {"pretension": {"tendon_q": 1}}}, "tendon_q"),
    ({"path": {"type": "circle", "center": [0, 0], "radius": 0.1, "duration": 1}}, "circle.center"),
    ({"dynamics": {"dt": 1.0}}, "dynamics.dt"),
    ({"speed": 3}, "plan.speed"),
])
def test_plan_file_errors_name_the_field(tmp_path, patch, match, capsys):
    d = {**SMALL, **patch}
    with pytest.raises(ValueError, match=match):
        plan_from_dict(d, str(tmp_path))
    assert cli.main(["plan", _write(tmp_path, d), "-o", str(tmp_path / "x")]) == 2
    assert match.split(".")[-1] in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_shipped_example_circle_within_1mm():
    model, path, opts, u0, dyn = load_plan_file("tendon_arm_circle")
    assert path.duration == 4.0
    r = np.linalg.norm(path.positions - path.positions[:-1].mean(axis=0), axis=1)
    assert np.allclose(r, 0.05)                                # a 10 cm circle
    plan = pl.plan_path(model, path, opts, start=u0, from_start=u0 is not None)
    assert plan.reached.all() and plan.weighted_error.max() < 1e-3
    assert pl.check_plan(plan) == []
    assert dyn == {"dt": 0.005, "compensation_iterations": 3}
    with pytest.raises(PlanFileError):
        plan_from_dict({"path": {}})


def test_plan_cli_plot_writes_nonblank_figures(tmp_path):
    """--plot DIR (issue 13): the planned vs achieved tip path (with the
    simulated tips) and the actuation sequence, PNG and SVG, not blank."""
    from PIL import Image
    f = _write(tmp_path, SMALL)
    rc = cli.main(["plan", f, "-o", str(tmp_path / "out"), "--plot", str(tmp_path / "figs")])
    assert rc == 0
    for stem in ("plan_tip_path", "plan_actuation"):
        img = np.asarray(Image.open(tmp_path / "figs" / f"{stem}.png").convert("RGB"), dtype=float)
        h, w, _ = img.shape
        assert w >= 800 and h >= 600, (stem, img.shape)
        dark = (img.mean(axis=2) < 200).mean()
        colour = (np.ptp(img, axis=2) > 60).mean()
        assert 0.01 < dark < 0.5 and colour > 0.002, (stem, dark, colour)
        assert (tmp_path / "figs" / f"{stem}.svg").stat().st_size > 10_000
    # a blank figure fails the same check
    blank = np.full((700, 900, 3), 255.0)
    assert not (blank.mean(axis=2) < 200).mean() > 0.01
