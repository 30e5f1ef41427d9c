"""Contact of soft members with obstacles (soft_twin_core.engine.contact,
soft_twin_core.solve.contact): the penalty law and the obstacles' distance
functions against their definitions and finite differences, the statics
tangent with contacts against a finite difference of the residual, and a
heavy rod lifted off a plane against its small-deflection closed form."""

from pathlib import Path

import numpy as np
import pytest

from soft_twin_core.engine.contact import (ContactPoints, Obstacle, contact_forces, discrete_gradient, friction_force,
                                           normal_force_density, normal_potential_density, signed_distance)
from soft_twin_core.errors import ModelError, ScenarioError
from soft_twin_core.robot.mechanism import from_robot_model, mechanism_from_dict
from soft_twin_core.robot.model import model_from_dict
from soft_twin_core.robot.obstacles import obstacles_from_list
from soft_twin_core.solve.constrained import MechanismSimulator, _Equilibrium, make_inputs, solve_equilibrium
from soft_twin_core.solve.contact import mechanism_contact_points

RNG = np.random.default_rng(7)


def test_the_normal_law_is_continuous_with_its_derivative():
    """f(delta) and f'(delta) continuous at 0 and at eps; f' the
    derivative of f (central differences); zero force outside."""
    k, eps = 3.0e6, 2e-4
    for d0 in (0.0, eps):
        f_lo, df_lo = normal_force_density(d0 - 1e-12, k, eps)
        f_hi, df_hi = normal_force_density(d0 + 1e-12, k, eps)
        assert abs(f_hi - f_lo) < 1e-3 and abs(df_hi - df_lo) < 1e-1
    delta = np.array([-1e-4, 0.3 * eps, 0.9 * eps, 2 * eps, 10 * eps])
    f, df = normal_force_density(delta, k, eps)
    h = 1e-9
    fd = (normal_force_density(delta + h, k, eps)[0] - normal_force_density(delta - h, k, eps)[0]) / (2 * h)
    np.testing.assert_allclose(df, fd, rtol=1e-6, atol=1e-3)
    assert f[0] == 0.0 and f[-1] == pytest.approx(k * (10 * eps - eps / 2))


def _obstacles():
    return [Obstacle("floor", "plane", np.array([0.1, -0.2, -0.05]), np.array([0.3, 0.1, 1.0]) / np.sqrt(1.1)),
            Obstacle("ball", "sphere", np.array([0.2, 0.1, 0.0]), radius=0.07),
            Obstacle("post", "capsule", np.array([-0.1, 0.0, 0.1]), np.array([0.2, 0.3, 0.0]), radius=0.02)]


def _brute_distance(ob, p):
    """Distance by definition: to the plane along its normal; to the
    sphere's centre less its radius; to a dense sampling of the capsule's
    segment less its radius."""
    if ob.kind == "plane":
        return (p - ob.a) @ ob.b
    if ob.kind == "sphere":
        return np.linalg.norm(p - ob.a, axis=1) - ob.radius
    t = np.linspace(0, 1, 200001)
    seg = ob.a + t[:, None] * (ob.b - ob.a)
    return np.array([np.min(np.linalg.norm(seg - x, axis=1)) for x in p]) - ob.radius


@pytest.mark.parametrize("k", range(3))
def test_signed_distances_their_gradient_and_hessian(k):
    ob = _obstacles()[k]
    p = RNG.uniform(-0.3, 0.4, (12, 3))
    d, n, H = signed_distance(ob, p)
    np.testing.assert_allclose(d, _brute_distance(ob, p), atol=1e-9)
    _check_derivatives(ob, p, n, H, 1e-6, 1e-7, 1e-5)


def _check_derivatives(ob, p, n, H, h, atol_n, atol_H):
    """The normal and the Hessian of ob's distance at p against central differences of step h."""
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        dp, n_p, _ = signed_distance(ob, p + e)
        dm, n_m, _ = signed_distance(ob, p - e)
        np.testing.assert_allclose(n[:, a], (dp - dm) / (2 * h), atol=atol_n)
        np.testing.assert_allclose(H[:, :, a], (n_p - n_m) / (2 * h), atol=atol_H)


def test_contact_forces_and_their_derivative():
    """F = w f(r - d) grad d on every pressed point, none elsewhere; dF/dp
    against central differences."""
    obs = _obstacles() + list(obstacles_from_list([{"type": "box", "center": [0.0, 0.05, 0.1], "size": [0.3, 0.2, 0.1],
                                                    "rpy": [0.2, 0.0, 0.4]}]))
    P = 40
    pts = ContactPoints(np.zeros(P, np.int64), np.zeros(P), RNG.uniform(0.001, 0.003, P),
                        np.full(P, 0.01), np.full(P, 2e6), ("m",) * P, np.zeros(P))
    p = RNG.uniform(-0.2, 0.3, (P, 3))
    st = contact_forces(pts, obs, p)
    assert len(st) > 3
    for c in range(len(st)):
        i, ob = st.point[c], obs[st.obstacle[c]]
        d, n, _ = signed_distance(ob, p[i:i + 1])
        f, _ = normal_force_density(0.01 - d, 2e6, 0.001)
        np.testing.assert_allclose(st.force[c], pts.weight[i] * f[0] * n[0], rtol=1e-12)
        h = 1e-8
        for a in range(3):
            e = np.zeros(3)
            e[a] = h

            def force(x):
                s = contact_forces(pts, [ob], x)
                return s.force[list(s.point).index(i)]
            fd = (force(p + e) - force(p - e)) / (2 * h)
            np.testing.assert_allclose(st.dF_dp[c][:, a], fd, rtol=1e-5, atol=1e-6 * np.abs(st.dF_dp[c]).max())
    # every pair not listed is out of contact
    for o, ob in enumerate(obs):
        d, _, _ = signed_distance(ob, p)
        listed = set(st.point[st.obstacle == o])
        assert {i for i in range(P) if d[i] < 0.01} == listed


# -- the heavy rod ------------------------------------------------------------

E, R_ROD, RHO, G = 5e7, 0.005, 1000.0, 9.81
A_ROD, I_ROD = np.pi * R_ROD ** 2, np.pi * R_ROD ** 4 / 4
EI, Q = E * I_ROD, RHO * G * A_ROD          # bending stiffness [N m^2], weight per length [N/m]


def _heavy_rod(h, stiffness, length=0.6, sections=60, spacing=0.002):
    """A horizontal rod clamped at height h above a table (its centreline
    h above the table's surface less its radius), bending in the vertical
    plane only."""
    d = {"name": "heavy_rod", "gravity": [0, 0, -G],
         "segments": [{"name": "rod", "length": length, "sections": sections,
                       "cross_section": {"shape": "solid_circle", "radius": R_ROD},
                       "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": RHO},
                       "free_modes": ["bending_y"]}],
         "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -h - R_ROD], "normal": [0, 0, 1],
                        "stiffness": stiffness}],
         "contact": {"spacing": spacing}}
    return from_robot_model(model_from_dict(d), d)


def test_the_statics_tangent_with_contacts_is_the_residuals_derivative():
    mech = _heavy_rod(0.0035, E, length=0.4, sections=12, spacing=0.01)
    eq = solve_equilibrium(mech)
    assert len(eq.contacts) > 5
    pb = _Equilibrium(mech, make_inputs(mech))
    lam = np.zeros(0)
    q = eq.q + RNG.normal(0, 1e-6, eq.q.shape)        # (1e-6 /m: microns, as deep as the contacts are)
    Kt = pb.tangent(q, lam)
    h = 1e-7
    fd = np.column_stack([(pb.residual(q + h * e, lam)[0] - pb.residual(q - h * e, lam)[0]) / (2 * h)
                          for e in np.eye(len(q))])
    assert np.abs(Kt - pb.K).max() > 0.1 * np.abs(pb.K).max()        # the contacts do stiffen it
    np.testing.assert_allclose(Kt, fd, atol=1e-6 * np.abs(fd).max())


def test_a_heavy_rod_lifted_off_a_plane_matches_the_small_deflection_solution():
    """A heavy rod (weight q per length, bending stiffness EI) clamped
    horizontally at height h above a rigid table, long enough to lie on it
    beyond a lifted span a. Small deflections: EI w'''' = -q on [0, a] with
    w(0) = w'(0) = 0 (the clamp) and w(a) = -h, w'(a) = 0, w''(a) = 0 (the
    flat part carries no moment), so w = -q x^4/(24 EI) + q a x^3/(9 EI) -
    q a^2 x^2/(12 EI), h = q a^4 / (72 EI): a = (72 EI h / q)^(1/4); the
    clamp carries 2 q a / 3 and the moment q a^2 / 6, the lift-off point
    q a / 3 (a concentrated reaction), the lifted span nothing (the
    clamped variant of the classic heavy-elastica lift-off, whose pinned
    version has a = (24 EI h / q)^(1/4)). Measured from the contact
    forces: the clamp's force and moment within 0.5 %, for contact
    stiffnesses from E/10 to 10 E; no contact force over the first 85 % of
    the lifted span."""
    a, L = 0.3, 0.6
    h = Q * a ** 4 / (72 * EI)              # 3.5 mm: slopes of about 1 %, small deflection holds
    for k in (E / 10, 10 * E):
        eq = solve_equilibrium(_heavy_rod(h, k))
        c = eq.contacts
        assert eq.stable and len(c) > 100
        F_base = Q * L - c.force[:, 2].sum()
        M_base = Q * L * L / 2 - np.sum(c.p[:, 0] * c.force[:, 2])      # about the clamp (x = s to 1e-4)
        assert F_base == pytest.approx(2 * Q * a / 3, rel=5e-3)
        assert M_base == pytest.approx(Q * a * a / 6, rel=5e-3)
        assert c.p[:, 0].min() > 0.85 * a
        assert np.all(c.force[:, :2] == 0) and np.all(c.force[:, 2] > 0)
        assert -c.gap.min() < 1e-4 * h / 3.5e-3 * 10             # pressed in by microns


def test_contact_in_a_tree_robot_file_and_on_a_sphere():
    """Obstacles in the tree schema; a member resting on a sphere: the
    contact forces and the clamp hold the member's weight (the base
    reaction from the member's loads sums to it)."""
    d = {"name": "on_a_ball", "gravity": [0, 0, -9.81],
         "bodies": [{"name": "arm", "type": "member", "parent": "base",
                     "segments": [{"name": "s", "length": 0.3, "sections": 8,
                                   "cross_section": {"shape": "solid_circle", "radius": 0.005},
                                   "material": {"youngs_modulus": 2e8, "poisson_ratio": 0.5, "density": 1000},
                                   "free_modes": "bending"}]}],
         "obstacles": [{"name": "ball", "type": "sphere", "center": [0.25, 0.0, -0.055], "radius": 0.05}]}
    mech = mechanism_from_dict(d)
    eq = solve_equilibrium(mech)
    c = eq.contacts
    assert len(c) >= 1 and eq.stable
    np.testing.assert_allclose(np.linalg.norm(c.p - [0.25, 0, -0.055], axis=1) - 0.05, c.gap + 0.005, atol=1e-12)
    n = (c.p - [0.25, 0, -0.055]) / np.linalg.norm(c.p - [0.25, 0, -0.055], axis=1)[:, None]
    np.testing.assert_allclose(c.force / np.linalg.norm(c.force, axis=1)[:, None], n, atol=1e-12)
    assert 0 < c.force[:, 2].sum() < 1000 * 9.81 * np.pi * 0.005 ** 2 * 0.3


@pytest.mark.parametrize("entry, field", [
    ({"type": "wall"}, "[0].type"),
    ({"type": "plane", "point": [0, 0, float("nan")], "normal": [0, 0, 1]}, "[0].point"),
    ({"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 0]}, "[0].normal"),
    ({"type": "sphere", "center": [0, 0, 0], "radius": -0.1}, "[0].radius"),
    ({"type": "capsule", "from": [0, 0, 0], "to": [0, 0, 0], "radius": 0.1}, "[0]"),
    ({"type": "sphere", "center": [0, 0, 0], "radius": 0.1, "normal": [0, 0, 1]}, "[0]: unknown field"),
    ({"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "stiffness": 0}, "[0].stiffness"),
    ({"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "friction": -1}, "[0].friction"),
    ({"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "torsional_friction": float("nan")},
     "[0].torsional_friction"),
    ({"type": "tube", "path": [[0, 0, 0]], "radius": 0.01}, "[0].path"),
    ({"type": "tube", "path": [[0, 0, 0], [0, 0, 0], [1, 0, 0]], "radius": 0.01}, "[0].path[1]"),
    ({"type": "tube", "path": [[0, 0, 0], [1, 0, float("inf")]], "radius": 0.01}, "[0].path"),
    ({"type": "tube", "path": [[0, 0, 0], [1, 0, 0]], "radius": 0}, "[0].radius"),
])
def test_bad_obstacles_are_rejected_naming_the_field(entry, field):
    with pytest.raises(ModelError, match=r"robot\.obstacles" + field.replace("[", r"\[").replace("]", r"\]")):
        obstacles_from_list([entry])


def test_obstacle_names_are_unique_and_a_member_needs_a_cross_section():
    plane = {"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]}
    with pytest.raises(ModelError, match="unique"):
        obstacles_from_list([dict(plane, name="t"), dict(plane, name="t")])
    d = {"name": "sectional", "segments": [{"name": "s", "length": 0.2, "sections": 2,
                                            "sectional": {"stiffness": {"EA": 1e6, "GA2": 1e6, "GA3": 1e6, "GJ": 1e-1,
                                                                        "EI2": 1e-1, "EI3": 1e-1},
                                                          "inertia": {"mass_per_length": 0.1, "J1": 1e-6,
                                                                      "J2": 1e-6, "J3": 1e-6}}}],
         "obstacles": [dict(plane, name="t")]}
    with pytest.raises(ModelError, match="cross_section"):
        solve_equilibrium(from_robot_model(model_from_dict(d), d))


def _bouncer(viscosity, damping=0.0, sections=8):
    d = {"name": "bouncer", "gravity": [0, 0, -9.81],
         "segments": [{"name": "rod", "length": 0.3, "sections": sections,
                       "cross_section": {"shape": "solid_circle", "radius": 0.005},
                       "material": {"youngs_modulus": 5e7, "poisson_ratio": 0.5, "density": 1000,
                                    "viscosity": viscosity}, "free_modes": ["bending_y"]}],
         "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -0.015], "normal": [0, 0, 1],
                        "damping": damping}],
         "contact": {"spacing": 0.005}}
    return from_robot_model(model_from_dict(d), d)


def test_a_rod_falling_onto_a_table_comes_to_rest_at_the_static_equilibrium():
    """A cantilever released straight above a table falls onto it and,
    with material and contact damping (implicit Euler), comes to rest at
    the static equilibrium with contact: the dynamics and the statics agree."""
    mech = _bouncer(2e3, damping=5.0)
    eq = solve_equilibrium(mech)
    sim = MechanismSimulator(mech, 2e-3, 1.0, tol=1e-9)
    sim.step(n=600)
    assert len(sim.contacts) == len(eq.contacts) >= 1          # resting on its tip
    np.testing.assert_allclose(sim.q, eq.q, atol=1e-5 * np.abs(eq.q).max())     # (still settling: 1e-6 at 1.2 s)


def test_a_bouncing_rod_gains_no_energy():
    """Without any damping the implicit midpoint step with the contacts'
    mean (discrete-gradient) force keeps the total energy (kinetic,
    elastic, gravity, the contacts' stored energy) from growing through
    repeated bounces: never above its start by 1 % of the peak kinetic
    energy (with the force at the midpoint it grows without bound)."""
    sim = MechanismSimulator(_bouncer(0.0), 1e-3, 0.5, tol=1e-9)
    E0 = sum(sim.energy())
    growth, T_max, touched = 0.0, 0.0, 0
    for _ in range(300):
        sim.step()
        T, V = sim.energy()
        growth, T_max = max(growth, T + V - E0), max(T_max, T)
        touched = max(touched, len(sim.contacts))
    assert touched > 3 and T_max > 0
    assert growth < 0.01 * T_max


def test_the_mean_force_of_a_step_is_the_stored_energy_over_the_penetration():
    """discrete_gradient: (Phi(d1) - Phi(d0)) / (d1 - d0) in every branch
    pairing (Phi the integral of f, checked by quadrature), its closed forms
    continuous with the quotient as d1 -> d0, and d fbar / d d1 against
    central differences."""
    from scipy.integrate import quad
    k, eps = 2e6, 5e-4
    for d in (-1e-4, 2e-4, 1e-3):
        assert normal_potential_density(d, k, eps) == pytest.approx(
            quad(lambda x: float(normal_force_density(x, k, eps)[0]), 0, max(d, 0), points=[eps])[0], rel=1e-9,
            abs=1e-18)
    d0 = np.array([-2e-4, -2e-4, 1e-4, 1e-4, 7e-4, 3e-4, 3e-4])
    d1 = np.array([-1e-4, 3e-4, 2e-4, 9e-4, 8e-4, 3e-4 + 1e-13, 3e-4 - 1e-13])
    fbar, dfbar = discrete_gradient(d0, d1, k, eps)
    quotient = (normal_potential_density(d1, k, eps) - normal_potential_density(d0, k, eps)) / (d1 - d0)
    np.testing.assert_allclose(fbar[:5], quotient[:5], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fbar[5:], normal_force_density(3e-4, k, eps)[0], rtol=1e-8)
    h = 1e-10
    fd = (discrete_gradient(d0, d1 + h, k, eps)[0] - discrete_gradient(d0, d1 - h, k, eps)[0]) / (2 * h)
    np.testing.assert_allclose(dfbar[:5], fd[:5], rtol=1e-5, atol=1e-3)


def test_regularised_friction_and_its_derivative():
    """F = -mu fn vt / sqrt(|vt|^2 + v_s^2): Coulomb's magnitude when
    slipping fast, opposite to the slip; dF/dvt against central differences."""
    fn = np.array([2.0, 0.5, 1.0])
    vt = np.array([[0.3, -0.1, 0.0], [1e-5, 2e-5, 0.0], [0.0, 0.0, 0.0]])
    F, dF = friction_force(fn, vt, 0.4, 1e-4)
    assert np.linalg.norm(F[0]) == pytest.approx(0.4 * 2.0, rel=1e-6) and F[0] @ vt[0] < 0
    assert not np.any(F[2])
    h = 1e-9
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fd = (friction_force(fn, vt + e, 0.4, 1e-4)[0] - friction_force(fn, vt - e, 0.4, 1e-4)[0]) / (2 * h)
        np.testing.assert_allclose(dF[:, :, a], fd, rtol=1e-5, atol=1e-6)


def _slider(theta_deg, mu):
    """A short stiff rod with a floating base lying along the fall line of
    a plane inclined by theta, friction mu."""
    th, r = np.radians(theta_deg), 0.005
    n = [np.sin(th), 0.0, np.cos(th)]
    d = {"name": "slider", "gravity": [0, 0, -9.81],
         "base": {"position": (r * np.array(n)).tolist(), "rpy": [0, float(th), 0], "motion": "floating"},
         "bodies": [{"name": "rod", "type": "member", "parent": "base",
                     "segments": [{"name": "s", "length": 0.1, "sections": 2,
                                   "cross_section": {"shape": "solid_circle", "radius": r},
                                   "material": {"youngs_modulus": 1e8, "poisson_ratio": 0.5, "density": 1000,
                                                "viscosity": 1e3}, "free_modes": "bending"}]}],
         "obstacles": [{"name": "slope", "type": "plane", "point": [0, 0, 0], "normal": n, "friction": mu,
                        "damping": 2.0}],
         "contact": {"spacing": 0.01}}
    return mechanism_from_dict(d)


def test_a_rod_on_an_incline_slides_at_the_coulomb_acceleration_or_sticks():
    """tan(theta) > mu: the rod slides at a = g (sin theta - mu cos theta)
    (within 0.1 %: the free joint's position along the slope fitted by a
    parabola after touch-down). tan(theta) < mu: it sticks, creeping at
    the regularisation's v = v_s t / sqrt(1 - t^2), t = tan(theta) / mu
    (within 2 %), under 0.1 mm/s."""
    for theta, mu in ((30, 0.3), (20, 0.6)):
        sim = MechanismSimulator(_slider(theta, mu), 1e-3, 1.0, tol=1e-9)
        t, x = [], []
        for _ in range(400):
            sim.step()
            t.append(sim.t)
            x.append(sim.q[0])           # the free joint's translation along the rod's axis, down the slope
        t, x = np.array(t), np.array(x)
        th = np.radians(theta)
        if np.tan(th) > mu:
            a = 2 * np.polyfit(t[t > 0.1], x[t > 0.1], 2)[0]
            assert a == pytest.approx(9.81 * (np.sin(th) - mu * np.cos(th)), rel=1e-3)
        else:
            creep = (x[-1] - x[-101]) / (t[-1] - t[-101])
            ratio = np.tan(th) / mu
            assert creep == pytest.approx(1e-4 * ratio / np.sqrt(1 - ratio ** 2), rel=0.02)
            assert 0 < creep < 1e-4
        assert len(sim.contacts) == 10 and np.all(sim.contacts.force @ [np.sin(th), 0, np.cos(th)] > 0)



def test_a_soft_cylinder_across_an_incline_rolls_at_two_thirds_g_sin_theta():
    """A short stiff rod (along x) lying across the fall line (y) of a 20 degree incline
    (friction 0.5 > 1/3 tan(theta)): friction at the contact surface turns
    its cross-sections (polar inertia 1/2 m r^2 per length, the rotary
    inertia of the Cosserat rod), so it rolls without slipping at ``2/3 g
    sin(theta)`` (within 0.5 %: the free base's position fitted by a
    parabola over 0.1-0.3 s), turning at that over r; its surface creeps
    only (slip under 1 mm/s). Friction at the backbone held it still."""
    th, r, L = np.radians(20.0), 0.005, 0.1
    d = {"name": "roller", "gravity": (9.81 * np.array([0.0, np.sin(th), -np.cos(th)])).tolist(),   # down: +y
         "base": {"position": [0.0, 0.0, r], "motion": "floating"},
         "bodies": [{"name": "rod", "type": "member", "parent": "base",
                     "segments": [{"name": "s", "length": L, "sections": 2,
                                   "cross_section": {"shape": "solid_circle", "radius": r},
                                   "material": {"youngs_modulus": 1e8, "poisson_ratio": 0.5, "density": 1000,
                                                "viscosity": 1e3}, "free_modes": "bending"}]}],
         "obstacles": [{"name": "floor", "type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "friction": 0.5,
                        "damping": 2.0}],
         "contact": {"spacing": 0.01}}
    # (the midpoint rule: implicit Euler damps the free base's body-frame velocity, which turns at omega, by
    # 1/sqrt(1 + (omega h)^2) a step: 0.5 % at 100 rad/s and 1 ms)
    sim = MechanismSimulator(mechanism_from_dict(d), 1e-3, 0.5, tol=1e-9)
    t, x, phi = [], [], []
    for _ in range(300):
        sim.step()
        t.append(sim.t)
        x.append(sim.q[1])             # the floating base's position: world y, down the incline
        phi.append(-2 * np.arctan2(sim.q[3], sim.q[6]))    # its turn about -x, the rod's axis (quaternion x, y, z, w)
    t, x, phi = np.array(t), np.array(x), np.unwrap(np.array(phi))
    fit = (t >= 0.1) & (t <= 0.3)
    a = 2 * np.polyfit(t[fit], x[fit], 2)[0]
    ang = 2 * np.polyfit(t[fit], phi[fit], 2)[0]
    assert a == pytest.approx(2 / 3 * 9.81 * np.sin(th), rel=5e-3)
    assert ang * r == pytest.approx(a, rel=5e-3)
    assert len(sim.contacts) >= 10 and np.abs(sim.contacts.slip).max() < 1e-3

def _heavy_rod_dict(h=0.0035, length=0.4, sections=12):
    return {"name": "heavy_rod", "gravity": [0, 0, -G],
            "segments": [{"name": "rod", "length": length, "sections": sections,
                          "cross_section": {"shape": "solid_circle", "radius": R_ROD},
                          "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": RHO, "viscosity": 2e3},
                          "free_modes": ["bending_y"]}],
            "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -h - R_ROD], "normal": [0, 0, 1],
                           "damping": 5.0}],
            "contact": {"spacing": 0.01}}


def test_the_twin_reports_its_contacts_and_its_base_wrench_includes_them():
    """Quasi-static and dynamic twins of a robot with obstacles: the
    snapshot lists the contacts, and the base reaction balances the
    weight less the contact forces (the loads inside the robot include
    them); the diagnostics count them."""
    from types import SimpleNamespace
    from soft_twin import diagnostics
    from soft_twin_core.twin import Twin, TwinSettings
    d = _heavy_rod_dict()
    mech = from_robot_model(model_from_dict(d), d)
    weight = Q * 0.4
    for mode in ("quasi_static", "dynamic"):
        twin = Twin(mech, TwinSettings(mode=mode, dt=0.002, theta=1.0))
        info = twin.step(400 if mode == "dynamic" else 1)
        assert info.converged
        snap = twin.outputs()
        assert snap.contacts is not None and len(snap.contacts) > 3
        Fz = snap.contacts.force[:, 2].sum()
        assert 0.2 * weight < Fz < weight
        # the support's reaction on the robot (base axes = world here) and the contacts hold the weight
        assert snap.base_wrench[2] + Fz == pytest.approx(weight, rel=1e-3 if mode == "dynamic" else 1e-8)
        cfg = SimpleNamespace(mode=mode, step_rate_hz=200.0, time_scale=1.0)
        stats = diagnostics.Stats()
        gaps = {k: SimpleNamespace(supported=True) for k in ("actuation", "wrench", "joint")}
        vals = diagnostics.values(stats, cfg, twin, gaps, stats.window_start + 1.0)[0]
        assert vals["contacts_active"] == str(len(twin.contacts))


def test_scenario_runs_carry_the_contacts(tmp_path):
    """soft-twin-sim statics lists every contact (member, s, obstacle,
    position, normal, gap, force, slip); dynamics records the count and
    the total contact force at every row, in the JSON and the CSV."""
    import json
    import yaml
    from soft_twin_core import cli
    robot = tmp_path / "rod.yaml"
    robot.write_text(yaml.safe_dump(_heavy_rod_dict()))
    scen = tmp_path / "s.yaml"
    scen.write_text(yaml.safe_dump({"robot": "rod.yaml"}))
    assert cli.main(["statics", str(scen), "-o", str(tmp_path / "s.json")]) == 0
    js = json.loads((tmp_path / "s.json").read_text())
    assert len(js["contacts"]) > 3
    c = js["contacts"][0]
    assert set(c) == {"member", "s", "obstacle", "position", "normal", "gap", "force", "slip", "moment", "spin"}
    assert c["member"] == "backbone" and c["obstacle"] == "table" and c["gap"] < 0 and c["force"][2] > 0
    assert cli.main(["dynamics", str(scen), "--duration", "0.2", "--dt", "0.002", "-o",
                     str(tmp_path / "d.json")]) == 0
    dj = json.loads((tmp_path / "d.json").read_text())
    assert dj["contact_count"][0] == 0 and max(dj["contact_count"]) > 3
    k = int(np.argmax(dj["contact_count"]))
    assert dj["contact_force"][k][2] > 0
    assert cli.main(["dynamics", str(scen), "--duration", "0.2", "--dt", "0.002", "--format", "csv", "-o",
                     str(tmp_path / "d.csv")]) == 0
    header = (tmp_path / "d.csv").read_text().splitlines()[0].split(",")
    assert "contact_count" in header and "contact_force_z" in header


def test_figures_outline_the_obstacles_and_mark_the_contacts():
    """The scene of a statics result outlines each obstacle (the plane's
    square lies in the plane, around the robot; a sphere's circles on the
    sphere; a capsule's outline within its radius of the segment) and
    marks the contact points; the shapes figure draws them."""
    from soft_twin_core.engine.contact import Obstacle
    from soft_twin_core.viz import plots, scene
    from soft_twin_core.files import runs
    from soft_twin_core.files.scenario import scenario_from_dict
    sc = scenario_from_dict({"robot": _heavy_rod_dict()})
    result = runs.run_mechanism_statics(sc)
    snap = scene.statics_snapshot(result, sc.mech)
    assert len(snap.obstacles) == 1 and len(snap.contacts) == len(result["contacts"]) > 3
    P = snap.obstacles[0][np.all(np.isfinite(snap.obstacles[0]), axis=1)]
    on_plane = np.abs(P[:, 2] + 0.0035 + R_ROD) < 1e-12
    assert on_plane.sum() >= 5 and P[on_plane, 0].min() < 0 < 0.4 < P[on_plane, 0].max()
    ball = Obstacle("b", "sphere", np.array([0.1, 0.2, 0.3]), radius=0.05)
    Q_ = scene.obstacle_outline(ball, np.zeros(3), 1.0)
    Q_ = Q_[np.all(np.isfinite(Q_), axis=1)]
    np.testing.assert_allclose(np.linalg.norm(Q_ - ball.a, axis=1), 0.05, atol=1e-12)
    cap = Obstacle("c", "capsule", np.array([0.0, 0.0, 0.0]), np.array([0.2, 0.1, 0.0]), radius=0.02)
    Q_ = scene.obstacle_outline(cap, np.zeros(3), 1.0)
    Q_ = Q_[np.all(np.isfinite(Q_), axis=1)]
    d, _, _ = signed_distance(cap, Q_)
    np.testing.assert_allclose(d, 0.0, atol=1e-12)
    box = obstacles_from_list([{"type": "box", "center": [0.1, 0.2, 0.0], "size": [0.2, 0.1, 0.04],
                                "rpy": [0.1, 0.2, 0.3]}])[0]
    Q_ = scene.obstacle_outline(box, np.zeros(3), 1.0)
    Q_ = Q_[np.all(np.isfinite(Q_), axis=1)]
    np.testing.assert_allclose(signed_distance(box, Q_)[0], 0.0, atol=1e-12)
    fig = plots.shapes_figure([snap], "heavy rod")
    assert any(ln.get_linestyle() == "--" for ln in fig.axes[0].lines)
    plots._plt().close(fig)


def test_the_example_robot_on_a_table_loads_with_its_obstacle():
    from soft_twin_core.files.scenario import load_scenario
    from soft_twin_core.robot.mechanism import load_mechanism
    mech = load_mechanism("tendon_arm_on_table")
    (table,) = mech.obstacles
    assert table.kind == "plane" and table.friction == 0.3 and mech.contact_spacing == 0.015
    assert load_scenario("tendon_arm_on_table").mech.obstacles[0].name == "table"


def test_the_node_markers_draw_the_obstacles_and_an_arrow_per_contact():
    """~/markers of a robot with obstacles: the plane as a thin square in
    the plane, a sphere, a capsule (cylinder and two spheres); an arrow
    per contact from its point along its force (the largest 5 cm); a state
    with fewer contacts deletes the extra arrows."""
    from types import SimpleNamespace
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker
    from soft_twin import markers
    from soft_twin_core.lie import rotation_with_z
    from soft_twin_core.twin import Twin, TwinSettings
    z = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    Rz = rotation_with_z(z)
    np.testing.assert_allclose(Rz.T @ Rz, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rz) == pytest.approx(1.0) and np.allclose(Rz[:, 2], z)
    d = _heavy_rod_dict()
    d["obstacles"] += [{"name": "ball", "type": "sphere", "center": [0.2, 0.5, 0.0], "radius": 0.05},
                       {"name": "post", "type": "capsule", "from": [0.0, 0.6, 0.0], "to": [0.0, 0.6, 0.2],
                        "radius": 0.01},
                       {"name": "block", "type": "box", "center": [0.5, 0.5, 0.0], "size": [0.1, 0.2, 0.3]}]
    mech = from_robot_model(model_from_dict(d), d)
    snap = Twin(mech, TwinSettings(mode="quasi_static")).outputs()
    mk = markers.Markers()
    out = mk(snap, SimpleNamespace(mech=mech), Header())
    obs = [m for m in out.markers if m.ns == "obstacles"]
    assert [m.type for m in obs] == [Marker.CUBE, Marker.SPHERE, Marker.SPHERE, Marker.SPHERE, Marker.CYLINDER,
                                     Marker.CUBE]
    assert (obs[5].scale.x, obs[5].scale.y, obs[5].scale.z) == pytest.approx((0.1, 0.2, 0.3))
    table = obs[0]
    assert table.scale.z == 0.001 and abs(table.pose.position.z - (-0.0035 - R_ROD - 0.0005)) < 1e-12
    assert obs[4].scale.z == pytest.approx(0.2) and obs[4].pose.position.z == pytest.approx(0.1)
    arrows = [m for m in out.markers if m.ns == "contacts"]
    assert len(arrows) == len(snap.contacts) > 3
    lengths = []
    for a, p, f in zip(arrows, snap.contacts.p, snap.contacts.force):
        start = np.array([a.points[0].x, a.points[0].y, a.points[0].z])
        d_ = np.array([a.points[1].x, a.points[1].y, a.points[1].z]) - start
        np.testing.assert_allclose(start, p, atol=1e-12)
        assert np.cross(d_, f) == pytest.approx(np.zeros(3), abs=1e-12) and d_ @ f > 0
        lengths.append(np.linalg.norm(d_))
    assert max(lengths) == pytest.approx(0.05)
    fewer = SimpleNamespace(**{k: getattr(snap, k) for k in ("backbones", "points_per_section", "frames",
                                                               "main_member", "tip_pose")})
    fewer.contacts = None
    fewer.obstacles = snap.obstacles[:2]          # two obstacles removed (~/obstacles): their markers go
    out2 = mk(fewer, SimpleNamespace(mech=mech), Header())
    gone = [m.id for m in out2.markers if m.ns == "contacts" and m.action == Marker.DELETE]
    assert gone == list(range(len(arrows)))
    shapes = [m for m in out2.markers if m.ns == "obstacles"]
    assert [m.action for m in shapes] == [Marker.ADD] * 2 + [Marker.DELETE] * 4
    assert [m.id for m in shapes if m.action == Marker.DELETE] == [2, 3, 4, 5]


def test_a_box_its_distance_gradient_and_hessian():
    """Box obstacles: the distance by definition (outside: to the closest
    point, the point clamped to the box; inside: minus the distance to the
    nearest face), its gradient and Hessian against central differences
    (faces, edges, corners, inside), the robot-file entry checked."""
    R = obstacles_from_list([{"type": "box", "center": [0.1, -0.2, 0.05], "size": [0.2, 0.1, 0.3],
                              "rpy": [0.3, -0.2, 0.7]}])[0]
    assert R.kind == "box" and np.allclose(R.half_size, [0.1, 0.05, 0.15])
    p = np.vstack([RNG.uniform(-0.4, 0.4, (60, 3)), RNG.uniform(-0.04, 0.04, (6, 3))]) + R.a
    d, n, H = signed_distance(R, p)
    loc = (p - R.a) @ R.rotation
    clamped = np.clip(loc, -R.half_size, R.half_size)
    inside = np.all(np.abs(loc) <= R.half_size, axis=1)
    ref = np.where(inside, -np.min(R.half_size - np.abs(loc), axis=1), np.linalg.norm(loc - clamped, axis=1))
    np.testing.assert_allclose(d, ref, atol=1e-14)
    assert inside.sum() >= 2 and (~inside).sum() >= 20
    _check_derivatives(R, p, n, H, 1e-7, 1e-6, 1e-4 * max(1.0, np.abs(H).max()))
    with pytest.raises(ModelError, match=r"robot\.obstacles\[0\]\.size"):
        obstacles_from_list([{"type": "box", "center": [0, 0, 0], "size": [0.1, 0.0, 0.1]}])


def test_a_heavy_rod_lifted_off_a_plane_by_a_pin_matches_the_classic_solution():
    """The classic heavy rod lifted off a rigid plane (issue 27): one end
    held by a pin at height h (zero end moment), the rest lying on the
    plane. Small deflections: lifted length a = (24 EI h / q)^(1/4), the
    pin carries q a / 2, a concentrated reaction q a / 2 at the lift-off
    point, no pressure in the lifted span (EI w'''' = -q on [0, a], w(0) =
    0, w''(0) = 0, w(a) = -h, w'(a) = w''(a) = 0). The penalty spreads the
    concentrated reaction over the foundation length (4 EI / k)^(1/4):
    its resultant (the contact force in excess of the lying weight) sits
    at a within 1 % from k = E on, converging as k grows (stiffness
    continuation: each solve starts from the softer one's); the pin's
    force within 0.2 % at every k; nothing touches before 0.9 a."""
    a, L = 0.3, 0.6
    h = Q * a ** 4 / (24 * EI)                  # 10.6 mm: slopes of 3.5 %
    d = {"name": "pinned", "gravity": [0, 0, -G],
         "bodies": [{"name": "rod", "type": "member", "parent": "base",
                     "joint": {"name": "pin", "type": "revolute", "axis": [0, 1, 0], "control": "passive"},
                     "segments": [{"name": "s", "length": L, "sections": 60,
                                   "cross_section": {"shape": "solid_circle", "radius": R_ROD},
                                   "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": RHO},
                                   "free_modes": ["bending_y"]}]}],
         "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -h - R_ROD], "normal": [0, 0, 1]}],
         "contact": {"spacing": 0.002}}
    q, errors = None, []
    for k in (E / 10, E, 10 * E, 100 * E):
        d["obstacles"][0]["stiffness"] = k
        mech = mechanism_from_dict(d)
        if q is None:                          # tilted down so that its far end presses on the table
            q = mech.tree.q0.copy()
            q[mech.tree.idx_q[mech.tree.joint_index("pin")]] = np.arcsin(1.05 * h / L)
        eq = solve_equilibrium(mech, q_init=q)
        q, c = eq.q, eq.contacts
        assert eq.stable and len(c) > 100
        assert Q * L - c.force[:, 2].sum() == pytest.approx(Q * a / 2, rel=2e-3)        # the pin's share
        excess = c.force[:, 2] - Q * mechanism_contact_points(mech).weight[c.point]
        errors.append(abs(np.sum(c.p[:, 0] * excess) / np.sum(excess) / a - 1))
        assert c.p[:, 0].min() > 0.9 * a
    assert errors[1] < 0.01 and errors[1] > errors[2] > errors[3]


def test_a_moving_table_in_a_scenario_and_a_conveyor_dragging_a_rod():
    """Scenario obstacles with trajectories: the statics at the end of a
    rising table's trajectory is the equilibrium on a table fixed at its
    final height. A rod lying on a conveyor (a plane moving along itself at
    u) is dragged at a = mu g until it moves with the belt (Coulomb: the
    slip is relative to the moving surface), within 2 %."""
    from soft_twin_core.engine.contact import moved
    from soft_twin_core.files import runs
    from soft_twin_core.files.scenario import scenario_from_dict
    robot = _heavy_rod_dict()
    table = robot.pop("obstacles")[0]
    sc = scenario_from_dict({"robot": robot, "obstacles": [dict(table, trajectory=[[0, 0, 0, 0], [1, 0, 0, 0.002]])]})
    assert runs.run_mechanism_statics(sc, t=1.0)["contacts"][0]["obstacle"] == "table"
    moving = solve_equilibrium(sc.mech, obstacles=sc.obstacles_at(1.0))
    fixed_robot = dict(robot, obstacles=[dict(table, point=[0, 0, table["point"][2] + 0.002])])
    fixed = solve_equilibrium(from_robot_model(model_from_dict(fixed_robot), fixed_robot))
    np.testing.assert_allclose(moving.q, fixed.q, atol=1e-9 * np.abs(fixed.q).max())
    with pytest.raises(ScenarioError, match=r"scenario\.obstacles\[0\]\.trajectory"):
        scenario_from_dict({"robot": robot, "obstacles": [dict(table, trajectory=[[1, 0, 0, 0], [0, 1, 0, 0]])]})
    with pytest.raises(ScenarioError, match="already name"):
        scenario_from_dict({"robot": _heavy_rod_dict(), "obstacles": [table]})
    # the conveyor
    mu, u, h = 0.3, 0.2, 1e-3
    mech = _slider(0.0, mu)
    belt = mech.obstacles[0]
    sim = MechanismSimulator(mech, h, 1.0, tol=1e-9)
    v = []
    for k in range(1, 151):
        sim.step(obstacles=(moved(belt, [u * k * h, 0, 0]),))
        v.append(sim.v[0])                       # the free joint's velocity along the rod (x)
    v = np.array(v)
    t = h * np.arange(1, 151)
    t_catch = u / (mu * 9.81)                    # 68 ms
    early = (t > 0.01) & (t < 0.8 * t_catch)
    slope = np.polyfit(t[early], v[early], 1)[0]
    assert slope == pytest.approx(mu * 9.81, rel=0.02)
    assert v[-1] == pytest.approx(u, rel=0.02)


def test_a_closed_chain_leaning_on_an_obstacle_statics_and_dynamics_agree():
    """The parallel robot (soft rods, both clamped to the platform) with a
    block pressed 3 mm into rod 1's side at mid-height: statics (the KKT Newton with the
    loops' rows and the contacts' stiffness) finds a stable equilibrium on
    the block, and dynamics (the same KKT step, implicit Euler, damped),
    the block moving in from touching, creeps onto it: one path for rods, trees and closed chains. Giving
    obstacles to a simulator made without any, or changing their kinds,
    is refused and leaves its state as it was."""
    from soft_twin_core.engine.contact import moved
    from soft_twin_core.robot.model import find_file, read_yaml_file
    d = read_yaml_file(find_file("planar_parallel_robot", "robots"))
    for b in d["bodies"]:
        for seg in b.get("segments", []):
            seg["material"].update(youngs_modulus=2.0e9)       # polymer: stiff enough to stand
    base = mechanism_from_dict(d)
    x_rod = solve_equilibrium(base).q                  # where the rods hang without the post
    # a block whose face stands 1 mm inside rod 1's axis: 3 mm into the 2 mm rod
    d["obstacles"] = [{"name": "post", "type": "box", "center": [-0.049 + 0.01, 0.0, 0.2], "size": [0.02, 0.1, 0.1]}]
    d["contact"] = {"spacing": 0.005}
    mech = mechanism_from_dict(d)
    eq = solve_equilibrium(mech, q_init=x_rod)
    assert eq.stable and len(eq.contacts) > 0 and eq.constraint_error < 1e-9
    assert np.all(eq.contacts.force[:, 0] < 0)                     # the post pushes rod 1 towards -x
    assert set(mechanism_contact_points(mech).member[i] for i in eq.contacts.point) == {"rod1"}
    # dynamics: the block comes in from touching over 0.2 s (a moving obstacle), then holds
    block = mech.obstacles[0]
    sim = MechanismSimulator(mech, 2e-3, 1.0, q=x_rod, tol=1e-9, obstacles=(moved(block, [0.003, 0, 0]),))
    for k in range(1, 1201):
        sim.step(obstacles=(moved(block, [0.003 * max(0.0, 1 - k / 100), 0, 0]),))
    # the heavily damped rods creep onto it (2.4 s: 1e-3 of the strains left, the force within 2 %)
    np.testing.assert_allclose(sim.q, eq.q, atol=1e-3 * np.abs(eq.q).max())
    assert sim.contacts.force[:, 0].sum() == pytest.approx(eq.contacts.force[:, 0].sum(), rel=0.02)
    q_before = sim.q.copy()
    with pytest.raises(ValueError, match="keeps its kind"):
        sim.step(obstacles=(Obstacle("post", "sphere", np.zeros(3), radius=0.01),))
    bare = MechanismSimulator(base, 2e-3, 1.0, q=x_rod)
    with pytest.raises(ValueError, match="made without obstacles"):
        bare.step(obstacles=(moved(mech.obstacles[0], [0.01, 0, 0]),))
    np.testing.assert_array_equal(sim.q, q_before)
    np.testing.assert_array_equal(bare.q, x_rod)


def _floating_rod(alpha, radius=0.005, E=1e9):
    """A free, stiff 0.2 m rod (floating base, no gravity) lying flat just
    above a table (0.1 mm gap) whose Hunt-Crossley damping is ``alpha``."""
    d = {"name": "dropper", "gravity": [0, 0, 0], "base": {"position": [0, 0, 0], "motion": "floating"},
         "bodies": [{"name": "rod", "type": "member", "parent": "base", "joint": {"type": "fixed"},
                     "segments": [{"name": "s", "length": 0.2, "sections": 2,
                                   "cross_section": {"shape": "solid_circle", "radius": radius},
                                   "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000},
                                   "free_modes": ["bending_y", "bending_z"]}]}],
         "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -radius - 1e-4], "normal": [0, 0, 1],
                        "damping": alpha}],
         "contact": {"spacing": 0.005}}
    return mechanism_from_dict(d)


def _restitution(alpha, v_in, dt):
    """The restitution sqrt(T_out / T_in) (kinetic energies) of the rod
    dropped flat at v_in [m/s]."""
    mech = _floating_rod(alpha)
    v = np.zeros(mech.tree.nv)
    v[2] = -v_in                                   # the floating base's vertical velocity
    sim = MechanismSimulator(mech, dt, 0.5, v=v, tol=1e-10)
    T_in = sim.energy()[0]
    touched = False
    for _ in range(2000):
        sim.step()
        n = len(sim.contacts) if sim.contacts is not None else 0
        touched = touched or n > 0
        if touched and n == 0:
            return np.sqrt(sim.energy()[0] / T_in)
    raise AssertionError("the rod did not leave the table")


def _restitution_ode(alpha, v_in, radius=0.005, E=1e9):
    """The same impact as one degree of freedom: per unit length,
    rho A x'' = -f(x) (1 + alpha x') (x the penetration, f the penalty
    law), integrated by scipy to 1e-11."""
    from scipy.integrate import solve_ivp
    m = 1000.0 * np.pi * radius ** 2

    def rhs(t, y):
        x, xd = y
        f = float(normal_force_density(x, E, 0.1 * radius)[0]) if x > 0 else 0.0
        return [xd, -f * max(1.0 + alpha * xd, 0.0) / m]
    out = lambda t, y: y[0] + 1e-12                 # noqa: E731  (leaves the surface)
    out.terminal, out.direction = True, -1
    sol = solve_ivp(rhs, [0, 1], [0.0, v_in], events=out, rtol=1e-11, atol=1e-14, max_step=1e-6)
    return -sol.y[1, -1] / v_in


def test_a_rod_dropped_flat_rebounds_with_the_restitution_of_the_hunt_crossley_law():
    """Restitution of the law F = f(delta) (1 + alpha delta'): along the
    undamped path delta'^2 = v^2 - 2 Phi(delta)/m', so the energy lost,
    alpha int f delta'^2 dt = 2 alpha int_0^{m' v^2/2} sqrt(v^2 - 2 u/m') du
    = (2/3) m' alpha v^3 whatever f is, and e^2 = 1 - (4/3) alpha v to first
    order in alpha v (Hunt and Crossley, J. Appl. Mech. 42, 1975: 1 - e =
    (2/3) alpha v). A stiff free rod dropped flat on the table is that
    single degree of freedom per unit length: its rebound matches scipy's
    integration of it (to 1e-3 at dt = 25 us, converging with dt), the
    first-order closed form at alpha v = 0.005 (1 - e to 2 %), and without
    damping it leaves with the kinetic energy it came with (to 1e-6).
    (Restitution here: sqrt(T_out / T_in), the kinetic energies.)"""
    v = 0.1
    e0 = _restitution(0.0, v, 2.5e-5)
    assert abs(e0 - 1.0) < 1e-6
    for alpha in (0.5, 2.0):
        ref = _restitution_ode(alpha, v)
        coarse, fine = _restitution(alpha, v, 2.5e-5), _restitution(alpha, v, 1e-5)
        assert abs(fine - ref) < 1e-3 and abs(fine - ref) < 0.5 * abs(coarse - ref)
    assert _restitution_ode(2.0, v) == pytest.approx(0.882, abs=1e-3)        # beyond first order here
    alpha = 0.05
    closed = 1 - np.sqrt(1 - 4 * alpha * v / 3)
    assert 1 - _restitution_ode(alpha, v) == pytest.approx(closed, rel=0.02)
    assert 1 - _restitution(alpha, v, 2.5e-5) == pytest.approx(closed, rel=0.05)


def test_a_column_buckling_between_two_walls_first_touches_at_the_elastica_load():
    """Constrained Euler buckling (Domokos, Holmes and Royce, J. Nonlinear
    Sci. 7, 1997: an elastica between two parallel frictionless walls): a
    clamped-free column (half of their pinned-pinned one) under a dead
    compressive tip load P buckles onto the elastica branch with tip
    deflection ``delta = 2 k L / K(k)`` at ``P = K(k)^2 EI / L^2`` (Love;
    K the complete elliptic integral of the first kind); walls at
    +-(r + delta_c) are first touched, at the tip, at the load P_c of
    delta_c. Followed by continuation in P from a bent start (the straight
    column is an equilibrium too): the branch within 0.2 % of the closed
    form; no contact at 0.995 P_c; at 1.005 P_c the near wall holds the tip
    at its surface and the far wall is not touched. (Their later events,
    the contact spreading and the second wall, are not checked.)"""
    from scipy.optimize import brentq
    from scipy.special import ellipk
    from soft_twin_core.robot.mechanism import tip_frame
    from soft_twin_core.solve.constrained import FrameLoad
    from soft_twin_core.solve.outputs import state_outputs
    L, r, E = 0.4, 0.005, 2e6
    EI = E * np.pi * r ** 4 / 4
    P_euler = np.pi ** 2 * EI / (4 * L ** 2)

    def deflection(P):
        k = brentq(lambda k: ellipk(k * k) ** 2 * EI / L ** 2 - P, 1e-9, 1 - 1e-9)
        return 2 * k * L / ellipk(k * k)

    def column(gap=None):
        d = {"name": "column", "gravity": [0, 0, 0], "segments": [{
            "name": "s", "length": L, "sections": 32, "cross_section": {"shape": "solid_circle", "radius": r},
            "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000.0}, "free_modes": ["bending_z"]}]}
        if gap is not None:
            d["obstacles"] = [{"name": "left", "type": "plane", "point": [0, gap, 0], "normal": [0, -1, 0]},
                              {"name": "right", "type": "plane", "point": [0, -gap, 0], "normal": [0, 1, 0]}]
            d["contact"] = {"spacing": 0.002}
        return from_robot_model(model_from_dict(d), d)

    def solve(mech, P, q):
        eq = solve_equilibrium(mech, point_loads=[FrameLoad(tip_frame(mech), np.array([-P, 0, 0, 0, 0, 0.0]),
                                                            "world")], q_init=q, max_iterations=100)
        return eq, state_outputs(mech, eq.q, eq.lam, eq.inputs).frames[tip_frame(mech)][1, 3]

    P_c = 1.15 * P_euler
    free, q = column(), np.full(32, 1.25)
    for P in np.linspace(1.06, 0.995 * 1.15, 5) * P_euler:
        eq, tip = solve(free, P, q)
        q = eq.q
        assert tip == pytest.approx(deflection(P), rel=2e-3)
    gap = r + deflection(P_c)
    walls = column(gap)
    eq, tip = solve(walls, 0.995 * P_c, q)
    assert not len(eq.contacts) and tip < gap - r
    eq, tip = solve(walls, 1.005 * P_c, eq.q)
    c = eq.contacts
    assert len(c) >= 1 and set(c.obstacle.tolist()) == {0}            # the near wall only
    pts = mechanism_contact_points(walls)
    assert np.all(pts.s[c.point] > 0.98 * L) and np.all(c.force[:, 1] < 0)
    # held at the surface: the touching points pressed in by microns; the tip, 1 mm past the
    # last contact point (the points sit at the middles of 2 mm intervals), by less than that
    assert np.all((c.gap > -2e-5) & (c.gap < 0)) and 0 < tip - (gap - r) < 0.001


def test_the_compiled_step_is_the_python_step():
    """A robot without multipliers steps with contacts through the compiled
    step (engine.contact_step); the Python step (the one of robots with
    multipliers, a fresh Newton matrix every step) solves the same step
    equations: a rod falling onto a ball with
    friction and damping that slides sideways on a table with friction,
    stepped by both (sub-steps included) from the same states, agrees to
    round-off (1e-8 of the strains, the same contacts and forces)."""
    from soft_twin_core.engine.contact import moved
    d = _heavy_rod_dict(h=0.001, sections=6)
    d["segments"][0]["free_modes"] = "bending_torsion"
    d["obstacles"][0].update(friction=0.4, stiction_velocity=1e-3)
    d["obstacles"].append({"name": "ball", "type": "sphere", "center": [0.3, 0.0, -0.001 - R_ROD - 0.0085],
                           "radius": 0.01, "damping": 2.0, "friction": 0.2, "stiction_velocity": 1e-3})
    mech = from_robot_model(model_from_dict(d), d)
    sims = [MechanismSimulator(mech, 2e-3, 0.5, tol=1e-12) for _ in range(2)]
    python = sims[1]
    python._compiled_step = lambda inp, targets, h: python._step(inp, targets, h)     # (halving included)
    touched = set()
    for k in range(250):
        obs = [mech.obstacles[0], moved(mech.obstacles[1], [0.0, 2e-5 * k, 0.0])]
        for sim in sims:
            sim.step(obstacles=obs)
        a, b = sims
        assert np.abs(a.q - b.q).max() <= 1e-8 * max(np.abs(b.q).max(), 1.0), k
        assert np.array_equal(a.contacts.point, b.contacts.point) and np.array_equal(a.contacts.obstacle,
                                                                                     b.contacts.obstacle)
        np.testing.assert_allclose(a.contacts.force, b.contacts.force, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(a.contacts.slip, b.contacts.slip, rtol=1e-6, atol=1e-9)
        b.q, b.v, b.a = a.q.copy(), a.v.copy(), a.a.copy()      # from the same state on
        touched |= {int(o) for o in a.contacts.obstacle}
    assert touched == {0, 1}


def _catheter_pushed():
    """The example catheter, its base prescribed by a clamp (6 rows), pushed
    4 mm along the vessel in 0.2 s (a smooth push, at rest at both ends)
    while the rod lies on the vessel's wall with friction."""
    from soft_twin_core.robot.mechanism import base_targets, load_mechanism
    from soft_twin_core.robot.model import find_file
    mech = load_mechanism(find_file("catheter_in_vessel", "robots"))

    def step_inputs(k):
        pose = np.eye(4)
        pose[0, 3] = 0.004 * (1 - np.cos(np.pi * (k + 1) / 200)) / 2
        return dict(targets=base_targets(mech, pose))
    return mech, 1e-3, 200, step_inputs


def _parallel_robot_pushed():
    """The planar parallel robot (a closed chain: 6 rows) with a ball, with
    friction, pushed 15 mm into one of its rods in 0.75 s."""
    import yaml
    from soft_twin_core.engine.contact import moved
    from soft_twin_core.robot.model import find_file
    with open(find_file("planar_parallel_robot", "robots")) as f:
        d = yaml.safe_load(f)
    d["obstacles"] = [{"name": "ball", "type": "sphere", "center": [-0.08, 0.0, 0.2], "radius": 0.02,
                       "friction": 0.2, "stiction_velocity": 1e-3, "damping": 1.0}]
    d["contact"] = {"spacing": 0.01}
    mech = mechanism_from_dict(d)

    def step_inputs(k):
        return dict(obstacles=[moved(mech.obstacles[0], [0.015 * (1 - np.cos(np.pi * (k + 1) / 150)) / 2, 0, 0])])
    return mech, 5e-3, 150, step_inputs


@pytest.mark.parametrize("case", [_catheter_pushed, _parallel_robot_pushed], ids=["prescribed_base", "closed_chain"])
def test_the_compiled_step_with_constraint_rows_is_the_python_step(case):
    """Constraint rows and contacts in one compiled step (engine.contact_step,
    the rows by their Schur complement): stepped by the compiled step and by
    the Python KKT step from the same states, a robot with constraint rows
    against obstacles agrees to round-off: the configuration to 1e-8, the
    multipliers (the wrench holding the base, the loop's reactions) and the
    contacts' forces to 1e-6. (A step one of them splits in halves and the
    other takes whole, at a contact's onset, is not compared: one in each
    run.) The converged states agree whatever Newton matrix each used; the
    iterations tell whether the compiled step's matrix is the Python step's
    (the contacts' stiffness, damping and friction brought to the
    coordinates by the kernel's own loops): on the catheter the two take the
    same iterations on all but 3 of 200 steps, and on 117 without the
    friction's stiffness, 56 without the contacts' damping (checked). (The
    parallel robot's differ on 17 of 150 either way: not asserted.)"""
    mech, dt, n, step_inputs = case()
    sims = [MechanismSimulator(mech, dt, 0.5, tol=1e-12) for _ in range(2)]
    assert sims[0]._use_compiled_step and mech.n_constraint_rows == 6
    calls = [0, 0]
    steps = (sims[0]._compiled_step, lambda inp, targets, h: sims[1]._step(inp, targets, h))
    for i, (sim, step) in enumerate(zip(sims, steps)):
        def counted(*a, i=i, step=step):
            calls[i] += 1
            return step(*a)
        sim._compiled_step = counted
    compared, contacts, other_iterations = 0, 0, 0
    for k in range(n):
        before, it0 = list(calls), [sim.newton_iterations for sim in sims]
        for sim in sims:
            sim.step(**step_inputs(k))
        a, b = sims
        other_iterations += a.newton_iterations - it0[0] != b.newton_iterations - it0[1]
        if calls[0] - before[0] == calls[1] - before[1]:           # (both whole, or split alike)
            assert np.abs(a.q - b.q).max() <= 1e-8 * max(np.abs(b.q).max(), 1.0), k
            np.testing.assert_allclose(a.lam, b.lam, rtol=1e-6, atol=1e-6 * np.abs(b.lam).max(), err_msg=str(k))
            assert np.array_equal(a.contacts.point, b.contacts.point)
            np.testing.assert_allclose(a.contacts.force, b.contacts.force, rtol=1e-6, atol=1e-9)
            compared += 1
            contacts += len(a.contacts.point) > 0
        b.q, b.v, b.a, b.lam = a.q.copy(), a.v.copy(), a.a.copy(), a.lam.copy()      # from the same state on
    assert compared >= n - 2 and contacts >= 40
    if case is _catheter_pushed:
        assert other_iterations <= 10, other_iterations


def test_a_failed_compiled_step_with_constraint_rows_is_retried_by_the_python_step():
    """With constraint rows, a compiled step that fails (its rows'
    factorisation singular, Newton stalled) is retried by the Python KKT
    step at the same dt before the step is split in halves, and its rows
    are taken again at the next step."""
    from soft_twin_core.errors import StepError
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.robot.model import find_file
    mech = load_mechanism(find_file("catheter_in_vessel", "robots"))
    sim = MechanismSimulator(mech, 1e-3, 0.5, tol=1e-12)
    ref = MechanismSimulator(mech, 1e-3, 0.5, tol=1e-12, compiled=False)
    sim.step()
    assert sim._compiled_held is not None
    calls = {"compiled": [], "python": []}
    python = sim._step

    def failing(inp, targets, h):
        calls["compiled"].append(h)
        raise StepError("singular Newton matrix (forced)")

    def counted(inp, targets, h=None):
        calls["python"].append(h)
        return python(inp, targets, h)
    sim._compiled_step, sim._step = failing, counted
    ref.q, ref.v, ref.a, ref.lam = sim.q.copy(), sim.v.copy(), sim.a.copy(), sim.lam.copy()
    sim.step()
    ref.step()
    assert calls == {"compiled": [1e-3], "python": [1e-3]} and sim._compiled_held is None
    assert np.abs(sim.q - ref.q).max() <= 1e-12 * max(np.abs(ref.q).max(), 1.0)


def _cube_mesh(centre, size):
    """A box's 8 corners and 12 triangles (some turned inward: the loader
    turns them out)."""
    h = 0.5 * np.asarray(size)
    V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h + centre
    F = []
    for a, b, c, d in ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)):
        F += [[a, b, c], [a, c, d]]
    F[3] = F[3][::-1]
    return {"type": "mesh", "vertices": V.tolist(), "faces": F}


def test_a_convex_mesh_is_the_box_it_bounds_and_its_derivatives_are_right():
    """A cube given as a triangle mesh has the box obstacle's signed
    distance, normal and Hessian everywhere (outside a face, an edge or a
    corner; inside), also turned by a pose; an irregular convex hull's
    gradient and Hessian match central differences of its distance."""
    from scipy.spatial import ConvexHull
    from soft_twin_core.robot.obstacles import obstacle_from_dict, obstacle_placed
    centre, size = np.array([0.5, 0.1, -0.2]), [0.2, 0.4, 0.6]
    mesh = obstacle_from_dict(dict(_cube_mesh(centre, size), name="m"), "m")
    box = obstacle_from_dict({"name": "b", "type": "box", "center": centre.tolist(), "size": size}, "b")
    P = RNG.uniform(-0.6, 0.6, (1000, 3)) + centre
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(RNG.standard_normal((3, 3)))[0]
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))          # a rotation
    T[:3, 3] = [0.1, 0.2, 0.3]
    for m, b in ((mesh, box), (obstacle_placed(mesh, T), obstacle_placed(box, T))):
        for x, y in zip(signed_distance(m, P), signed_distance(b, P)):
            np.testing.assert_allclose(x, y, atol=1e-9)
    hull = ConvexHull(RNG.standard_normal((30, 3)) * [0.1, 0.2, 0.15])
    ob = obstacle_from_dict({"name": "rock", "type": "mesh", "vertices": hull.points.tolist(),
                             "faces": hull.simplices.tolist()}, "rock")
    h = 1e-7
    for p in RNG.standard_normal((60, 3)) * 0.3:
        d, n, H = signed_distance(ob, p[None])
        e = np.eye(3) * h
        grad = [(signed_distance(ob, (p + e[k])[None])[0][0] - signed_distance(ob, (p - e[k])[None])[0][0]) / (2 * h)
                for k in range(3)]
        hess = np.column_stack([(signed_distance(ob, (p + e[k])[None])[1][0]
                                 - signed_distance(ob, (p - e[k])[None])[1][0]) / (2 * h) for k in range(3)])
        np.testing.assert_allclose(n[0], grad, atol=1e-6)
        np.testing.assert_allclose(H[0], hess, atol=1e-4 * max(1.0, np.abs(hess).max()))


# A U-shaped profile in its (u, v) plane [m]: two posts and the floor of a notch 10 mm wide and 8 mm deep,
# and its triangulation on its own corners (three quadrilaterals)
_U = np.array([[0, 0], [0.03, 0], [0.03, 0.02], [0.02, 0.02], [0.02, 0.012], [0.01, 0.012], [0.01, 0.02],
               [0, 0.02]]) - [0.015, 0.0]
_U_CAP = [[0, 5, 6], [0, 6, 7], [0, 1, 4], [0, 4, 5], [1, 2, 3], [1, 3, 4]]


def _prism_mesh(profile, cap, length, windings=None, inner=()):
    """The profile (its (u, v) = (y, z)) extruded along x over [0, length]:
    vertices and faces, the faces' windings scrambled by ``windings`` (the
    loader turns them to one, outward). The caps' triangles index the
    profile's corners, then the ``inner`` points."""
    n, m = len(profile), len(inner)
    V = [[x, u, v] for x in (0.0, length) for u, v in profile] + [[x, u, v] for x in (0.0, length) for u, v in inner]
    at = (lambda i, top: (i + n * top) if i < n else (2 * n + i - n + m * top))
    F = [[at(i, 0) for i in t] for t in cap] + [[at(i, 1) for i in t][::-1] for t in cap]
    for k in range(n):
        a, b = k, (k + 1) % n
        F += [[a, b, n + b], [a, n + b, n + a]]
    if windings is not None:
        F = [f[::-1] if w else f for f, w in zip(F, windings.integers(0, 2, len(F)))]
    return {"type": "mesh", "vertices": V, "faces": F}


# a five-pointed star (tips of 36 degrees: acute edges and saddle corners at the prism's ends), a fan from its
# centre
_STAR = np.array([[np.cos(a), np.sin(a)] for a in np.pi / 2 + np.arange(10) * np.pi / 5]) \
    * np.where(np.arange(10) % 2, 0.0076, 0.02)[:, None]
_STAR_CAP = [[10, k, (k + 1) % 10] for k in range(10)]


def _prism_distance(profile, length, p):
    """The prism's exact signed distance at points p (N, 3), not by its
    triangles: the profile's own (the nearest edge; the side by crossing
    count) extruded (the distance to a slab's ends combined as for a box)."""
    out = []
    for x, u, v in p:
        d2 = np.inf
        inside = False
        for a, b in zip(profile, np.roll(profile, -1, axis=0)):
            e = b - a
            t = np.clip(np.dot([u, v] - a, e) / np.dot(e, e), 0.0, 1.0)
            d2 = min(d2, float(np.sum(([u, v] - a - t * e) ** 2)))
            if (a[1] > v) != (b[1] > v) and u < a[0] + (v - a[1]) * e[0] / e[1]:
                inside = not inside
        w = np.array([-np.sqrt(d2) if inside else np.sqrt(d2), abs(x - 0.5 * length) - 0.5 * length])
        out.append(min(w.max(), 0.0) + np.linalg.norm(np.maximum(w, 0.0)))
    return np.array(out)


def test_a_mesh_that_is_not_convex_has_its_exact_signed_distance_and_derivatives():
    """A star-shaped prism (acute edges, concave edges, and corners where
    both meet) and a U-shaped one (a channel), their faces given in
    scrambled windings: the signed distance, inside and out, is the prism's
    exact one computed from its profile (no triangles, no pseudonormals);
    where it is smooth, the gradient and Hessian match central differences
    of the distance."""
    from soft_twin_core.robot.obstacles import obstacle_from_dict
    star = obstacle_from_dict(dict(_prism_mesh(_STAR, _STAR_CAP, 0.04, np.random.default_rng(3), inner=[[0, 0]]),
                                   name="star"), "star")
    rng = np.random.default_rng(12)
    lo, hi = np.array([-0.01, -0.025, -0.025]), np.array([0.05, 0.025, 0.025])
    P = lo + (hi - lo) * rng.uniform(size=(3000, 3))
    np.testing.assert_allclose(signed_distance(star, P)[0], _prism_distance(_STAR, 0.04, P), atol=1e-12)
    ob = obstacle_from_dict(dict(_prism_mesh(_U, _U_CAP, 0.04, np.random.default_rng(3)), name="u"), "u")
    lo, hi = np.array([-0.01, -0.025, -0.01]), np.array([0.05, 0.025, 0.03])
    P = lo + (hi - lo) * rng.uniform(size=(3000, 3))
    d, n, H = signed_distance(ob, P)
    ref = _prism_distance(_U, 0.04, P)
    np.testing.assert_allclose(d, ref, atol=1e-12)
    assert (ref < 0).sum() > 400 and (ref > 0).sum() > 1000          # both sides sampled
    h, checked = 1e-7, 0
    for p in P[:300]:
        e = np.eye(3) * h
        grad = np.array([(_prism_distance(_U, 0.04, [p + e[k]])[0] - _prism_distance(_U, 0.04, [p - e[k]])[0])
                         / (2 * h) for k in range(3)])
        if abs(np.linalg.norm(grad) - 1.0) > 1e-6:
            continue             # on a ridge of the distance (equidistant from two features): not smooth
        k = np.flatnonzero((P == p).all(axis=1))[0]
        np.testing.assert_allclose(n[k], grad, atol=1e-6)
        hess = np.column_stack([(signed_distance(ob, (p + e[j])[None])[1][0]
                                 - signed_distance(ob, (p - e[j])[None])[1][0]) / (2 * h) for j in range(3)])
        np.testing.assert_allclose(H[k], hess, atol=1e-4 * max(1.0, np.abs(hess).max()))
        checked += 1
    assert checked > 250


def test_a_rod_lying_in_a_channel_mesh_rests_as_on_its_floor():
    """The heavy rod (bending in its vertical plane) lying along the notch
    of a U-shaped channel (a mesh that is not convex, 2.5 mm clear of each
    wall): its statics and a dynamic settle equal those on a box whose top
    is the notch's floor. A sign wrong near the notch's walls would push
    the rod or let it sink."""
    floor = -0.0035 - R_ROD
    U = np.array([[0, 0], [0.03, 0], [0.03, 0.02], [0.015, 0.02], [0.015, 0.012], [0.005, 0.012], [0.005, 0.02],
                  [0, 0.02]]) + [-0.015, floor - 0.012]
    U[[3, 4], 0] = R_ROD + 0.0025
    U[[5, 6], 0] = -R_ROD - 0.0025
    channel = _prism_mesh(U, _U_CAP, 0.6, np.random.default_rng(5))
    channel["vertices"] = (np.array(channel["vertices"]) + [-0.1, 0, 0]).tolist()
    _rests_as_on_the_box(floor, channel)


def _rests_as_on_the_box(top, table):
    """The heavy rod's statics and a dynamic settle on ``table`` (an
    obstacle entry) equal those on a box table whose top is at ``top``
    [m]; returns the mechanism with ``table``."""
    results = []
    for ob in ({"type": "box", "center": [0.2, 0, top - 0.05], "size": [0.6, 0.2, 0.1]}, table):
        d = _heavy_rod_dict()
        d["obstacles"] = [dict(ob, name="table")]
        mech = from_robot_model(model_from_dict(d), d)
        eq = solve_equilibrium(mech)
        sim = MechanismSimulator(mech, 2e-3, 1.0)
        sim.step(n=50)
        results.append((eq.q, len(eq.contacts), sim.q))
    np.testing.assert_allclose(results[1][0], results[0][0], rtol=1e-9, atol=1e-12)
    assert results[1][1] == results[0][1] > 3
    np.testing.assert_allclose(results[1][2], results[0][2], rtol=1e-7, atol=1e-10)
    return mech


def bumpy_sphere(levels, radius=0.05):
    """A closed mesh that is not convex: an octahedron's faces split in four
    ``levels`` times (8 4^levels triangles) onto the sphere, each vertex then
    at radius (1 + 0.3 sin(3 theta) cos(2 phi)) [m]; (vertices, faces)."""
    V = [np.array(v, dtype=float) for v in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))]
    F = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]
    for _ in range(levels):
        mid, out = {}, []

        def m(a, b):
            if (min(a, b), max(a, b)) not in mid:
                c = V[a] + V[b]
                V.append(c / np.linalg.norm(c))
                mid[(min(a, b), max(a, b))] = len(V) - 1
            return mid[(min(a, b), max(a, b))]
        for a, b, c in F:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            out += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        F = out
    V = np.array(V)
    theta, phi = np.arccos(np.clip(V[:, 2], -1, 1)), np.arctan2(V[:, 1], V[:, 0])
    return V * (radius * (1 + 0.3 * np.sin(3 * theta) * np.cos(2 * phi)))[:, None], np.array(F)


def test_a_mesh_s_box_tree_finds_the_nearest_triangle_of_every_point():
    """A bumpy sphere of 2048 triangles: the signed distance, gradient and
    Hessian through its box tree (4 triangles a leaf) equal those of every
    triangle searched (one leaf), at points inside, near and far; its
    bounding sphere holds it."""
    from soft_twin_core.engine.kernels import contact as kc
    from soft_twin_core.robot.obstacles import obstacle_from_dict
    V, F = bumpy_sphere(4)
    ob = obstacle_from_dict({"name": "rock", "type": "mesh", "vertices": V.tolist(), "faces": F.tolist()}, "rock")
    assert len(ob.triangles) == 2048
    rng = np.random.default_rng(13)
    P = np.concatenate([rng.standard_normal((1500, 3)) * 0.04, rng.standard_normal((500, 3)) * 0.3])
    out = []
    for leaf in (4, 4096):
        arrays = kc.obstacle_arrays((ob,), leaf)
        assert len(arrays.node) == (1 if leaf > 2048 else 1023)
        d, n, H = np.empty(len(P)), np.empty((len(P), 3)), np.empty((len(P), 3, 3))
        kc.distance_arrays(arrays, 0, np.ascontiguousarray(P), d, n, H)
        out.append((d, n, H))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    for x, y in zip(out[0][1:], out[1][1:]):      # (a point nearest a shared edge: either face's, to round-off)
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
    assert (out[0][0] < 0).sum() > 300 and (out[0][0] > 0.05).sum() > 300
    from soft_twin_core.robot.obstacles import obstacle_placed
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
    T[:3, 3] = [0.3, -0.2, 0.1]
    V[V[:, 0] > 0, 0] *= 4                       # lopsided: the box's centre off the vertices' mean
    lop = obstacle_from_dict({"name": "lop", "type": "mesh", "vertices": V.tolist(), "faces": F.tolist()}, "lop")
    for m in (ob, lop, obstacle_placed(lop, T)):
        *c, R = kc.bounding_sphere(kc.obstacle_arrays((m,)), 0)
        world = m.triangles.reshape(-1, 3) @ m.rotation.T + m.a
        assert np.linalg.norm(world - c, axis=1).max() <= R * (1 + 1e-12)


# the real projective plane in 6 vertices and 10 triangles: closed (each edge in two faces), not orientable
_RP2 = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5], [0, 5, 1], [1, 2, 4], [2, 3, 5], [3, 4, 1], [4, 5, 2], [5, 1, 3]]


@pytest.mark.parametrize("change, message", [
    (lambda m: m.update(faces=m["faces"][:-1]), "faces: the mesh is not closed: edge"),
    (lambda m: m.update(vertices=np.random.default_rng(14).standard_normal((6, 3)).tolist(), faces=_RP2),
     r"faces\[\d\]: the faces' windings cannot agree"),
    (lambda m: m["vertices"][0].__setitem__(1, float("nan")), "vertices: expected at least 4 finite"),
    (lambda m: m["faces"][0].__setitem__(2, 8), "faces: expected at least 4 triples of vertex indices in 0..7"),
    (lambda m: m.update(vertices=m["vertices"][:3]), "vertices: expected at least 4 finite"),
])
def test_a_mesh_that_is_not_closed_or_not_orientable_is_refused_naming_the_field(change, message):
    from soft_twin_core.robot.obstacles import obstacle_from_dict
    m = dict(_cube_mesh(np.zeros(3), [0.2, 0.2, 0.2]), name="m")
    change(m)
    with pytest.raises(ModelError, match=message):
        obstacle_from_dict(m, "robot.obstacles[0]")


def test_a_rod_on_a_mesh_table_rests_as_on_the_box():
    """The heavy rod lying on a table that is a cube mesh: the statics and
    a dynamic settle equal the box table's, and the markers draw it as
    triangles."""
    from types import SimpleNamespace
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker
    from soft_twin import markers
    from soft_twin_core.twin import Twin, TwinSettings
    from soft_twin_core.viz.scene import obstacle_outline
    top = -0.0035 - R_ROD
    mech = _rests_as_on_the_box(top, _cube_mesh(np.array([0.2, 0, top - 0.05]), [0.6, 0.2, 0.1]))
    snap = Twin(mech, TwinSettings(mode="quasi_static")).outputs()
    draw, robot = markers.Markers(), SimpleNamespace(mech=mech)
    meshes = (lambda: [m for m in draw(snap, robot, Header()).markers if m.ns == "obstacle_meshes"])
    (shape,) = meshes()
    assert shape.type == Marker.TRIANGLE_LIST and shape.action == Marker.ADD and len(shape.points) == 36
    corners = np.array([[p.x, p.y, p.z] for p in shape.points])       # in the mesh's frame, placed by its pose
    assert corners[:, 2].max() + shape.pose.position.z == pytest.approx(top)
    # a mesh is sent when it changes and every MESH_REFRESH_S, not with every state (60 ms a message at 2048
    # triangles); a mesh taken away is deleted
    old = markers.MESH_REFRESH_S
    try:
        markers.MESH_REFRESH_S = 1e9
        assert meshes() == []
        markers.MESH_REFRESH_S = 0.0
        assert [m.action for m in meshes()] == [Marker.ADD]
        from dataclasses import replace
        snap = replace(snap, obstacles=())
        assert [(m.action, m.id) for m in meshes()] == [(Marker.DELETE, 0)]
    finally:
        markers.MESH_REFRESH_S = old
    outline = obstacle_outline(mech.obstacles[0], np.zeros(3), 1.0)
    assert outline.shape == (12 * 5 - 1, 3) and np.nanmax(outline[:, 2]) == pytest.approx(top)
    assert obstacle_outline(mech.obstacles[0], np.zeros(3), 1.0) is outline          # built once


def test_a_tube_its_distance_gradient_and_hessian():
    """A tube (the free space within its radius of a bent centre line, open
    at both ends): the signed distance is the radius less the distance to
    the nearest point of the polyline (brute force over a fine sampling of
    it), its gradient and Hessian central differences of it; beyond an
    open end nothing is touched."""
    path = [[0, 0, 0], [0.1, 0, 0], [0.15, 0.05, 0], [0.15, 0.15, 0.02]]
    (ob,) = obstacles_from_list([{"name": "vessel", "type": "tube", "path": path, "radius": 0.004}])
    P = np.asarray(path, float)
    fine = np.concatenate([a + np.linspace(0, 1, 2001)[:, None] * (b - a) for a, b in zip(P[:-1], P[1:])])
    rng = np.random.default_rng(11)                # its own draws: the same points in any order of the tests
    s = rng.uniform(0.05, 0.95, 12) * 3
    centre = np.array([P[int(k)] + (k % 1) * (P[int(k) + 1] - P[int(k)]) for k in s])
    p = centre + rng.normal(0, 0.002, (12, 3))
    d, n, H = signed_distance(ob, p)
    brute = 0.004 - np.min(np.linalg.norm(p[:, None] - fine[None], axis=2), axis=1)
    np.testing.assert_allclose(d, brute, atol=2e-5)
    _check_derivatives(ob, p, n, H, 1e-7, 1e-6, 1e-3)
    assert np.all(np.einsum("ij,ij->i", n, p - centre) < 0)            # the wall pushes towards the axis
    d_out, _, _ = signed_distance(ob, np.array([[-0.01, 0.0, 0.0], [0.15, 0.16, 0.02]]))
    assert np.all(d_out > 1e29)


def test_a_catheter_pushed_through_a_curved_vessel_takes_the_bend():
    """The example scenario (config/scenarios/catheter_in_vessel.yaml): the
    rod pushed through the vessel's 90-degree bend (2.5 s of the 3 s push,
    90 mm). Its tip ends in the bend's second half, and the rod stays in
    the lumen (every backbone point but the tip within the lumen's radius
    less the rod's, plus the penetration the penalty allows, 0.5 mm: the
    contact points are the midpoints of 5 mm intervals, and the tip, 2.5 mm
    beyond the last, is not checked); the wall pushes on it. Friction at
    the rod's surface twists it (its torsion: stiff, and overdamped by its
    viscosity, which the midpoint rule rings from step to step at 2 ms,
    failing Newton at 0.24 s): at dt = 2 ms and theta = 0.6 its tip is the
    midpoint rule's at 1 ms to 0.03 mm, in a fifth of the time."""
    from pathlib import Path
    from soft_twin_core.files.runs import run_mechanism_dynamics
    from soft_twin_core.files.scenario import load_scenario
    sc = load_scenario(str(Path(__file__).resolve().parents[2] / "config" / "scenarios" / "catheter_in_vessel.yaml"))
    run = run_mechanism_dynamics(sc, 2.5, 2e-3, theta=0.6, record_every=50, backbone_every=50)
    assert run.get("error") is None
    tip = np.asarray(run["tip_position"])[-1]
    assert tip[0] > 0.19 and tip[1] > 0.015          # round the bend (its centre at (0.15, 0.05)), towards +y
    vessel = sc.mech.obstacles[0]
    mech = sc.mech
    sim_pts = mechanism_contact_points(mech)
    assert sim_pts.s.max() == pytest.approx(0.12 - 0.0025)      # (midpoints: the tip's last 2.5 mm unchecked)
    pts = np.asarray(run["members"][-1]["catheter"]["positions"])[:-1]     # every 10 mm but the tip
    d, _, _ = signed_distance(vessel, pts)
    assert d.min() > 0.001 - 5e-4
    assert np.asarray(run["contact_count"])[-1] >= 2


def _strip_on_a_drum_bvp(P, L, rho, EI):
    """Large-deflection reference (our own BVP) of a strip clamped
    tangentially on top of a rigid frictionless cylinder (its centreline
    on a circle of radius rho) under a dead tip load P (downwards): the
    wrapped length a lies on the circle (curvature 1/rho, tangent angle
    s/rho, no shear, a constant tension); the free span [a, L] is an
    elastica, EI theta'' = -P cos(theta), leaving with the circle's slope
    and curvature (the moment is continuous; the shear is not: a
    concentrated reaction P cos(a/rho) at the lift-off point) and free of
    moment at the tip. Shooting on a; returns a and the tip (x, z)."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import brentq

    def shoot(a):
        def rhs(s, y):
            return [y[1], -P / EI * np.cos(y[0]), np.cos(y[0]), -np.sin(y[0])]
        y0 = [a / rho, 1 / rho, rho * np.sin(a / rho), rho * np.cos(a / rho) - rho]
        return solve_ivp(rhs, (a, L), y0, rtol=1e-12, atol=1e-14).y[:, -1]
    a = brentq(lambda a: shoot(a)[1], 0.0, L * (1 - 1e-9))
    return a, shoot(a)[2:]


def test_a_strip_clamped_on_a_drum_wraps_as_the_small_slope_and_large_deflection_solutions():
    """A strip clamped tangentially on top of a rigid frictionless
    cylinder (radius R; its centreline on the circle rho = R + r) bent
    over it by a dead tip load P (issue 27). Small slopes: the wrapped
    length has the cylinder's curvature, so the lift-off point carries
    the moment EI/rho: a = L - EI/(P rho) (for P > EI/(rho L)), tip
    deflection a^2/(2 rho) + a b/rho + P b^3/(3 EI), b = L - a. Large
    deflection: :func:`_strip_on_a_drum_bvp`. The twin's wrapped length
    is read from the contact forces: they are radial, so their horizontal
    resultant is the tension the clamp holds, P sin(a/rho) (the
    distributed pressure P sin(a/rho)/rho over the wrapped arc and the
    concentrated P cos(a/rho) at its end). Checks: on a large drum (wrap
    angle 0.05 rad) BVP and small-slope solution agree to O(slope^2)
    (0.7 % in a, 0.3 % in the tip), and the twin matches the BVP; on a
    small drum (0.53 rad of wrap; the small-slope a = 0.2 m is 3.6 times
    too long) the twin's tip within 1e-4 L of the BVP's, its wrapped
    length within 1 %, both converging as the contact stiffness grows
    (the penalty spreads the concentrated reaction over the foundation
    length (4 EI/k)^(1/4) and ramps the pressure up from the clamp)."""
    from soft_twin_core.robot.mechanism import tip_frame
    from soft_twin_core.solve.constrained import FrameLoad
    from soft_twin_core.solve.outputs import state_outputs
    L, r = 0.3, R_ROD
    EI = E * np.pi * r ** 4 / 4

    def strip(R, k):
        d = {"name": "strip", "gravity": [0, 0, 0], "segments": [{
            "name": "s", "length": L, "sections": 60, "cross_section": {"shape": "solid_circle", "radius": r},
            "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": RHO}, "free_modes": ["bending_y"]}],
            "obstacles": [{"name": "drum", "type": "capsule", "from": [0, -0.1, -R - r], "to": [0, 0.1, -R - r],
                           "radius": R, "stiffness": k}],
            "contact": {"spacing": 0.002}}
        return from_robot_model(model_from_dict(d), d)

    def twin(R, P, stiffnesses):
        q, out = None, []
        for k in stiffnesses:
            mech = strip(R, k)
            eq = solve_equilibrium(mech, point_loads=[FrameLoad(tip_frame(mech), np.array([0, 0, -P, 0, 0, 0.0]),
                                                                "world")], q_init=q, max_iterations=100)
            q, c = eq.q, eq.contacts
            assert eq.stable and len(c) > 10 and np.all(c.force[:, 1] == 0)
            tip = state_outputs(mech, eq.q, eq.lam, eq.inputs).frames[tip_frame(mech)][[0, 2], 3]
            out.append(((R + r) * np.arcsin(c.force[:, 0].sum() / P), tip))
        return out

    R = 2.0                                     # a large drum: small slopes
    rho = R + r
    P = 1.5 * EI / (rho * L)
    a_small = L - EI / (P * rho)
    b = L - a_small
    w_small = a_small ** 2 / (2 * rho) + a_small * b / rho + P * b ** 3 / (3 * EI)
    a_ref, tip_ref = _strip_on_a_drum_bvp(P, L, rho, EI)
    assert a_ref == pytest.approx(a_small, rel=0.01) and -tip_ref[1] == pytest.approx(w_small, rel=0.005)
    (a, tip), = twin(R, P, [10 * E])
    assert a == pytest.approx(a_ref, rel=5e-3)
    np.testing.assert_allclose(tip, tip_ref, atol=1e-4 * L)

    R = 0.1                                     # a small drum: half a radian of wrap
    rho = R + r
    P = 3 * EI / (rho * L)
    a_ref, tip_ref = _strip_on_a_drum_bvp(P, L, rho, EI)
    assert a_ref / rho > 0.5 and (L - EI / (P * rho)) / a_ref > 3
    runs = twin(R, P, [E, 10 * E, 100 * E])
    a_err = [abs(a / a_ref - 1) for a, _ in runs]
    tip_err = [np.abs(tip - tip_ref).max() for _, tip in runs]
    assert a_err[2] < 0.01 and a_err[0] > a_err[1] > a_err[2]
    assert tip_err[1] < 1e-4 * L and tip_err[0] > tip_err[1] > tip_err[2]


# -- an elastic rod on a capstan (Singh, J. Elasticity 151, 2022) ---------------

CAP_EI, CAP_R, CAP_LIFT = 0.0245, 0.05, 0.5     # bending stiffness [N m^2], drum radius [m], lift-off angle [rad]


def _lift_off_angle(EI, T, rho):
    """The angle between the rod's tangent where it leaves a drum (its
    centreline on a circle of radius rho) and the pull T of a long free
    span: the elastica's first integral EI k^2 / 2 = T (1 - cos(angle))
    with the drum's curvature 1/rho at lift-off (the moment is continuous)."""
    return np.arccos(1 - EI / (2 * T * rho ** 2))


def _capstan(r, stiffness, mu=0.0, pulled=False, n_wrap=60, spacing=0.002):
    """A rod (radius r, bending in its plane only, inextensible) pinned at
    its base on the drum's top tangent line, 8 elastic lengths sqrt(EI/T)
    to the left, laid half way around a drum (a capsule along y, radius
    CAP_R) and pulled back to the left at its tip by a dead load T that
    makes it leave the drum at CAP_LIFT. ``pulled``: the pin rides on a
    position-controlled slider along x. Returns (mechanism, T, rho, the
    wrapped initial guess)."""
    rho = CAP_R + r
    T = CAP_EI / (2 * (1 - np.cos(CAP_LIFT)) * rho ** 2)
    span = 8 * np.sqrt(CAP_EI / T)
    wrap = np.pi * rho + 0.04

    def seg(name, length, n):
        return {"name": name, "length": length, "sections": n,
                "cross_section": {"shape": "solid_circle", "radius": r},
                "material": {"youngs_modulus": CAP_EI / (np.pi * r ** 4 / 4), "poisson_ratio": 0.5, "density": 1000.0},
                "free_modes": ["bending_y"]}
    rod = {"name": "rod", "type": "member", "parent": "base",
           "joint": {"name": "pin", "type": "revolute", "axis": [0, 1, 0], "control": "passive"},
           "segments": [seg("a", span - 0.02, 20), seg("b", wrap, n_wrap), seg("c", span - 0.02, 20)]}
    bodies = [rod]
    if pulled:
        rod["parent"] = "slider"
        bodies.insert(0, {"name": "slider", "type": "link", "parent": "base", "mass": 0.01,
                          "inertia": [1e-6, 1e-6, 1e-6, 0, 0, 0],
                          "joint": {"name": "pull", "type": "prismatic", "axis": [1, 0, 0], "control": "position"}})
    d = {"name": "capstan", "gravity": [0, 0, 0], "base": {"position": [-span, 0, rho]}, "bodies": bodies,
         "obstacles": [{"name": "drum", "type": "capsule", "from": [0, -0.1, 0], "to": [0, 0.1, 0], "radius": CAP_R,
                        "stiffness": stiffness, "friction": mu}],
         "contact": {"spacing": spacing}}
    mech = mechanism_from_dict(d)
    tree = mech.tree
    q = tree.q0.copy()                  # straight to the drum's top, half way round it, straight on
    h = wrap / n_wrap
    k0, k1 = round(0.02 / h), round(0.02 / h) + round(np.pi * rho / h)
    for k in range(20 + k0, 20 + k1):
        q[tree.idx_q[tree.joint_index(f"rod_{k}")]] = np.pi / ((k1 - k0) * h)
    return mech, T, rho, q


def _capstan_at_rest(r, stiffnesses, **kw):
    """Frictionless statics of :func:`_capstan`, continued over the contact
    stiffnesses: [(mechanism, T, rho, Equilibrium)]."""
    from soft_twin_core.robot.mechanism import tip_frame
    from soft_twin_core.solve.constrained import FrameLoad
    out, q = [], None
    for k in stiffnesses:
        mech, T, rho, q0 = _capstan(r, k, **kw)
        load = [FrameLoad(tip_frame(mech), np.array([-T, 0, 0, 0, 0, 0.0]), "world")]
        eq = solve_equilibrium(mech, point_loads=load, q_init=q0 if q is None else q, max_iterations=200)
        q = eq.q
        assert eq.stable and len(eq.contacts) > 20
        out.append((mech, T, rho, eq))
    return out


def _wrap_angle(T, contacts):
    """The angle [rad] between the two far pulls: the tip's load (-x) and
    the pin's, the balance of the load and the contact forces (no
    gravity, at rest or sliding steadily)."""
    F = -(np.array([-T, 0.0, 0.0]) + contacts.force.sum(axis=0))
    return np.pi - np.arctan2(F[2], -F[0]), np.linalg.norm(F)


def test_an_elastic_rod_on_a_frictionless_capstan_leaves_it_where_the_elastica_says():
    """A rod wrapped on a frictionless drum and pulled at both ends by T
    (Singh, "Planar equilibria of an elastic rod wrapped around a circular
    capstan", J. Elasticity 151 (2022) 321-346, the continuous-arc case in
    its long-rod limit). A flexible filament would touch the drum over the
    whole wrap angle W between the pulls with tension T. The rod leaves
    the drum early, at the angle phi to each pull (:func:`_lift_off_angle`),
    so that it touches over W - 2 phi, with the tension T cos(phi) there
    (constant curvature: no shear), and point forces T sin(phi) at the
    ends of the contact arc. Checks: the pressure inside the arc, rho p
    = T cos(phi), within 2e-4 at the stiffest contact (2.5e-3 at a tenth);
    the normal forces' sum, 2 T sin(phi) + T cos(phi) (W - 2 phi), which
    measures the arc's extent (a shift of the contact ends by 0.01 rad
    moves it by 0.35 %), within 5e-4; the pin's pull equals the load
    (frictionless: both pulls T); the filament's answers are 12 % and
    10 % off."""
    runs = _capstan_at_rest(0.005, [5e7, 5e8, 5e9], n_wrap=100, spacing=0.001)
    errors = []
    for mech, T, rho, eq in runs:
        c = eq.contacts
        phi = _lift_off_angle(CAP_EI, T, rho)
        assert phi == pytest.approx(CAP_LIFT)
        fn = np.linalg.norm(c.force, axis=1)
        angle = np.arctan2(c.p[:, 0], c.p[:, 2])             # about y from the drum's top
        inside = np.abs(angle - np.pi / 2) < 0.3
        tension = rho * np.median(fn[inside] / mechanism_contact_points(mech).weight[c.point[inside]])
        errors.append(abs(tension / (T * np.cos(phi)) - 1))
        wrap, pin = _wrap_angle(T, c)
    assert errors[2] < 2e-4 < errors[1]                   # (the softest only starts the continuation)
    assert pin == pytest.approx(T, rel=1e-5) and abs(wrap - np.pi) < 0.05
    total = 2 * T * np.sin(phi) + T * np.cos(phi) * (wrap - 2 * phi)
    assert fn.sum() == pytest.approx(total, rel=5e-4)
    assert abs(fn.sum() / (T * wrap) - 1) > 0.09 and abs(tension / T - 1) > 0.1


def _sliding_capstan_ratio(T1, wrap, rho, r, mu):
    """The tension ratio T2 / T1 of a rod sliding over a drum (the limiting
    equilibrium of Singh 2022, sec. 6, in its long-rod limit, derived here
    for a thin rod): the rod leaves the slack side at phi1 and the tight
    side at phi2 (:func:`_lift_off_angle` at T1 and T2); point forces N_i
    = T_i sin(phi_i) at the contact's ends carry frictions mu N_i, so
    that the arc's tension starts at T1 (cos phi1 + mu sin phi1) and ends
    at T2 (cos phi2 - mu sin phi2); inside it grows as exp(lam s), where
    friction acts on the rod's surface (the drum's radius R = rho - r) and
    its moment about the centreline makes a shear r mu p:
    lam (1 + r mu lam) = mu R / rho^2 (T' = mu p R / rho, p = T / rho -
    r mu p'); over the arc rho (wrap - phi1 - phi2). The thin-rod
    approximation leaves out the point frictions' moments r mu N_i (a jump
    of the lift-off curvature by r mu N_i / EI: 0.5 % at r = 0.5 mm)."""
    from scipy.optimize import brentq
    R = rho - r
    c1 = 1 - CAP_EI / (2 * T1 * rho ** 2)
    p1 = np.arccos(c1)
    Tc1 = T1 * (c1 + mu * np.sin(p1))
    a, b = r * mu, mu * R / rho ** 2
    lam = (np.sqrt(1 + 4 * a * b) - 1) / (2 * a)

    def gap(T2):
        c2 = 1 - CAP_EI / (2 * T2 * rho ** 2)
        p2 = np.arccos(c2)
        return T2 * (c2 - mu * np.sin(p2)) - Tc1 * np.exp(lam * rho * (wrap - p1 - p2))
    return brentq(gap, T1, 10 * T1) / T1


def test_an_elastic_rod_sliding_over_a_capstan_holds_the_bending_corrected_tension_ratio():
    """The rod of the test above, its pin dragged away from the drum at
    20 mm/s by a slider while its tip holds T (mu = 0.3), after 25 ms
    held at rest (each step converging at once): it slides over the drum,
    and the pin's pull reaches a steady T2, the same in the compiled and
    the Python step. Singh (J. Elasticity
    151, 2022) generalises Euler's capstan equation T2 / T1 = exp(mu W)
    to an elastic rod; :func:`_sliding_capstan_ratio` is that limit for a
    thin rod. The twin's ratio, within 0.5 % at r = 0.5 mm (2.384 against
    2.390), where Euler's is 8 % off and Euler's with friction at the
    drum's surface 7 %; steady (the same at 0.15 and 0.2 s); every contact
    slipping at about the pull's speed (regularised Coulomb friction at
    its sliding limit)."""
    from soft_twin_core.robot.mechanism import tip_frame
    from soft_twin_core.solve.constrained import FrameLoad
    r, mu, v = 0.0005, 0.3, 0.02
    (_, T, rho, eq), = _capstan_at_rest(r, [5e8])
    mech, *_ = _capstan(r, 5e8, mu, pulled=True)
    load = [FrameLoad(tip_frame(mech), np.array([-T, 0, 0, 0, 0, 0.0]), "world")]
    runs = []
    for compiled in (True, False):
        sim = MechanismSimulator(mech, 5e-3, 1.0, q=np.concatenate([[0.0], eq.q]), tol=1e-9, compiled=compiled)
        for _ in range(5):              # held: at rest, sticking (a step's scale is the pin's effort, not the
            sim.step(positions={"pull": 0.0}, point_loads=load)      # round-off residual of the equilibrium)
            assert sim.iterations <= 3
        ratios = {}
        for i in range(1, 41):          # (the Python step starts the pull from iterates at the command)
            sim.step(positions={"pull": -v * i * 5e-3}, point_loads=load)
            if i in (30, 40):
                wrap, pin = _wrap_angle(T, sim.contacts)
                ratios[i] = pin / T
        runs.append(ratios[40])
        assert ratios[30] == pytest.approx(ratios[40], rel=1e-3)
    assert runs[1] == pytest.approx(runs[0], rel=1e-6)     # the Python step, the compiled one's reference
    ratio = runs[0]
    assert ratio == pytest.approx(_sliding_capstan_ratio(T, wrap, rho, r, mu), rel=5e-3)
    assert np.exp(mu * wrap) / ratio > 1.07 and np.exp(mu * (rho - r) / rho * wrap) / ratio > 1.06
    slip = np.linalg.norm(sim.contacts.slip, axis=1)
    assert np.all(slip > 0.8 * v) and np.all(slip < 1.1 * v)


def test_statics_from_straight_onto_a_table_gives_up_a_stalled_newton_for_the_continuation(monkeypatch):
    """The arm-on-a-table scenario (config/scenarios/tendon_arm_on_table.yaml)
    solved from the straight reference: the full Newton step goes far
    through the table and the line search creeps (steps cut to 1/512 for
    50 iterations, then the load continuation converges: 104 iterations).
    Newton now gives the stalled start up after 4 steps cut to 1/32 or
    less: the same equilibrium (to round-off) in at most 70 iterations;
    with the old rule (never give up), more than 100."""
    from soft_twin_core.files.scenario import load_scenario, run_statics
    from soft_twin_core.solve import constrained as cs
    sc = load_scenario(str(Path(__file__).resolve().parents[2] / "config" / "scenarios" / "tendon_arm_on_table.yaml"))
    new = run_statics(sc, 1)
    monkeypatch.setattr(cs, "STALL_ITERATIONS", 10 ** 9)
    old = run_statics(sc, 1)
    assert new["iterations"] <= 70 < 100 < old["iterations"], (new["iterations"], old["iterations"])
    assert np.allclose(new["tip_position"], old["tip_position"], atol=1e-12)
    assert len(new["contacts"]) == len(old["contacts"]) >= 1
