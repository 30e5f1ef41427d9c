"""Calibration of a tree robot (soft_twin_core.calibration on the
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

from soft_twin_core import calibration as cal
from soft_twin_core import sensors as sn
from soft_twin_core.cli import main as cli_main
from soft_twin_core.constrained import FrameLoad
from soft_twin_core.mechanism import mechanism_from_dict
from soft_twin_core.model import find_file, read_yaml_file
from test_calibration import assert_sensitivities

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
    assert header[:7] == ["t", "tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg", "pan", "tilt"]
    back = cal.read_csv(path, mech, _sensors())
    np.testing.assert_allclose(back.joints, recording.joints)
    for k in recording.readings:
        np.testing.assert_allclose(back.readings[k], recording.readings[k], atol=1e-12)
    bad = path.read_text().replace(",pan,", ",pann,", 1)
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
    assert cli_main(["calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "viscosity", "--dynamic"]) == 2
    assert "classic robots" in capsys.readouterr().err
