"""Planner (soft_twin_core.planning.planner, soft_twin_core.planning.paths) on classic rods
(one-member mechanisms; the pan-tilt arm's: test_articulated_planner.py): exact
sensitivities against finite differences of full statics solves, the
slides' constant-curvature arm against its closed form, the default robot's
circle, redundancy resolution against a linear programme, bounds and rate
limits over random paths (hypothesis), unreachable samples flagged, and the
dynamic verification with lag compensation."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hst

from soft_twin_core.engine.forces import actuation_matrix, actuator_arrays
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError
from soft_twin_core.planning import paths
from soft_twin_core.planning import planner as pl
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference.loads import actuation_force
from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
from soft_twin_core.robot.model import load_model, model_from_dict
from rod_statics import solve_statics

EI, D_OFFSET, L = 1.0, 0.02, 1.0


def slides_arm(n_sections=4, tendon_model="point_moment"):
    return from_robot_model(slides_model(n_sections, tendon_model))


def slides_model(n_sections=4, tendon_model="point_moment"):
    """The slides' planar arm (part C): L = 1 m, EI = 1 N m^2, inextensible,
    unshearable, bending in the x-y plane only (free mode bending_z), no
    gravity, one tendon at offset d = 2 cm along +y (point-moment model:
    the tip moment T d, so the curvature is T d / EI everywhere)."""
    return model_from_dict({
        "name": "slides_arm", "gravity": [0, 0, 0],
        "segments": [{"length": L, "sections": n_sections, "free_modes": ["bending_z"],
                      "sectional": {"stiffness": {"EA": 1e3, "GA2": 1e3, "GA3": 1e3, "GJ": 1.0,
                                                  "EI2": EI, "EI3": EI},
                                    "inertia": {"mass_per_length": 0.1, "J1": 1e-5, "J2": 1e-5,
                                                "J3": 1e-5}}}],
        "actuators": [{"name": "tendon", "type": "tendon", "offset": [D_OFFSET, 0.0],
                       "model": tendon_model}]})


def slides_tip(kappa):
    """Tip of the slides' H(alpha) at alpha = L for f_w = [0, 0, kappa]:
    [sin(kL)/k, (1 - cos(kL))/k, 0] (seed 001, 'Soft continuum arm with
    constant curvature')."""
    return np.array([np.sin(kappa * L) / kappa, (1 - np.cos(kappa * L)) / kappa, 0.0])


@pytest.fixture(scope="module")
def arm():
    return load_mechanism("tendon_arm")


@pytest.fixture(scope="module")
def arm_model():
    return load_model("tendon_arm")


# --------------------------------------------------------------------------
# Sensitivities
# --------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["tendon_arm", "pneumatic_arm"])
def test_actuation_matrix_matches_reference(name):
    m = load_model(name)
    u = np.array([3.0 if a.kind == "tendon" else 2e4 for a in m.actuators])
    q = solve_statics(m, u).q
    B = actuation_matrix(m.tree, Workspace(m.tree), actuator_arrays(m.tree), q)
    ch = kin.chain(m, q)
    ref = np.stack([actuation_force(m, ch, e) for e in np.eye(len(m.actuators))], axis=1)
    assert np.abs(B - ref).max() <= 1e-12 * np.abs(ref).max()


def test_actuation_matrix_point_moment():
    m = slides_model()
    q = np.array([0.3, 0.3, 0.3, 0.3])
    ch = kin.chain(m, q)
    ref = actuation_force(m, ch, np.array([1.0]))
    mech = from_robot_model(m)
    assert np.allclose(actuation_matrix(mech.tree, Workspace(mech.tree), actuator_arrays(mech.tree), q)[:, 0], ref, rtol=1e-12, atol=1e-15)


def test_tip_sensitivity_matches_finite_differences(arm, arm_model):
    u = np.array([2.0, 0.5, 6.0, 1.0])
    r = solve_statics(arm_model, u)
    S = pl.frame_sensitivity(arm, r.q, u)
    h = 1e-4
    fd = np.empty((3, 4))
    for k in range(4):
        up, um = u.copy(), u.copy()
        up[k] += h
        um[k] -= h
        pp = solve_statics(arm_model, up, q_init=r.q, tol=1e-13).tip_pose[:3, 3]
        pm = solve_statics(arm_model, um, q_init=r.q, tol=1e-13).tip_pose[:3, 3]
        fd[:, k] = (pp - pm) / (2 * h)
    assert np.abs(S - fd).max() <= 1e-6 * np.abs(S).max()


# --------------------------------------------------------------------------
# The slides' case: T = EI kappa / d, tips on the slides' curve
# --------------------------------------------------------------------------

def test_slides_constant_curvature_arm_closed_form():
    m = slides_arm()
    kappas = np.pi / 10 * np.arange(1, 11)              # pi/10 : pi/10 : pi (1/m)
    path = paths.waypoints(np.arange(10.0), [slides_tip(k) for k in kappas])
    plan = pl.plan_path(m, path, pl.PlanOptions(tolerance=1e-11))
    assert plan.reached.all(), plan.status
    T_closed = EI * kappas / D_OFFSET
    assert np.abs(plan.u[:, 0] / T_closed - 1).max() <= 1e-8
    # the tips lie on the slides' curve, and every section has the curvature kappa
    assert np.abs(plan.tip - np.array([slides_tip(k) for k in kappas])).max() <= 1e-12
    assert np.abs(plan.q - kappas[:, None]).max() <= 1e-8 * np.pi


def test_slides_arm_distributed_tendon_is_the_same():
    # the exact (distributed) tendon in this planar inextensible arm gives the same tensions
    m = slides_arm(tendon_model="distributed")
    kappas = np.array([np.pi / 10, np.pi / 2, np.pi])
    path = paths.waypoints(np.arange(3.0), [slides_tip(k) for k in kappas])
    plan = pl.plan_path(m, path, pl.PlanOptions(tolerance=1e-11))
    assert np.abs(plan.u[:, 0] / (EI * kappas / D_OFFSET) - 1).max() <= 1e-8


# --------------------------------------------------------------------------
# Default robot
# --------------------------------------------------------------------------

CIRCLE = dict(center=[0.38, 0.0, -0.22], radius=0.05, duration=4.0, normal=[1.0, 0.0, 0.0])


def test_circle_quasi_static_within_1mm(arm):
    path = paths.circle(**CIRCLE, sample_period=0.08)
    plan = pl.plan_path(arm, path, pl.PlanOptions(position_weights=(0, 1, 1), tolerance=1e-6))
    assert plan.reached.all()
    assert plan.weighted_error.max() <= 1e-6       # far below 1 mm
    assert pl.check_plan(plan) == []
    # continuity: no jumps between consecutive samples (bounded by the path's own speed)
    assert np.abs(np.diff(plan.u, axis=0)).max() <= 1.0


def test_redundancy_minimum_total_tension(arm):
    """Antagonistic pairs: the slack tendon of each pair sits at the
    pretension, and no other inputs reaching the same tip (linearised: a
    linear programme over the null space) have a smaller total tension."""
    from scipy.optimize import linprog
    pre = 0.5
    path = paths.circle(**CIRCLE, sample_period=0.5)
    plan = pl.plan_path(arm, path, pl.PlanOptions(position_weights=(0, 1, 1), pretension=pre))
    assert plan.reached.all()
    for u, q in zip(plan.u, plan.q):
        assert min(u[0], u[1]) == pytest.approx(pre, abs=1e-9)
        assert min(u[2], u[3]) == pytest.approx(pre, abs=1e-9)
        S = pl.frame_sensitivity(arm, q, u)[1:]                  # tracked rows y, z
        res = linprog(np.ones(4), A_eq=S, b_eq=S @ u, bounds=[(pre, None)] * 4, method="highs")
        assert res.status == 0
        assert u.sum() <= res.fun + 1e-6 * u.sum()


def test_unreachable_samples_flagged_and_closest_followed(arm):
    # a tension cap makes the top of a big circle unreachable
    path = paths.circle([0.3, 0.0, -0.2], 0.1, 4.0, sample_period=0.2)
    o = pl.PlanOptions(position_weights=(0, 1, 1), max_tension=8.0)
    plan = pl.plan_path(arm, path, o)
    assert pl.check_plan(plan) == []
    bad = ~plan.reached
    assert bad.any() and plan.reached.any()
    assert set(np.array(plan.status)[bad]) <= {"at_limit", "out_of_workspace", "rate_limit"}
    assert all(s == "reached" for s in np.array(plan.status)[~bad])
    assert np.all(plan.weighted_error[bad] > o.tolerance)
    # at an unreached sample a tension is at its cap, and no feasible small change gets closer
    for i in np.flatnonzero(bad):
        assert plan.u[i].max() == pytest.approx(8.0, abs=1e-9) or plan.status[i] == "out_of_workspace"


def test_rate_limit_flags_and_holds(arm):
    path = paths.circle(**CIRCLE, sample_period=0.1)
    o = pl.PlanOptions(position_weights=(0, 1, 1), max_rate=2.0)        # N/s: too slow for this circle
    plan = pl.plan_path(arm, path, o, start=np.zeros(4), from_start=True)
    assert pl.check_plan(plan) == []
    assert "rate_limit" in plan.status
    rates = np.abs(np.diff(np.vstack([np.zeros(4), plan.u]), axis=0)) / 0.1
    assert rates.max() <= 2.0 * (1 + 1e-12)


def test_robot_without_actuators_refused():
    m = model_from_dict({"segments": [{"length": 0.3, "cross_section": {"shape": "solid_circle", "radius": 0.01},
                                       "material": {"youngs_modulus": 1e6, "density": 1000}}]})
    with pytest.raises(pl.PlanError, match="no actuators"):
        pl.TipSolver(from_robot_model(m))


def test_bad_options_name_the_field(arm):
    with pytest.raises(pl.PlanError, match="pretension: unknown actuator 'nope'"):
        pl.actuator_bounds(arm, pl.PlanOptions(pretension={"nope": 1.0}))
    with pytest.raises(pl.PlanError, match="max_rate"):
        pl.rate_limits(arm, pl.PlanOptions(max_rate=-1.0))
    with pytest.raises(pl.PlanError, match="position_weights"):
        pl.PlanOptions(position_weights=(0, 0, 0)).weights()


# --------------------------------------------------------------------------
# Property: bounds and rate limits never violated; unreachable never reported as reached
# --------------------------------------------------------------------------

@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cy=hst.floats(-0.1, 0.1), cz=hst.floats(-0.3, 0.0), r=hst.floats(0.005, 0.15),
       kind=hst.sampled_from(["circle", "line", "figure_eight"]),
       cap=hst.one_of(hst.none(), hst.floats(2.0, 20.0)), rate=hst.one_of(hst.none(), hst.floats(1.0, 50.0)),
       pre=hst.floats(0.0, 1.0))
def test_property_bounds_rates_flags(arm, cy, cz, r, kind, cap, rate, pre):
    c = [0.3, cy, cz]
    if kind == "circle":
        path = paths.circle(c, r, 1.0, sample_period=0.25)
    elif kind == "line":
        path = paths.line(c, [0.3, cy + r, cz - r], 1.0, sample_period=0.25)
    else:
        path = paths.figure_eight(c, r, 1.0, sample_period=0.25)
    o = pl.PlanOptions(position_weights=(0, 1, 1), max_tension=cap, max_rate=rate, pretension=pre,
                       max_iterations=15)
    plan = pl.plan_path(arm, path, o, start=np.full(4, pre), from_start=True)
    assert pl.check_plan(plan) == []
    assert np.all(plan.u >= pre) and (cap is None or np.all(plan.u <= cap))
    if rate is not None:
        du = np.abs(np.diff(np.vstack([np.full(4, pre), plan.u]), axis=0))
        assert np.all(du <= rate * 0.25 * (1 + 1e-12))
    # "reached" exactly when the predicted tip is within the tolerance
    assert np.array_equal(plan.reached, plan.weighted_error <= o.tolerance)
    assert all((s == "reached") == bool(ok) for s, ok in zip(plan.status, plan.reached))


# --------------------------------------------------------------------------
# Paths
# --------------------------------------------------------------------------

def test_paths_geometry():
    p = paths.circle([0, 0, 0], 0.05, 4.0, normal=[1, 0, 0], sample_period=0.01)
    assert np.allclose(np.linalg.norm(p.positions, axis=1), 0.05)
    assert np.allclose(p.positions[:, 0], 0.0) and np.allclose(p.positions[0], p.positions[-1])
    assert p.duration == 4.0
    f = paths.figure_eight([0, 0, 0], 0.1, 2.0, sample_period=0.01)
    assert np.allclose(f.positions[:, 2], f.positions[:, 1] * np.cos(np.arcsin(f.positions[:, 1] / 0.1)) / 1.0
                       * 0 + 0.1 * np.sin(2 * np.pi * f.times / 2) * np.cos(2 * np.pi * f.times / 2))
    ln = paths.line([0, 0, 0], [1, 2, 3], 1.0, sample_period=0.5)
    assert np.allclose(ln.positions[1], [0.5, 1, 1.5])
    R = [np.eye(3), np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])]
    w = paths.waypoints([0, 1], [[0, 0, 0], [1, 0, 0]], R, sample_period=0.5)
    ang = math.atan2(w.orientations[1][1, 0], w.orientations[1][0, 0])
    assert len(w) == 3 and ang == pytest.approx(np.pi / 4)


@pytest.mark.parametrize("d, match", [
    ({"type": "square"}, "path.type"),
    ({"type": "circle", "center": [0, 0, 0], "duration": 1}, "path.radius"),
    ({"type": "circle", "center": [0, 0, 0], "radius": -1, "duration": 1}, "circle.radius"),
    ({"type": "line", "start": [0, 0, 0], "end": [1, 0, 0], "duration": 1, "speed": 2}, "path.speed"),
    ({"type": "waypoints", "points": [{"t": 0, "position": [0, 0, 0]}, {"t": 0, "position": [1, 0, 0]}]},
     "times: must be strictly increasing"),
    ({"type": "waypoints", "points": [{"t": 0, "position": [0, 0]}]}, r"points\[0\].position"),
])
def test_path_errors_name_the_field(d, match):
    with pytest.raises(paths.PathError, match=match):
        paths.path_from_dict(d)


# --------------------------------------------------------------------------
# Dynamic verification and lag compensation
# --------------------------------------------------------------------------

def test_dynamic_verification_and_compensation(arm):
    path = paths.circle(**CIRCLE, sample_period=0.05)
    o = pl.PlanOptions(position_weights=(0, 1, 1))
    plan, tr, hist = pl.compensate_lag(arm, path, o, iterations=2, dt=0.01)
    assert hist[0]["converged"] and len(hist) == 3
    # the quasi-static plan lags in the dynamics (mm), the compensation reduces the rms error
    assert 1e-3 < hist[0]["rms_error_m"] < 0.02
    assert min(h["rms_error_m"] for h in hist[1:]) < 0.8 * hist[0]["rms_error_m"]
    assert tr.summary()["rms_error_m"] == min(h["rms_error_m"] for h in hist)


def test_box_lstsq_matches_scipy_bvls():
    from scipy.optimize import lsq_linear
    rng = np.random.default_rng(3)
    for _ in range(200):
        m, n = rng.integers(1, 7), rng.integers(1, 6)
        A, b = rng.normal(size=(m, n)), rng.normal(size=m)
        lo = -rng.uniform(0, 1, n) * (rng.uniform(size=n) < 0.8)
        hi = np.where(rng.uniform(size=n) < 0.2, np.inf, rng.uniform(0, 1, n))
        fixed = rng.uniform(size=n) < 0.1            # lo = hi = 0: a variable held at 0
        lo[fixed], hi[fixed] = 0.0, 0.0
        x = pl.box_lstsq(A, b, lo, hi)
        assert np.all(x >= lo) and np.all(x <= hi)
        ref = np.zeros(n)                             # scipy wants lo < hi: the held variables left out
        if np.any(~fixed):
            ref[~fixed] = lsq_linear(A[:, ~fixed], b, bounds=(lo[~fixed], hi[~fixed]), method="bvls", tol=1e-13).x
        f = lambda z: np.sum((A @ z - b) ** 2)  # noqa: E731
        assert f(x) <= f(ref) + 1e-9 * max(1.0, f(ref))


def test_bounded_gauss_newton_step_solves_the_stacked_problem():
    """The compiled step (kernels.bvls.regularised_box_step) against scipy's
    BVLS on the stacked least squares written out from its definition,
    held inputs (empty box) left out."""
    from scipy.optimize import lsq_linear
    rng = np.random.default_rng(5)
    for _ in range(200):
        m, n = rng.integers(1, 7), rng.integers(1, 6)
        Je, e = rng.normal(size=(m, n)), rng.normal(size=m)
        x = rng.uniform(0, 2, n)
        lo = np.where(rng.uniform(size=n) < 0.5, 0.0, x - rng.uniform(0, 1, n))
        hi = np.where(rng.uniform(size=n) < 0.2, np.inf, x + rng.uniform(0, 1, n))
        held = rng.uniform(size=n) < 0.15
        lo[held], hi[held] = x[held], x[held]
        scale, x_ref = rng.uniform(0.1, 3, n), rng.uniform(0, 1, n)
        eps, lam = rng.choice([0.0, 1e-3, 0.3]), rng.choice([0.0, 1e-4, 0.5])
        dx, all_held = pl.bounded_gauss_newton_step(Je, e, x, lo, hi, scale, eps, x_ref, lam)
        assert all_held == bool(np.all(held))
        assert np.all(dx[held] == 0.0) and np.all(x + dx >= lo) and np.all(x + dx <= hi)
        A = np.vstack([Je, eps * np.diag(scale), np.sqrt(max(lam, 1e-12)) * np.diag(scale)])
        b = np.concatenate([-e, -eps * scale * (x - x_ref), np.zeros(n)])
        f = lambda z: np.sum((A @ z - b) ** 2)  # noqa: E731
        ref = np.zeros(n)
        if np.any(~held):
            ref[~held] = lsq_linear(A[:, ~held], b, bounds=((lo - x)[~held], (hi - x)[~held]), method="bvls",
                                    tol=1e-13).x
        assert f(dx) <= f(ref) + 1e-9 * max(1.0, f(ref))


def test_tip_error_kernels_match_their_definitions(arm):
    """kernels.tip_error: e against lie.log_so3 (small angles, generic, near
    pi); de/du against central differences of e along dq/du of the
    equilibrium (the tip pose of q + h dq/du dv)."""
    from soft_twin_core import lie
    from soft_twin_core.engine.kernels.tip_error import error_jacobian, tip_error
    rng = np.random.default_rng(2)
    sw, swo = np.array([1.0, 0.5, 2.0]), 0.3
    for k in range(300):
        w = rng.normal(size=3)
        angle = (1e-7, 0.1, rng.uniform(0, np.pi), np.pi - 1e-6, np.pi - 1e-10)[k % 5]
        w *= angle / np.linalg.norm(w)
        g = np.eye(4)
        g[:3, :3], g[:3, 3] = lie.exp_so3(rng.normal(size=3)), rng.normal(size=3)
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = g[:3, :3] @ lie.exp_so3(w), rng.normal(size=3)
        e = np.empty(6)
        pe, we, oe = tip_error(g, t, sw, swo, True, e)
        ref = lie.log_so3(g[:3, :3].T @ t[:3, :3])
        np.testing.assert_allclose(e[3:] / swo, ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(e[:3], sw * (t[:3, 3] - g[:3, 3]), rtol=1e-15, atol=0)
        assert abs(pe - np.linalg.norm(t[:3, 3] - g[:3, 3])) < 1e-14 and abs(oe - np.linalg.norm(ref)) < 1e-12
        assert abs(we - np.linalg.norm(e[:3])) < 1e-14
    # the Jacobian: e(q(u)) with q(u) linear along dq/du, through the engine's tip pose
    solver = pl.TipSolver(arm)
    u = np.array([1.0, 0.0, 0.5, 0.0])
    e_eq = solver.statics.solve(u, None)
    q = e_eq.q
    g, Js, dq_du = solver.statics.sensitivity(e_eq, u)
    target = np.eye(4)
    target[:3, :3], target[:3, 3] = lie.exp_so3([0.3, -0.2, 0.5]), g[:3, 3] + [0.01, -0.02, 0.03]
    solver.sw, solver.swo = sw, swo
    for with_rot in (False, True):
        solver.with_rot = with_rot
        e = solver._error(g, target)
        Je = np.empty((e.size, 4))
        error_jacobian(g, Js, dq_du, e, sw, swo, with_rot, Je)
        h = 1e-6
        fd = np.column_stack([(solver._error(solver.statics.pose(q + h * dq_du[:, k]), target)
                               - solver._error(solver.statics.pose(q - h * dq_du[:, k]), target)) / (2 * h)
                              for k in range(4)])
        np.testing.assert_allclose(Je, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_a_sample_whose_statics_fails_from_every_start_is_held_and_flagged(arm, monkeypatch):
    """A sample whose statics fails from the extrapolated start and from the
    sample before keeps that sample's inputs and shape, flagged
    ``statics_failed`` (never reached); the plan goes on after it."""
    path = paths.line([0.3, 0.0, -0.05], [0.3, 0.02, -0.07], 1.0, sample_period=0.25)
    o = pl.PlanOptions(position_weights=(0, 1, 1))
    ref = pl.plan_path(arm, path, o)
    solver = pl.TipSolver(arm, o)
    solve, calls = solver.solve, {"n": 0}

    def failing(target, *a, **k):
        calls["n"] += 1
        if np.allclose(target[:3, 3], path.positions[2]):
            raise StaticsError("forced")
        return solve(target, *a, **k)
    monkeypatch.setattr(solver, "solve", failing)
    plan = pl.plan_path(arm, path, o, solver=solver)
    assert plan.status[2] == "statics_failed" and not plan.reached[2]
    np.testing.assert_array_equal(plan.u[2], plan.u[1])
    assert plan.status[3] == ref.status[3] and pl.check_plan(plan) == []
    np.testing.assert_allclose(plan.u[:2], ref.u[:2])
