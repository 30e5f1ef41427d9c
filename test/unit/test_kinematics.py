"""PCS model, forward kinematics, Jacobians and IK (issue 4)."""

import numpy as np
import pytest

from soft_twin_core import lie
from soft_twin_core.planning import ik
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.model import (ModelError, State, benchmark_cantilever_dict, load_model,
                                        model_from_dict)
from rod_statics import solve_statics

RNG = np.random.default_rng(7)


def random_q(model, scale=0.3, rng=RNG):
    return model.q0 + scale * rng.normal(size=model.n_dof) / np.sqrt(model.lengths.mean())


def three_section(free="all", kmap="exponential", offsets=False):
    d = benchmark_cantilever_dict(3, free)
    d["kinematic_map"] = kmap
    d["base"] = {"position": [0.1, -0.2, 0.3], "rpy": [0.3, -0.2, 0.5]}
    if offsets:
        seg = dict(d["segments"][0], length=0.2, sections=2,
                   offset_to_next={"position": [0.01, 0, 0], "rpy": [0, 0, 0.7]})
        d["segments"] = [dict(seg, name="proximal"), dict(d["segments"][0], name="distal", length=0.3, sections=2)]
    return model_from_dict(d)


# --- closed forms from the slides -------------------------------------------

def slides_helix(kappa, tau, a):
    """Slides part B "Example": one element, f_u = [1,0,0], f_w = [tau, 0, kappa]."""
    kg = np.sqrt(kappa**2 + tau**2)
    s, c = np.sin(a * kg), np.cos(a * kg)
    return np.array([
        [1 - (1 - c) * kappa**2 / kg**2, -s * kappa / kg, (1 - c) * kappa * tau / kg**2,
         a + (s - a * kg) * kappa**2 / kg**3],
        [s * kappa / kg, c, -s * tau / kg, (1 - c) * kappa / kg**2],
        [(1 - c) * kappa * tau / kg**2, s * tau / kg, 1 - (1 - c) * tau**2 / kg**2,
         (a * kg - s) * kappa * tau / kg**3],
        [0, 0, 0, 1.0]])


def one_section_model(free="all", length=1.0):
    d = benchmark_cantilever_dict(1, free, length=length)
    return model_from_dict(d)


@pytest.mark.parametrize("kappa,tau", [(3.0, 0.5), (np.pi / 2, 3.0), (2 * np.pi, 3.0), (0.7, 1e-3)])
def test_slides_helix_equals_poe(kappa, tau):
    m = one_section_model()
    q = m.q_from_strains(np.array([[1.0, 0, 0, tau, 0, kappa]]))
    s = np.linspace(0, 1.0, 7)
    H = kin.poses(m, q, s)
    for si, Hi in zip(s, H):
        assert np.abs(Hi - slides_helix(kappa, tau, si)).max() < 1e-12


@pytest.mark.parametrize("kappa", np.linspace(np.pi / 10, np.pi, 4))
def test_constant_curvature_matrix_equals_poe(kappa):
    """Slides part C: f = [1,0,0,0,0,kappa]."""
    m = one_section_model()
    q = m.q_from_strains(np.array([[1.0, 0, 0, 0, 0, kappa]]))
    for a in [0.25, 0.5, 1.0]:
        c, s = np.cos(a * kappa), np.sin(a * kappa)
        ref = np.array([[c, -s, 0, s / kappa], [s, c, 0, (1 - c) / kappa], [0, 0, 1, 0], [0, 0, 0, 1]])
        assert np.abs(kin.poses(m, q, [a])[0] - ref).max() < 1e-12


def test_helix_parameters_match_slides():
    kappa, tau = 2.0, 3.0
    k, t, F = kin.helix_parameters(np.array([1.0, 0, 0, tau, 0, kappa]))
    assert np.isclose(k, kappa) and np.isclose(t, tau)
    # Frenet: t' = kappa n in the body frame (t = e_x) -> n along w x u
    assert np.allclose(F[:, 0], [1, 0, 0]) and np.allclose(F[:, 1], [0, 1, 0])
    # the curve's curvature from FK positions (finite differences) equals kappa
    m = one_section_model()
    q = m.q_from_strains(np.array([[1.0, 0, 0, tau, 0, kappa]]))
    h = 1e-4
    p = kin.poses(m, q, [0.5 - h, 0.5, 0.5 + h])[:, :3, 3]
    d1, d2 = (p[2] - p[0]) / (2 * h), (p[2] - 2 * p[1] + p[0]) / h**2
    assert np.isclose(np.linalg.norm(np.cross(d1, d2)) / np.linalg.norm(d1) ** 3, kappa, rtol=1e-6)


# --- PoE structure, batching -------------------------------------------------

def test_poe_matches_matrix_exponentials():
    m = three_section()
    q = random_q(m)
    xi = m.strains(q)
    import scipy.linalg as sla
    H = m.base_pose.copy()
    for i in range(3):
        H = H @ sla.expm(lie.hat6(m.lengths[i] * xi[i]))
    assert np.abs(kin.tip_pose(m, q) - H).max() < 1e-12
    # a point inside section 2
    s = m.s_starts[1] + 0.3 * m.lengths[1]
    H2 = m.base_pose @ sla.expm(lie.hat6(m.lengths[0] * xi[0])) @ sla.expm(lie.hat6(0.3 * m.lengths[1] * xi[1]))
    assert np.abs(kin.poses(m, q, [s])[0] - H2).max() < 1e-12


def test_batched_configurations():
    m = three_section()
    qs = np.stack([random_q(m) for _ in range(4)])
    s = kin.backbone_abscissae(m, 5)
    P = kin.poses(m, qs, s)
    J = kin.jacobian(m, qs, s)
    assert P.shape == (4, len(s), 4, 4) and J.shape == (4, len(s), 6, m.n_dof)
    assert np.allclose(P[2], kin.poses(m, qs[2], s))
    assert np.allclose(J[3], kin.jacobian(m, qs[3], s))


def test_backbone_sampling_and_rest_shape():
    m = model_from_dict(benchmark_cantilever_dict(4))
    s, P = kin.backbone(m, m.q0, 10)
    assert len(s) == 41 and s[-1] == pytest.approx(0.5)
    assert np.allclose(P[:, :3, 3], np.stack([s, 0 * s, 0 * s], -1), atol=1e-15)


# --- Jacobian and its derivative against finite differences ------------------

@pytest.mark.parametrize("kmap", ["exponential", "cayley"])
@pytest.mark.parametrize("free", ["all", "bending_torsion"])
@pytest.mark.parametrize("offsets", [False, True])
def test_jacobian_matches_fd(kmap, free, offsets):
    m = three_section(free, kmap, offsets)
    q, qd = random_q(m), RNG.normal(size=m.n_dof)
    s = np.concatenate([[0.0], RNG.uniform(0, m.total_length, 6), m.s_starts[1:], [m.total_length]])
    h = 1e-6
    g = kin.poses(m, q, s)
    dg = (kin.poses(m, q + h * qd, s) - kin.poses(m, q - h * qd, s)) / (2 * h)
    eta_fd = lie.vee6(lie.se3_inv(g) @ dg)
    J = kin.jacobian(m, q, s)
    assert np.abs(eta_fd - J @ qd).max() < 1e-7
    Jw = kin.jacobian(m, q, s, frame="world")
    assert np.abs(dg[:, :3, 3] - Jw[:, :3] @ qd).max() < 1e-7
    assert np.abs(kin.tip_jacobian(m, q) - J[-1]).max() < 1e-13
    g2, J2, Jdot, eta = kin.jacobian_and_derivative(m, q, qd, s)
    Jdot_fd = (kin.jacobian(m, q + h * qd, s) - kin.jacobian(m, q - h * qd, s)) / (2 * h)
    assert np.abs(Jdot_fd - Jdot).max() < 1e-7
    assert np.abs(eta - J @ qd).max() < 1e-13


def test_point_motion_world_acceleration_fd():
    """Second derivative of world positions along q(t) = q + t qd + t^2/2 qdd."""
    m = three_section("all", offsets=True)
    q, qd, qdd = random_q(m), RNG.normal(size=m.n_dof), RNG.normal(size=m.n_dof)
    s = np.array([0.07, 0.33, 0.5])
    path = lambda t: q + t * qd + 0.5 * t * t * qdd  # noqa: E731
    h = 1e-4
    p = [kin.poses(m, path(t), s)[:, :3, 3] for t in (-h, 0.0, h)]
    mot = kin.point_motion(m, q, qd, qdd, s)
    assert np.abs((p[2] - p[0]) / (2 * h) - mot["v_world"]).max() < 1e-7
    assert np.abs((p[2] - 2 * p[1] + p[0]) / h**2 - mot["a_world"]).max() < 1e-5


# --- model building and validation ------------------------------------------

def test_model_is_immutable_and_state_separate():
    m = three_section()
    with pytest.raises(Exception):
        m.n_dof = 3
    with pytest.raises(ValueError):
        m.K_q[0, 0] = 1.0
    st = State.rest(m)
    st.q += 0.1
    assert np.allclose(m.q0, model_from_dict(benchmark_cantilever_dict(3)).q0)


@pytest.mark.parametrize("patch,msg", [
    ({"length": -1.0}, r"segments\[0\]\.length: must be > 0, got -1.0"),
    ({"sections": 0}, r"segments\[0\]\.sections: expected an integer >= 1, got 0"),
    ({"free_modes": ["bend"]}, r"segments\[0\]\.free_modes: unknown strain mode 'bend'"),
    ({"cross_section": {"shape": "hexagon"}}, r"cross_section\.shape: expected one of"),
    ({"material": {"youngs_modulus": "soft", "density": 1}}, r"material\.youngs_modulus: expected a number"),
    ({"material": {"youngs_modulus": 1e6, "density": 1000, "poisson_ratio": 0.7}}, r"poisson_ratio"),
    ({"reference_strain": [1, 0, 0]}, r"reference_strain: expected 6 finite numbers"),
    ({"colour": "red"}, r"segments\[0\]: unknown field\(s\) \['colour'\]"),
])
def test_bad_model_fields_are_named(patch, msg):
    d = benchmark_cantilever_dict(2)
    d["segments"][0].update(patch)
    with pytest.raises(ModelError, match=msg):
        model_from_dict(d)


def test_wrong_q_shape_message():
    m = three_section()
    with pytest.raises(ValueError, match=r"q: expected shape \(\.\.\., 18\) .* got \(5,\)"):
        kin.tip_pose(m, np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        kin.tip_pose(m, np.full(18, np.nan))


def test_config_files_load():
    import glob
    import os
    here = os.path.dirname(__file__)
    files = glob.glob(os.path.join(here, "..", "..", "config", "robots", "*.yaml"))
    assert files, "config/robots/*.yaml should exist"
    from soft_twin_core.robot.mechanism import is_tree_file, load_mechanism
    from soft_twin_core.robot.model import read_yaml_file
    classic = 0
    for f in files:
        if is_tree_file(read_yaml_file(f)):          # articulated robots: test_constrained.py
            assert load_mechanism(f).tree.nv > 0
            continue
        m = load_model(f)
        assert m.n_dof > 0 and np.isfinite(kin.tip_pose(m, m.q0)).all()
        classic += 1
    assert classic >= 5


def test_cross_sections():
    from soft_twin_core.robot.model import CrossSection
    c = CrossSection.solid_circle(0.01)
    assert np.isclose(c.J, np.pi * 0.01**4 / 2)
    t = CrossSection.hollow_tube(0.01, 0.0)
    assert np.isclose(t.I2, c.I2)
    r = CrossSection.rectangle(0.0123777, 0.0032024)
    assert np.isclose(r.I2, 0.0123777 * 0.0032024**3 / 12) and r.I3 > r.I2


# --- inverse kinematics ---------------------------------------------------

def test_one_section_ik_closed_form():
    m = one_section_model(length=0.4)
    f = np.array([1.1, 0.05, -0.02, 0.7, -2.0, 3.0])
    H = kin.tip_pose(m, m.q_from_strains(f[None]))
    assert np.abs(ik.one_section_strain(m.base_pose, H, 0.4) - f).max() < 1e-12


@pytest.mark.parametrize("kappa,phi,length", [(2.0, 0.3, 0.5), (5.0, -2.0, 0.8), (0.1, 1.0, 1.0)])
def test_constant_curvature_closed_form(kappa, phi, length):
    m = one_section_model("bending", length=length)
    w = kappa * np.array([0, -np.sin(phi), np.cos(phi)])
    f = np.array([[1.0, 0, 0, *w]])
    p = kin.tip_pose(m, m.q_from_strains(f))[:3, 3]
    k, ph, arc, wb = ik.constant_curvature_from_tip(p)
    assert np.isclose(k, kappa, rtol=1e-12) and np.isclose(arc, length, rtol=1e-12)
    assert np.isclose(ph, phi, atol=1e-12) and np.allclose(wb, w, atol=1e-12)


def test_numerical_ik_many_random_targets():
    """Issue 4 target: >= 99 % of reachable random targets to 1e-8 m / rad."""
    m = model_from_dict(benchmark_cantilever_dict(3, "bending_torsion"))
    rng = np.random.default_rng(2024)
    bounds = np.tile([1.0, 2 * np.pi / m.total_length, 2 * np.pi / m.total_length], 3)
    n, ok = 1000, 0
    for _ in range(n):
        q = rng.uniform(-0.5, 0.5, m.n_dof) * bounds
        r = ik.solve_ik(m, kin.tip_pose(m, q))
        ok += r.success
        assert r.position_error < 1e-8 or not r.success
    assert ok >= 0.99 * n


def test_ik_position_only_and_bounds():
    m = model_from_dict(benchmark_cantilever_dict(3, "bending"))
    target = np.array([0.3, 0.2, 0.1])
    r = ik.solve_ik(m, target, position_only=True)
    assert r.success and r.position_error < 1e-8
    ub = np.full(m.n_dof, 1.0)
    r2 = ik.solve_ik(m, target, position_only=True, lower=-ub, upper=ub)
    assert not r2.success and np.all(np.abs(r2.q) <= 1.0 + 1e-15)


def test_ik_unreachable_returns_best_without_nan():
    m = model_from_dict(benchmark_cantilever_dict(3, "bending"))
    r = ik.solve_ik(m, np.array([2.0, 0.0, 0.0]), position_only=True)
    assert not r.success and np.isfinite(r.q).all()
    assert r.position_error == pytest.approx(1.5, abs=1e-6)   # straight is the closest
    assert r.message


def test_ik_warm_start_and_error_jacobian():
    m = model_from_dict(benchmark_cantilever_dict(3, "all"))
    q = random_q(m, 0.2)
    T = kin.tip_pose(m, q)
    r = ik.solve_ik(m, T, q_init=q + 1e-3)
    assert r.success and r.iterations <= 4


def test_engine_backbone_matches_reference():
    m = three_section("all", offsets=True)
    q = random_q(m)
    s = kin.backbone_abscissae(m, 7)
    assert np.abs(kin.backbone(m, q, 7)[1] - kin.poses(m, q, s)).max() < 1e-14


def test_actuation_ik_recovers_tensions_of_a_reachable_target():
    """The actuation IK (the planner's sample solve, planner.TipSolver):
    tensions whose equilibrium reaches a reachable target, checked by an
    independent statics solve; an unreachable target flagged, no exception."""
    from soft_twin_core.planning import planner as pl
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import load_model
    m = load_model("tendon_arm")
    solver = pl.TipSolver(from_robot_model(m), pl.PlanOptions(tolerance=1e-9))
    u_true = np.array([1.5, 0.0, 0.0, 0.8])
    r = solve_statics(m, u_true)
    res = solver.solve(r.tip_pose[:3, 3], np.zeros(4), None)
    assert res.reached and res.position_error < 1e-9
    assert np.all(res.x >= 0)
    # its equilibrium really reaches the target
    r2 = solve_statics(m, res.x, q_init=res.q)
    assert np.linalg.norm(r2.tip_pose[:3, 3] - r.tip_pose[:3, 3]) < 1e-8
    # an unreachable target: best effort, flagged, no exception
    far = solver.solve(np.array([0.0, 0.0, 0.5]), np.zeros(4), None)
    assert not far.reached and far.status != "reached" and np.all(np.isfinite(far.x)) and np.all(far.x >= 0)


def test_engine_tip_jacobian_matches_reference():
    m = three_section("bending_torsion", offsets=True)
    q = random_q(m)
    g, Js = kin.tip_and_spatial_jacobian(m, q)
    assert np.abs(g - kin.tip_pose(m, q)).max() < 1e-14
    J_ref = kin.jacobian(m, q, [m.total_length])[0]          # numpy chain, body frame
    assert np.abs(lie.Ad_inv(g) @ Js - J_ref).max() < 1e-13
    assert np.abs(kin.tip_jacobian(m, q, "world") - kin.jacobian(m, q, [m.total_length], "world")[0]).max() < 1e-13


@pytest.mark.filterwarnings("ignore::soft_twin_core.limits.PlausibilityWarning")   # fuzzed files: implausible on purpose
def test_model_fuzz_only_model_errors():
    """Any single corrupted field of a robot description gives a ModelError
    (never a TypeError, OverflowError, ... from deep inside)."""
    from conftest import single_field_corruptions
    base = benchmark_cantilever_dict(3)
    base["actuators"] = [{"name": "t", "offset": [0.005, 0]},
                         {"name": "c", "type": "chamber", "area": 1e-5, "offset": [0, 0.004]}]
    values = [None, -1, 0, 1e300, float("nan"), float("inf"), "x", [], {}, [1, 2], True, "1e9",
              [1, 2, 3, 4, 5, 6], {"a": 1}, 3]
    for d in single_field_corruptions(base, values, 1500, seed=0):
        try:
            model_from_dict(d)
        except ModelError:
            pass
