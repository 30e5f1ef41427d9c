"""The extended Kalman filter (soft_twin_core.estimation.ekf) on a classic rod
(a one-member mechanism) with synthetic data
made by a DIFFERENT model: the same rod discretised 3.2 times finer (16
PCS sections instead of 5; 48 strain modes instead of 15), simulated with
its own integrator at a 2 ms step, observed by three pose sensors (s = 0.16,
0.28, 0.40 m) with noise 1 mm per position axis and 0.01 rad per rotation
axis, at 100 Hz. Arm: config/robots/tracked_arm.yaml (length 0.4 m, so
1 % of the length is 4 mm)."""

import numpy as np
import pytest
from scipy.stats import chi2

from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file
from soft_twin_core.solve.constrained import MechanismSimulator
from rod_statics import solve_statics

DT = 0.01
ONE_PERCENT = 0.004          # m: 1 % of the 0.4 m arm


def _arm_dict(youngs_scale=1.0):
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for seg in d["segments"]:
        seg["material"]["youngs_modulus"] = float(seg["material"]["youngs_modulus"]) * youngs_scale
    return d


@pytest.fixture(scope="module")
def coarse():
    return model_from_dict(_arm_dict())


@pytest.fixture(scope="module")
def fine():
    return model_from_dict(_arm_dict(), 8)


@pytest.fixture(scope="module")
def sensors():
    return [sn.PoseSensor(f"em{i}", 1e-3, 0.01, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]


def _mech(model):
    """The model's mechanism (made once per model)."""
    return from_robot_model(model)


def _ekf(model, sensors, **kw):
    """The filter on the classic rod, a tip force estimated unless told."""
    return es.EKF(_mech(model), sensors, DT, **{"wrench": "force", **kw})


def _pose(model, q, sensor):
    return sn.sensor_pose(_mech(model), q, sensor)


def _reading(model, q, sensor, rng):
    """A noisy reading of a pose sensor or marker of the model at q."""
    T = _pose(model, q, sensor)
    return sn.simulate_measurement(sensor, T[:3, 3] if sensor.position_only else T, rng)


def _tip(model, q):
    return _pose(model, q, sn.PoseSensor("tip", 1.0, 1.0, s=model.total_length))[:3, 3]


def _tip_position(ekf):
    return ekf.tip_pose()[:3, 3]


def _tip_std(ekf):
    return np.sqrt(np.diag(ekf.tip_position_cov()))


def _payload(model, mass):
    return Loads(point=(PointLoad(model.total_length, (0.0, 0.0, -9.81 * mass, 0.0, 0.0, 0.0)),))


def _run_static(model_est, truth_model, sensors, u, loads, steps, seed, **kw):
    rng = np.random.default_rng(seed)
    truth = solve_statics(truth_model, u, loads)
    T = [_pose(truth_model, truth.q, s) for s in sensors]
    ekf = _ekf(model_est, sensors, **kw)
    for _ in range(steps):
        ekf.predict(u)
        ekf.update({s.name: sn.simulate_measurement(s, Ts, rng) for s, Ts in zip(sensors, T)})
    return ekf, truth


# ---------------------------------------------------------------- process model

def _integrator_step(ekf, x, u, lam0=None):
    """The filter's mean prediction from the augmented state x."""
    ekf.x = np.array(x, dtype=float)
    ekf.a = np.zeros(ekf.n)
    ekf.lam = lam0.copy() if lam0 is not None else ekf.lam
    if ekf._sim._theta_integrator is not None:          # no extrapolation from earlier steps
        ekf._sim._theta_integrator._prev_a = None
    ekf.predict(u)
    return ekf.x.copy()


def assert_linearisation_at_rest(ekf, x0, u, h=1e-6, hu=1e-4):
    """At the rest state x0 under inputs u: the filter's step keeps x0, and
    its analytic Phi and Gamma_u equal central differences of that step."""
    assert np.abs(_integrator_step(ekf, x0, u) - x0).max() < 1e-8        # at rest it stays
    lam0 = ekf.lam.copy()                  # and its multipliers are the loop's reactions at rest
    ekf.x = x0.copy()
    Phi, Gamma = ekf.linearisation()

    def step(x, u):
        return _integrator_step(ekf, x, u, lam0)
    Phi_fd = np.stack([(step(x0 + h * e, u) - step(x0 - h * e, u)) / (2 * h) for e in np.eye(len(x0))], axis=1)
    assert np.abs(Phi - Phi_fd).max() <= 1e-5 * np.abs(Phi_fd).max()
    Gamma_fd = np.stack([(step(x0, u + hu * e) - step(x0, u - hu * e)) / (2 * hu) for e in np.eye(len(u))], axis=1)
    assert np.abs(Gamma_fd).max() > 1e-6
    assert np.abs(Gamma - Gamma_fd).max() <= 1e-5 * np.abs(Gamma_fd).max()


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_process_jacobian_is_the_integrator_step_linearisation_at_rest(coarse, sensors, theta):
    """At an equilibrium (tendons, gravity and a tip wrench) the analytic
    Phi and Gamma_u equal central differences of the integrator's step."""
    u = np.array([12.0, 2.0, 6.0, 1.0])
    w = np.array([0.3, -0.2, -0.5, 0.01, 0.02, -0.015])
    eq = solve_statics(coarse, u, Loads(point=(PointLoad(coarse.total_length, tuple(w)),)))
    ekf = _ekf(coarse, sensors, theta=theta, wrench="wrench", actuation=u, q_init=eq.q)
    assert_linearisation_at_rest(ekf, np.concatenate([eq.q, np.zeros(ekf.n), w]), u)


def test_point_moment_tendons_in_the_process_model(sensors):
    """Tendons of the point-moment model act by a follower moment at their
    end: the filter's step carries them (its mean stays at the bent
    equilibrium) and its Phi and Gamma_u (the moments' geometric stiffness,
    their B(q) columns) equal central differences of the integrator's step
    (the filter refused these tendons before)."""
    d = _arm_dict()
    for a in d["actuators"]:
        a["model"] = "point_moment"
    model = model_from_dict(d)
    u = np.array([3.0, 0.5, 1.0, 0.5])
    eq = solve_statics(model, u)
    assert np.abs(eq.q - model.q0).max() > 0.05                    # bent
    ekf = _ekf(model, sensors, wrench=None, actuation=u, q_init=eq.q)
    assert_linearisation_at_rest(ekf, np.concatenate([eq.q, np.zeros(ekf.n)]), u)


# ---------------------------------------------------------------------- statics

def test_static_tip_within_one_percent_where_the_open_loop_twin_is_not(coarse, sensors):
    """The real arm is 25 % stiffer than the twin and carries tendon
    tensions: the open-loop twin misses the tip by > 1 % of the length, the
    filter is within it (and within 3 standard deviations)."""
    stiff_fine = model_from_dict(_arm_dict(1.25), 8)
    u = np.array([14.0, 0.0, 8.0, 0.0])
    ekf, truth = _run_static(coarse, stiff_fine, sensors, u, Loads(), 150, seed=2, actuation=u)
    tip_true = truth.tip_pose[:3, 3]
    open_loop = solve_statics(coarse, u).tip_pose[:3, 3]
    assert np.linalg.norm(open_loop - tip_true) > ONE_PERCENT
    err = _tip_position(ekf) - tip_true
    assert np.linalg.norm(err) < ONE_PERCENT
    assert np.all(np.abs(err) < 3 * _tip_std(ekf) + 1e-4)


def test_unknown_50_g_payload_estimated_within_10_percent(coarse, fine, sensors):
    u = np.array([10.0, 0.0, 0.0, 5.0])
    ekf, truth = _run_static(coarse, fine, sensors, u, _payload(fine, 0.05), 200, seed=3,
                             wrench="payload", actuation=u)
    m, m_std = ekf.payload_mass_kg()
    assert abs(m - 0.05) < 0.005, (m, m_std)
    assert abs(m - 0.05) < 3 * m_std
    assert np.linalg.norm(_tip_position(ekf) - truth.tip_pose[:3, 3]) < ONE_PERCENT


def test_a_payload_hung_on_the_moving_arm_is_found_within_10_percent_in_1_5_s(coarse, fine, sensors):
    """Issue 29: a 50 g payload hung on the tip at t = 1 s while two tendons
    keep swinging the arm (the fine model, 1 ms midpoint steps; pose sensors
    at 100 Hz): the filter's default payload estimate is within 10 % of it
    1.5 s after the hanging and stays there (to 5 s), and its 3 standard
    deviations cover the truth from then on."""
    from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium
    truth = _mech(fine)

    def u_at(t):
        return np.array([4 + 4 * np.sin(np.pi * t), 0.0, 3 + 3 * np.sin(0.6 * np.pi * t), 0.0])
    sim = MechanismSimulator(truth, 1e-3, 0.5, q=solve_equilibrium(truth, u_at(0.0)).q)
    ekf = _ekf(coarse, sensors, wrench="payload", actuation=u_at(0.0))
    rng = np.random.default_rng(2)
    est = []
    for k in range(500):
        t = k * DT
        hung = (FrameLoad("tip", np.array([0.0, 0.0, -9.81 * 0.05, 0.0, 0.0, 0.0])),) if t >= 1.0 else ()
        sim.step(u_at(t), point_loads=hung, n=10)
        ekf.step({s.name: _reading(fine, sim.q, s, rng) for s in sensors}, actuation=u_at(t))
        est.append(ekf.payload_mass_kg())
    m, sd = np.array(est).T
    assert abs(m[99]) < 0.005                                    # before: none
    after = slice(249, 500)                                      # from 1.5 s after the hanging on
    assert np.all(np.abs(m[after] - 0.05) < 0.005), m[after].min()
    assert np.all(np.abs(m[after] - 0.05) < 3 * sd[after])


@pytest.mark.parametrize("force", [(0.0, 0.1, 0.0), (0.0, 0.0, 0.1), (0.0, 0.0707, 0.0707)])
def test_a_0_1_N_contact_force_across_the_arm_within_30_percent(coarse, fine, force):
    """Issue 29: a 0.1 N force at the tip of the straight arm (no tension;
    the finer model), read by pose sensors with the lab's noise (0.5 mm,
    0.3 degree) at 100 Hz: with the force confined to the plane across the
    arm (``force_directions``), each of four runs reads it within 30 % after
    1.5 s, within 3 reported standard deviations. Left free in 3D, the
    axial component, which the readings barely see on a straight arm,
    soaks up the coarse model's own error (about 1 N of it in these runs)
    and pulls the transverse estimate off."""
    lab = [sn.PoseSensor(f"em{i}", 5e-4, np.radians(0.3), s=s) for i, s in enumerate([0.16, 0.28, 0.40])]
    u = np.zeros(4)
    loads = Loads(point=(PointLoad(fine.total_length, force + (0.0, 0.0, 0.0)),))
    F = np.array(force)
    for seed in (1, 2, 3, 4):
        ekf, _ = _run_static(coarse, fine, lab, u, loads, 150, seed, actuation=u,
                             force_directions=[[0, 1, 0], [0, 0, 1]])
        est, sd = ekf.wrench()[:3], ekf.wrench_std()[:3]
        assert est[0] == 0.0 and sd[0] == 0.0                  # nothing estimated along the arm
        assert np.linalg.norm(est - F) < 0.03, (seed, est)
        assert np.all(np.abs(est - F)[1:] < 3 * sd[1:]), (seed, est, sd)


def test_force_directions_are_checked_at_the_door(coarse, sensors):
    ekf = _ekf(coarse, sensors, force_directions=[0, 0, 2])     # one direction, normalised
    assert ekf.k == 1 and np.allclose(ekf.S[:, 0], [0, 0, 1, 0, 0, 0])
    # the reported std is that of S w: sqrt(S P_w S^T), for a direction off the axes too
    ekf = _ekf(coarse, sensors, force_directions=[[0, 1, 1]])
    i = 2 * ekf.n + ekf.nb
    assert np.allclose(ekf.wrench_std()[1:3], np.sqrt(ekf.P[i, i] / 2))
    for bad, match in [([[0, 0, 0]], "zero"), ([[0, 1, 0], [0, 2, 0]], "not independent"),
                       ([1, 2], "1 to 3 directions"), ([[0, np.nan, 1]], "not finite"), ("up", "1 to 3")]:
        with pytest.raises(ValueError, match=f"force_directions: .*{match}"):
            _ekf(coarse, sensors, force_directions=bad)
    with pytest.raises(ValueError, match="force_directions: only with wrench='force'"):
        _ekf(coarse, sensors, wrench="payload", force_directions=[0, 0, 1])


# ------------------------------------------------------------ dynamic manoeuvre

def _inputs(t):
    """Tendon tensions [N]: two smooth swings, then a 15 N step at 2 s."""
    if t < 2.0:
        return np.array([10 * (1 - np.cos(np.pi * t)), 0.0, 8 * (1 - np.cos(1.6 * np.pi * t)), 0.0])
    return np.array([0.0, 15.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def manoeuvre(coarse, fine, sensors):
    """Truth (fine model, 2 ms steps) and filter (coarse, 10 ms) over 3 s."""
    q0 = solve_statics(fine).q
    sim = MechanismSimulator(_mech(fine), 0.002, q=q0, tol=1e-4, max_iterations=10, full_newton=False)
    rng = np.random.default_rng(7)
    ekf = _ekf(coarse, sensors)
    errors, nees, std = [], [], []
    for k in range(300):
        for _ in range(5):
            sim.step(_inputs(sim.t + 0.001))              # the inputs at each step's midpoint
        ekf.predict(_inputs((k + 0.5) * DT))
        ekf.update({s.name: _reading(fine, sim.q, s, rng) for s in sensors})
        e = _tip_position(ekf) - _tip(fine, sim.q)
        errors.append(np.linalg.norm(e))
        nees.append(es.nees(e, ekf.tip_position_cov()))
        std.append(_tip_std(ekf))
    return np.array(errors), np.array(nees), np.array(std), ekf


def test_dynamic_manoeuvre_tip_error_below_one_percent(manoeuvre):
    errors, _, std, ekf = manoeuvre
    assert errors[20:].max() < ONE_PERCENT           # after 0.2 s of convergence
    assert ekf.health.integrator_failures == 0
    assert 0.2e-3 < np.median(std) < 2e-3            # the reported std is of the error's size


def test_dynamic_manoeuvre_covariance_is_consistent(manoeuvre):
    """Tip-position NEES (3 dof) over the run: at most 10 % of the steps
    outside the per-step two-sided 95 % chi-square interval (nominal 5 %),
    neither side dominating, and the average NEES between the 0.5 % and
    99.5 % quantiles of chi2(3 N_eff)/N_eff with N_eff = N/10 (the errors of
    a 100 Hz filter are correlated over about 0.1 s)."""
    _, nees, _, _ = manoeuvre
    nees = nees[20:]
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    assert np.mean(nees > hi) <= 0.10
    assert np.mean(nees < lo) <= 0.10
    n_eff = len(nees) / 10
    a_lo, a_hi = chi2.ppf([0.005, 0.995], 3 * n_eff) / n_eff
    assert a_lo <= nees.mean() <= a_hi, (nees.mean(), a_lo, a_hi)


# ---------------------------------------------------- robustness and bookkeeping

def test_outliers_are_gated_and_counted(coarse, fine, sensors):
    u = np.array([8.0, 0.0, 0.0, 0.0])
    truth = solve_statics(fine, u)
    T = [_pose(fine, truth.q, s) for s in sensors]
    rng = np.random.default_rng(11)
    ekf = _ekf(coarse, sensors, actuation=u)
    bad_steps = set(range(40, 100, 7))
    for k in range(100):
        ekf.predict(u)
        meas = {s.name: sn.simulate_measurement(s, Ts, rng) for s, Ts in zip(sensors, T)}
        if k in bad_steps:
            meas["em1"] = meas["em1"].copy()
            meas["em1"][:3, 3] += [0.0, 0.03, 0.0]                 # a 3 cm glitch
        rep = ekf.update(meas)
        if k in bad_steps:
            assert rep.gated == ["em1"] and "em1" in rep.nis
    assert ekf.health.gated == len(bad_steps)
    assert np.linalg.norm(_tip_position(ekf) - truth.tip_pose[:3, 3]) < ONE_PERCENT


def test_dropped_and_malformed_measurements(coarse, fine, sensors):
    u = np.array([8.0, 0.0, 0.0, 0.0])
    truth = solve_statics(fine, u)
    T = [_pose(fine, truth.q, s) for s in sensors]
    rng = np.random.default_rng(12)
    ekf = _ekf(coarse, sensors, actuation=u)
    for _ in range(60):
        ekf.step({s.name: sn.simulate_measurement(s, Ts, rng) for s, Ts in zip(sensors, T)}, actuation=u)
    std_all = _tip_std(ekf).max()
    for _ in range(30):                                    # the tip tracker drops out
        rep = ekf.step({"em0": sn.simulate_measurement(sensors[0], T[0], rng), "em1": None}, actuation=u)
        assert rep.dropped == ["em1", "em2"] and rep.accepted == ["em0"]
    assert _tip_std(ekf).max() > 1.5 * std_all    # less information: larger uncertainty
    assert np.linalg.norm(_tip_position(ekf) - truth.tip_pose[:3, 3]) < ONE_PERCENT
    assert ekf.health.dropped == 60
    nan_pose = np.full((4, 4), np.nan)
    rep = ekf.step({"em0": nan_pose, "em1": np.zeros(5), "em2": sn.simulate_measurement(sensors[2], T[2], rng)},
                   actuation=u)
    assert set(rep.rejected) == {"em0", "em1"} and "NaN" in rep.rejected["em0"]
    assert "shape" in rep.rejected["em1"] and rep.accepted == ["em2"]
    assert ekf.health.rejected == 2
    with pytest.raises(ValueError, match="unknown sensor 'em9'"):
        ekf.update({"em9": T[0]})
    ekf.reset()
    assert ekf.health.updates == 0 and np.allclose(ekf.v, 0)


def test_tension_sensor_sets_the_input_and_its_noise_widens_the_prediction(coarse, sensors):
    tsen = sn.TensionSensor("t_y", "tendon_y_pos", 0.5)
    ekf = _ekf(coarse, list(sensors) + [tsen])
    quiet = _ekf(coarse, sensors)
    ekf.update({"t_y": 12.0})
    assert ekf.u[0] == 12.0
    quiet.u[0] = 12.0
    _, Gamma = quiet.linearisation()
    ekf.predict()
    quiet.predict()
    assert np.allclose(ekf.x, quiet.x)
    assert np.trace(ekf.P) > np.trace(quiet.P)
    assert np.allclose(ekf.P - quiet.P, 0.25 * np.outer(Gamma[:, 0], Gamma[:, 0]), atol=1e-12 * np.abs(ekf.P).max())


def test_motion_capture_markers_alone_track_the_static_tip(coarse, fine):
    """Three position-only markers on the surface (0.5 mm noise): within 1 %."""
    markers = [sn.marker(f"mk{i}", 5e-4, [0.0, 0.0, 0.012 if s < 0.24 else 0.009], s=s)
               for i, s in enumerate([0.16, 0.28, 0.40])]
    u = np.array([0.0, 12.0, 0.0, 9.0])
    rng = np.random.default_rng(21)
    truth = solve_statics(fine, u)
    ekf = _ekf(coarse, markers, actuation=np.zeros(4))
    for _ in range(150):
        ekf.step({m.name: _reading(fine, truth.q, m, rng) for m in markers}, actuation=u)
    assert np.linalg.norm(_tip_position(ekf) - truth.tip_pose[:3, 3]) < ONE_PERCENT
    assert ekf.health.accepted >= 440 and ekf.health.rejected == 0


def test_unsupported_models_are_refused(sensors):
    from soft_twin_core.robot.model import benchmark_cantilever_dict
    d = benchmark_cantilever_dict(3)
    d["kinematic_map"] = "cayley"
    with pytest.raises(ValueError, match="exponential-map"):
        es.EKF(from_robot_model(model_from_dict(d)), [sn.marker("m", 1e-3, s=0.5)], DT)


def test_one_gate_with_lock_out_protection(coarse, fine, sensors):
    """The gate (estimation.gate_reading): the NIS is
    e^T (H P H^T + R)^-1 e (checked by hand on a 2-D case); a sensor that
    stays far off is gated max_gated_run times in a row, then its next
    reading is taken (the filter, not the sensor, has drifted), and the
    run starts again."""
    rep = es.UpdateReport()
    runs = {"s": 0}
    e, H, R, P = np.array([1.0, 2.0]), np.eye(2), np.diag([1.0, 3.0]), np.diag([1.0, 1.0])
    assert es.gate_reading(rep, "s", e, H, R, P, 10.0, runs, 3) and rep.nis["s"] == pytest.approx(0.5 + 1.0)
    assert not es.gate_reading(rep, "s", 10 * e, H, R, P, 10.0, runs, 3) and runs["s"] == 1
    u = np.array([8.0, 0.0, 0.0, 0.0])
    truth = solve_statics(fine, u)
    T = [_pose(fine, truth.q, s) for s in sensors]
    rng = np.random.default_rng(13)
    ekf = _ekf(coarse, sensors, actuation=u, max_gated_run=4)
    for _ in range(30):
        ekf.step({s.name: sn.simulate_measurement(s, Ts, rng) for s, Ts in zip(sensors, T)}, actuation=u)
    verdicts = []
    for _ in range(6):
        meas = {s.name: sn.simulate_measurement(s, Ts, rng) for s, Ts in zip(sensors, T)}
        meas["em1"] = meas["em1"].copy()
        meas["em1"][:3, 3] += [0.0, 0.05, 0.0]                # 5 cm off from now on
        rep = ekf.step(meas, actuation=u)
        verdicts.append("em1" in rep.accepted)
    assert verdicts[:5] == [False, False, False, False, True]


def test_the_base_force_sensor_carries_the_estimated_tip_load(coarse, fine):
    """The base F/T sensor's model with a dead tip load [f; m] equals the
    support's reaction of the statics (solve.outputs, through the root
    joint's transmitted wrench: an independent path) at the equilibrium
    under that load, to round-off; its Jacobians in q and in the load match
    central differences. In the filter with a payload state, the F/T sensor
    then weighs the payload: with it and one tip marker, an unknown 50 g is
    found within 2 % in 0.5 s (without the load in the model the sensor's
    extra 0.49 N could only be gated or misread)."""
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    mech = _mech(coarse)
    tree = mech.tree
    ref = mech.frame("tip")
    w = np.array([0.3, -0.2, -0.5, 0.01, 0.02, -0.015])
    eq = solve_equilibrium(mech, np.array([6.0, 0.0, 3.0, 0.0]), point_loads=(FrameLoad("tip", w),))
    ws = Workspace(tree)
    load = (ref.joint, ref.x, w)
    W, H = sn.base_wrench_and_jacobian(tree, ws, eq.q, point_load=load)
    np.testing.assert_allclose(W, state_outputs(mech, eq.q, eq.lam, eq.inputs).base_wrench, rtol=0, atol=1e-11)
    q = eq.q + 0.05 * np.random.default_rng(1).standard_normal(tree.nv)
    W, H = sn.base_wrench_and_jacobian(tree, ws, q, point_load=load)
    fd = np.column_stack([(sn.base_wrench_and_jacobian(tree, ws, q + h, False, load)[0]
                           - sn.base_wrench_and_jacobian(tree, ws, q - h, False, load)[0]) / 2e-6
                          for h in 1e-6 * np.eye(tree.nv)])
    assert np.abs(H - fd).max() <= 1e-7 * np.abs(fd).max()
    D = sn.base_wrench_load_jacobian(tree, ws, q, ref.joint, ref.x)
    fd = np.column_stack([(sn.base_wrench_and_jacobian(tree, ws, q, False, (ref.joint, ref.x, w + h))[0]
                           - sn.base_wrench_and_jacobian(tree, ws, q, False, (ref.joint, ref.x, w - h))[0]) / 2e-6
                          for h in 1e-6 * np.eye(6)])
    np.testing.assert_allclose(D, fd, atol=1e-8)
    # the filter weighs the payload with the F/T sensor
    ft = sn.BaseWrenchSensor("ft", 0.02, 0.002)
    marker = sn.marker("tip_marker", 1e-3, s=0.40)
    truth = _mech(fine)
    q_true = solve_equilibrium(truth, np.zeros(4), loads=_payload(fine, 0.05)).q
    _, where = sn.check_sensors(truth, [ft, marker])
    wt = Workspace(truth.tree)
    clean = sn.predict_readings(wt, q_true, [marker], where)
    hung = (truth.frame("tip").joint, truth.frame("tip").x, np.array([0.0, 0.0, -9.81 * 0.05, 0.0, 0.0, 0.0]))
    clean["ft"] = sn.predict_measurement(wt, sn.forward(wt, q_true), ft, None, point_load=hung)
    rng = np.random.default_rng(5)
    ekf = es.EKF(mech, [ft, marker], DT, wrench="payload")
    for _ in range(50):
        ekf.step({s.name: sn.simulate_measurement(s, clean[s.name], rng) for s in (ft, marker)})
    m, sd = ekf.payload_mass_kg()
    assert abs(m - 0.05) < 0.001 and abs(m - 0.05) < 3 * sd, (m, sd)
    assert ekf.health.gated == 0
