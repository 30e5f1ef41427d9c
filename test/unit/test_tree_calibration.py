"""Calibration of a tree robot (soft_twin_core.estimation.calibration on the
mechanism): the pan-tilt arm, whose recording carries the joint commands
(pan, tilt) beside the tendon tensions. Analytic sensitivities (segment
moduli, tendon offset, payload at the tool, sensor offset) against finite
differences through the KKT equilibrium of the position-controlled joints;
moduli and payload recovered from a sweep of a robot 30 % / 20 % off its
nominal moduli carrying 40 g at the tool, read by a tool tracker and a
marker (0.3 mm, 5 mrad); the CSV with joint columns and the command line."""

import copy
import json

import numpy as np
import pytest

from soft_twin_core.cli import main as cli_main
from soft_twin_core.estimation import calibration as cal
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import find_file, read_yaml_file
from soft_twin_core.solve.constrained import FrameLoad
from test_calibration import assert_sensitivities, damping_cli

TRUE_SCALE = {"proximal": 1.3, "distal": 0.8}
PAYLOAD = 0.04                                       # kg at the tool


def _nominal():
    return copy.deepcopy(read_yaml_file(find_file("pan_tilt_arm", "robots")))


def _segments(d):
    return {s["name"]: s for b in d["bodies"] if b.get("type") == "member" for s in b["segments"]}


def _true_dict():
    d = _nominal()
    for name, k in TRUE_SCALE.items():
        m = _segments(d)[name]["material"]
        m["youngs_modulus"] = float(m["youngs_modulus"]) * k
    return d


def _sensors():
    return [sn.PoseSensor("em_tool", 3e-4, 5e-3, frame="tool"), sn.marker("mk_mid", 3e-4, [0.0, 0.0, 0.012],
                                                                         member="arm", s=0.15)]


def _sweep():
    """(tensions, joint commands): each tendon alone and pairs at two
    levels, at three pan/tilt poses: 27 rows."""
    U = [np.zeros(4)]
    for k in range(4):
        for T in (3.0, 7.0):
            u = np.zeros(4)
            u[k] = T
            U.append(u)
    U = np.array(U)
    poses = [(0.0, 0.0), (0.4, -0.3), (-0.3, 0.25)]
    return np.vstack([U] * len(poses)), np.repeat(np.array(poses), len(U), axis=0)


@pytest.fixture(scope="module")
def recording():
    truth = mechanism_from_dict(_true_dict())
    g = np.asarray(truth.tree.gravity, dtype=float)
    U, J = _sweep()
    load = (FrameLoad("tool", np.concatenate([PAYLOAD * g, np.zeros(3)]), "world"),)
    return cal.record_static_sweep(truth, _sensors(), U, np.random.default_rng(0), joints=J, point_loads=load)


def test_tree_sensitivities_match_finite_differences():
    d = _nominal()
    mech = mechanism_from_dict(d)
    U, J = _sweep()
    rec = cal.record_static_sweep(mech, _sensors(), U[::4], np.random.default_rng(1), joints=J[::4])
    names = ["youngs_modulus:proximal", "youngs_modulus:distal", "tendon_offset:tendon_y_pos", "payload_mass",
             "sensor_offset:mk_mid:y", "sensor_offset:em_tool:x"]
    pb = cal.Problem(d, _sensors(), rec, names)
    assert_sensitivities(pb, pb.theta0 + np.array([1.5e5, -1e5, 4e-4, 0.02, 1e-3, -2e-3]), 1e-5)


def test_tree_calibration_recovers_moduli_and_payload(recording):
    names = ["youngs_modulus:proximal", "youngs_modulus:distal", "payload_mass"]
    res = cal.calibrate(_nominal(), _sensors(), recording, names, holdout_every=4)
    E0 = {n: float(_segments(_nominal())[n]["material"]["youngs_modulus"]) for n in TRUE_SCALE}
    truth = np.array([E0["proximal"] * 1.3, E0["distal"] * 0.8, PAYLOAD])
    print(res.table())
    assert np.all(np.abs(res.values / truth - 1) < 0.02), res.table()
    assert np.all(np.abs(res.values - truth) < 3 * res.std), res.table()
    assert 0.7 < res.residual_sigma < 1.3
    h = res.heldout
    assert h["tip_rms_after_m"] < 1e-3 < h["tip_rms_before_m"], h
    assert _segments(res.robot_dict)["proximal"]["material"]["youngs_modulus"] == pytest.approx(res.values[0])


def test_tree_csv_has_joint_columns_and_the_cli_calibrates(tmp_path, recording, capsys):
    import yaml
    mech = mechanism_from_dict(_nominal())
    path = tmp_path / "sweep.csv"
    cal.write_csv(path, mech, _sensors(), recording)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:7] == ["t [s]", "tendon_y_pos [N]", "tendon_y_neg [N]", "tendon_z_pos [N]", "tendon_z_neg [N]",
                          "pan [rad]", "tilt [rad]"]                  # (each column's SI unit, issue 29)
    back = cal.read_csv(path, mech, _sensors())
    np.testing.assert_allclose(back.joints, recording.joints)
    for k in recording.readings:
        np.testing.assert_allclose(back.readings[k], recording.readings[k], atol=1e-12)
    bad = path.read_text().replace(",pan [rad],", ",pann [rad],", 1)
    (tmp_path / "bad.csv").write_text(bad)
    with pytest.raises(cal.CalibrationError, match=r"missing column\(s\) \['pan'\]"):
        cal.read_csv(tmp_path / "bad.csv", mech, _sensors())
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(_sensors())}))
    out = tmp_path / "calibrated.yaml"
    code = cli_main(["calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "youngs_modulus,payload_mass", "-o", str(out)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)["parameters"]
    assert abs(rep["payload_mass"]["fitted"] / PAYLOAD - 1) < 0.05, rep
    assert _segments(read_yaml_file(str(out)))["proximal"]["material"]["youngs_modulus"] == pytest.approx(
        rep["youngs_modulus:proximal"]["fitted"])
    mechanism_from_dict(read_yaml_file(str(out)))                      # the calibrated file loads


def test_tree_damping_fitted_to_a_step_response(tmp_path, capsys):
    """The viscosities of the pan-tilt arm's two segments, 1.6x nominal in
    the truth, from a 1 s recording at 40 Hz (truth simulated at 2 ms, fit at
    5 ms through the command line): a tendon step, then a pan and tilt
    motion that the recording's joint columns carry. The proximal
    viscosity within 1 % (0.12 % found), the distal within twice its 95 %
    interval (0.34 % off)."""
    true = _nominal()
    for s in _segments(true).values():
        s["material"]["viscosity"] = 1.6 * float(s["material"]["viscosity"])
    times = np.arange(0.0, 1.0, 0.025)
    inputs = np.zeros((len(times), 4))
    inputs[times >= 0.05, 0] = 6.0
    joints = np.zeros((len(times), 2))
    joints[:, 0] = np.clip((times - 0.4) / 0.2, 0, 1) * 0.3          # pan ramps to 0.3 rad over 0.2 s
    joints[:, 1] = -np.clip((times - 0.5) / 0.2, 0, 1) * 0.2         # tilt to -0.2 rad
    rec = cal.record_dynamic(mechanism_from_dict(true), _sensors(), times, inputs, np.random.default_rng(5),
                             dt=2e-3, joints=joints)
    rep = damping_cli(tmp_path, capsys, "pan_tilt_arm", mechanism_from_dict(_nominal()), _sensors(), rec, 0.005)
    eta = 1.6 * float(_segments(_nominal())["proximal"]["material"]["viscosity"])
    prox, dist = rep["viscosity:proximal"], rep["viscosity:distal"]
    assert abs(prox["fitted"] / eta - 1) < 0.01, rep
    assert abs(dist["fitted"] - eta) < 2 * dist["ci95"], rep
    assert _segments(read_yaml_file(str(tmp_path / "damped.yaml")))["proximal"]["material"]["viscosity"] == \
        pytest.approx(prox["fitted"])
    assert cli_main(["calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "step.csv"), "--fit", "viscosity:elbow", "--dynamic"]) == 2
    assert "no segment 'elbow' with a material" in capsys.readouterr().err
