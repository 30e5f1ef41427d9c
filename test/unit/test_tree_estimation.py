"""Estimation of a soft articulated robot (soft_twin_core.estimation.ekf,
sensors): the pan-tilt arm. Synthetic data from a DIFFERENT model:
the same robot with its member discretised 3 times finer (12 sections
against the filter's 4), its soft member 20 % stiffer, simulated by the
engine's MechanismSimulator (exact position control of the joints) at 2 ms
while the pan and tilt joints sweep and a tendon pulls; read at 100 Hz by
encoders (1 mrad), a pose sensor at mid-member and one on the tool frame
(1 mm, 0.01 rad). Measurement Jacobians against finite differences;
filter's tool error and NEES within chi-square bounds; bad readings
rejected and counted."""

import copy

import numpy as np
import pytest
from scipy.stats import chi2

from soft_twin_core import lie
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as ts
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import find_file, read_yaml_file
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
from test_estimation import assert_linearisation_at_rest

ARM_LENGTH = 0.30                       # m, the soft member
DT, SIM_DT, DURATION = 0.01, 0.002, 3.0


def _robot(sections=2, stiffness=1.0):
    d = read_yaml_file(find_file("pan_tilt_arm", "robots"))
    d = copy.deepcopy(d)
    for b in d["bodies"]:
        for s in b.get("segments", []):
            s["sections"] = sections
            s["material"]["youngs_modulus"] = float(s["material"]["youngs_modulus"]) * stiffness
    return mechanism_from_dict(d)


def _sensors():
    return [ts.JointStateSensor("encoders", ("pan", "tilt"), np.array([1e-3, 1e-3])),
            ts.PoseSensor("em_mid", 1e-3, 0.01, member="arm", s=0.15),
            ts.PoseSensor("em_tool", 1e-3, 0.01, frame="tool")]


def _commands(t):
    ramp = min(t / 0.5, 1.0)
    pos = {"pan": 0.5 * ramp * np.sin(2 * np.pi * 0.4 * t), "tilt": -0.3 * ramp * np.sin(2 * np.pi * 0.3 * t)}
    u = np.array([6.0 if t > 1.0 else 0.0, 0.0, 0.0, 3.0 if t > 1.8 else 0.0])
    return pos, u


@pytest.fixture(scope="module")
def truth_run():
    return simulate_truth()


def simulate_truth():
    """(times, true readings {sensor: [...]}, true tool positions) every DT."""
    mech = _robot(sections=6, stiffness=1.2)
    sens = _sensors()
    _, where = ts.check_sensors(mech, sens)
    q0 = solve_equilibrium(mech, positions=_commands(0.0)[0]).q
    sim = MechanismSimulator(mech, SIM_DT, theta=0.5, q=q0)
    ws = Workspace(mech.tree)
    tool = mech.frame("tool")
    from soft_twin_core.engine import algorithms as alg
    times, reads, tips = [], {s.name: [] for s in sens}, []
    per = int(round(DT / SIM_DT))
    for k in range(int(round(DURATION / DT))):
        t = (k + 1) * DT
        for i in range(per):
            ts_ = k * DT + (i + 1) * SIM_DT
            pos, u = _commands(ts_)
            sim.step(actuation=u, positions=pos)
        alg.forward_kinematics(mech.tree, ws, sim.q)
        for s in sens:
            reads[s.name].append(ts.predict_measurement(ws, sim.q, s, where[s.name]))
        tips.append(alg.point_poses(mech.tree, ws, sim.q, [tool.joint], [tool.x])[0][:3, 3].copy())
        times.append(t)
    return np.array(times), reads, np.array(tips)


def test_measurement_jacobians_match_finite_differences():
    """Every sensor kind at a bent, turned configuration, including a
    large rotation error and a marker with an offset."""
    mech = _robot()
    P = lie.exp_se3(np.array([0.0, 0.01, 0.005, 0.2, 0.0, 0.1]))
    sens = _sensors() + [ts.PoseSensor("mk", 5e-4, None, member="arm", s=0.22, placement=P),
                         ts.PoseSensor("em_p", 1e-3, 0.01, member="arm", s=0.05, placement=P)]
    _, where = ts.check_sensors(mech, sens)
    tree = mech.tree
    rng = np.random.default_rng(3)
    q = tree.q0 + 0.3 * rng.standard_normal(tree.nv)
    ws = Workspace(tree)
    from soft_twin_core.engine.kernels import passes
    z = {}
    q_meas = tree.q0 + 0.3 * rng.standard_normal(tree.nv)
    passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q_meas), ws.zeros_v, ws.zeros_v, 0)
    for s in sens:
        z[s.name] = ts.predict_measurement(ws, q_meas, s, where[s.name])
    for s in sens:
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q), ws.zeros_v, ws.zeros_v, 0)
        e, H = ts.residual_and_jacobian(ws, q, s, where[s.name], z[s.name])
        if s.size == 6:
            assert np.linalg.norm(e[3:]) > 0.3, s.name                 # a large rotation error
        fd = np.zeros_like(H)
        h = 1e-6
        for i in range(tree.nv):
            dq = np.zeros(tree.nv)
            dq[i] = h
            r = []
            for sign in (1, -1):
                qq = np.ascontiguousarray(q + sign * dq)
                passes.forward_pass(ws.m, ws.w, qq, ws.zeros_v, ws.zeros_v, 0)
                r.append(ts.residual_and_jacobian(ws, qq, s, where[s.name], z[s.name])[0])
            fd[:, i] = (r[0] - r[1]) / (2 * h)
        assert np.abs(H - fd).max() <= 1e-7 * max(1.0, np.abs(fd).max()), s.name


def _run(truth_run, corrupt=False):
    times, reads, tips = truth_run
    mech = _robot()                                   # the nominal, coarser, softer twin
    ekf = es.EKF(mech, _sensors(), DT, positions=_commands(0.0)[0])
    rng = np.random.default_rng(7)
    errs, nees_, joint_err, open_loop = [], [], [], []
    for k, t in enumerate(times):
        pos, u = _commands(t)
        meas = {s.name: ts.simulate_measurement(s, reads[s.name][k], rng) for s in ekf.sensors}
        if corrupt and k % 50 == 10:
            meas["em_mid"] = np.full((4, 4), np.nan)             # rejected
            meas["encoders"] = np.array([0.1])                   # wrong length: rejected
        if corrupt and k % 50 == 30:
            meas["em_tool"] = meas["em_tool"].copy()
            meas["em_tool"][:3, 3] += 0.05                       # a 5 cm outlier: gated
        ekf.step(meas, actuation=u, positions=pos)
        p = ekf.frame_pose("tool")[:3, 3]
        errs.append(np.linalg.norm(p - tips[k]))
        nees_.append(es.nees(p - tips[k], ekf.frame_position_cov("tool")))
        jp = ekf.joint_positions()
        joint_err.append([jp["pan"][0] - reads["encoders"][k][0], jp["tilt"][0] - reads["encoders"][k][1]])
    return np.array(errs), np.array(nees_), np.array(joint_err), ekf


def test_tree_filter_tracks_the_finer_stiffer_robot_consistently(truth_run):
    """Tool error below 1 % of the member length over the manoeuvre (after
    0.2 s), joints within 5 mrad (RMS below the encoders' 1 mrad), the tool-position NEES within the
    chi-square bounds as in test_estimation (at most 10 % of the steps above
    or below the per-step 95 % interval, the mean within the 99 % bounds of
    chi2(3 N_eff)/N_eff, N_eff = N/10 for errors correlated over ~10 steps)."""
    errs, nees_, jerr, ekf = _run(truth_run)
    errs, nees_, jerr = errs[20:], nees_[20:], jerr[20:]
    print(f"tool error max {errs.max() * 1e3:.2f} mm, RMS {np.sqrt(np.mean(errs ** 2)) * 1e3:.2f} mm; "
          f"joints max {np.abs(jerr).max() * 1e3:.2f} mrad, RMS {np.sqrt(np.mean(jerr ** 2)) * 1e3:.2f} mrad; NEES mean {nees_.mean():.2f}")
    assert errs.max() < 0.01 * ARM_LENGTH
    assert np.abs(jerr).max() < 5e-3 and np.sqrt(np.mean(jerr ** 2)) < 1e-3     # encoders: 1 mrad noise
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    assert np.mean(nees_ > hi) <= 0.10 and np.mean(nees_ < lo) <= 0.10, (np.mean(nees_ > hi), np.mean(nees_ < lo))
    n_eff = len(nees_) / 10
    a_lo, a_hi = chi2.ppf([0.005, 0.995], 3 * n_eff) / n_eff
    assert a_lo <= nees_.mean() <= a_hi, (nees_.mean(), a_lo, a_hi)
    assert ekf.health.integrator_failures == 0 and ekf.health.gated <= 3


def test_open_loop_twin_misses_and_bad_readings_are_counted(truth_run):
    """Without measurements the twin (servo model, nominal stiffness) misses
    the tool by more than the filter; NaN and wrong-length readings are
    rejected, a 5 cm outlier gated, and the filter still tracks."""
    times, reads, tips = truth_run
    mech = _robot()
    ol = es.EKF(mech, _sensors(), DT, positions=_commands(0.0)[0])
    err_ol = []
    for k, t in enumerate(times):
        pos, u = _commands(t)
        ol.predict(actuation=u, positions=pos)
        err_ol.append(np.linalg.norm(ol.frame_pose("tool")[:3, 3] - tips[k]))
    errs, _, _, ekf = _run(truth_run, corrupt=True)
    assert max(err_ol) > 3 * errs[20:].max()
    n = len(times)
    bad = len([k for k in range(n) if k % 50 == 10])
    assert ekf.health.rejected == 2 * bad
    assert ekf.health.gated >= len([k for k in range(n) if k % 50 == 30])
    assert errs[20:].max() < 0.01 * ARM_LENGTH


def test_tree_sensor_files_and_errors():
    mech = _robot()
    items = [{"name": "enc", "type": "joint_state", "joints": ["pan", "tilt"], "sigma_position": 1e-3},
             {"name": "mid", "type": "pose", "member": "arm", "s": 0.15, "sigma_position": 1e-3,
              "sigma_rotation": 0.01},
             {"name": "tip", "type": "marker", "frame": "tool", "sigma_position": 5e-4}]
    sens = ts.sensors_from_list(items, mech)
    assert sens[0].size == 2 and np.allclose(sens[0].sigma, 1e-3) and sens[2].position_only
    bad = [({**items[0], "joints": ["pan", "elbow"]}, "unknown joint 'elbow'"),
           ({**items[1], "member": "leg"}, "no member named 'leg'"),
           ({**items[1], "s": 0.5}, r"\.s: "),
           ({**items[2], "frame": "hand"}, "no frame named 'hand'"),
           ({**items[0], "sigma_position": [1e-3]}, "expected 2 positive values"),
           ({**items[2], "sigma_rotation": 0.1}, r"unknown field\(s\) \['sigma_rotation'\]")]
    for d, msg in bad:
        with pytest.raises(ValueError, match=msg):
            ts.sensors_from_list([d], mech)
    ekf = es.EKF(mech, sens, DT)
    with pytest.raises(ValueError, match="unknown sensor 'x'"):
        ekf.update({"x": 1.0})
    with pytest.raises(ValueError, match="unknown joint 'elbow'"):
        ekf.set_inputs(positions={"elbow": 0.1})


def test_joint_tracking_offset_is_estimated():
    """The real pan joint stands 30 mrad off its command (static, the finer
    stiffer robot): the filter's offset state finds it from the encoders
    (within 3 of its standard deviations and 3 mrad; the tilt offset, 0,
    within 3 of its), the joints within 3 of theirs, and the tool follows."""
    real = _robot(sections=6, stiffness=1.2)
    cmd = {"pan": 0.2, "tilt": -0.1}
    u = np.array([5.0, 0.0, 0.0, 0.0])
    truth = solve_equilibrium(real, u, positions={"pan": 0.23, "tilt": -0.1})
    sens = _sensors()
    _, where = ts.check_sensors(real, sens)
    ws = Workspace(real.tree)
    from soft_twin_core.engine import algorithms as alg
    alg.forward_kinematics(real.tree, ws, truth.q)
    z_true = {s.name: ts.predict_measurement(ws, truth.q, s, where[s.name]) for s in sens}
    tool = real.frame("tool")
    tip = alg.point_poses(real.tree, ws, truth.q, [tool.joint], [tool.x])[0][:3, 3]
    ekf = es.EKF(_robot(), sens, DT, positions=cmd, actuation=u)
    rng = np.random.default_rng(11)
    for _ in range(300):
        ekf.step({s.name: ts.simulate_measurement(s, z_true[s.name], rng) for s in sens}, positions=cmd)
    off, jp = ekf.joint_offsets(), ekf.joint_positions()
    assert abs(off["pan"][0] - 0.03) < min(3 * off["pan"][1], 3e-3), off
    assert abs(off["tilt"][0]) < 3 * off["tilt"][1], off
    assert abs(jp["pan"][0] - 0.23) < 3 * jp["pan"][1] and abs(jp["tilt"][0] + 0.1) < 3 * jp["tilt"][1], jp
    assert np.linalg.norm(ekf.frame_pose("tool")[:3, 3] - tip) < 0.01 * ARM_LENGTH


def test_base_wrench_sensor_model_and_jacobian():
    """The base force/torque sensor: at rest the support carries the total
    weight (force -m g, m summed from the robot file: links and members'
    density x area x length) and the moment of the first mass moment; its
    Jacobian matches central differences; in a filter with the encoders and
    no tracker, unaware of a 6 N tendon pull (its inputs say 0), the F/T
    sensor at least halves the tool error (the bend moves the arm's centre
    of mass)."""
    mech = _robot()
    tree = mech.tree
    ft = ts.sensors_from_list([{"name": "ft", "type": "base_wrench", "sigma_force": 0.05,
                                     "sigma_moment": 0.002}], mech)[0]
    ws = Workspace(tree)
    rng = np.random.default_rng(2)
    q = tree.q0 + 0.3 * rng.standard_normal(tree.nv)
    W, H = ts.base_wrench_and_jacobian(tree, ws, q)
    rho = 1100.0
    m_arm = rho * np.pi * (0.012 ** 2 + 0.009 ** 2) * 0.15
    assert np.allclose(W[:3], [0.0, 0.0, (0.40 + 0.15 + m_arm) * 9.81], rtol=1e-9, atol=1e-12)
    fd = np.zeros_like(H)
    for i in range(tree.nv):
        dq = np.zeros(tree.nv)
        dq[i] = 1e-6
        fd[:, i] = (ts.base_wrench_and_jacobian(tree, ws, q + dq, False)[0]
                    - ts.base_wrench_and_jacobian(tree, ws, q - dq, False)[0]) / 2e-6
    assert np.abs(fd).max() > 0.01
    assert np.abs(H - fd).max() <= 1e-7 * np.abs(fd).max()
    # straight, level arm (pan = tilt = 0, no gravity sag): moment about y of the weights ahead of the base
    q0 = tree.q0.copy()
    W0, _ = ts.base_wrench_and_jacobian(tree, ws, q0, False)
    x_c = (0.15 * 0.025 + rho * np.pi * 0.012 ** 2 * 0.15 * (0.05 + 0.075)
           + rho * np.pi * 0.009 ** 2 * 0.15 * (0.05 + 0.225))
    assert W0[4] == pytest.approx(-9.81 * x_c, rel=1e-9)   # hat(g) c with g = -9.81 z: m_y = -9.81 c_x
    assert np.allclose(W0[[3, 5]], 0.0, atol=1e-12)
    # in the filter: encoders and the F/T sensor only
    enc = ts.JointStateSensor("encoders", ("pan", "tilt"), np.array([1e-3, 1e-3]))
    truth = solve_equilibrium(mech, [6.0, 0.0, 0.0, 0.0], positions={"pan": 0.0, "tilt": 0.0}).q
    ref = mech.frame("tool")
    from soft_twin_core.engine import algorithms as alg
    tip = alg.point_poses(tree, ws, truth, [ref.joint], [ref.x])[0][:3, 3]
    _, where = ts.check_sensors(mech, [enc, ft])
    alg.forward_kinematics(tree, ws, truth)
    z = {s.name: ts.predict_measurement(ws, truth, s, where[s.name]) for s in (enc, ft)}
    for sensors, better in (([enc], False), ([enc, ft], True)):
        ekf = es.EKF(mech, sensors, DT, actuation=[0.0, 0.0, 0.0, 0.0], q_init=tree.q0)
        for _ in range(200):      # the filter believes in no tendon pull: only the F/T sensor sees the bend
            ekf.step({s.name: ts.simulate_measurement(s, z[s.name], rng) for s in sensors},
                     actuation=[0.0, 0.0, 0.0, 0.0])
        err = np.linalg.norm(ekf.frame_pose("tool")[:3, 3] - tip)
        print(f"F/T sensor {better}: tool error {err * 1e3:.2f} mm")
        if better:
            assert err < 0.5 * err_without, (err, err_without)
        else:
            err_without = err


# ------------------------------------------- tip wrench and tension inputs on a tree

def _sprung_robot():
    """The pan-tilt arm with passive joints on springs (2 N m/rad): an
    equilibrium without servo, so that one filter step is exactly one theta
    step of the equations of motion."""
    d = copy.deepcopy(read_yaml_file(find_file("pan_tilt_arm", "robots")))
    for b in d["bodies"]:
        j = b.get("joint", {})
        if j.get("type") == "revolute":
            j["control"] = "passive"
            j["stiffness"] = 2.0
    return mechanism_from_dict(d)


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_tree_process_jacobian_with_tip_wrench_and_inputs(theta):
    """At an equilibrium of the sprung pan-tilt arm under tendons, gravity
    and a wrench on the tool (the tip frame), the analytic Phi (rigid
    joints, strains, the 6 wrench states) and Gamma_u equal central
    differences of the filter's own integrator step."""
    from soft_twin_core.solve.constrained import FrameLoad
    mech = _sprung_robot()
    u = np.array([5.0, 1.0, 2.0, 0.5])
    w = np.array([0.2, -0.1, -0.3, 0.004, 0.01, -0.006])
    eq = solve_equilibrium(mech, u, point_loads=[FrameLoad("tool", w)]).q
    ekf = es.EKF(mech, [ts.JointStateSensor("enc", ("pan", "tilt"), np.array([1e-3, 1e-3]))], DT, theta=theta,
                 wrench="wrench", actuation=u, q_init=eq)
    assert ekf.tip == "tool" and ekf.nb == 0 and ekf.k == 6
    assert_linearisation_at_rest(ekf, np.concatenate([eq, np.zeros(ekf.n), w]), u)


def test_payload_on_the_tool_of_a_tree_robot():
    """A 50 g payload hung on the pan-tilt arm's tool, unknown to the
    filter: encoders and the two pose sensors at 100 Hz for 2 s; the
    payload state reads 50 g within 10 % (and within 3 of its standard
    deviations), the tool within 1 % of the member's length and within 3
    of its reported standard deviations."""
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.solve.constrained import FrameLoad
    mech = _robot()
    pos = {"pan": 0.3, "tilt": -0.2}
    u = np.array([4.0, 0.0, 0.0, 0.0])
    truth = solve_equilibrium(mech, u, positions=pos, point_loads=[FrameLoad("tool", [0, 0, -0.05 * 9.81, 0, 0, 0])]).q
    sens = _sensors()
    _, where = ts.check_sensors(mech, sens)
    ws = Workspace(mech.tree)
    z = ts.predict_readings(ws, truth, sens, where)
    tool = alg.point_poses(mech.tree, ws, truth, [mech.frame("tool").joint], [mech.frame("tool").x])[0][:3, 3]
    rng = np.random.default_rng(9)
    ekf = es.EKF(mech, sens, DT, wrench="payload", actuation=u, positions=pos)
    for _ in range(200):
        ekf.step({s.name: ts.simulate_measurement(s, z[s.name], rng) for s in sens})
    m, m_std = ekf.payload_mass_kg()
    print(f"payload {m * 1e3:.1f} +- {m_std * 1e3:.1f} g")
    assert abs(m - 0.05) < 0.005 and abs(m - 0.05) < 3 * m_std
    err = np.linalg.norm(ekf.tip_pose()[:3, 3] - tool)
    assert err < 0.01 * ARM_LENGTH and err < 3 * np.sqrt(np.trace(ekf.tip_position_cov()))
    assert ekf.health.integrator_failures == 0


def test_tension_sensor_on_a_tree_robot():
    """A tension sensor's reading becomes the input of its tendon (a
    negative tendon reading is read as slack, 0 N), and its noise widens
    the prediction by Gamma_u sigma^2 Gamma_u^T."""
    mech = _sprung_robot()
    enc = ts.JointStateSensor("enc", ("pan", "tilt"), np.array([1e-3, 1e-3]))
    tsen = ts.TensionSensor("t_y", "tendon_y_pos", 0.5)
    ekf = es.EKF(mech, [enc, tsen], DT)
    quiet = es.EKF(mech, [enc], DT)
    ekf.update({"t_y": -1.0})
    assert ekf.u[0] == 0.0
    ekf.update({"t_y": 6.0})
    assert ekf.u[0] == 6.0 and ekf.health.dropped == 2          # the encoders' readings were absent
    quiet.u[0] = 6.0
    _, Gamma = quiet.linearisation()
    ekf.predict()
    quiet.predict()
    assert np.allclose(ekf.x, quiet.x)
    assert np.allclose(ekf.P - quiet.P, 0.25 * np.outer(Gamma[:, 0], Gamma[:, 0]), atol=1e-12 * np.abs(ekf.P).max())
    with pytest.raises(ValueError, match="unknown actuator 'nope'"):
        es.EKF(mech, [ts.TensionSensor("t", "nope", 0.5)], DT)
