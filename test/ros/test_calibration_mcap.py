"""Calibration from an MCAP recording (soft_twin_core.estimation.mcap_data,
``soft-twin-sim calibrate --data FILE.mcap``). The recording is written by
the node's own recorder (soft_twin.recorder.McapRecording: CDR-encoded
rclpy messages, ros2msg schemas) with the messages a live system carries:
the twin's actuation commands and the estimator's measurement topics plus a
tip tracker on a topic of its own. The "real" arm is a DIFFERENT model (the
tracked arm discretised 3.2 times finer, Young's moduli +30 % / -30 %);
during the first half of every hold the sensors still read the previous
equilibrium (the arm has not settled), so a wrong time alignment biases the
fit. Malformed messages are skipped and counted."""

import json

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="needs ROS 2 messages: the venv of `make setup`")

from geometry_msgs.msg import PointStamped, PoseArray, PoseStamped  # noqa: E402

from soft_twin import conversions as cv  # noqa: E402
from soft_twin.msg import ActuationCommand  # noqa: E402
from soft_twin.recorder import McapRecording  # noqa: E402
from soft_twin_core.cli import main as cli_main  # noqa: E402
from soft_twin_core.estimation import calibration as cal  # noqa: E402
from soft_twin_core.estimation import mcap_data as cm  # noqa: E402
from soft_twin_core.estimation import sensors as sn  # noqa: E402
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file  # noqa: E402
from rod_statics import solve_statics  # noqa: E402

pytestmark = pytest.mark.ros

NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
T0 = 1_700_000_000                    # s: stamps of a real clock
HOLD_S, READ_EVERY_S = 1.0, 0.1
SENSORS = [sn.marker("mk0", 3e-4, s=0.16), sn.PoseSensor("em1", 5e-4, 0.01, s=0.28),
           sn.PoseSensor("tip", 5e-4, 0.01, s=0.40)]


def _nominal():
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for s in d["segments"]:
        s["material"]["youngs_modulus"] = float(s["material"]["youngs_modulus"])
    return d


def _sweep():
    U = []
    for k in range(4):
        for T in (6.0, 12.0, 18.0):
            u = np.zeros(4)
            u[k] = T
            U.append(u)
    for a, b in ((0, 2), (1, 3), (0, 3)):
        for T in (9.0, 15.0):
            u = np.zeros(4)
            u[[a, b]] = T
            U.append(u)
    return np.array(U)


def _stamp(msg, t):
    ns = int(round(t * 1e9))
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return msg


def _point(name, p, t):
    m = PointStamped()
    m.header.frame_id = name
    m.point.x, m.point.y, m.point.z = (float(x) for x in p)
    return _stamp(m, t)


def _pose(name, T, t):
    m = PoseStamped()
    m.header.frame_id = name
    m.pose = cv.pose_msg(T)
    return _stamp(m, t)


def _record(path, truth, U, rng):
    """Commands at T0 + k HOLD_S (each sent twice: a repeat must not cut the
    hold); readings every READ_EVERY_S, of the previous equilibrium in the
    first half of each hold. Returns the number of bad messages written."""
    rec = McapRecording(path)
    q_prev = solve_statics(truth, np.zeros(4)).q
    for j in range(5):                              # before the first command: at rest
        _readings(rec, truth, q_prev, T0 - 0.5 + j * READ_EVERY_S, rng)
    for k, u in enumerate(U):
        q = solve_statics(truth, u, q_init=q_prev).q
        tc = T0 + k * HOLD_S
        for rep in (0.0, 0.3):
            cmd = ActuationCommand(names=NAMES, values=[float(x) for x in u])
            rec.write("/soft_twin/actuation", _stamp(cmd, tc + rep))
        for j in range(int(round(HOLD_S / READ_EVERY_S))):
            tr = tc + 0.05 + j * READ_EVERY_S
            _readings(rec, truth, q if j >= 4 else q_prev, tr, rng)
        q_prev = q
    bad = 0
    tb = T0 + 2.7
    rec.write("/soft_twin_estimator/measurements/position", _point("mk0", [np.nan, 0, 0], tb))
    rec.write("/soft_twin_estimator/measurements/position", _point("nobody", [0, 0, 0], tb))
    rec.write("/soft_twin_estimator/measurements/poses", _stamp(PoseArray(), tb))
    bad_cmd = ActuationCommand(names=["tendon_x"], values=[1.0])
    rec.write("/soft_twin/actuation", _stamp(bad_cmd, tb))
    bad += 4
    rec.close()
    return bad


def _readings(rec, truth, q, t, rng):
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.robot.mechanism import from_robot_model
    mech = from_robot_model(truth)
    _, where = sn.check_sensors(mech, SENSORS)
    clean = sn.predict_readings(Workspace(mech.tree), q, SENSORS, where)
    z = {s.name: sn.simulate_measurement(s, clean[s.name], rng) for s in SENSORS}
    rec.write("/soft_twin_estimator/measurements/position", _point("mk0", z["mk0"], t))
    rec.write("/soft_twin_estimator/measurements/pose", _pose("em1", z["em1"], t + 0.001))
    rec.write("/tracker/tip", _pose("", z["tip"], t + 0.002))       # a tracker of its own


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    true = _nominal()
    true["segments"][0]["material"]["youngs_modulus"] *= 1.3
    true["segments"][1]["material"]["youngs_modulus"] *= 0.7
    truth = model_from_dict(true, 8)                               # 16 sections, the twin 8
    path = tmp_path_factory.mktemp("mcap") / "sweep.mcap"
    bad = _record(path, truth, _sweep(), np.random.default_rng(4))
    return path, bad


def test_static_sweep_read_from_mcap_is_aligned_and_counts_bad_messages(recording):
    path, bad = recording
    model = model_from_dict(_nominal(), 4)
    rec, rep = cm.read_static_sweep(path, model, SENSORS, topics={"tip": "/tracker/tip"})
    U = _sweep()
    assert len(rec) == len(U) + 1                         # the rest hold before the first command, then one per row
    assert np.array_equal(rec.inputs[0], np.zeros(4)) and np.array_equal(rec.inputs[1:], U)
    assert np.allclose(rec.time[1:] - rec.time[1], np.arange(len(U)) * HOLD_S)
    assert rep["skipped"] == {"bad_reading": 1, "unknown_sensor": 1, "wrong_length": 1, "bad_command": 1}
    assert sum(rep["skipped"].values()) == bad
    # each row is the mean of the settled second half (5 readings): its noise is sigma/sqrt(5)
    assert rec.readings["tip"].shape == (len(U) + 1, 4, 4) and rec.readings["mk0"].shape == (len(U) + 1, 3)
    with pytest.raises(cal.CalibrationError, match="unknown sensor 'tool'"):
        cm.read_static_sweep(path, model, SENSORS, topics={"tool": "/tracker/tip"})
    with pytest.raises(cal.CalibrationError, match="no actuation command on '/twin/actuation'"):
        cm.read_static_sweep(path, model, SENSORS, actuation_topic="/twin/actuation")


def test_cli_calibrates_from_an_mcap_recording(recording, tmp_path, capsys):
    """Both moduli (30 % off nominal) within 2 %, the truth in the 95 %
    intervals to 3x, held-out tips within 1 % of the length; settling at 0
    (readings of the previous equilibrium mixed in) is measurably worse."""
    import yaml
    path, _ = recording
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(SENSORS)}))
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
            "--fit", "youngs_modulus", "--sections", "4", "--topic", "tip=/tracker/tip", "--holdout-every", "4"]
    code = cli_main(args + ["-o", str(out)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    p = rep["parameters"]
    true_E = {"youngs_modulus:proximal": 2.6e7, "youngs_modulus:distal": 1.4e7}
    for k, E in true_E.items():
        assert p[k]["fitted"] == pytest.approx(E, rel=0.02), cap.err
        # (averaging 5 readings per hold shrinks the intervals by sqrt(5), not the discretisation
        # bias of the coarser twin: the truth lies within 3 of them, not 2 as from single readings)
        assert 0 < p[k]["ci95"] < 0.01 * E and abs(p[k]["fitted"] - E) < 3 * p[k]["ci95"], cap.err
    assert rep["heldout"]["tip_max_after_m"] < 0.004 < rep["heldout"]["tip_max_before_m"], rep["heldout"]
    assert rep["recording"]["rows"] == len(_sweep()) + 1 and rep["recording"]["skipped"]["bad_command"] == 1
    assert out.exists() and "youngs_modulus:proximal" in out.read_text()
    code = cli_main(args + ["--settle", "0"])
    rep0 = json.loads(capsys.readouterr().out)
    assert code == 0 and rep0["residual_sigma"] > 2 * rep["residual_sigma"]
    assert cli_main(args[:-4] + ["--topic", "tip"]) == 2
    assert "--topic: expected SENSOR=/topic" in capsys.readouterr().err


def test_time_series_rows_hold_the_commands(recording):
    path, _ = recording
    model = model_from_dict(_nominal(), 4)
    rec, rep = cm.read_time_series(path, model, SENSORS, topics={"tip": "/tracker/tip"})
    n = int(round(HOLD_S / READ_EVERY_S))
    assert len(rec) == 5 + n * len(_sweep())                  # every mk0 reading but the NaN one
    assert np.allclose(np.diff(rec.time)[5:5 + n - 1], READ_EVERY_S)
    U = _sweep()
    assert np.array_equal(rec.inputs[:5], np.zeros((5, 4)))
    assert np.array_equal(rec.inputs[5 + 3 * n + 2], U[3])    # zero-order hold
    # em1 and tip are stamped 1-2 ms after mk0: matched within half a period
    assert np.all(np.isfinite(rec.readings["tip"][:, 0, 0]))


# ------------------------------------------- a tree robot: joint commands too

PT_NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
PT_SENSORS = [sn.PoseSensor("em_tool", 3e-4, 5e-3, frame="tool"),
              sn.marker("mk_mid", 3e-4, [0.0, 0.0, 0.012], member="arm", s=0.15)]
PT_SCALE = {"proximal": 1.3, "distal": 0.8}


def _pan_tilt(scale=None):
    d = read_yaml_file(find_file("pan_tilt_arm", "robots"))
    for b in d["bodies"]:
        for s in b.get("segments", ()) if b.get("type") == "member" else ():
            s["material"]["youngs_modulus"] = float(s["material"]["youngs_modulus"]) * (scale or {}).get(s["name"], 1)
    return d


def _pan_tilt_sweep():
    """Each tendon alone at two levels, at three pan/tilt poses (27 rows)."""
    U = [np.zeros(4)] + [np.eye(4)[k] * T for k in range(4) for T in (3.0, 7.0)]
    poses = [(0.0, 0.0), (0.4, -0.3), (0.4, 0.25)]
    return np.vstack([U] * len(poses)), np.repeat(np.array(poses), len(U), axis=0)


@pytest.fixture(scope="module")
def tree_recording(tmp_path_factory):
    """The pan-tilt arm's sweep (moduli 30 % / 20 % off) as the twin's node
    records it: per hold an actuation command, and a joint command naming
    only the joints that change (the others keep their positions), then the
    settled readings in the hold's second half; one joint command naming a
    joint the robot does not have."""
    from sensor_msgs.msg import JointState
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    U, J = _pan_tilt_sweep()
    truth = cal.record_static_sweep(mechanism_from_dict(_pan_tilt(PT_SCALE)), PT_SENSORS, U,
                                    np.random.default_rng(5), joints=J)
    path = tmp_path_factory.mktemp("mcap") / "pan_tilt.mcap"
    rec = McapRecording(path)
    for k in range(len(U)):
        tc = T0 + k * HOLD_S
        rec.write("/soft_twin/actuation", _stamp(ActuationCommand(names=PT_NAMES, values=[float(x) for x in U[k]]), tc))
        changed = [i for i in range(2) if J[k, i] != (J[k - 1, i] if k else 0.0)]
        if changed:
            cmd = JointState(name=[("pan", "tilt")[i] for i in changed], position=[float(J[k, i]) for i in changed])
            rec.write("/soft_twin/joint_commands", _stamp(cmd, tc + 0.01))
        for j in range(5, 10):
            t = tc + j * READ_EVERY_S
            rec.write("/soft_twin_estimator/measurements/pose", _pose("em_tool", truth.readings["em_tool"][k], t))
            rec.write("/soft_twin_estimator/measurements/position", _point("mk_mid", truth.readings["mk_mid"][k], t))
    rec.write("/soft_twin/joint_commands", _stamp(JointState(name=["elbow"], position=[0.1]), T0 + 2.5))
    rec.close()
    return path, truth


def test_joint_commands_of_a_tree_robot_read_from_mcap(tree_recording):
    """Each hold's row carries the joints' commanded positions beside the
    tensions, the mean of its settled readings, and the bad command is
    skipped and counted (the reader refused these robots before)."""
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    path, truth = tree_recording
    mech = mechanism_from_dict(_pan_tilt())
    rec, rep = cm.read_static_sweep(path, mech, PT_SENSORS)
    U, J = _pan_tilt_sweep()
    assert len(rec) == len(U) and rep["skipped"] == {"bad_joint_command": 1}
    np.testing.assert_array_equal(rec.inputs, U)
    np.testing.assert_array_equal(rec.joints, J)
    for name in truth.readings:
        np.testing.assert_allclose(rec.readings[name], truth.readings[name], atol=1e-12)
    series, _ = cm.read_time_series(path, mech, PT_SENSORS)
    assert series.joints.shape == (len(series), 2) and np.array_equal(series.joints[-1], J[-1])
    with pytest.raises(cal.CalibrationError, match="no actuation command on '/a' or '/j'"):
        cm.read_static_sweep(path, mech, PT_SENSORS, actuation_topic="/a", joint_command_topic="/j")


def test_cli_calibrates_a_tree_robot_from_an_mcap_recording(tree_recording, tmp_path, capsys):
    """Both moduli of the pan-tilt arm within 3 % from the node's recording."""
    import yaml
    path, _ = tree_recording
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(PT_SENSORS)}))
    code = cli_main(["calibrate", "pan_tilt_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "youngs_modulus"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    nominal = {s["name"]: float(s["material"]["youngs_modulus"]) for b in _pan_tilt()["bodies"]
               if b.get("type") == "member" for s in b["segments"]}
    for seg, k in PT_SCALE.items():
        assert rep["parameters"][f"youngs_modulus:{seg}"]["fitted"] == pytest.approx(k * nominal[seg], rel=0.03), rep
    assert rep["recording"]["rows"] == len(_pan_tilt_sweep()[0])


# ------------------------------------------- a closed chain: the parallel robot

def _parallel(scale=(1.0, 1.0)):
    """The planar parallel robot with soft rods (5 MPa) and a tendon in each."""
    d = read_yaml_file(find_file("planar_parallel_robot", "robots"))
    for b, k in zip([b for b in d["bodies"] if b.get("type") == "member"], scale):
        b["actuators"] = [{"name": f"{b['name']}_tendon", "type": "tendon", "offset": [0.0, 0.0015]}]
        b["segments"][0]["material"]["youngs_modulus"] = 5.0e6 * k
    return d


def test_cli_calibrates_a_closed_chain_from_an_mcap_recording(tmp_path, capsys):
    """The parallel robot's two rod moduli (the truth's 1.2x and 0.9x
    nominal) within 3 % through the command line from a recording of its
    tendon sweep (per hold an actuation command, then the settled readings
    of a platform tracker and a marker on rod 2): the reader and the fit
    through the KKT equilibrium of the closed chain."""
    import yaml
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    names = ["rod1_tendon", "rod2_tendon"]
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    U = np.array([[t1, t2] for t1 in (0.0, 0.5, 1.2) for t2 in (0.0, 0.5, 1.2)])
    truth = cal.record_static_sweep(mechanism_from_dict(_parallel((1.2, 0.9))), sensors, U, np.random.default_rng(4))
    path = tmp_path / "parallel.mcap"
    rec = McapRecording(path)
    for k in range(len(U)):
        tc = T0 + k * HOLD_S
        rec.write("/soft_twin/actuation", _stamp(ActuationCommand(names=names, values=[float(x) for x in U[k]]), tc))
        for j in range(5, 10):
            t = tc + j * READ_EVERY_S
            rec.write("/soft_twin_estimator/measurements/pose", _pose("platform", truth.readings["platform"][k], t))
            rec.write("/soft_twin_estimator/measurements/position", _point("mk", truth.readings["mk"][k], t))
    rec.close()
    robot = tmp_path / "parallel.yaml"
    robot.write_text(yaml.safe_dump(_parallel()))
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(sensors)}))
    code = cli_main(["calibrate", str(robot), "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "youngs_modulus"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    assert rep["recording"]["rows"] == len(U)
    for rod, k in (("rod1", 1.2), ("rod2", 0.9)):
        assert rep["parameters"][f"youngs_modulus:{rod}"]["fitted"] == pytest.approx(k * 5.0e6, rel=0.03), rep


# ------------------------------------------- known loads: the node's load commands (issue 29)

def test_a_sweep_of_known_loads_recorded_by_the_node_calibrates(tmp_path, capsys):
    """A lab's experiment as the twin's node records it: no tendon pulled,
    hung weights sent as the tip's load (~/tip_wrench_command, a dead load
    along the base axes) and a force gauge on the backbone's point at 0.2 m
    (~/point_wrench_command, soft_twin/PointWrench; one hold as a follower
    load, frame_id the point), each hold's settled readings after it; a
    load on a point the robot does not have is skipped and counted. Every
    hold's row carries its loads; both moduli (1.3x nominal) come within
    2 % through the command line."""
    import yaml
    from geometry_msgs.msg import WrenchStamped
    from soft_twin.msg import PointWrench
    true = _nominal()
    for s in true["segments"]:
        s["material"]["youngs_modulus"] *= 1.3
    truth = model_from_dict(true, 16)
    masses = [0.0, 0.05, 0.1, 0.2, 0.0, 0.0, 0.0, 0.1, 0.1]
    gauge = [0.0, 0.0, 0.0, 0.0, 0.3, -0.3, 0.5, 0.4, 0.0]
    follower = [False] * 6 + [True] + [False] * 2         # the 0.5 N push along the point's own z axis
    W_tip = np.zeros((len(masses), 6))
    W_tip[:, 2] = -9.81 * np.array(masses)
    G_dead, G_body = np.zeros((len(masses), 6)), np.zeros((len(masses), 6))
    for k, (f, body) in enumerate(zip(gauge, follower)):
        (G_body if body else G_dead)[k, 2 if body else 1] = f
    sensors = [sn.marker(f"mk{i}", 3e-4, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]
    truth_rec = cal.record_static_sweep(truth, sensors, np.zeros((len(masses), 4)), np.random.default_rng(6),
                                        wrenches={("tip", "world"): W_tip, ("backbone@0.2", "world"): G_dead,
                                                  ("backbone@0.2", "body"): G_body})
    path = tmp_path / "loads.mcap"
    rec = McapRecording(path)
    for k in range(len(masses)):
        tc = T0 + k * HOLD_S
        tw = WrenchStamped()
        tw.header.frame_id = "base_link"
        tw.wrench.force.z = float(W_tip[k, 2])
        rec.write("/soft_twin/tip_wrench_command", _stamp(tw, tc))
        pw = PointWrench(point="backbone@0.2")
        pw.header.frame_id = "backbone@0.2" if follower[k] else "base_link"
        if follower[k]:
            pw.wrench.force.z = float(gauge[k])
        else:
            pw.wrench.force.y = float(gauge[k])
        rec.write("/soft_twin/point_wrench_command", _stamp(pw, tc + 0.01))
        for j in range(5, 10):
            t = tc + j * READ_EVERY_S
            for s in sensors:
                rec.write("/soft_twin_estimator/measurements/position", _point(s.name, truth_rec.readings[s.name][k], t))
    rec.write("/soft_twin/point_wrench_command", _stamp(PointWrench(point="elbow"), T0 + 2.5))
    rec.close()
    model = model_from_dict(_nominal(), 4)
    got, rep = cm.read_static_sweep(path, model, sensors)
    assert len(got) == len(masses) and rep["skipped"] == {"bad_load": 1}
    np.testing.assert_allclose(got.wrenches[("tip", "world")], W_tip, atol=1e-15)
    np.testing.assert_allclose(got.wrenches[("backbone@0.2", "world")], G_dead, atol=1e-15)
    np.testing.assert_allclose(got.wrenches[("backbone@0.2", "body")], G_body, atol=1e-15)
    for s in sensors:
        np.testing.assert_allclose(got.readings[s.name], truth_rec.readings[s.name], atol=1e-12)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(sensors)}))
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "youngs_modulus", "--sections", "4", "--holdout-every", "0"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    out = json.loads(cap.out)
    for seg in ("proximal", "distal"):
        assert out["parameters"][f"youngs_modulus:{seg}"]["fitted"] == pytest.approx(2.6e7, rel=0.02), cap.err
    assert sorted(out["known_loads"]) == ["backbone@0.2 (body)", "backbone@0.2 (world)", "tip (world)"]


def test_estimate_replays_the_filter_over_an_mcap_recording(recording, tmp_path, capsys):
    """``soft-twin-sim estimate`` on the node's recording (issue 29): one
    row per reading of the first sensor, the commands held, the tracker's
    topic as for calibrate; the figure written."""
    import yaml
    path, _ = recording
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(SENSORS)}))
    code = cli_main(["estimate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--topic", "tip=/tracker/tip", "--plot", str(tmp_path / "fig")])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    n = int(round(HOLD_S / READ_EVERY_S))
    assert rep["rows"] == 5 + n * len(_sweep()) and rep["sensor"] == "tip" and rep["integrator_failures"] == 0
    # (the readings of each hold's first half show the previous equilibrium, and the arm is 30 % off: cm)
    assert rep["tip_sensor_rms_error_m"] < 0.05 and (tmp_path / "fig" / "estimation.png").exists()


def test_encoders_and_a_base_force_sensor_read_from_mcap(tmp_path, capsys):
    """The estimator's ``measurements/joint_states`` and
    ``measurements/base_wrench`` topics feed a static sweep too: on the
    pan-tilt arm, each hold's row carries the mean of its encoder and F/T
    readings (a JointState naming only some of a sensor's joints gives no
    reading; one with fewer positions than names is skipped and counted);
    on the tracked arm, an unknown 30 g payload is weighed through the
    command line from the F/T readings and a tip marker, beside the hung
    weights of the node's tip load commands."""
    import yaml
    from geometry_msgs.msg import WrenchStamped
    from sensor_msgs.msg import JointState
    from soft_twin_core.robot.mechanism import from_robot_model

    def wrench_msg(w, t, frame=""):
        m = WrenchStamped()
        m.header.frame_id = frame
        m.wrench.force.x, m.wrench.force.y, m.wrench.force.z = (float(x) for x in w[:3])
        m.wrench.torque.x, m.wrench.torque.y, m.wrench.torque.z = (float(x) for x in w[3:])
        return _stamp(m, t)
    true = _nominal()
    for s in true["segments"]:
        s["material"]["youngs_modulus"] *= 1.3
    truth = from_robot_model(model_from_dict(true, 16), true)
    sensors = [sn.BaseWrenchSensor("ft", 0.02, 0.002), sn.marker("mk2", 3e-4, s=0.40)]
    masses = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.05])
    W_tip = np.zeros((len(masses), 6))
    W_tip[:, 2] = -9.81 * masses
    payload = (cal.FrameLoad("tip", np.array([0.0, 0.0, -9.81 * 0.03, 0.0, 0.0, 0.0])),)
    truth_rec = cal.record_static_sweep(truth, sensors, np.zeros((len(masses), 4)), np.random.default_rng(7),
                                        point_loads=payload, wrenches={("tip", "world"): W_tip})
    path = tmp_path / "ft.mcap"
    rec = McapRecording(path)
    for k in range(len(masses)):
        tc = T0 + k * HOLD_S
        rec.write("/soft_twin/tip_wrench_command", wrench_msg(W_tip[k], tc, "base_link"))
        for j in range(5, 10):
            t = tc + j * READ_EVERY_S
            rec.write("/soft_twin_estimator/measurements/base_wrench", wrench_msg(truth_rec.readings["ft"][k], t))
            rec.write("/soft_twin_estimator/measurements/position", _point("mk2", truth_rec.readings["mk2"][k], t))
    rec.write("/soft_twin_estimator/measurements/joint_states", _stamp(JointState(name=["a", "b"], position=[0.1]),
                                                                        T0 + 2.5))
    rec.close()
    got, rep = cm.read_static_sweep(path, model_from_dict(_nominal(), 4), sensors)
    assert len(got) == len(masses) and rep["skipped"] == {"wrong_length": 1}
    np.testing.assert_allclose(got.readings["ft"], truth_rec.readings["ft"], atol=1e-12)
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"sensors": sn.sensors_to_list(sensors)}))
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "s.yaml"), "--data", str(path),
                     "--fit", "payload_mass,youngs_modulus:proximal+distal", "--sections", "4", "--holdout-every", "0"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    p = json.loads(cap.out)["parameters"]
    assert abs(p["payload_mass"]["fitted"] - 0.03) < 1e-3, cap.err
    # encoders: a tree robot's joint states, averaged per hold
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    mech = mechanism_from_dict(_pan_tilt())
    enc = [sn.JointStateSensor("enc", ("pan", "tilt"), np.array([1e-3, 1e-3])), sn.marker("mk", 1e-3, frame="tool")]
    path = tmp_path / "enc.mcap"
    rec = McapRecording(path)
    for k, (pan, tilt) in enumerate([(0.0, 0.0), (0.3, -0.2)]):
        tc = T0 + k * HOLD_S
        rec.write("/soft_twin/actuation", _stamp(ActuationCommand(names=PT_NAMES, values=[float(k), 0.0, 0.0, 0.0]), tc))
        for j in range(5, 10):
            t = tc + j * READ_EVERY_S
            rec.write("/soft_twin_estimator/measurements/joint_states",
                      _stamp(JointState(name=["pan", "tilt"], position=[pan + 1e-3 * (j - 7), tilt]), t))
            rec.write("/soft_twin_estimator/measurements/joint_states", _stamp(JointState(name=["pan"], position=[9.0]),
                                                                                t + 0.001))
            rec.write("/soft_twin_estimator/measurements/position", _point("mk", [0.2, 0.0, 0.1], t))
    rec.close()
    got, rep = cm.read_static_sweep(path, mech, enc)
    np.testing.assert_allclose(got.readings["enc"], [[0.0, 0.0], [0.3, -0.2]], atol=1e-12)
