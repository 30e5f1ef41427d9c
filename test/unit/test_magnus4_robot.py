"""The fourth-order Magnus step through the robot file (``strain_basis:
{..., magnus: 4}``, soft_twin_core.robot.soft_chain, issue 28): the
robot's segment is the study's commutator-free field
(soft_twin_core.solve.magnus4) to round-off; the engine's elastic field
(one energy over a segment's sections) gives the forces and derivatives
of its definition; the error falls at fourth order in the sections through
the robot's own solvers (statics, the compiled step, a closed chain,
tendons, chambers and sheath friction reading the field), where the
midpoint step falls at second; the actuators' tangent is their forces'
derivative; the compiled
closed-chain and contact steps agree with the Python KKT step on such
segments; the filter's and the planner's derivatives are their steps'
and solves'; bad input is refused, naming the field."""

import copy

import numpy as np
import pytest

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import from_robot_model, is_tree_file, load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import (ModelError, benchmark_cantilever_dict, find_file, model_from_dict,
                                        read_yaml_file)
from soft_twin_core.solve import magnus4 as m4
from soft_twin_core.solve.constrained import MechanismSimulator, dense_stiffness_damping, solve_equilibrium

L = 0.5


def _cantilever(n, magnus=4, order=3, viscosity=None):
    d = benchmark_cantilever_dict(n, "all", length=L)
    if viscosity is not None:
        d["segments"][0]["material"]["viscosity"] = viscosity
    pcs = from_robot_model(model_from_dict(copy.deepcopy(d)))
    d["segments"][0]["strain_basis"] = {"type": "legendre", "order": order, "magnus": magnus}
    return pcs, from_robot_model(model_from_dict(d))


def _file(name, sections=None, order=3, magnus=4):
    """The robot file ``name`` with every segment on Legendre ``order``
    (at most what its sections carry) with the ``magnus`` step, and
    ``sections`` a segment when given."""
    path = find_file(name, "robots")
    d = read_yaml_file(path)
    tree = is_tree_file(d)
    segments = [s for b in d["bodies"] if b.get("type") == "member" for s in b["segments"]] if tree \
        else d["segments"]
    for seg in segments:
        if sections is not None:
            seg["sections"] = sections
        cap = 2 * int(seg.get("sections", 1)) - 1 if magnus == 4 else int(seg.get("sections", 1)) - 1
        seg["strain_basis"] = {"type": "legendre", "order": min(order, cap), "magnus": magnus}
    return mechanism_from_dict(d, str(path.parent)) if tree else from_robot_model(model_from_dict(d), d,
                                                                                  str(path.parent))


def _point(mech, q, member=0):
    """The position of a member's end at q."""
    ws = Workspace(mech.tree)
    return alg.forward_kinematics(mech.tree, ws, q)[1][mech.members[member].joints[-1]][:3, 3].copy()


def _differences(xs):
    """Successive differences max |x_n - x_2n| and their ratios."""
    d = [np.abs(a - b).max() for a, b in zip(xs[:-1], xs[1:])]
    return d, [a / b for a, b in zip(d[:-1], d[1:])]


def test_the_robot_files_fourth_order_segment_is_the_studys_commutator_free_field():
    """The cantilever, Legendre 3 on 8 sections: the same B, field energy
    and mass matrix as :func:`magnus4.commutator_free_field`, the same
    equilibrium under gravity (solve_equilibrium against the study's
    Newton), and the same 0.3 s of motion (MechanismSimulator's compiled
    step against the study's Python step), to the solvers' tolerances."""
    pcs, mech = _cantilever(8)
    study = m4.commutator_free_field(pcs, 3)
    B = mech.basis
    assert B.shape == (6 * (4 * 8 + 2), 24) and mech.tree.n_joints == 4 * 8 + 2
    assert np.array_equal(B, study.B)
    K, _ = dense_stiffness_damping(mech.tree)
    assert np.abs(B.T @ K @ B - study.K_z).max() < 1e-13 * np.abs(study.K_z).max()
    z = 0.1 * np.random.default_rng(1).standard_normal(24)
    Mz = m4.mass_matrix(study, z)
    assert np.abs(B.T @ alg.crba(mech.tree, Workspace(mech.tree), study.q(z)) @ B - Mz).max() < 1e-13 * np.abs(Mz).max()
    assert np.abs(mech.tree.mass_and_size[0] - pcs.tree.mass_and_size[0]) < 1e-15      # the Gauss weights' sum
    q_study, _, _ = m4.solve_magnus4(study)
    assert np.abs(solve_equilibrium(mech).q - q_study).max() < 1e-10
    sim = MechanismSimulator(mech, dt=0.01)
    sim.step(n=30)
    z, zd, _, _ = m4.simulate(study, 0.3, 0.01)
    assert np.abs(study.q(z) - sim.q).max() < 1e-10 * np.abs(sim.q).max()
    assert np.abs(study.B @ zd - sim.v).max() < 1e-8 * np.abs(sim.v).max()


def test_the_elastic_fields_forces_and_derivatives_are_its_definition():
    """With viscosity: the engine's joint forces on a fourth-order segment
    are ``P^T (K_z z + D_z zdot)`` with z = P (q - q0) (the field's energy
    replacing the sections' own, which are zero), and RNEA's derivatives
    (the field's blocks among them) equal central differences."""
    _, mech = _cantilever(4, viscosity=3.0e4)
    tree = mech.tree
    (field,) = tree.elastic_fields
    ws = Workspace(tree)
    rng = np.random.default_rng(3)
    B = mech.basis
    q = tree.q0 + B @ (0.2 * rng.standard_normal(B.shape[1]))
    v, a = rng.standard_normal(tree.nv), rng.standard_normal(tree.nv)
    z, zd = field.P @ (q - tree.q0), field.P @ v
    elastic = alg.rnea(tree, ws, q, v, a, gravity=np.zeros(3)).copy() - alg.rnea(tree, ws, q, v, a,
                                                                                 gravity=np.zeros(3), elastic=False)
    expect = field.P.T @ (field.K @ z + field.D @ zd)
    assert np.abs(field.D).max() > 0 and np.abs(elastic - expect).max() < 1e-12 * np.abs(expect).max()
    assert np.all(tree.arrays.Kb == 0) and np.all(tree.arrays.Db == 0)
    dq, dv = (x.copy() for x in alg.rnea_derivatives(tree, ws, q, v, a, tree.gravity))
    for wrt, D in ((0, dq), (1, dv)):
        fd = np.empty_like(D)
        for k in range(tree.nv):
            e = 1e-6 * np.eye(tree.nv)[k]
            x = [q, v]
            plus, minus = [y.copy() for y in x], [y.copy() for y in x]
            plus[wrt] += e
            minus[wrt] -= e
            fd[:, k] = (alg.rnea(tree, ws, *plus, a).copy() - alg.rnea(tree, ws, *minus, a)) / 2e-6
        assert np.abs(D - fd).max() < 1e-6 * np.abs(fd).max()


def test_the_error_falls_at_fourth_order_through_the_robots_solvers():
    """Legendre 3 on 4, 8, 16, 32 sections a segment (the same field, so
    the successive differences are the discretisation's alone):

    - the cantilever's tip under gravity (solve_equilibrium) and after a
      0.3 s swing from rest at 10 ms (the compiled reduced step): 22.4,
      18.8 and 9.6, 12.8 a halving with ``magnus: 4``; 4.1 and 4.3 with
      the midpoint step, whose difference on 16-32 sections is 2400x
      (statics) and 100x (swing) larger;
    - the fixed-fixed beam's reactions at its two clamps (a closed chain,
      the KKT Newton in z) under gravity: 18.8, 17.3 against 3.5, 3.9.
    """
    tips, swings = {2: [], 4: []}, {2: [], 4: []}
    for magnus in (2, 4):
        for n in (4, 8, 16, 32):
            _, mech = _cantilever(n, magnus)
            tips[magnus].append(_point(mech, solve_equilibrium(mech).q))
            sim = MechanismSimulator(mech, 0.01)
            sim.step(n=30)
            swings[magnus].append(_point(mech, sim.q))
    (d4, r4), (d2, r2) = _differences(tips[4]), _differences(tips[2])
    assert min(r4[1:]) > 15 and max(r2) < 4.5 and d2[-1] > 1000 * d4[-1]
    (d4, r4), (d2, r2) = _differences(swings[4]), _differences(swings[2])
    assert r4[-1] > 11 and max(r2) < 4.5 and d2[-1] > 50 * d4[-1]
    reactions = {2: [], 4: []}
    for magnus in (2, 4):
        for n in (4, 8, 16, 32):
            mech = _file("fixed_fixed_beam", n, magnus=magnus)
            reactions[magnus].append(solve_equilibrium(mech).lam)
    (_, r4), (_, r2) = _differences(reactions[4]), _differences(reactions[2])
    assert min(r4) > 15 and max(r2) < 4.5


def _actuated_arm(n, magnus, end=0.45, friction=0.0, chamber=False):
    """The GVS tendon arm (three segments) on Legendre 3 with the ``magnus``
    step, n sections a segment; its first tendon ending at ``end`` [m]
    (with sheath ``friction``), or replaced by a chamber (``chamber``)."""
    d = read_yaml_file(find_file("gvs_arm", "robots"))
    for seg in d["segments"]:
        seg["sections"] = n
        seg["strain_basis"] = {"type": "legendre", "order": 3, "magnus": magnus}
    d["actuators"][0].update(end=end, friction=friction)
    if chamber:
        d["actuators"][0] = {"name": "c1", "type": "chamber", "area": 4.0e-5, "offset": [0.005, 0.0], "end": end}
    return from_robot_model(model_from_dict(d), d)


@pytest.mark.parametrize("kw, u, fourth, second", [
    (dict(), [2.0, 0.0, 1.0, 0.0], (15.9, 16.0), 4.0),                 # tendons to the segments' ends
    (dict(end=0.37), [2.0, 0.0, 1.0, 0.0], (15.4, 15.8), 4.1),         # a tendon ending inside an interval
    (dict(end=0.41, chamber=True), [2e4, 0.0, 1.0, 0.0], (15.9, 16.0), 4.0),      # a chamber [Pa]
    (dict(friction=0.2), [2.0, 0.0, 1.0, 0.0], (15.9, 16.0), 4.0),     # sheath friction: the wrap angle too
])
def test_tendons_and_chambers_on_fourth_order_segments(kw, u, fourth, second):
    """The GVS arm's tip under its actuators (Legendre 3; 4, 8, 16, 32
    sections a segment): their quadrature reads the field at the field
    pairs' Gauss points (a cubic through two pairs' where an actuator ends
    inside an interval), so the tip falls at fourth order with ``magnus:
    4`` (the ratios in ``fourth`` from 4-8 to 16-32) and at second with the
    midpoint step."""
    tips = {2: [], 4: []}
    for magnus in (2, 4):
        for n in (4, 8, 16, 32):
            mech = _actuated_arm(n, magnus, **kw)
            tips[magnus].append(_point(mech, solve_equilibrium(mech, actuation=u).q))
    (d4, r4), (d2, r2) = _differences(tips[4]), _differences(tips[2])
    assert min(r4) > 14 and max(abs(r / second - 1) for r in r2) < 0.1 and d2[-1] > 1e4 * d4[-1]


@pytest.mark.parametrize("kw", [dict(end=0.37, friction=0.3), dict(end=0.41, chamber=True)])
def test_the_actuators_tangent_on_fourth_order_segments_is_their_forces_derivative(kw):
    """On the ``magnus: 4`` arm (3 sections a segment), at a bent state:
    the compiled actuation tangent (the field pairs' blocks, a tendon's end
    inside an interval, sheath friction's wrap angle) equals central
    differences of the compiled actuation forces."""
    from soft_twin_core.engine.forces import actuation_pass, actuation_tangent_pass, actuator_arrays
    from soft_twin_core.engine.kernels import passes
    mech = _actuated_arm(3, 4, **kw)
    tree = mech.tree
    ws, act = Workspace(tree), actuator_arrays(tree)
    assert act.mixed.shape[1] == 4 and np.any(act.mixed[:, 2] >= 0) and np.any(act.mix[:, 1] != 0)
    coef = np.ascontiguousarray(act.unit @ np.array([3.0e4 if kw.get("chamber") else 3.0, 1.0, 2.0, 0.5]))
    zeros = np.zeros(tree.nv)
    q = tree.q0 + mech.basis @ (2.0 * np.random.default_rng(4).standard_normal(mech.basis.shape[1]))

    def forces(x):
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(x), zeros, zeros, 0)
        out = np.zeros(tree.nv)
        actuation_pass(ws.m, ws.w, act, coef, out)
        return out
    forces(q)
    K = np.zeros((tree.nv, tree.nv))
    actuation_tangent_pass(ws.m, ws.w, act, coef, K)
    fd = np.column_stack([(forces(q + 1e-6 * e) - forces(q - 1e-6 * e)) / 2e-6 for e in np.eye(tree.nv)])
    assert np.abs(fd).max() > 0 and np.abs(-K - fd).max() < 1e-6 * np.abs(fd).max()


@pytest.mark.parametrize("name, inputs, steps, kernel", [
    ("planar_parallel_robot", dict(point_loads="platform"), 100, "closed"),       # a loop's rows
    ("catheter_in_vessel", dict(), 100, "contact"),        # a prescribed base's clamp and contacts
])
def test_closed_chains_and_contact_on_fourth_order_segments_compiled_as_in_the_python_kkt_step(name, inputs, steps,
                                                                                             kernel):
    """The compiled closed-chain and contact steps (the Galerkin inverse,
    the field's energy in the engine's residual and matrix) against the
    Python KKT step in z: the same trajectory, the velocities on the basis."""
    from soft_twin_core.solve.constrained import FrameLoad
    mech = _file(name, order=2)
    B = mech.basis
    if inputs.get("point_loads") == "platform":
        inputs = {"point_loads": (FrameLoad("platform", np.array([2.0, 0.0, -3.0, 0.0, 0.0, 0.0]), "world"),)}
    out = []
    for compiled in (True, False):
        sim = MechanismSimulator(mech, 2e-3, 0.5, tol=1e-12, constraint_tol=1e-12, max_iterations=60,
                                 compiled=compiled)
        assert (sim._use_closed_step if kernel == "closed" else sim._use_compiled_step) == compiled
        sim.step(n=steps, **inputs)
        w = np.linalg.lstsq(B, sim.v, rcond=None)[0]
        assert np.abs(B @ w - sim.v).max() <= 1e-10 * np.abs(sim.v).max()
        out.append((sim.q.copy(), sim.v.copy()))
    (q1, v1), (q2, v2) = out
    assert np.abs(q1 - mech.tree.q0).max() > 1e-3
    assert np.abs(q1 - q2).max() < 1e-8 and np.abs(v1 - v2).max() < 1e-6 * np.abs(v2).max()


def test_the_filters_and_the_planners_derivatives_on_fourth_order_segments():
    """The tracked arm (Legendre 1, ``magnus: 4``): the filter's analytic
    process Jacobian equals central differences of its step
    (test_gvs_robot's check); the pan-tilt arm's planner sensitivity (the
    tool's motion per joint command and tension) equals central
    differences of its statics."""
    from test_gvs_robot import assert_gvs_linearisation
    from soft_twin_core.engine.loads import Loads, PointLoad
    from soft_twin_core.estimation import ekf as es
    from soft_twin_core.estimation import sensors as sn
    from soft_twin_core.planning import planner as pl
    mech = _file("tracked_arm", 4, order=1)
    assert mech.tree.elastic_fields
    u = np.array([12.0, 2.0, 6.0, 1.0])
    w = np.array([0.3, -0.2, -0.5, 0.01, 0.02, -0.015])
    eq = solve_equilibrium(mech, u, loads=Loads(point=(PointLoad(0.4, tuple(w)),)))
    ekf = es.EKF(mech, [sn.PoseSensor("em", 1e-3, 0.01, s=0.4)], 0.01, wrench="wrench", actuation=u, q_init=eq.q)
    assert_gvs_linearisation(ekf, eq.q, w, u)

    arm = _file("pan_tilt_arm", 4, order=2)
    s = pl.TipSolver(arm, pl.PlanOptions(frame="tool"))
    x = np.array([0.3, -0.2, 0.5, 0.1, 0.2, 0.05])
    g, S = s.frame_motion(s.statics.solve(x, None), x)

    def pose(x):
        return s.statics.solve(x, None).pose
    fd = np.empty_like(S)
    for k in range(x.size):
        e = 1e-6 * np.eye(x.size)[k]
        gp, gm = pose(x + e), pose(x - e)
        fd[:3, k] = (gp[:3, 3] - gm[:3, 3]) / 2e-6
        fd[3:, k] = lie.log_so3(gp[:3, :3] @ gm[:3, :3].T) / 2e-6
    assert np.abs(S - fd).max() <= 1e-6 * np.abs(fd).max()


@pytest.mark.parametrize("basis, message", [
    ({"type": "legendre", "order": 3, "magnus": 3}, r"segments\[0\].strain_basis.magnus: expected 2"),
    ({"type": "legendre", "order": 3, "magnus": "4"}, r"segments\[0\].strain_basis.magnus: expected 2"),
    ({"type": "fem_linear", "elements": 2, "magnus": True}, r"segments\[0\].strain_basis.magnus: expected 2"),
    ({"type": "legendre", "order": 8, "magnus": 4}, r"segments\[0\].strain_basis: 4 sections have 8 Gauss points"),
])
def test_bad_magnus_options_are_refused_naming_the_field(basis, message):
    d = benchmark_cantilever_dict(4, "all", length=L)
    d["segments"][0]["strain_basis"] = basis
    with pytest.raises(ModelError, match=message):
        from_robot_model(model_from_dict(d))


def test_the_cayley_map_is_refused_for_the_fourth_order_step():
    d = benchmark_cantilever_dict(4, "all", length=L)
    d["kinematic_map"] = "cayley"
    d["segments"][0]["strain_basis"] = {"type": "legendre", "order": 2, "magnus": 4}
    with pytest.raises(ModelError, match="kinematic_map must be 'exponential'"):
        from_robot_model(model_from_dict(d))
    assert load_mechanism(find_file("gvs_arm", "robots")).tree.elastic_fields == ()


def test_calibrations_sensitivities_on_fourth_order_segments():
    """Calibration of the tracked arm with ``magnus: 4`` (Legendre 1, 4
    sections a segment: 18 engine sections each): every Young's modulus
    covers its own segment's engine sections (the members' segment names,
    not their section counts), and the analytic sensitivities of the
    moduli and tendon offsets equal central differences."""
    from test_calibration import ALL, _markers, assert_sensitivities
    from soft_twin_core.estimation import calibration as cal
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for seg in d["segments"]:
        seg["material"]["youngs_modulus"] = float(seg["material"]["youngs_modulus"])
        seg["sections"] = 4
        seg["strain_basis"] = {"type": "legendre", "order": 1, "magnus": 4}
    U = np.array([[12.0, 0.0, 6.0, 0.0], [0.0, 9.0, 0.0, 14.0], [5.0, 0.0, 0.0, 7.0]])
    rec = cal.record_static_sweep(model_from_dict(copy.deepcopy(d)), _markers(), U, np.random.default_rng(1))
    pb = cal.Problem(d, _markers(), rec, ALL)
    mech = from_robot_model(model_from_dict(copy.deepcopy(d)))
    assert [int(pb.rows_of[k].sum()) for k in ("proximal", "distal")] == [18 * 3, 18 * 3]     # 3 free modes
    assert not np.any(pb.rows_of["proximal"] & pb.rows_of["distal"]) and mech.tree.nv == 36 * 3
    assert_sensitivities(pb, pb.theta0 + np.array([3e6, -2e6, 4e-4, -3e-4, 2e-4, 5e-4]), 1e-6)


def test_energy_is_kept_at_the_midpoint_rules_order_on_fourth_order_segments():
    """No damping: the cantilever (``magnus: 4``, 4 sections) released
    straight under gravity for 0.5 s by the robot's simulator (implicit
    midpoint): the largest change of kinetic + elastic (the field's) +
    gravity energy falls 3.8 and 4.1x a halving of dt, 1.1e-4 of the energy
    released at 10 ms."""
    _, mech = _cantilever(4)
    drifts = []
    for h in (0.01, 0.005, 0.0025):
        sim = MechanismSimulator(mech, h, tol=1e-12, max_iterations=60)
        E0, drift, released = sum(sim.energy()), 0.0, 0.0
        for _ in range(int(round(0.5 / h))):
            sim.step()
            T, V = sim.energy()
            drift, released = max(drift, abs(T + V - E0)), max(released, E0 - V)
        drifts.append(drift / released)
    assert drifts[0] < 2e-4 and all(3.5 < a / b < 4.5 for a, b in zip(drifts[:-1], drifts[1:]))


@pytest.mark.parametrize("basis", [
    {"kind": "fem_cubic", "elements": 3},             # element ends inside the sections
    {"kind": "fem_linear", "elements": 5},
    {"kind": "chebyshev", "orders": (4, 2, 3)},       # per-mode orders
])
def test_the_fields_energy_is_its_integral(basis):
    """:func:`soft_chain.field_energy` (Gauss-Legendre on every piece
    between the sections' and the elements' ends) against the midpoint
    rule on 4000 points (its error 1e-7 here), over four sections of
    different lengths and stiffnesses, three free modes."""
    from soft_twin_core.robot.soft_chain import field_energy
    from soft_twin_core.robot.strain_bases import StrainBasis, field_rows
    b = StrainBasis(magnus=4, **basis)
    rng = np.random.default_rng(0)
    lengths = np.array([0.1, 0.15, 0.12, 0.13])
    K = [np.diag(rng.uniform(1.0, 2.0, 6)) for _ in lengths]
    modes = np.array([3, 4, 5])
    Kz, Dz = field_energy(b, lengths, K, [0.1 * k for k in K], modes)
    n, L = 4000, lengths.sum()
    x = (np.arange(n) + 0.5) / n
    Phi = field_rows(b, x[:, None], np.ones((n, 1)), 3).reshape(n, 3, -1)
    owner = np.searchsorted(np.cumsum(lengths) / L, x)
    ref = sum(L / n * P.T @ K[k][np.ix_(modes, modes)] @ P for P, k in zip(Phi, owner))
    assert np.abs(Kz - ref).max() < 2e-6 * np.abs(ref).max() and np.allclose(Dz, 0.1 * Kz, rtol=1e-12, atol=0)
