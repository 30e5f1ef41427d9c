"""Dynamics: M, C, forces, integrators (issue 6)."""

import numpy as np
import pytest
import scipy.linalg as sla

from soft_twin_core.engine import loads as ld
from soft_twin_core.reference import dynamics as dy
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference import statics as st
from soft_twin_core.robot.model import State, benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator, make_inputs
from rod_statics import mechanism, solve_statics

RNG = np.random.default_rng(11)


def arm(n=3, free="all", offsets=False, actuators=True, viscosity=0.0):
    d = benchmark_cantilever_dict(n, free)
    d["segments"][0]["material"]["viscosity"] = viscosity
    if offsets:
        d["segments"][0]["offset_to_next"] = {"position": [0.01, 0, 0], "rpy": [0.0, 0.4, 0.2]}
        d["segments"].append(dict(d["segments"][0], name="distal", length=0.2, sections=2, offset_to_next=None))
        del d["segments"][1]["offset_to_next"]
    if actuators:
        d["actuators"] = [{"name": "a", "offset": [0.005, 0.002]},
                          {"name": "h", "routing": "helical", "radius": 0.006, "turns_per_meter": 1.0,
                           "start": 0.1},
                          {"name": "p", "offset": [0.0, 0.006], "model": "point_moment", "end": 0.4}]
    return model_from_dict(d)


def simulator(m, dt=1e-3, theta=0.5, **options):
    """The simulator of every robot on a classic model, with the node's
    Newton tolerance (1e-4 of the largest strain rate) unless told."""
    return MechanismSimulator(mechanism(m), dt, theta, **{"tol": 1e-4, "max_iterations": 10, **options})


def random_state(m, scale=0.2):
    return m.q0 + scale * RNG.normal(size=m.n_dof), RNG.normal(size=m.n_dof)


def test_mass_matrix_spd_and_passivity():
    m = arm(3, "all", offsets=True)
    q, qd = random_state(m)
    M = dy.mass_matrix(m, q)
    assert np.abs(M - M.T).max() < 1e-15 * np.abs(M).max() * 10
    assert np.linalg.eigvalsh(M).min() > 0
    C = dy.coriolis_matrix(m, q, qd)
    h = 1e-6
    Mdot = (dy.mass_matrix(m, q + h * qd) - dy.mass_matrix(m, q - h * qd)) / (2 * h)
    S = Mdot - 2 * C
    assert np.abs(S + S.T).max() < 1e-7 * np.abs(S).max()
    assert np.abs(C @ qd - dy.bias_force(m, q, qd)).max() < 1e-12 * np.abs(C @ qd).max()


def test_kinetic_energy_matches_rigid_section_sum():
    """T = 1/2 qd^T M qd equals the sum over quadrature points of the cross
    sections' kinetic energies from finite-difference velocities of FK."""
    m = arm(2, "all", actuators=False)
    q, qd = random_state(m)
    from soft_twin_core.reference.loads import gauss_points
    s, w, sec = gauss_points(m)
    h = 1e-6
    gp, gm = kin.poses(m, q + h * qd, s), kin.poses(m, q - h * qd, s)
    g = kin.poses(m, q, s)
    from soft_twin_core import lie
    eta = lie.vee6(lie.se3_inv(g) @ (gp - gm) / (2 * h))
    Mc = np.array([m.sections[i].M for i in sec])
    T_ref = 0.5 * np.einsum("p,pa,pab,pb->", w, eta, Mc, eta)
    assert abs(0.5 * qd @ dy.mass_matrix(m, q) @ qd - T_ref) < 1e-8 * T_ref


def test_lagrange_equations_by_finite_differences():
    """M qdd + C qd = d/dt dT/dqd - dT/dq, with T from the mass matrix."""
    m = arm(2, "all", actuators=False)
    q, qd = random_state(m)
    h = 1e-5
    T = lambda q_, qd_: 0.5 * qd_ @ dy.mass_matrix(m, q_) @ qd_  # noqa: E731
    dTdq = np.array([(T(q + h * e, qd) - T(q - h * e, qd)) / (2 * h) for e in np.eye(m.n_dof)])
    # d/dt (M qd) along qdd = 0
    ddt = (dy.mass_matrix(m, q + h * qd) - dy.mass_matrix(m, q - h * qd)) @ qd / (2 * h)
    assert np.abs(dy.bias_force(m, q, qd) - (ddt - dTdq)).max() < 1e-6 * np.abs(ddt).max()


def test_engine_matches_reference():
    """The multibody engine's mass matrix and forces (loads of every kind,
    tendons, gravity, damping) equal the numpy chain dynamics."""
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.integrators import residual_pass
    m = arm(3, "all", offsets=True)
    q, qd = random_state(m)
    loads = ld.Loads(point=(ld.tip_load(m, (0.01, 0.02, -0.01), (0.001, 0, 0)),
                            ld.PointLoad(0.3, (0, 0.01, 0, 0, 0, 0.002), "body")),
                     distributed=(ld.DistributedLoad((0, 0, 0.01, 0, 0, 0), "world", 0.1, 0.4),))
    u = np.array([0.3, 0.2, 0.25])
    M0, f0 = dy.dynamics_terms(m, q, qd, u, loads)
    sim = simulator(m)
    inp = make_inputs(sim.mech, u, loads=loads)
    M1 = alg.crba(sim.tree, sim.ws, q)
    coef = sim.act.unit @ u
    R = np.empty(m.n_dof)
    residual_pass(sim.ws.m, sim.ws.w, sim.act, inp.loads, inp.gravity, coef, inp.effort, q, qd, np.zeros(m.n_dof),
                  R, False)
    assert np.abs(M1 - M0).max() < 1e-12 * np.abs(M0).max()
    assert np.abs(-R - f0).max() < 1e-12 * np.abs(f0).max()


def test_energy_conserved_by_continuous_model():
    """Adaptive reference integration (DOP853, tight tolerances): total energy
    of the undamped arm with gravity and constant tendon tension is constant."""
    from scipy.integrate import solve_ivp
    m = arm(2, "bending_torsion")
    u = np.array([0.2, 0.1, 0.0])
    n = m.n_dof

    def rhs(t, y):
        return np.concatenate([y[n:], dy.forward_dynamics(m, y[:n], y[n:], u)])

    sol = solve_ivp(rhs, (0, 0.5), np.zeros(2 * n) + np.concatenate([m.q0, np.zeros(n)]),
                    rtol=1e-11, atol=1e-12, method="DOP853")
    E = np.array([sum(dy.energy(m, y[:n], y[n:], u)) for y in sol.y.T[::10]])
    scale = max(abs(e) for e in dy.energy(m, sol.y[:n, -1], sol.y[n:, -1], u))
    assert np.ptp(E) < 1e-8 * scale


def midpoint_energy_drift(m, dt, T, u=None):
    sim = simulator(m, dt, tol=1e-12, max_iterations=30)
    E0 = sum(dy.energy(m, sim.q, sim.v, u))
    scale = None
    drift = 0.0
    for k in range(int(round(T / dt))):
        sim.step(u)
        E = dy.energy(m, sim.q, sim.v, u)
        scale = max(scale or 0.0, abs(E[0]))
        drift = max(drift, abs(sum(E) - E0))
    return drift / scale


def test_midpoint_energy_drift_small_and_second_order():
    m = arm(2, "bending_torsion", actuators=False)
    d1 = midpoint_energy_drift(m, 4e-3, 0.4)
    d2 = midpoint_energy_drift(m, 2e-3, 0.4)
    assert d1 < 1e-3
    assert 3.0 < d1 / d2 < 5.5          # ~ 2^2: second order


def test_midpoint_energy_over_ten_seconds_at_node_step():
    """Issue 6: < 1e-3 relative drift over 10 s at the node's 1 ms step."""
    m = arm(2, "bending_torsion", actuators=False)
    assert midpoint_energy_drift(m, 1e-3, 10.0) < 1e-3


@pytest.mark.parametrize("theta", [1.0, 0.6])
def test_damped_response_settles_on_statics(theta):
    """Kelvin-Voigt damping near critical for the first mode; the L-stable
    (theta = 1) and damped (0.6) schemes reach the statics solution."""
    m = arm(3, "bending_torsion", viscosity=3e5)
    u = {"a": 0.2, "h": 0.1, "p": 0.1}
    loads = ld.Loads(point=(ld.tip_load(m, (0.0, 0.02, 0.0)),))
    ref = solve_statics(m, u, loads)
    sim = simulator(m, 1e-2, theta)
    for _ in range(60):
        sim.step(u, loads=loads, n=100)
        if np.abs(sim.v).max() < 1e-10:
            break
    assert np.abs(sim.q - ref.q).max() < 1e-8


@pytest.mark.parametrize("n", [20])
def test_cantilever_frequencies_converge_to_euler_bernoulli(n):
    """Small oscillations about the straight rod (no gravity): K v = w^2 M v."""
    d = benchmark_cantilever_dict(n, "bending")
    d["gravity"] = [0, 0, 0]
    m = model_from_dict(d)
    M = dy.mass_matrix(m, m.q0)
    w2 = np.sort(sla.eigh(m.K_q, M, eigvals_only=True))
    # bending about y and z give pairs of equal frequencies
    w = np.sqrt(w2[::2][:3])
    sec = m.sections[0]
    EI, rhoA, L = sec.K[4, 4], sec.M[0, 0], m.total_length
    ref = np.array([1.8751, 4.6941, 7.8548]) ** 2 * np.sqrt(EI / (rhoA * L**4))
    assert np.all(np.abs(w / ref - 1) < 0.01), w / ref


def test_frequency_error_falls_with_sections():
    errs = []
    for n in (3, 6, 12):
        d = benchmark_cantilever_dict(n, "bending")
        d["gravity"] = [0, 0, 0]
        m = model_from_dict(d)
        w2 = np.sort(sla.eigh(m.K_q, dy.mass_matrix(m, m.q0), eigvals_only=True))
        sec = m.sections[0]
        ref = 4.6941**2 * np.sqrt(sec.K[4, 4] / (sec.M[0, 0] * m.total_length**4))
        errs.append(abs(np.sqrt(w2[2]) / ref - 1))
    assert errs[0] > errs[1] > errs[2]


def test_adaptive_radau_matches_midpoint():
    m = arm(2, "bending_torsion", actuators=False, viscosity=1e3)
    sol = dy.simulate_ivp(m, (0, 0.2), State.rest(m), method="Radau", rtol=1e-9, atol=1e-11)
    assert sol.success
    sim = simulator(m, 1e-4)
    sim.step(n=2000)
    assert np.abs(sim.q - sol.y[:m.n_dof, -1]).max() < 1e-5


def test_base_reaction_dynamic_equals_static_at_rest_and_balances_momentum():
    m = arm(3, "all", actuators=False)
    ref = solve_statics(m)
    z = np.zeros(m.n_dof)
    R = dy.base_reaction_dynamic(m, ref.q, z, z)
    assert np.abs(R - ref.base_wrench_world).max() < 1e-10 * np.abs(R).max()
    # free motion: reaction force = d/dt(linear momentum) - weight, by FD
    q, qd = random_state(m, 0.1)
    qdd = dy.forward_dynamics(m, q, qd)
    from soft_twin_core.reference.loads import gauss_points
    s, w, sec = gauss_points(m)
    rhoA = m.sections[0].M[0, 0]

    def momentum(q_, qd_):
        Jw = kin.jacobian(m, q_, s, frame="world")
        return np.sum((w * rhoA)[:, None] * (Jw[:, :3] @ qd_), axis=0)
    h = 1e-6
    dp = (momentum(q + h * qd, qd + h * qdd) - momentum(q - h * qd, qd - h * qdd)) / (2 * h)
    R = dy.base_reaction_dynamic(m, q, qd, qdd)
    weight = rhoA * m.total_length * m.gravity
    assert np.abs(R[:3] - (dp - weight)).max() < 1e-6 * np.abs(dp - weight).max()


def test_simulator_rejects_bad_input_and_keeps_state():
    m = arm(2, "bending")
    with pytest.raises(ValueError, match="dt"):
        simulator(m, -1.0)
    sim = simulator(m)
    sim.step({"a": 0.1}, n=5)
    q = sim.q.copy()
    with pytest.raises(ValueError, match="tension must be >= 0"):
        sim.step({"a": -1.0})
    assert np.array_equal(sim.q, q)
    sim.step({"a": 0.1})
    assert sim.t == pytest.approx(6e-3)


def test_dynamic_internal_wrench_at_base_equals_reaction():
    m = arm(3, "all", actuators=False)
    q, qd = random_state(m, 0.1)
    qdd = dy.forward_dynamics(m, q, qd)
    W0 = dy.internal_wrenches_dynamic(m, q, qd, qdd, [0.0])[0]
    R = dy.base_reaction_dynamic(m, q, qd, qdd)
    Rb = m.base_pose[:3, :3]            # body frame at s = 0 is the base frame
    assert np.allclose(np.concatenate([Rb.T @ R[:3], Rb.T @ R[3:]]), -W0, atol=1e-10 * np.abs(W0).max())
    # at rest it equals the statics cut
    z = np.zeros(m.n_dof)
    s = np.array([0.1, 0.3])
    assert np.allclose(dy.internal_wrenches_dynamic(m, q, z, z, s), st.internal_wrenches(m, q, s), atol=1e-15)


def test_compiled_base_reaction_matches_reference():
    pytest.importorskip("numba")
    m = arm(3, "all", offsets=True)
    q, qd = random_state(m)
    qdd = RNG.normal(size=m.n_dof)
    u = np.array([0.3, 0.2, 0.25])
    loads = ld.Loads(point=(ld.tip_load(m, (0.01, 0.02, -0.01), (0.001, 0, 0)),
                            ld.PointLoad(0.3, (0, 0.01, 0, 0, 0, 0.002), "body")))
    ref = dy._base_reaction_reference(m, q, qd, qdd, loads)
    R = dy.base_reaction_dynamic(m, q, qd, qdd, u, loads)
    assert np.abs(R - ref).max() < 1e-12 * np.abs(ref).max()


def test_recorded_accelerations_are_the_chains_forward_dynamics():
    """The accelerations a run records at a state (the scenario runner's
    probe: start_multipliers of a simulator at that state, a workspace of
    its own, so the integrator's steps are untouched) equal the numpy chain's
    forward dynamics, tendons (a point-moment one too) and loads included."""
    m = arm(3, "bending_torsion", offsets=True)
    u = np.array([0.3, 0.2, 0.25])
    loads = ld.Loads(point=(ld.tip_load(m, (0.01, 0.02, -0.01), (0.001, 0, 0)),))
    sim = simulator(m, 2e-3)
    sim.step(u, loads=loads, n=20)
    probe = simulator(m, 2e-3, q=sim.q, v=sim.v)
    acc = probe.start_multipliers(sim.inputs).a
    ref = dy.forward_dynamics(m, sim.q, sim.v, u, loads)
    assert np.abs(acc - ref).max() < 1e-9 * np.abs(ref).max()


def test_default_newton_tolerance_is_far_below_the_time_step_error():
    """The node's Newton tolerance (TwinSettings.tolerance: 1e-4 of the largest strain
    rate) moves the tip trajectory of the benchmark cantilever (all six
    modes, falling under gravity) by under 20 % of the time-step error at
    the same dt (estimated by Richardson from dt and dt/2, both converged to
    1e-11; measured 13 %, and 1.1 % with a fresh factorisation every step:
    a fresh Newton matrix contracts the error ~100-1000-fold an iteration
    and two iterations overshoot the tolerance, a reused one leaves about
    what the tolerance allows), and takes fewer iterations than a tight
    tolerance."""
    m = model_from_dict(benchmark_cantilever_dict(6, "all"))

    def tips(dt, **kw):
        sim = simulator(m, dt, **kw)
        out = []
        for _ in range(25):
            sim.step(n=int(round(0.02 / dt)))
            out.append(kin.tip_pose(m, sim.q)[:3, 3].copy())
        return np.array(out), sim.newton_iterations
    default, it_default = tips(2e-3)
    tight, it_tight = tips(2e-3, tol=1e-11)
    half, _ = tips(1e-3, tol=1e-11)
    newton_error = np.abs(default - tight).max()
    step_error = 4.0 / 3.0 * np.abs(tight - half).max()
    assert step_error > 1e-5                       # 0.5 s of the fall: the time step matters
    assert newton_error < 0.2 * step_error, (newton_error, step_error)
    assert it_default < 0.7 * it_tight


def test_run_reuses_factorisations_across_steps_and_calls():
    """MechanismSimulator.step(n=k) (one compiled run) and step() one at a time (the
    node's path) reuse Newton's factorisation while it contracts the error
    as a fresh one does (integrators.REUSE_MAX_RATIO), also across calls,
    and take the steps of a simulator that factorises at every step
    (``reuse_factorisation=False``) to the Newton tolerance's effect."""
    m = model_from_dict(benchmark_cantilever_dict(6, "all"))
    dt = 2e-3
    run, single = simulator(m, dt), simulator(m, dt)
    fresh = simulator(m, dt, reuse_factorisation=False)
    tips = {"run": [], "single": [], "fresh": []}
    for _ in range(25):                            # 0.5 s of the fall
        run.step(n=5)
        fresh.step(n=5)
        for _ in range(5):
            single.step()
        for name, sim in (("run", run), ("single", single), ("fresh", fresh)):
            tips[name].append(kin.tip_pose(m, sim.q)[:3, 3].copy())
    assert fresh.factorisations == 125
    assert run.factorisations < 25, run.factorisations      # fewer than one per call of 5 steps
    assert single.factorisations < 0.5 * 125, single.factorisations
    ref = np.array(tips["fresh"])
    assert np.abs(np.array(tips["run"]) - ref).max() < 2e-4
    assert np.abs(np.array(tips["single"]) - ref).max() < 2e-4


def test_an_outside_factorisation_of_the_workspace_is_never_reused():
    """A factorisation that another caller leaves in the simulator's
    workspace (algorithms.factor, here of a matrix 1e6 times too stiff, whose
    tiny Newton updates would pass the convergence test at once) is not
    mistaken for the integrator's: the next steps are those of an untouched
    simulator, to the Newton tolerance."""
    from soft_twin_core.engine import algorithms as alg
    m = model_from_dict(benchmark_cantilever_dict(6, "all"))
    # a tight tolerance: every step iterates more than twice and so takes a
    # fresh factorisation, the two runs compute the same (reusing the
    # outside factorisation: 0.55 and 151 /s apart)
    a, b = simulator(m, 2e-3, tol=1e-8), simulator(m, 2e-3, tol=1e-8)
    for sim in (a, b):
        sim.step(n=5)
    alg.factor(m.tree, b.ws, b.q, 1e6, 1e6)
    assert b.ws.factor_key is None
    for sim in (a, b):
        sim.step(n=5)
    assert np.abs(a.q - b.q).max() < 1e-6
    assert np.abs(a.v - b.v).max() < 1e-3


def test_the_released_cantilever_follows_soromoxs_pcs_dynamics():
    """The benchmark cantilever (every strain free, undamped) released from
    straight: its tip at t = 0.1, 0.2, 0.3 s (0.45 m down by then) here
    (midpoint rule, dt 0.1 ms: converged in time to 1e-8 m) and in
    SoRoMoX's PCS model with as many segments (Tsit5 at dt 0.1 ms; values
    stored by ``benchmarks/soromox_pcs_dynamics.py``). Two codes, two
    integrators, the same discretised mechanics: they agree to 7.7e-5 m on
    8 sections and 8.8e-6 m on 16, and the difference shrinks as the
    sections do (SoRoMoX integrates a segment's inertia at 5 Gauss points,
    the engine at 2)."""
    import json
    from pathlib import Path
    from soft_twin_core.robot.mechanism import from_robot_model
    data = json.loads((Path(__file__).parents[1] / "data" / "soromox_pcs_release.json").read_text())
    assert data["model"]["strains"] == "all six" and data["model"]["shear_stiffness"] == "G A"
    worst = {}
    for r in data["results"]:
        n, dt = r["segments"], 1e-4
        m = model_from_dict(benchmark_cantilever_dict(n, "all", length=data["model"]["length_m"]))
        sim = MechanismSimulator(from_robot_model(m), dt, 0.5, tol=1e-10)
        done, errors = 0, []
        for t, p in zip(r["times_s"], r["tips_m"]):
            k = int(round(t / dt)) - done
            sim.step(n=k)
            done += k
            errors.append(np.linalg.norm(kin.tip_pose(m, sim.q)[:3, 3] - p))
        worst[n] = max(errors)
        assert kin.tip_pose(m, sim.q)[2, 3] < -0.4
    assert worst[8] < 1.5e-4 and worst[16] < 2e-5 and worst[16] < worst[8] / 4, worst
