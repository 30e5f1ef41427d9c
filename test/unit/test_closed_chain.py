"""The planner, the calibration and the filter on a closed chain (through
the KKT system of the constraints): the planar parallel robot with a
tendon in each rod. The frame's sensitivity to the tensions against finite
differences of full equilibrium solves, a platform position reached by
the tensions (checked by an independent equilibrium solve of the answer),
the calibration's sensitivities through the constraint rows, and the
filter's process Jacobian against central differences of its constrained
step and its estimate of a load on the platform."""

import copy

import numpy as np
import pytest

from soft_twin_core.planning import planner as pl
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import find_file, read_yaml_file
from soft_twin_core.solve import constrained as cs


E_ROD = 2.0e9          # Pa: polymer rods (the file's steel ones bend too little under a tendon for a fit)


def _robot_dict(scale=(1.0, 1.0), modulus=E_ROD):
    d = copy.deepcopy(read_yaml_file(find_file("planar_parallel_robot", "robots")))
    members = [b for b in d["bodies"] if b.get("type") == "member"]
    for b, k in zip(members, scale):
        b["actuators"] = [{"name": f"{b['name']}_tendon", "type": "tendon", "offset": [0.0, 0.0015]}]
        b["segments"][0]["material"]["youngs_modulus"] = modulus * k
    return d


@pytest.fixture(scope="module")
def robot():
    return mechanism_from_dict(_robot_dict())


def _platform(mech, u):
    eq = cs.solve_equilibrium(mech, actuation=u)
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.workspace import Workspace
    ref = mech.frame("platform")
    return alg.point_poses(mech.tree, Workspace(mech.tree), eq.q, [ref.joint], [ref.x])[0][:3, 3]


def test_closed_chain_sensitivity_matches_finite_differences(robot):
    s = pl.TipSolver(robot, pl.PlanOptions(frame="platform"))
    assert type(s.statics).__name__ == "_Statics" and s.n_j == 0 and s.n_u == 2     # the KKT path
    u = np.array([6.0, 2.0])
    e = s.statics.solve(u, None)
    g, S = s.frame_motion(e, u)
    h = 1e-3
    fd = np.column_stack([(_platform(robot, u + h * k) - _platform(robot, u - h * k)) / (2 * h) for k in np.eye(2)])
    assert np.abs(fd).max() > 1e-6
    assert np.abs(S[:3] - fd).max() <= 1e-6 * np.abs(fd).max()


def test_closed_chain_platform_target_reached(robot):
    s = pl.TipSolver(robot, pl.PlanOptions(frame="platform", position_weights=(1.0, 0.0, 0.0)))
    target = _platform(robot, np.array([5.0, 1.0]))
    r = s.solve(target, np.zeros(2), None)
    assert r.reached and r.position_error < 1e-3 and abs(r.pose[0, 3] - target[0]) <= 1e-6, r.status
    check = _platform(robot, r.x)
    assert abs(check[0] - target[0]) < 2e-6
    assert np.all(r.x >= 0.0)


def test_closed_chain_calibration_sensitivities():
    """The calibration's sensitivities of the rods' moduli and of a payload
    on the platform's rod end through the constraint rows against finite
    differences (steps of 1 % of each parameter's scale: the rods move
    little, and smaller steps meet the equilibrium's own tolerance; at the
    best step, 1e-4 kg, the payload's column matches to 2e-7).
    (The fit itself: :func:`test_closed_chain_calibration_recovers_the_rods_moduli`,
    on softer rods: these move the platform by under a millimetre.)"""
    from soft_twin_core.estimation import calibration as cal
    from soft_twin_core.estimation import sensors as sn
    from test_calibration import assert_sensitivities
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    U = np.array([[t1, t2] for t1 in (0.0, 4.0, 10.0) for t2 in (0.0, 3.0, 8.0)])
    rec = cal.record_static_sweep(mechanism_from_dict(_robot_dict((1.2, 0.9))), sensors, U, np.random.default_rng(4))
    pb = cal.Problem(_robot_dict(), sensors, rec, ["youngs_modulus:rod1", "youngs_modulus:rod2", "payload_mass"])
    assert_sensitivities(pb, np.array([1.1 * E_ROD, 0.95 * E_ROD, 0.01]), 1e-3, step=1e-2)


def test_closed_chain_calibration_recovers_the_rods_moduli():
    """A static sweep of the parallel robot with soft rods (5 MPa, so that
    tensions up to 1.2 N move the platform by centimetres), the truth's rods
    20 % stiffer and 10 % softer than nominal, read by a platform tracker
    and a marker on rod 2 (0.1 mm, 2 mrad): both moduli recovered within
    3 % and three standard deviations, the residual at the sensors' noise,
    the held-out rows' tip error down to it."""
    from soft_twin_core.estimation import calibration as cal
    from soft_twin_core.estimation import sensors as sn
    E = 5.0e6
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    U = np.array([[t1, t2] for t1 in (0.0, 0.5, 1.2) for t2 in (0.0, 0.5, 1.2)])
    truth = np.array([1.2 * E, 0.9 * E])
    rec = cal.record_static_sweep(mechanism_from_dict(_robot_dict((1.2, 0.9), E)), sensors, U,
                                  np.random.default_rng(4))
    res = cal.calibrate(_robot_dict(modulus=E), sensors, rec, ["youngs_modulus:rod1", "youngs_modulus:rod2"],
                        holdout_every=4)
    assert np.all(np.abs(res.values / truth - 1) < 0.03), res.table()
    assert np.all(np.abs(res.values - truth) < 3 * res.std), res.table()
    assert 0.7 < res.residual_sigma < 1.3, res.table()
    h = res.heldout
    assert h["tip_rms_after_m"] < 0.25e-3 < h["tip_rms_before_m"], h


def _filter(mech, **kw):
    from soft_twin_core.estimation import ekf
    from soft_twin_core.estimation import sensors as sn
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    return ekf.EKF(mech, sensors, **kw), sensors


def _loaded(mech, u, force):
    return cs.solve_equilibrium(mech, u, point_loads=[cs.FrameLoad("rod2_tip", [*force, 0, 0, 0], "world")])


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_filter_process_jacobian_on_a_closed_chain(robot, theta):
    """The filter's process model steps the robot with the loop's reactions
    as multipliers (it refused closed chains before). At a loaded rest
    state (tendons, a force on the tip, gravity: the reactions non-zero) the
    step stays put, and the analytic Phi and Gamma_u (the KKT system of the
    linearised step, the reactions' geometric stiffness included) equal
    central differences of the constrained step, which pulls a perturbed
    state back onto the loop."""
    from test_estimation import assert_linearisation_at_rest
    u, f = np.array([6.0, 2.0]), np.array([0.2, 0.0, -0.3])
    eq = _loaded(robot, u, f)
    ekf, _ = _filter(robot, theta=theta, wrench="force", actuation=u, q_init=eq.q)
    assert ekf.tip == "rod2_tip" and np.abs(ekf.lam).max() > 0.1          # the loop carries load
    assert_linearisation_at_rest(ekf, np.concatenate([eq.q, np.zeros(ekf.n), f]), u)
    Phi, _ = ekf.linearisation()
    G = cs.constraint_rows(robot, ekf.ws, eq.q)[1]
    assert np.abs(G @ Phi[:ekf.n]).max() <= 1e-9 * np.abs(Phi[:ekf.n]).max()   # onto the loop's tangent


def test_filter_estimates_a_load_on_a_closed_chain(robot):
    """A force on the platform's rod end, unknown to the filter, estimated
    from two readings of 0.1 mm (a pose on the platform, a marker on rod 2)
    by a filter tuned for a slow robot: consistent (the error's normalised
    square under the chi-square bound of 3 dof at 0.999), informative on the
    lateral axis (under 0.05 N, where the rods bend), honest on the vertical
    one (which the stiff rods hardly show: a large deviation); the estimate
    stays on the loop, and its covariance holds no motion that breaks it."""
    from soft_twin_core.estimation import sensors as sn
    u, f = np.array([4.0, 1.0]), np.array([0.2, 0.0, -0.3])
    truth = _loaded(robot, u, f)
    ekf, sensors = _filter(robot, dt=0.01, wrench="force", actuation=u, process_noise_q=0.02,
                           process_noise_v=1.0)                                # starts unloaded
    rng = np.random.default_rng(3)
    z = {s.name: sn.sensor_pose(robot, truth.q, s) for s in sensors}
    z["mk"] = z["mk"][:3, 3]
    for _ in range(150):
        ekf.step({s.name: sn.simulate_measurement(s, z[s.name], rng) for s in sensors})
    n, e, std = ekf.n, ekf.wrench()[:3] - f, ekf.wrench_std()[:3]
    print("force error", e, "std", std)
    assert e @ np.linalg.solve(ekf.P[2 * n:, 2 * n:], e) < 16.27                  # chi2(3).ppf(0.999)
    assert std[0] < 0.05 and std[2] > 5 * std[0] and ekf.health.integrator_failures == 0
    phi, G = cs.constraint_rows(robot, ekf.ws, ekf.q)
    assert np.abs(phi).max() < 1e-8                                           # m, rad
    assert np.abs(G @ ekf.P[:n, :n] @ G.T).max() <= 1e-6 * np.abs(ekf.P[:n, :n]).max()       # (round-off)


def test_closed_chain_damping_fitted_to_a_step_response(tmp_path, capsys):
    """The rods' viscosities of the parallel robot (soft rods, 5 MPa; the
    truth's 1.6x nominal) from a 0.5 s recording at 40 Hz of a tendon step
    (truth simulated at 2 ms, fitted at 5 ms through the command line, each
    simulation through the KKT step of the clamped platform): both within
    1 % (the 5 ms fit's discretisation bias: 0.4 and 0.15 % found)."""
    import yaml
    from soft_twin_core.estimation import calibration as cal
    from soft_twin_core.estimation import sensors as sn
    from test_calibration import damping_cli
    E, eta = 5.0e6, 2.0e5

    def robot(k):
        d = _robot_dict(modulus=E)
        for b in d["bodies"]:
            for seg in b.get("segments", []):
                seg["material"]["viscosity"] = eta * k
        return d
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    times = np.arange(0.0, 0.5, 0.025)
    inputs = np.zeros((len(times), 2))
    inputs[times >= 0.05, 0] = 1.0
    rec = cal.record_dynamic(mechanism_from_dict(robot(1.6)), sensors, times, inputs, np.random.default_rng(5),
                             dt=2e-3)
    path = tmp_path / "parallel.yaml"
    path.write_text(yaml.safe_dump(robot(1.0)))
    rep = damping_cli(tmp_path, capsys, str(path), mechanism_from_dict(robot(1.0)), sensors, rec, 0.005)
    for name in ("viscosity:rod1", "viscosity:rod2"):
        assert abs(rep[name]["fitted"] / (1.6 * eta) - 1) < 0.01, rep
