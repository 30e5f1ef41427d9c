"""Tendon-sheath friction: the capstan decay of a tendon's tension along its
routing (issue 27).

A tendon pulled in slides along its sheath; Coulomb friction with
coefficient mu lowers its tension by the capstan (Euler-Eytelwein) law
``T(s) = u exp(-mu theta(s))``, theta the angle its path has wrapped
(Euler 1762; as a tendon-sheath law e.g. Kaneko, Wada, Maekawa and Tanie,
IEEE Trans. Robot. Autom. 7(6), 1991). The references here are closed
forms: a sheath bent into a known arc or helix (the wrap angle from
geometry alone), and the arm a frictional tendon bends (an ODE in closed
form); plus finite differences of the analytic derivatives.
"""

import math
import re

import numpy as np
import pytest

from soft_twin_core.engine import forces
from soft_twin_core.engine.forces import actuation_matrix, actuator_arrays, tendon_tension, wrap_rate
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import ModelError
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs

E, RADIUS, LENGTH = 2.0e6, 0.01, 0.4
EI = E * math.pi * RADIUS ** 4 / 4


def _rod(n, actuators, free_modes=("bending_z",), viscosity=0.0):
    d = {"name": "rod", "gravity": [0.0, 0.0, 0.0], "segments": [{
        "name": "s", "length": LENGTH, "sections": n,
        "cross_section": {"shape": "solid_circle", "radius": RADIUS},
        "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000.0, "viscosity": viscosity},
        "free_modes": list(free_modes)}], "actuators": actuators}
    return from_robot_model(model_from_dict(d), d)


def _posed(tree, q):
    ws = Workspace(tree)
    z = np.zeros(tree.nv)
    passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, dtype=float), z, z, 0)
    return ws


@pytest.mark.parametrize("mu", [0.1, 0.5])
def test_a_tendon_in_a_sheath_bent_into_an_arc_keeps_exp_minus_mu_theta_of_its_tension(mu):
    """Capstan: a sheath bent into an arc of angle theta = kappa L (uniform
    curvature kappa, in either bending plane and obliquely) passes
    exp(-mu theta) of the pull to the termination, to 1e-6; half-way along,
    exp(-mu theta / 2). The wrap angle does not depend on the tendon's
    offset (its tangent stays the backbone's without torsion)."""
    tendons = [{"name": "a", "routing": "straight", "offset": [0.006, 0.0], "friction": mu},
               {"name": "b", "routing": "straight", "offset": [0.003, -0.005], "friction": mu}]
    mech = _rod(6, tendons, ("bending_y", "bending_z"))
    tree = mech.tree
    for ky, kz in ((0.0, 4.0), (3.0, 0.0), (-2.0, 2.5)):
        ws = _posed(tree, np.tile([ky, kz], 6))
        theta = math.hypot(ky, kz) * LENGTH
        for k in range(2):
            T = tendon_tension(tree, ws, k, 7.0, [LENGTH / 2, LENGTH])
            assert T == pytest.approx(7.0 * np.exp(-mu * theta * np.array([0.5, 1.0])), rel=1e-6)


def test_a_helical_tendon_on_a_straight_arm_wraps_by_the_helix_curvature():
    """A helix of radius r and wave number k around a straight backbone:
    the tangent turns at |t'| = r k^2 / sqrt(1 + r^2 k^2) per unit backbone
    length (the helix's curvature r k^2/(1 + r^2 k^2) times its speed
    sqrt(1 + r^2 k^2)): this checks the d'' part of the wrap rate."""
    r, turns = 0.006, 5.0
    k = 2 * math.pi * turns
    mech = _rod(5, [{"name": "h", "routing": "helical", "radius": r, "turns_per_meter": turns, "phase": 0.3,
                     "friction": 0.2, "start": 0.05, "end": 0.35}], ("bending_y", "bending_z"))
    ws = _posed(mech.tree, np.zeros(mech.tree.nv))
    theta = r * k * k / math.sqrt(1 + (r * k) ** 2) * 0.30
    assert tendon_tension(mech.tree, ws, 0, 1.0)[0] == pytest.approx(math.exp(-0.2 * theta), rel=1e-6)
    assert tendon_tension(mech.tree, ws, 0, 1.0, 0.05)[0] == 1.0      # nothing wrapped at its start


def test_the_wrap_rate_gradient_is_its_derivative():
    """d wrap_rate / d xi (analytic) against central differences, for
    straight, converging and helical offsets at random strains."""
    rng = np.random.default_rng(4)
    g = np.empty(6)
    for _ in range(20):
        xi = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]) + 0.3 * rng.standard_normal(6) * [0.1, 0.1, 0.1, 10, 10, 10]
        d = np.array([0.0, *(0.01 * rng.standard_normal(2))])
        dd = np.array([0.0, *(0.05 * rng.standard_normal(2))])
        ddd = np.array([0.0, *(2.0 * rng.standard_normal(2))])
        forces.wrap_rate_gradient(xi, d, dd, ddd, g)
        h = 1e-6
        fd = [(wrap_rate(xi + h * e, d, dd, ddd) - wrap_rate(xi - h * e, d, dd, ddd)) / (2 * h) for e in np.eye(6)]
        assert np.allclose(g, fd, rtol=1e-6, atol=1e-7)


def test_a_frictional_tendon_bends_the_arm_by_the_capstan_ode_and_converges_at_second_order():
    """A planar inextensible arm (bending only, no gravity) pulled by a
    straight tendon at offset d: the distal part's balance at s gives the
    bending moment T(s) d, so kappa = T(s) d / EI = a exp(-mu theta) with
    a = u d / EI, and theta' = kappa (the tendon's tangent is the
    backbone's): exp(mu theta) = 1 + mu a s, so the tip turns by
    ln(1 + mu a L)/mu (a L without friction) -- at any deflection. PCS
    sections converge to it at second order; the statics Newton keeps its
    quadratic convergence (its tangent has the friction's coupling)."""
    u, d, mu = 20.0, 0.005, 0.3
    a = u * d / EI
    ref = math.log1p(mu * a * LENGTH) / mu
    errors = []
    for n in (4, 8, 16, 32):
        mech = _rod(n, [{"name": "t", "routing": "straight", "offset": [d, 0.0], "friction": mu}])
        eq = solve_equilibrium(mech, [u])
        tip = eq.q.sum() * LENGTH / n
        errors.append(abs(tip - ref) / ref)
        assert eq.iterations <= 6
    assert ref == pytest.approx(1.892, abs=1e-3) and a * LENGTH == pytest.approx(2.546, abs=1e-3)
    assert errors[-1] < 3e-5
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(rates > 1.9), rates
    # the tension reaching the termination is exp(-mu * tip angle) of the pull
    ws = _posed(mech.tree, eq.q)
    assert tendon_tension(mech.tree, ws, 0, u)[0] == pytest.approx(u * math.exp(-mu * tip), rel=1e-9)
    # the internal wrench carries the tendon's tension across each cut: the
    # bending moment T(s) d and the axial force -T(s), T from the closed form
    mo = state_outputs(mech, eq.q, eq.lam, eq.inputs).members[0]
    inner = mo.s < LENGTH
    T_ref = u / (1 + mu * a * mo.s[inner])                   # u exp(-mu theta(s))
    assert mo.internal_wrench[inner, 5] == pytest.approx(T_ref * d, rel=2e-5)
    assert mo.internal_wrench[inner, 0] == pytest.approx(-T_ref, rel=2e-5)
    # the generalised force stays linear in the pull: B(q) u is the actuation force
    B = actuation_matrix(mech.tree, ws, actuator_arrays(mech.tree), eq.q)
    tau = np.zeros(mech.tree.nv)
    act = actuator_arrays(mech.tree)
    forces.actuation_pass(ws.m, ws.w, act, np.ascontiguousarray(act.unit @ [u]), tau)
    assert np.allclose(B @ [u], tau, rtol=1e-13, atol=0)


def test_dynamics_settles_on_the_frictional_statics():
    """The dynamics' residual has the same capstan tension: a damped arm
    pulled by a frictional tendon comes to rest on the statics' shape."""
    tendon = [{"name": "t", "routing": "straight", "offset": [0.005, 0.0], "friction": 0.4}]
    mech = _rod(4, tendon, viscosity=2e5)
    eq = solve_equilibrium(mech, [5.0])
    sim = MechanismSimulator(mech, dt=0.01, theta=1.0)
    sim.step(actuation=[5.0], n=300)
    assert np.allclose(sim.q, eq.q, rtol=1e-4, atol=1e-6)
    free = solve_equilibrium(_rod(4, [dict(tendon[0], friction=0.0)]), [5.0])
    assert np.abs(free.q - eq.q).max() > 0.05 * np.abs(free.q).max()     # friction matters here


@pytest.mark.parametrize("actuator, message", [
    ({"name": "t", "offset": [0.005, 0.0], "friction": -0.1}, "actuators[0].friction: must be >= 0"),
    ({"name": "t", "offset": [0.005, 0.0], "friction": "lots"}, "actuators[0].friction"),
    ({"name": "c", "type": "chamber", "area": 1e-4, "offset": [0.005, 0.0], "friction": 0.2},
     "actuators[0].friction: sheath friction (0.2) applies to a tendon"),
    ({"name": "t", "offset": [0.005, 0.0], "model": "point_moment", "friction": 0.2},
     "not to a tendon of the point_moment model"),
])
def test_bad_friction_is_refused_naming_the_field(actuator, message):
    with pytest.raises(ModelError, match=re.escape(message)):
        _rod(2, [actuator])

