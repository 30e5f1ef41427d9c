"""Calibration from experiments as a lab runs them (issue 29): a sweep of
known loads (hung weights, a force gauge on the backbone) with no actuator
moving, recorded on a DIFFERENT "real" arm (the tracked arm at 4x the
sections, both Young's moduli 30 % above nominal, three markers with 0.3 mm
noise), written as CSV and fitted through the API and ``soft-twin-sim
calibrate``; the standard errors, correlations and identifiability warnings
of the report; records refused naming the column and the row."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from soft_twin_core.cli import main as cli_main
from soft_twin_core.errors import CalibrationError, CalibrationFailed
from soft_twin_core.estimation import calibration as cal
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("calibration_example", ROOT / "scripts" / "calibration_example.py")
ex = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ex)
TRUE_E = ex.TRUE_E
G = 9.81


def _nominal():
    return ex.nominal()


def _markers():
    return ex.markers()


def _experiment():
    return ex.experiment()


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The docs' example dataset (docs/data, scripts/calibration_example.py):
    the experiment recorded on the true arm, written the way a lab logs it
    (the weights in kg, ``mass:tip [kg]``; the gauge's force in N). Written
    again here, it equals the shipped files (they are what they say)."""
    out = tmp_path_factory.mktemp("lab")
    path, sensors = ex.write_example(out)
    for p in (path, sensors):
        assert p.read_text() == (ROOT / "docs" / "data" / p.name).read_text(), p.name
    return ex.record(), path, sensors


def test_the_csv_reads_the_known_loads_as_they_were_applied(lab):
    rec, path, _ = lab
    mech = from_robot_model(model_from_dict(_nominal()), _nominal())
    got = cal.read_csv(path, mech, _markers())
    m, F = _experiment()
    assert set(got.wrenches) == {("tip", "world"), ("backbone@0.2", "world")}
    np.testing.assert_allclose(got.wrenches[("tip", "world")][:, 2], -G * m, rtol=1e-12)  # the robot's g
    np.testing.assert_allclose(got.wrenches[("backbone@0.2", "world")], F, rtol=1e-12)
    for s in _markers():
        np.testing.assert_allclose(got.readings[s.name], rec.readings[s.name], rtol=0, atol=5.01e-6)  # (0.01 mm)
    assert [ld.frame for ld in got.row_loads(0)] == [] and len(got.row_loads(10)) == 2


def test_youngs_modulus_from_a_sweep_of_known_loads(lab):
    """One material: its modulus (both segments', ``proximal+distal``)
    within 2 % of the truth (1.3 x nominal), inside its reported 95 %
    interval (to 3x: the discretisation's bias at 8 against 32 sections
    outweighs the noise's share), the residual at the stated noise, the
    held-out tips 5x closer. Fitted apart, the distal segment (whose bending
    the loads hardly exercise) is the poorly seen one: its standard error
    is ten times the proximal's, and the two correlate negatively. The same
    data with the loads left out cannot be fitted: the loads are what it
    fits."""
    rec, path, _ = lab
    res = cal.calibrate(_nominal(), _markers(), rec, ["youngs_modulus:proximal+distal"], holdout_every=4,
                        n_sections=4)
    assert abs(res.values[0] / TRUE_E - 1) < 0.02, res.table()
    assert abs(res.values[0] - TRUE_E) < 3 * res.ci95[0], res.table()
    assert 0 < res.std[0] < 0.01 * TRUE_E, res.table()
    assert 0.7 < res.residual_sigma < 1.4, res.table()
    assert not res.warnings, res.warnings
    h = res.heldout
    assert h["rows"] == 3 and h["tip_rms_after_m"] < 0.2 * h["tip_rms_before_m"], h
    fitted = res.robot_dict["segments"]
    assert fitted[0]["material"]["youngs_modulus"] == fitted[1]["material"]["youngs_modulus"] == res.values[0]
    apart = cal.calibrate(_nominal(), _markers(), rec, ["youngs_modulus:proximal", "youngs_modulus:distal"],
                          holdout_every=4, n_sections=4)
    assert apart.std[1] > 5 * apart.std[0] and apart.correlation[0, 1] < -0.5, apart.table()
    assert np.all(np.abs(apart.values - TRUE_E) < 3 * apart.ci95), apart.table()
    blind = cal.calibrate(_nominal(), _markers(), cal.Recording(rec.inputs, rec.readings),
                          ["youngs_modulus:proximal+distal"], holdout_every=0, n_sections=4)
    assert blind.residual_sigma > 10                 # the shapes the loads made cannot come from none


def test_cli_fits_the_lab_csv_and_reports_errors_and_correlations(lab, tmp_path, capsys):
    _, path, sensors = lab
    """The docs' command on the docs' dataset: the modulus within 2 % with
    its standard error; fitted per segment, the correlation is reported."""
    _, path, sensors = lab
    args = ["calibrate", "tracked_arm", "--sensors", str(sensors), "--data", str(path), "--sections", "4"]
    code = cli_main(args + ["--fit", "youngs_modulus:proximal+distal", "-o", str(tmp_path / "fitted.yaml")])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    p = rep["parameters"]["youngs_modulus:proximal+distal"]
    assert abs(p["fitted"] / TRUE_E - 1) < 0.02 and 0 < p["std"] < 0.01 * TRUE_E, rep
    assert rep["rows"] == 12 and rep["known_loads"] == ["tip (world)", "backbone@0.2 (world)"]
    assert rep["warnings"] == [] and "std error" in cap.err
    fitted = read_yaml_file(tmp_path / "fitted.yaml")
    assert fitted["segments"][1]["material"]["youngs_modulus"] == pytest.approx(p["fitted"])
    assert cli_main(args + ["--fit", "youngs_modulus"]) == 0
    cap = capsys.readouterr()
    rep = json.loads(cap.out)
    assert rep["correlation"]["parameters"] == ["youngs_modulus:proximal", "youngs_modulus:distal"]
    assert "correlations: youngs_modulus:proximal ~ youngs_modulus:distal" in cap.err


def test_what_the_data_cannot_identify_is_named(lab):
    """A tendon the experiment never pulls: its offset moves no reading (no
    sensitivity), and the report says so by name."""
    rec, _, _ = lab
    res = cal.calibrate(_nominal(), _markers(), rec, ["youngs_modulus:proximal+distal", "tendon_offset:tendon_y_pos"],
                        holdout_every=0, n_sections=4)
    assert any(w.startswith("tendon_offset:tendon_y_pos: not identifiable") for w in res.warnings), res.warnings
    assert "warning: tendon_offset:tendon_y_pos" in res.table()


def test_a_fit_that_does_not_converge_says_so_and_gives_no_result(lab):
    rec, _, _ = lab
    with pytest.raises(CalibrationFailed, match=r"did not converge in \d+ evaluations.*last residual sigma"):
        cal.calibrate(_nominal(), _markers(), rec, ["youngs_modulus:proximal", "youngs_modulus:distal"],
                      holdout_every=0, n_sections=4, max_evaluations=1)


def _rewrite(path, tmp_path, edit):
    lines = [ln.split(",") for ln in path.read_text().splitlines()]
    edit(lines)
    out = tmp_path / "bad.csv"
    out.write_text("\n".join(",".join(x) for x in lines) + "\n")
    return out


@pytest.mark.parametrize("case", ["missing", "unit", "time", "partial", "inf", "point", "component", "mass",
                                  "twice", "no_rows", "load_nan"])
def test_bad_records_are_refused_naming_the_column_and_row(lab, tmp_path, case):
    _, path, _ = lab
    mech = from_robot_model(model_from_dict(_nominal()), _nominal())
    head = path.read_text().splitlines()[0].split(",")
    col = {h.split(" [")[0]: j for j, h in enumerate(head)}

    def edit(lines):
        if case == "missing":
            for ln in lines:
                del ln[col["mk1.y"]]
        elif case == "unit":
            lines[0][col["t"]] = "t [ms]"
        elif case == "time":
            lines[4][col["t"]] = lines[2][col["t"]]
        elif case == "partial":
            lines[5][col["mk2.z"]] = ""
        elif case == "inf":
            lines[5][col["mk2.z"]] = "inf"
        elif case == "point":
            lines[0][col["wrench:backbone@0.2.fy"]] = "wrench:backbone@0.9.fy [N]"
        elif case == "component":
            lines[0][col["wrench:backbone@0.2.fy"]] = "wrench:backbone@0.2.fq [N]"
        elif case == "mass":
            lines[3][col["mass:tip"]] = "-0.1"
        elif case == "twice":
            lines[0][col["mk0.x"]] = "mk0.y [m]"
        elif case == "no_rows":
            del lines[1:]
        elif case == "load_nan":
            lines[7][col["wrench:backbone@0.2.fz"]] = "nan"
    expect = {"missing": r"missing column\(s\) \['mk1.y'\]",
              "unit": r"column 't \[ms\]': unit \[ms\], expected \[s\]",
              "time": r"row 5, column t: the time must increase",
              "partial": r"row 6, column mk2.z: sensor 'mk2' has some of its cells empty",
              "inf": r"row 6: sensor 'mk2' reads an infinite value",
              "point": r"column wrench:backbone@0.9.fy: backbone@0.9: the arc length must lie in \[0, 0.4\] m",
              "component": r"column wrench:backbone@0.2.fq: expected wrench:<point>.<component>",
              "mass": r"column mass:tip: a mass must be >= 0 kg",
              "twice": r"column 'mk0.y' appears twice",
              "no_rows": r"a header but no data row",
              "load_nan": r"row 8, column wrench:backbone@0.2.fz: a known load must be a finite number, got 'nan'"}
    with pytest.raises(CalibrationError, match=expect[case]):
        cal.read_csv(_rewrite(path, tmp_path, edit), mech, _markers())


def test_efforts_and_loads_round_trip_and_are_checked(tmp_path):
    """A tree robot with an effort-controlled joint: its efforts and a dead
    load write and read back exactly (units in the header); a recording
    naming a joint that takes no effort, or a follower load for a CSV, is
    refused by name."""
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    d = read_yaml_file(find_file("pan_tilt_arm", "robots"))
    for b in d["bodies"]:
        for j in [b.get("joint")] if isinstance(b.get("joint"), dict) else []:
            if j.get("name") == "tilt":
                j["control"] = "effort"
    mech = mechanism_from_dict(d, None)
    assert cal.effort_joints(mech) == ("tilt",)
    sensors = [sn.marker("m", 1e-3, frame="tool")]
    n = 3
    rec = cal.Recording(np.zeros((n, len(mech.actuator_names))),
                        {"m": np.array([[0.1, 0.2, 0.3], [np.nan] * 3, [0.3, 0.2, 0.1]])},
                        np.array([0.0, 1.0, 2.5]), np.tile([0.1], (n, 1)), {"tilt": np.array([0.0, 0.5, -0.25])},
                        {("tool", "world"): np.arange(18.0).reshape(n, 6)})
    cal.write_csv(tmp_path / "r.csv", mech, sensors, rec)
    head = (tmp_path / "r.csv").read_text().splitlines()[0]
    assert "t [s]" in head and "tilt [N m]" in head and "wrench:tool.mx [N m]" in head and "m.x [m]" in head
    back = cal.read_csv(tmp_path / "r.csv", mech, sensors)
    np.testing.assert_array_equal(back.efforts["tilt"], rec.efforts["tilt"])
    np.testing.assert_array_equal(back.wrenches[("tool", "world")], rec.wrenches[("tool", "world")])
    np.testing.assert_array_equal(back.joints, rec.joints)
    assert np.all(np.isnan(back.readings["m"][1])) and back.readings["m"][2][0] == 0.3
    with pytest.raises(CalibrationError, match=r"efforts: 'pan' is not an effort-controlled joint"):
        cal.check_recording(mech, cal.Recording(rec.inputs, rec.readings, efforts={"pan": np.zeros(n)}))
    with pytest.raises(CalibrationError, match=r"a CSV holds dead loads \(world axes\) only"):
        cal.csv_header(mech, sensors, cal.Recording(rec.inputs, rec.readings,
                                                    wrenches={("tool", "body"): np.zeros((n, 6))}))


def _release_test(d, seed, rows=33, sensors=None):
    """The record of a release test of the arm ``d`` (32 sections, 2 ms
    steps): held by 0.5 N sideways on the tip (the first row's
    ``wrench:tip.fy``), let go, read by ``sensors`` (the three markers) at
    40 Hz for ``rows`` rows."""
    truth = from_robot_model(model_from_dict(d, 16), d)
    times = np.arange(rows) * 0.025
    pull = np.zeros((len(times), 6))
    pull[0, 1] = 0.5
    return cal.record_dynamic(truth, _markers() if sensors is None else sensors, times, np.zeros((len(times), 4)),
                              np.random.default_rng(seed), dt=2e-3, wrenches={("tip", "world"): pull})


def test_damping_from_a_release_test(tmp_path, capsys):
    """A release test: the true arm (its viscosity 1.6x the file's, 32
    sections, 2 ms steps) held deflected by a known 0.5 N sideways pull on
    the tip, then let go, read by the three markers at 40 Hz for 0.8 s. The
    recording's first row carries the pull (``wrench:tip.fy``), the others
    none: the twin (8 sections, 5 ms steps) starts from its equilibrium
    under that pull and fits one viscosity for both segments within 10 %,
    through the API and the command line (CSV). Started from rest instead
    (the loads left out), no viscosity explains the swing."""
    d = _nominal()
    for s in d["segments"]:
        s["material"]["viscosity"] = 1.6 * float(s["material"]["viscosity"])
    rec = _release_test(d, 8)
    assert np.ptp(rec.readings["mk2"][:, 1]) > 0.01                 # it swings: 1 cm and more
    res = cal.calibrate_damping(_nominal(), _markers(), rec, ["proximal+distal"], dt=5e-3, n_sections=4)
    assert res.values[0] == pytest.approx(8.0e4, rel=0.10), res.table()
    assert 0.5 < res.residual_sigma < 2.0, res.table()
    blind = cal.calibrate_damping(_nominal(), _markers(), cal.Recording(rec.inputs, rec.readings, rec.time),
                                  ["proximal+distal"], dt=5e-3, n_sections=4)
    assert blind.residual_sigma > 10, blind.table()
    import yaml
    mech = from_robot_model(model_from_dict(_nominal()), _nominal())
    cal.write_csv(tmp_path / "release.csv", mech, _markers(), rec)
    assert "wrench:tip.fy [N]" in (tmp_path / "release.csv").read_text().splitlines()[0]
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(_markers())}))
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "release.csv"), "--dynamic", "--fit", "viscosity:proximal+distal", "--sections",
                     "4", "--dt", "0.005"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    got = json.loads(cap.out)["parameters"]["viscosity:proximal+distal"]
    assert got["fitted"] == pytest.approx(res.values[0], rel=1e-6) and got["std"] > 0


def test_stiffness_density_and_damping_from_one_release_test(tmp_path, capsys):
    """Issue 29, a dynamic fit of more than the damping: the true arm (32
    sections, 2 ms steps) with its moduli 30 % above the robot file's, its
    density 15 % below and its viscosity 1.6x, held by a 0.5 N sideways pull
    on the tip, let go, read by the three markers at 40 Hz for 0.8 s. From
    the file's values, the twin (8 sections, 5 ms steps) fits one modulus,
    one density and one viscosity for both segments: the static deflection
    under the known pull and the sag give E and the weight, the swing's
    frequency sqrt(E/rho) and its decay the viscosity. Each is found within
    3 % (E, density) and 10 % (viscosity); measured over three noise seeds:
    E -1.6..+0.4 %, density -0.8..+1.5 %, viscosity -0.8..+0.8 %, with
    standard errors of 0.5-0.8 %. The CLI gives the same."""
    d = _nominal()
    for seg in d["segments"]:
        seg["material"].update(youngs_modulus=TRUE_E, density=0.85 * float(seg["material"]["density"]),
                               viscosity=1.6 * float(seg["material"]["viscosity"]))
    rec = _release_test(d, 9)
    names = ["youngs_modulus:proximal+distal", "density:proximal+distal", "viscosity:proximal+distal"]
    res = cal.calibrate_dynamic(_nominal(), _markers(), rec, names, dt=5e-3, n_sections=4)
    true = np.array([TRUE_E, 0.85 * 1100.0, 1.6 * 5.0e4])
    err = res.values / true - 1
    assert abs(err[0]) < 0.03 and abs(err[1]) < 0.03 and abs(err[2]) < 0.10, res.table()
    assert 0.5 < res.residual_sigma < 2.0, res.table()
    assert np.all(res.std > 0), res.table()
    import yaml
    mech = from_robot_model(model_from_dict(_nominal()), _nominal())
    cal.write_csv(tmp_path / "release.csv", mech, _markers(), rec)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(_markers())}))
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data",
                     str(tmp_path / "release.csv"), "--dynamic", "--fit", ",".join(names), "--sections", "4",
                     "--dt", "0.005"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    got = json.loads(cap.out)["parameters"]
    for name, v in zip(names, res.values):
        assert got[name]["fitted"] == pytest.approx(v, rel=1e-6)


def test_a_sensor_offset_and_the_damping_from_a_release_test():
    """The dynamic fit takes sensor offsets too: the tip marker glued 4 mm
    off the centre line (the file says 0) on the arm of 1.6x viscosity,
    released from the 0.5 N pull, 0.6 s at 40 Hz: its offset within 0.3 mm
    and the viscosity within 10 %, from the file's values."""
    d = _nominal()
    for seg in d["segments"]:
        seg["material"]["viscosity"] = 1.6 * float(seg["material"]["viscosity"])
    real = _markers()[:2] + [sn.marker("mk2", 3e-4, (0.0, 0.004, 0.0), s=0.40)]
    rec = _release_test(d, 5, rows=25, sensors=real)
    res = cal.calibrate_dynamic(_nominal(), _markers(), rec, ["sensor_offset:mk2:y", "viscosity:proximal+distal"],
                                dt=5e-3, n_sections=4)
    assert res.values[0] == pytest.approx(0.004, abs=3e-4), res.table()
    assert res.values[1] == pytest.approx(8.0e4, rel=0.10), res.table()
    assert np.asarray(res.sensors[2].placement)[1, 3] == pytest.approx(res.values[0])


def test_a_base_force_sensor_and_encoders_calibrate_too(tmp_path):
    """Issue 29: a static sweep read by a base force/torque sensor and joint
    encoders besides markers. The sensitivities (the F/T sensor's through
    the equilibrium and, for the payload, its weight on the support) match
    central differences on the pan-tilt arm with known loads on the tool;
    on the tracked arm an unknown 30 g payload and the modulus come back
    from the known-load sweep read by the F/T sensor and one tip marker;
    the CSV carries the new columns with their units."""
    import importlib.util as iu
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    spec = iu.spec_from_file_location("test_calibration", ROOT / "test" / "unit" / "test_calibration.py")
    tc = iu.module_from_spec(spec)
    spec.loader.exec_module(tc)
    d = read_yaml_file(find_file("pan_tilt_arm", "robots"))
    mech = mechanism_from_dict(d)
    sensors = [sn.marker("tool_mk", 3e-4, frame="tool"), sn.JointStateSensor("enc", ("pan", "tilt"), np.array([1e-3, 1e-3])),
               sn.BaseWrenchSensor("ft", 0.02, 0.002)]
    W = np.zeros((3, 6))
    W[1, 1], W[2, 2] = 0.3, -0.4
    rec = cal.record_static_sweep(mech, sensors, np.array([[2.0, 0, 0, 0], [0, 0, 3.0, 0], [0, 1.0, 0, 0]]),
                                  np.random.default_rng(2), joints=np.array([[0.0, 0.1], [0.3, -0.2], [-0.2, 0.3]]),
                                  wrenches={("tool", "world"): W})
    pb = cal.Problem(d, sensors, rec, ["youngs_modulus:proximal", "payload_mass"])
    tc.assert_sensitivities(pb, pb.theta0 + np.array([3e5, 0.03]), 1e-6)
    # the tracked arm: F/T sensor and one marker, an unknown payload
    truth_d = _nominal()
    for s in truth_d["segments"]:
        s["material"]["youngs_modulus"] = TRUE_E
    truth = from_robot_model(model_from_dict(truth_d, 16), truth_d)
    ft = [sn.BaseWrenchSensor("ft", 0.02, 0.002), sn.marker("mk2", 3e-4, s=0.40)]
    m, F = _experiment()
    W_tip = np.zeros((len(m), 6))
    W_tip[:, 2] = -G * m
    payload = (cal.FrameLoad("tip", np.array([0.0, 0.0, -G * 0.03, 0.0, 0.0, 0.0])),)
    rec = cal.record_static_sweep(truth, ft, np.zeros((len(m), 4)), np.random.default_rng(4), point_loads=payload,
                                  wrenches={("tip", "world"): W_tip, ("backbone@0.2", "world"): F})
    res = cal.calibrate(_nominal(), ft, rec, ["youngs_modulus:proximal+distal", "payload_mass"], holdout_every=0,
                        n_sections=4)
    assert abs(res.values[1] - 0.03) < 1e-3 and abs(res.values[0] / TRUE_E - 1) < 0.02, res.table()
    assert 0.5 < res.residual_sigma < 2.0, res.table()
    mech = from_robot_model(model_from_dict(_nominal()), _nominal())
    cal.write_csv(tmp_path / "ft.csv", mech, ft, rec)
    head = (tmp_path / "ft.csv").read_text().splitlines()[0]
    assert "ft.fz [N]" in head and "ft.my [N m]" in head
    back = cal.read_csv(tmp_path / "ft.csv", mech, ft)
    np.testing.assert_allclose(back.readings["ft"], rec.readings["ft"], rtol=1e-12)
