"""``soft-twin-sim estimate`` (soft_twin_core.estimation.replay, issue 29):
the state estimator run over a recorded time series, its estimates, its
innovation statistics and its figure. The record is made by a DIFFERENT
model (the tracked arm at 3.2x the sections, 2 ms midpoint steps): two
tendons swing the arm, a 50 g payload the filter does not know is hung on
the tip at t = 1 s, three pose sensors read it at 100 Hz (1 mm, 0.01 rad)."""

import json

import numpy as np
import pytest
import yaml

from soft_twin_core.cli import main as cli_main
from soft_twin_core.estimation import calibration as cal
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.estimation.replay import estimate_recording
from soft_twin_core.viz.plots import estimation_figure
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file

MASS = 0.05
SENSORS = [sn.PoseSensor(f"em{i}", 1e-3, 0.01, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]


def _arm(n=None):
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    return from_robot_model(model_from_dict(d, n), d)


@pytest.fixture(scope="module")
def record():
    t = np.arange(301) * 0.01
    u = np.column_stack([4 + 4 * np.sin(np.pi * t), 0 * t, 3 + 3 * np.sin(0.6 * np.pi * t), 0 * t])
    hung = np.zeros((len(t), 6))
    hung[t >= 1.0, 2] = -9.81 * MASS
    rec = cal.record_dynamic(_arm(8), SENSORS, t, u, np.random.default_rng(4), dt=2e-3,
                             wrenches={("tip", "world"): hung})
    return cal.Recording(rec.inputs, rec.readings, rec.time)           # (the payload is unknown to the filter)


def test_the_filter_replayed_over_a_record(record):
    """The payload found within 10 % (and 3 of its standard deviations) by
    the end, the tip sensor followed to 2 mm rms, the innovations
    consistent with their stated covariance: NIS per dimension about 1,
    most updates inside their 95 % band; the figure draws the three."""
    run = estimate_recording(_arm(), SENSORS, record, wrench="payload")
    assert run.sensor == "em2" and run.estimated.shape == (len(record), 3)
    assert abs(run.payload[-1] - MASS) < 0.1 * MASS and abs(run.payload[-1] - MASS) < 3 * run.payload_std[-1]
    assert abs(run.payload[80]) < 0.1 * MASS                              # before the hanging
    err = np.linalg.norm(run.estimated - run.measured, axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 2e-3
    mean_nis, inside = run.consistency()
    assert 0.5 < mean_nis < 2.0 and inside > 0.8, (mean_nis, inside)
    assert np.all(run.nis_dof <= 18) and np.mean(run.nis_dof == 18) > 0.95 and run.integrator_failures == 0
    assert np.all(run.nis_dof + 6 * run.gated == 18)                 # (a gated pose reading: 6 dimensions out)
    import matplotlib.pyplot as plt
    fig = estimation_figure(run)
    try:
        assert len(fig.axes) == 3 and "payload [g]" in fig.axes[1].get_ylabel()
        assert "mean NIS per dimension" in fig.axes[2].get_title()
    finally:
        plt.close(fig)


def test_cli_estimate_writes_the_estimates_and_the_figure(record, tmp_path, capsys):
    from PIL import Image
    cal.write_csv(tmp_path / "run.csv", _arm(), SENSORS, record)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(SENSORS)}))
    code = cli_main(["estimate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "run.csv"), "--wrench", "payload", "--plot", str(tmp_path / "fig"),
                     "-o", str(tmp_path / "est.csv")])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    assert rep["rows"] == len(record) and abs(rep["final_payload_kg"] - MASS) < 0.1 * MASS
    assert 0.5 < rep["mean_nis_per_dof"] < 2.0 and rep["tip_sensor_rms_error_m"] < 2e-3
    head = (tmp_path / "est.csv").read_text().splitlines()[0].split(",")
    assert head[0] == "t [s]" and "payload [kg]" in head and "em2.x estimated [m]" in head
    data = np.loadtxt(tmp_path / "est.csv", delimiter=",", skiprows=1)
    assert data.shape == (len(record), len(head)) and data[-1, head.index("payload [kg]")] == pytest.approx(
        rep["final_payload_kg"], rel=1e-6)
    png = tmp_path / "fig" / "estimation.png"
    assert str(png) in rep["figures"]
    with Image.open(png) as im:
        assert im.size[0] >= 600 and np.mean(np.asarray(im.convert("L")) < 200) > 0.01
    # a record without times is refused by name
    lines = (tmp_path / "run.csv").read_text().splitlines()
    (tmp_path / "no_t.csv").write_text("\n".join(",".join(ln.split(",")[1:]) for ln in lines) + "\n")
    assert cli_main(["estimate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "no_t.csv")]) == 2
    assert "needs a time column t" in capsys.readouterr().err


def test_cli_estimate_takes_the_force_directions(record, tmp_path, capsys):
    """--wrench force --force-directions: the force is estimated along the
    given directions only (none along x); a bad text is refused by name."""
    cal.write_csv(tmp_path / "run.csv", _arm(), SENSORS, record)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(SENSORS)}))
    base = ["estimate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(tmp_path / "run.csv"),
            "--wrench", "force"]
    assert cli_main(base + ["--force-directions", "0,1,0;0,0,1"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["final_wrench"][0] == 0.0 and rep["final_wrench_std"][0] == 0.0
    # the payload's weight, read as a vertical force
    assert rep["final_wrench"][2] == pytest.approx(-9.81 * MASS, rel=0.1)
    for bad, said in [("0,1", "expected 'x,y,z'"), ("0,1,0;0,2,0", "the directions are not independent"), ("up", "expected")]:
        assert cli_main(base + ["--force-directions", bad]) == 2
        assert f"--force-directions: {said}" in capsys.readouterr().err
