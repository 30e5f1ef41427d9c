"""Calibration (soft_twin_core.estimation.calibration): analytic sensitivities against
finite differences, recovery of parameters from a sweep recorded on a
DIFFERENT model (the same arm discretised 3.2 times finer, with Young's
moduli 30 % off nominal and shifted tendons; three markers with 0.3 mm
noise), CSV round trip, and the ``soft-twin-sim calibrate`` command."""

import copy
import json

import numpy as np
import pytest

from soft_twin_core.cli import main as cli_main
from soft_twin_core.estimation import calibration as cal
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, load_model, model_from_dict, read_yaml_file

LENGTH = 0.4
TRUE_OFFSETS = [0.0085, -0.0076, 0.0084, -0.0077]      # m, nominal +-0.008


def _nominal():
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for s in d["segments"]:
        s["material"]["youngs_modulus"] = float(s["material"]["youngs_modulus"])
    return d


def _true_dict():
    d = _nominal()
    d["segments"][0]["material"]["youngs_modulus"] *= 1.3          # proximal 30 % stiffer
    d["segments"][1]["material"]["youngs_modulus"] *= 0.7          # distal 30 % softer
    for a, o in zip(d["actuators"], TRUE_OFFSETS):
        a["offset"] = [o, 0.0] if "_y_" in a["name"] else [0.0, o]
    return d


def _markers():
    return [sn.marker(f"mk{i}", 3e-4, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]


def _sweep():
    """Each tendon alone at 5..20 N, four pairs at 8 and 16 N, and rest: 25 rows."""
    U = [np.zeros(4)]
    for k in range(4):
        for T in (5.0, 10.0, 15.0, 20.0):
            u = np.zeros(4)
            u[k] = T
            U.append(u)
    for a, b in ((0, 2), (0, 3), (1, 2), (1, 3)):
        for T in (8.0, 16.0):
            u = np.zeros(4)
            u[[a, b]] = T
            U.append(u)
    return np.array(U)


ALL = ["youngs_modulus:proximal", "youngs_modulus:distal", "tendon_offset:tendon_y_pos",
       "tendon_offset:tendon_y_neg", "tendon_offset:tendon_z_pos", "tendon_offset:tendon_z_neg"]


@pytest.fixture(scope="module")
def recording():
    truth = model_from_dict(_true_dict(), 8)                        # 16 sections
    rng = np.random.default_rng(0)
    return cal.record_static_sweep(truth, _markers(), _sweep(), rng)


def test_sensitivities_match_finite_differences():
    """Every parameter kind, at a point away from the nominal values."""
    d = _nominal()
    model = model_from_dict(d)
    P = np.eye(4)
    P[:3, 3] = [0.0, 0.0, 0.01]
    sensors = _markers() + [sn.PoseSensor("em", 1e-3, 0.01, s=0.2, placement=P)]
    rng = np.random.default_rng(1)
    U = np.array([[12.0, 0.0, 6.0, 0.0], [0.0, 9.0, 0.0, 14.0], [5.0, 0.0, 0.0, 7.0]])
    rec = cal.record_static_sweep(model, sensors, U, rng)
    names = ALL + ["payload_mass", "sensor_offset:mk2:y", "sensor_offset:em:z", "sensor_offset:em:x"]
    pb = cal.Problem(d, sensors, rec, names)
    assert_sensitivities(pb, pb.theta0 + np.array([3e6, -2e6, 4e-4, -3e-4, 2e-4, 5e-4, 0.02, 2e-3, 1e-3, -1e-3]),
                         1e-6)


def damping_cli(tmp_path, capsys, robot, mech, sensors, rec, dt):
    """The JSON report's parameters of ``soft-twin-sim calibrate --dynamic
    --fit viscosity`` on the recording written as CSV (tmp_path/step.csv;
    the robot file written to tmp_path/damped.yaml)."""
    import yaml
    cal.write_csv(tmp_path / "step.csv", mech, sensors, rec)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(sensors)}))
    code = cli_main(["calibrate", robot, "--sensors", str(tmp_path / "s.yaml"), "--data", str(tmp_path / "step.csv"),
                     "--fit", "viscosity", "--dynamic", "--dt", str(dt), "-o", str(tmp_path / "damped.yaml")])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    return json.loads(cap.out)["parameters"]


def assert_sensitivities(pb, theta, rtol, step=1e-5):
    """The Problem's analytic Jacobian at theta against central differences
    of its residuals, column by column (steps ``step`` times each
    parameter's scale)."""
    names = [p.name for p in pb.params]
    r, J = pb.evaluate(theta)
    assert J.shape == (len(r), len(names))
    for j in range(len(names)):
        h = step * pb.scale[j]
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        fd = (pb.evaluate(tp, False)[0] - pb.evaluate(tm, False)[0]) / (2 * h)
        assert np.abs(fd).max() > 0, names[j]
        assert np.abs(J[:, j] - fd).max() <= rtol * np.abs(fd).max(), names[j]


def test_calibration_recovers_moduli_and_tendon_offsets_from_a_finer_model(recording):
    """Fit with 4 sections per member (the data come from 8 per member):
    both moduli within 2 %, the tendon offsets within 0.2 mm, the truth
    inside the reported 95 % intervals (to 2x, allowing for the remaining
    discretisation bias), held-out tip positions within 1 % of the length."""
    res = cal.calibrate(_nominal(), _markers(), recording, ALL, holdout_every=4, n_sections=4)
    true_E = np.array([2.6e7, 1.4e7])
    assert np.all(np.abs(res.values[:2] / true_E - 1) < 0.02), res.table()
    assert np.all(np.abs(res.values[2:] - np.abs(TRUE_OFFSETS)) < 2e-4), res.table()
    truth = np.concatenate([true_E, np.abs(TRUE_OFFSETS)])
    assert np.all(np.abs(res.values - truth) < 2 * res.ci95), res.table()
    assert 0.8 < res.residual_sigma < 1.2                         # fits to the stated noise level
    h = res.heldout
    assert h["rows"] == 6 and h["tip_max_after_m"] < 0.01 * LENGTH < h["tip_max_before_m"], h
    # the calibrated robot dict carries the fitted values
    assert res.robot_dict["segments"][0]["material"]["youngs_modulus"] == pytest.approx(res.values[0])
    assert np.linalg.norm(res.robot_dict["actuators"][1]["offset"]) == pytest.approx(res.values[3])
    assert res.robot_dict["actuators"][1]["offset"][0] < 0                  # direction kept


def test_csv_round_trip_and_errors(tmp_path, recording):
    model = load_model("tracked_arm")
    P = np.eye(4)
    sensors = _markers() + [sn.PoseSensor("em", 1e-3, 0.01, s=0.2, placement=P)]
    rec = cal.record_static_sweep(model, sensors, _sweep()[:4], np.random.default_rng(2))
    path = tmp_path / "sweep.csv"
    cal.write_csv(path, model, sensors, rec)
    back = cal.read_csv(path, model, sensors)
    assert np.array_equal(back.inputs, rec.inputs)
    for s in sensors:
        assert np.allclose(back.readings[s.name], rec.readings[s.name], atol=1e-15)
    text = path.read_text().splitlines()
    (tmp_path / "missing.csv").write_text("\n".join([text[0].replace("mk1.y", "mk1.w")] + text[1:]))
    with pytest.raises(cal.CalibrationError, match=r"missing column\(s\) \['mk1.y'\]"):
        cal.read_csv(tmp_path / "missing.csv", model, sensors)
    cells = text[2].split(",")
    cells[3] = "abc"
    (tmp_path / "bad.csv").write_text("\n".join(text[:2] + [",".join(cells)]))
    with pytest.raises(cal.CalibrationError, match=r"row 3, column tendon_z_pos: not a number"):
        cal.read_csv(tmp_path / "bad.csv", model, sensors)
    with pytest.raises(cal.CalibrationError, match="no segment 'elbow'"):
        cal.Problem(_nominal(), sensors, rec, ["youngs_modulus:elbow"])


def test_cli_calibrate_writes_a_calibrated_robot_file(tmp_path, capsys):
    """Same-model data (5 sections) with E 30 % off: the command recovers it,
    writes a robot file that loads, and reports JSON; a bad parameter exits 2."""
    true = _nominal()
    for s in true["segments"]:
        s["material"]["youngs_modulus"] *= 1.3
    truth = model_from_dict(true)
    sensors = _markers()
    rec = cal.record_static_sweep(truth, sensors, _sweep()[::3], np.random.default_rng(3))
    cal.write_csv(tmp_path / "d.csv", truth, sensors, rec)
    import yaml
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(sensors)}))
    out = tmp_path / "calibrated.yaml"
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "d.csv"), "--fit", "youngs_modulus", "--holdout-every", "3", "-o", str(out)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    assert rep["parameters"]["youngs_modulus:proximal"]["fitted"] == pytest.approx(2.6e7, rel=0.02)
    assert rep["parameters"]["youngs_modulus:distal"]["fitted"] == pytest.approx(2.6e7, rel=0.02)
    assert rep["heldout"]["tip_rms_after_m"] < rep["heldout"]["tip_rms_before_m"]
    m = load_model(str(out))
    assert m.sections[0].K[4, 4] == pytest.approx(load_model("tracked_arm").sections[0].K[4, 4] * 1.3, rel=0.02)
    assert "youngs_modulus:proximal" in out.read_text()            # the header comment
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "d.csv"), "--fit", "stiffness"])
    assert code == 2 and "parameter 'stiffness'" in capsys.readouterr().err


def test_sensor_files_round_trip():
    model = from_robot_model(load_model("tracked_arm"))
    items = [{"name": "em", "type": "pose", "s": 0.2, "sigma_position": 1e-3, "sigma_rotation": 0.01,
              "offset": [0, 0, 0.01], "rpy": [0.1, 0.2, 0.3]},
             {"name": "mk", "type": "marker", "s": 0.4, "sigma_position": 5e-4},
             {"name": "t", "type": "tension", "actuator": "tendon_y_pos", "sigma": 0.2}]
    sensors = sn.sensors_from_list(items, model)
    again = sn.sensors_from_list(sn.sensors_to_list(sensors), model)
    assert np.allclose(again[0].placement, sensors[0].placement)
    bad = copy.deepcopy(items)
    bad[1]["sigma_position"] = -1
    with pytest.raises(ValueError, match="positive"):
        sn.sensors_from_list(bad, model)
    bad = copy.deepcopy(items)
    bad[0]["colour"] = "red"
    with pytest.raises(ValueError, match=r"sensors\[0\]: unknown field\(s\) \['colour'\]"):
        sn.sensors_from_list(bad, model)


def test_damping_fitted_to_a_step_response(tmp_path, capsys):
    """Viscosities 60 % above nominal, two tendon steps recorded at 40 Hz
    for 1.2 s (truth simulated at 2 ms, fit at 10 ms): the proximal member's
    viscosity within 3 %, the distal one (less visible at the markers)
    within twice its 95 % interval; the command line gives the same."""
    d = _nominal()
    true = copy.deepcopy(d)
    for s in true["segments"]:
        s["material"]["viscosity"] = 1.6 * float(s["material"]["viscosity"])
    times = np.arange(0.0, 1.2, 0.025)
    inputs = np.zeros((len(times), 4))
    inputs[times >= 0.1, 0] = 15.0
    inputs[times >= 0.6, 0] = 0.0
    inputs[times >= 0.6, 3] = 12.0
    rec = cal.record_dynamic(model_from_dict(true), _markers(), times, inputs, np.random.default_rng(4), dt=2e-3)
    model = load_model("tracked_arm")
    rep = damping_cli(tmp_path, capsys, "tracked_arm", from_robot_model(model), _markers(), rec, 0.01)
    prox, dist = rep["viscosity:proximal"], rep["viscosity:distal"]
    assert abs(prox["fitted"] / 8.0e4 - 1) < 0.03, rep
    assert abs(dist["fitted"] - 8.0e4) < 2 * dist["ci95"], rep
    assert load_model(str(tmp_path / "damped.yaml")).sections[0].D[4, 4] == pytest.approx(
        model.sections[0].D[4, 4] * prox["fitted"] / 5.0e4, rel=1e-9)
    assert cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "step.csv"), "--fit", "payload_mass", "--dynamic"]) == 2
    assert "payload_mass is not fitted from a time series" in capsys.readouterr().err
    assert cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "step.csv"), "--fit", "viscosity"]) == 2                  # a static fit
    assert "fitted from a time series" in capsys.readouterr().err
