"""Fourth-order Magnus kinematics of a variable-strain rod in statics and
dynamics (soft_twin_core.solve.magnus4, issue 28): its map's derivatives
against finite differences; with a constant field it is the engine's PCS
rod; its second-order twin (:class:`LinearField`) steps as the robot's own
simulator does; the error falls at fourth order in the sections under
gravity, in the natural frequencies and in a transient, where the
second-order step falls at second; energy is kept at the midpoint rule's
order; SoRoMoX's variable-strain model is matched in statics,
frequencies and a release."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve import magnus4 as m4
from soft_twin_core.solve.constrained import MechanismSimulator, free_problem, make_inputs
from soft_twin_core.solve.strain_basis import legendre_basis, solve_reduced

L = 0.5


def _arm(n, modes="all", gravity=True, **kw):
    d = benchmark_cantilever_dict(n, modes, length=L, **kw)
    if not gravity:
        d["gravity"] = [0.0, 0.0, 0.0]
    return from_robot_model(model_from_dict(d))


def _fd(f, x, e=1e-6):
    return np.column_stack([(f(x + e * u) - f(x - e * u)) / (2 * e) for u in np.eye(len(x))])


def test_the_maps_jacobian_convective_term_and_statics_tangent_are_its_derivatives():
    """J = dq/dz, ``Jdot zdot`` = d/dt (J) zdot and the statics tangent
    against central differences, at a random state of a Legendre order-2
    field on 4 sections, with a tip force and gravity."""
    f = m4.Magnus4Field(_arm(4), 2)
    assert (f.nz, f.tree.nv, f.tree.n_joints) == (18, 6 * 9, 9 + 8)     # 2n + 1 intervals, 2n Gauss points
    rng = np.random.default_rng(5)
    z = 0.3 * rng.standard_normal(f.nz) / (1 + np.arange(f.nz) % 3)
    zd = rng.standard_normal(f.nz)
    fd = _fd(f.q, z)
    assert np.abs(f.jacobian(z) - fd).max() < 1e-8 * np.abs(fd).max()
    jd = ((f.jacobian(z + 1e-6 * zd) - f.jacobian(z - 1e-6 * zd)) / 2e-6) @ zd
    assert np.abs(f.convective(z, zd) - jd).max() < 1e-8 * np.abs(jd).max() and np.abs(jd).max() > 1e-3
    pb = f.problem(Loads(point=(PointLoad(L, (0.0, 0.02, -0.05, 0.0, 0.0, 0.0)),), gravity=True))
    fd = _fd(lambda x: f.residual(pb, x), z)
    assert np.abs(f.tangent(pb, z) - fd).max() < 1e-7 * np.abs(fd).max()


def test_a_constant_field_is_the_engines_pcs_rod():
    """Order 0 (a constant strain over the rod, no commutator): the Gauss
    points' masses are the engine's sections' own quadrature points, so
    mass matrix, inverse dynamics, energy, statics and 0.3 s of motion are
    the PCS rod's (:class:`LinearField` of the constant basis) to 1e-12,
    with the commutator or commutator-free."""
    arm = _arm(6)
    pcs = m4.LinearField(arm, legendre_basis(arm, 0))
    rng = np.random.default_rng(3)
    z, zd, zdd = 0.5 * rng.standard_normal((3, 6)) * [[1], [2], [2]]
    for cf in (False, True):
        _check_the_same_rod((m4.commutator_free_field if cf else m4.Magnus4Field)(arm, 0), pcs, arm, z, zd, zdd)


def _check_the_same_rod(g, pcs, arm, z, zd, zdd):
    assert np.abs(m4.mass_matrix(g, z) - m4.mass_matrix(pcs, z)).max() < 1e-12 * np.abs(m4.mass_matrix(pcs, z)).max()
    t_g, t_p = m4.inverse_dynamics(g, z, zd, zdd), m4.inverse_dynamics(pcs, z, zd, zdd)
    assert np.abs(t_g - t_p).max() < 1e-12 * np.abs(t_p).max()
    assert abs(m4.energy(g, z, zd) - m4.energy(pcs, z, zd)) < 1e-12 * abs(m4.energy(pcs, z, zd))
    q2, z2, _ = solve_reduced(free_problem(arm, make_inputs(arm)), pcs.B, arm.tree.q0, load_steps=2)
    _, z4, _ = m4.solve_magnus4(g, load_steps=2)
    assert np.abs(z4 - z2).max() < 1e-10 and np.abs(g.tip(z4) - pcs.tip(z2)).max() < 1e-12
    (zg, vg, _, _), (zp, vp, _, _) = (m4.simulate(f, 0.3, 0.01) for f in (g, pcs))
    assert np.abs(zg - zp).max() < 1e-12 * np.abs(zp).max() and np.abs(vg - vp).max() < 1e-12 * np.abs(vp).max()


def test_the_second_order_twin_steps_as_the_robots_simulator_does():
    """:func:`simulate` with :class:`LinearField` (Legendre order 3 on the
    sections' midpoints) against :class:`MechanismSimulator` on the robot
    file's ``strain_basis`` (the compiled reduced step), 0.3 s from rest
    under gravity at 10 ms: the same theta-method, to the Newton
    tolerance."""
    d = benchmark_cantilever_dict(8, "all", length=L)
    arm = from_robot_model(model_from_dict(d))
    d["segments"][0]["strain_basis"] = {"type": "legendre", "order": 3}
    robot = from_robot_model(model_from_dict(copy.deepcopy(d)))
    f = m4.LinearField(arm, legendre_basis(arm, 3))
    assert np.array_equal(robot.basis, f.B)
    sim = MechanismSimulator(robot, dt=0.01)
    sim.step(n=30)
    z, zd, _, _ = m4.simulate(f, 0.3, 0.01)
    assert np.abs(f.q(z) - sim.q).max() < 1e-8 * np.abs(sim.q).max()
    assert np.abs(f.B @ zd - sim.v).max() < 1e-6 * np.abs(sim.v).max()


def test_the_error_falls_at_fourth_order_in_the_sections_under_gravity_in_frequencies_and_in_motion():
    """Legendre order 3, every mode, on 4, 8, 16, 32 sections: the same
    field, so the successive differences x_n - x_2n are the
    discretisation's error alone. Fourth-order step with the mass at the
    Gauss points: from 8-16 to 16-32 they fall 15.0-18.3x in the tip under
    gravity (statics), the first three natural frequencies and the tip's
    largest difference over 0.5 s of swing from rest at 10 ms (from 4-8,
    7.7-22.7x: coarser is not yet asymptotic); under gravity still 15.5x
    from 16-32 to 32-64. The second-order step (midpoint strain, mass on
    the arcs) falls 4.0-4.5x, and on 16 sections its tip is 900x (statics)
    and 255x (swing) further from its 32 sections'; extrapolated, its
    statics meets the fourth-order step's to 2e-6 L (the same field's
    limit). With the masses on the intervals' arcs instead of the Gauss
    points (checked on a copy) the statics' differences stop falling at
    fourth order from 16 sections on (1.3e-7, 1.1e-7, 3.4e-8 m: ratios 1.2
    and 3.3), the arcs' second-order error. The commutator-free step (a
    constant B) falls 14.7-19.6x from 8-16 to 16-32 and meets the
    commutator's limit to 7e-8 L (statics) and 3.4e-7 L (swing)."""
    res = {}
    for n in (4, 8, 16, 32):
        arm = _arm(n)
        for kind, f in (("m4", m4.Magnus4Field(arm, 3)), ("cf", m4.commutator_free_field(arm, 3)),
                        ("m2", m4.LinearField(arm, legendre_basis(arm, 3)))):
            if kind != "m2":
                z = m4.solve_magnus4(f, load_steps=4)[1]
            else:
                z = solve_reduced(free_problem(arm, make_inputs(arm)), f.B, arm.tree.q0, load_steps=4)[1]
            tips = m4.simulate(f, 0.5, 0.01, observe=lambda z, zd: f.tip(z)[:3, 3])[3]
            res[kind, n] = (f.tip(z)[:3, 3], m4.modal_frequencies(f, 6)[[0, 2, 4]], np.array(tips))
    for kind, (lo, hi), first in (("m4", (13.0, 20.0), (5.0, 30.0)), ("cf", (13.0, 24.0), (5.0, 30.0)),
                                  ("m2", (3.5, 5.0), (3.5, 7.0))):
        d = np.array([[np.linalg.norm(res[kind, n][0] - res[kind, 2 * n][0]) / L,
                       *np.abs(res[kind, n][1] / res[kind, 2 * n][1] - 1),
                       np.linalg.norm(res[kind, n][2] - res[kind, 2 * n][2], axis=1).max() / L] for n in (4, 8, 16)])
        ratio = d[:-1] / d[1:]
        assert np.all((lo < ratio[1]) & (ratio[1] < hi)) and np.all((first[0] < ratio[0]) & (ratio[0] < first[1])), \
            (kind, d, ratio)
        res[kind] = d[-1]
    assert np.all(res["m2"][[0, 4]] > [500, 150] * res["m4"][[0, 4]]), (res["m2"], res["m4"])
    tips = [res["m4", 16][0], res["m4", 32][0]]
    f = m4.Magnus4Field(_arm(64), 3)
    tips.append(f.tip(m4.solve_magnus4(f, load_steps=4)[1])[:3, 3])
    r = np.linalg.norm(tips[0] - tips[1]) / np.linalg.norm(tips[1] - tips[2])
    assert 14.0 < r < 18.0, r                      # still fourth order from 16-32 to 32-64 under gravity
    # the commutator-free step: the same limit (its map linear, q = q0 + B z with a constant B)
    assert np.linalg.norm(res["cf", 32][0] - res["m4", 32][0]) / L < 2e-7
    assert np.linalg.norm(res["cf", 32][2] - res["m4", 32][2], axis=1).max() / L < 1e-6
    cf = m4.commutator_free_field(_arm(4), 3)
    z = np.random.default_rng(2).standard_normal(cf.nz)
    assert np.array_equal(cf.jacobian(z), cf.B) and np.allclose(cf.q(z), cf.q0 + cf.B @ z, atol=1e-15)
    limit2 = res["m2", 32][0] + (res["m2", 32][0] - res["m2", 16][0]) / 3      # its h^2 error extrapolated
    assert np.linalg.norm(res["m4", 32][0] - limit2) / L < 1e-5, (res["m4", 32][0], limit2)   # the same field


def test_a_tip_force_converges_at_fourth_order_to_the_continuum_reference(monkeypatch):
    """Legendre order 6, every mode, the cantilever under a transverse tip
    force (0.05 N: the tip 0.21 m down), against the continuum
    boundary-value reference (an independent solver): 8.9e-6, 1.9e-7,
    1.0e-8 L at 4, 8, 16 sections, 16-47x a halving (the field's energy
    integrated exactly; with the Gauss points' own quadrature it was
    3.0e-5, 1.9e-6, 1.2e-7 L). The midpoint step falls 4x (5.8e-3 ...
    3.6e-4 L; order n - 1 on 4 sections). The commutator-free step (two
    exponentials linear in the field): 7.5e-6, 1.0e-7, 5.1e-9 L. With the
    commutator's sign flipped, or the two exponentials in the other order,
    either is second order again (3.8x, 3.9x): the sign is the body-frame
    ODE's."""
    from soft_twin_core.reference.continuum import solve_cosserat_statics
    F = (0.0, 0.0, -0.05)
    loads = Loads(point=(PointLoad(L, F + (0.0, 0.0, 0.0)),), gravity=False)
    p_ref = solve_cosserat_statics(_arm(1).tree.joints[0].section.K, L, tip_force_world=F,
                                   load_steps=8).tip_pose()[:3, 3]

    def errors(kind):
        out = []
        for n in (4, 8, 16):
            arm = _arm(n)
            if kind == "m2":
                f = m4.LinearField(arm, legendre_basis(arm, min(6, n - 1)))
                z = solve_reduced(free_problem(arm, make_inputs(arm, loads=loads)), f.B, arm.tree.q0, load_steps=4)[1]
            else:
                f = (m4.commutator_free_field if kind == "cf" else m4.Magnus4Field)(arm, 6)
                z = m4.solve_magnus4(f, loads, load_steps=4)[1]
            out.append(np.linalg.norm(f.tip(z)[:3, 3] - p_ref) / L)
        return np.array(out)
    e4, cf, e2 = errors("m4"), errors("cf"), errors("m2")
    assert np.all(e4[:-1] / e4[1:] > 15.0) and e4[-1] < 2e-8, e4
    assert np.all(cf[:-1] / cf[1:] > 15.0) and cf[-1] < 1e-8, cf
    assert np.all((3.5 < e2[:-1] / e2[1:]) & (e2[:-1] / e2[1:] < 4.5)), e2
    monkeypatch.setattr(m4, "C4", -m4.C4)
    monkeypatch.setattr(m4, "CF_WEIGHTS", m4.CF_WEIGHTS[::-1])
    for flipped in (errors("m4"), errors("cf")):
        assert np.all(flipped[:-1] / flipped[1:] < 4.5) and flipped[-1] > 1e-4, flipped


def test_the_45_degree_bend_in_3d_converges_at_fourth_order():
    """The 45-degree bend (pre-curved, every mode free, 600 out of its plane
    at the tip: bending and torsion coupled, where the commutator is all
    three-dimensional), Legendre order 6, against the continuum
    boundary-value reference: 1.4e-5, 4.5e-7, 2.5e-8 R on 4, 8, 16
    sections (31x, 18x), where the midpoint step is 1.7e-3 and 4.1e-4 R
    off on 8 and 16 (4x)."""
    import warnings
    from soft_twin_core.reference.continuum import solve_cosserat_statics
    from soft_twin_core.robot.model import BEND45_RADIUS, bend45_dict

    def bend(n):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")          # 78.5 "m": the classic problem has no units
            return from_robot_model(model_from_dict(bend45_dict(n)))
    R = BEND45_RADIUS
    loads = Loads(point=(PointLoad(R * np.pi / 4, (0.0, 0.0, 600.0, 0.0, 0.0, 0.0)),), gravity=False)
    p_ref = solve_cosserat_statics(bend(1).tree.joints[0].section.K, R * np.pi / 4, f0=(1, 0, 0, 0, 0, 1 / R),
                                   tip_force_world=(0.0, 0.0, 600.0)).tip_pose()[:3, 3]
    e4, e2 = [], []
    for n in (4, 8, 16):
        arm = bend(n)
        f = m4.Magnus4Field(arm, 6)
        e4.append(np.linalg.norm(f.tip(m4.solve_magnus4(f, loads, load_steps=8)[1])[:3, 3] - p_ref) / R)
        if n > 4:
            g = m4.LinearField(arm, legendre_basis(arm, 6))
            z = solve_reduced(free_problem(arm, make_inputs(arm, loads=loads)), g.B, arm.tree.q0, load_steps=8)[1]
            e2.append(np.linalg.norm(g.tip(z)[:3, 3] - p_ref) / R)
    assert e4[0] / e4[1] > 14 and e4[1] / e4[2] > 14 and e4[2] < 5e-8, e4
    assert 3.5 < e2[0] / e2[1] < 4.5 and e2[1] > 3e-4, e2


def test_energy_is_kept_at_the_midpoint_rules_order():
    """No damping, gravity on: 0.4 s of swing from the straight rod at rest
    (Legendre order 2, 4 sections). The energy's largest change over the
    steps falls 4x a halving of h (second order: 3.7x, 4.3x) and is 3.5e-5
    of the potential energy released at 5 ms; implicit Euler (theta = 1) loses 10 % and
    more (the check can fail)."""
    f = m4.Magnus4Field(_arm(4), 2)
    e0 = m4.energy(f, np.zeros(f.nz), np.zeros(f.nz))
    drift = {}
    for theta, h in ((0.5, 0.02), (0.5, 0.01), (0.5, 0.005), (1.0, 0.01)):
        z, zd, es = np.zeros(f.nz), np.zeros(f.nz), []
        for _ in range(int(round(0.4 / h))):
            z, zd, _, _ = m4.simulate(f, h, h, z, zd, theta=theta)
            es.append(m4.energy(f, z, zd))
        exchanged = e0 - m4.energy(f, z, np.zeros(f.nz))          # the potential energy released
        drift[theta, h] = np.abs(np.array(es) - e0).max() / exchanged
    r = drift[0.5, 0.02] / drift[0.5, 0.01], drift[0.5, 0.01] / drift[0.5, 0.005]
    assert all(3.0 < x < 5.5 for x in r), drift
    assert drift[0.5, 0.005] < 1e-4 and drift[1.0, 0.01] > 0.1, drift


def test_it_matches_soromoxs_variable_strain_model_without_extrapolation():
    """SoRoMoX's GVS cantilever (its values stored by
    ``benchmarks/soromox_gvs.py``, extrapolated from 16 and 32 Gauss points
    as the fourth-order method it is), every mode Legendre of order p.
    Under gravity (0.45 m down), on 64 sections: 3.8e-8 to 8.9e-8 L at
    orders 1, 3, 5, where neighbouring orders differ by 1.7e-3 L or more
    (with the mass on the arcs it was 1.7e-7 to 7.4e-7). The lowest six
    natural frequencies on 64 sections: to 4.4e-7 without extrapolation,
    where SoRoMoX's own 32 Gauss points are up to 6.7e-6 from its
    extrapolation (the second-order step needs 64 and 128 sections and an
    extrapolation for 2e-7)."""
    data = json.loads((Path(__file__).parents[1] / "data" / "soromox_gvs_cantilever.json").read_text())
    assert data["model"]["basis"] == "legendre" and data["model"]["strains"] == "all six"
    tips = {(r["order"], r["gauss_points"]): np.array(r["tip_m"]) for r in data["results"]}
    freqs = {(r["order"], r["gauss_points"]): np.array(r["frequencies_hz"]) for r in data["results"]}
    geo = {"length": data["model"]["length_m"], "radius": data["model"]["radius_m"]}
    arm = from_robot_model(model_from_dict(benchmark_cantilever_dict(64, "all", **geo)))
    free = from_robot_model(model_from_dict({**benchmark_cantilever_dict(64, "all", **geo), "gravity": [0, 0, 0]}))
    for p in (1, 3, 5):
        ref = tips[p, 32] + (tips[p, 32] - tips[p, 16]) / 15
        f = m4.Magnus4Field(arm, p)
        tip = f.tip(m4.solve_magnus4(f, load_steps=8)[1])[:3, 3]
        assert np.linalg.norm(tip - ref) / L < 2e-7, (p, tip, ref)
        ref = freqs[p, 32] + (freqs[p, 32] - freqs[p, 16]) / 15
        assert np.abs(m4.modal_frequencies(m4.Magnus4Field(free, p), 6) / ref - 1).max() < 6e-7, p
    assert np.linalg.norm(tips[5, 32] - tips[3, 32]) / L > 1e-3 and tip[2] < -0.45


def test_a_release_matches_soromoxs_variable_strain_dynamics():
    """The cantilever released straight under gravity, 0.3 s, every mode
    Legendre of order p, against SoRoMoX's GVS model (its tips at 0.1, 0.2
    and 0.3 s stored by ``benchmarks/soromox_gvs_dynamics.py``: Tsit5 at
    0.1 ms, 16 and 32 Gauss points extrapolated as the fourth-order method
    it is; its 16 points are 1.9e-5 and 5.5e-5 L from that). Here 16
    sections (32 Gauss points). Order 1, the midpoint rule's h^2 extrapolated
    from 1 and 0.5 ms: within 6.6e-6 L at all three times. Order 3 at 0.5
    ms: 2.3e-5 L (our 16 sections' own error in a swing is about 1.7e-5 L,
    ``benchmarks/magnus4_dynamics.py``). The tip falls 0.43-0.44 m. The
    second-order step on 16 sections is 3.8e-4 and 1.7e-3 L off, the
    fourth-order step with the commutator's sign flipped 3.3e-4 and 1.2e-3
    L (checked)."""
    data = json.loads((Path(__file__).parents[1] / "data" / "soromox_gvs_release.json").read_text())
    assert data["model"]["basis"] == "legendre" and data["model"]["strains"] == "all six"
    peer = {(r["order"], r["gauss_points"]): np.array(r["tips_m"]) for r in data["results"]}
    assert data["results"][0]["times_s"] == [0.1, 0.2, 0.3]

    def tips(f, dt):
        out = np.array(m4.simulate(f, 0.3, dt, observe=lambda z, zd: f.tip(z)[:3, 3])[3])
        return out[[int(round(t / dt)) - 1 for t in (0.1, 0.2, 0.3)]]
    arm = _arm(16)
    for p, bound in ((1, 1.5e-5), (3, 4e-5)):
        ref = peer[p, 32] + (peer[p, 32] - peer[p, 16]) / 15
        f = m4.Magnus4Field(arm, p)
        fine = tips(f, 5e-4)
        ours = fine + (fine - tips(f, 1e-3)) / 3 if p == 1 else fine
        assert np.linalg.norm(ours - ref, axis=1).max() / L < bound, (p, ours, ref)
    assert ref[-1][2] < -0.44


def test_bad_input_is_refused_naming_it():
    """An order outside 0..12, more functions than Gauss points, a member
    without every mode free, a tree that is not a rod; a duration that is
    not whole steps, theta outside [1/2, 1], a step that is not positive, a
    start of the wrong size or not finite: ValueError naming the field."""
    with pytest.raises(ValueError, match=r"order: expected an integer in \[0, 12\]"):
        m4.Magnus4Field(_arm(4), -1)
    with pytest.raises(ValueError, match="member 'backbone' has 8 Gauss points for the basis's 9 functions"):
        m4.Magnus4Field(_arm(4), 8)
    with pytest.raises(ValueError, match="every strain mode free"):
        m4.Magnus4Field(_arm(4, "bending"), 2)
    with pytest.raises(ValueError, match="expected a rod"):
        m4.Magnus4Field(load_mechanism("pan_tilt_arm"), 2)
    f = m4.Magnus4Field(_arm(2), 1)
    with pytest.raises(ValueError, match="duration: expected a whole number of steps"):
        m4.simulate(f, 0.015, 0.01)
    with pytest.raises(ValueError, match=r"theta: expected a value in \[0.5, 1\]"):
        m4.simulate(f, 0.02, 0.01, theta=0.4)
    with pytest.raises(ValueError, match="h: expected a positive time step"):
        m4.simulate(f, 0.02, -0.01)
    with pytest.raises(ValueError, match="z0: expected 12 finite values"):
        m4.simulate(f, 0.02, 0.01, np.zeros(3))
    with pytest.raises(ValueError, match="zd0: expected 12 finite values"):
        m4.simulate(f, 0.02, 0.01, None, np.full(12, np.nan))
