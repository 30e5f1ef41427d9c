"""Variable-strain segments chosen in the robot file (``strain_basis``,
soft_twin_core.robot.strain_bases): the robot's coordinates z with
``q = q0 + B z``, and statics, dynamics, the filter, the planner and
calibration in them, with joints, closed chains, contact and moving bases.

Independent references: one PCS section of the segment's length (a
constant basis), the reduced statics of soft_twin_core.solve.strain_basis
(a basis built by another function, solved by another Newton), the
projected eigenproblem's natural frequency, energy conservation at the
integrator's order, central differences of the filter's step and of
calibration's residuals, the PCS robot itself under a full basis (a change
of coordinates), and the definition of the reduced equilibrium (B^T R = 0)."""

import numpy as np
import pytest

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import ModelError
from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model, mechanism_from_dict
from soft_twin_core.robot.model import benchmark_cantilever_dict, find_file, model_from_dict, read_yaml_file
from soft_twin_core.solve.constrained import MechanismSimulator, free_problem, make_inputs, solve_equilibrium
from soft_twin_core.solve.strain_basis import fem_basis, legendre_basis, modal_frequencies, solve_reduced


def _cantilever(n, basis=None, free="bending", **extra):
    d = benchmark_cantilever_dict(n, free)
    d.update(extra)
    if basis is not None:
        d["segments"][0]["strain_basis"] = basis
    return from_robot_model(model_from_dict(d))


# ------------------------------------------------------------- the robot file

def test_the_basis_columns_are_the_families_functions_at_the_sections_midpoints():
    """B's columns: Legendre P_j(2x - 1), Chebyshev T_j, monomials x^j at the
    midpoints x_k = (k + 1/2)/n, per free mode (rows interleaved by mode);
    the FEM families equal solve.strain_basis's (another function)."""
    n = 10
    x = (np.arange(n) + 0.5) / n
    cases = {"legendre": [np.ones(n), 2 * x - 1, 0.5 * (3 * (2 * x - 1) ** 2 - 1)],
             "chebyshev": [np.ones(n), 2 * x - 1, 2 * (2 * x - 1) ** 2 - 1],
             "monomial": [np.ones(n), x, x ** 2]}
    for kind, funcs in cases.items():
        B = _cantilever(n, {"type": kind, "order": 2}).basis
        assert B.shape == (2 * n, 6)
        for a in range(2):                    # bending_y, bending_z
            for j, f in enumerate(funcs):
                col = np.zeros(2 * n)
                col[a::2] = f
                assert np.abs(B[:, 3 * a + j] - col).max() < 1e-14, (kind, a, j)
    ref = _cantilever(n)
    for kind, degree in (("fem_linear", 1), ("fem_cubic", 3)):
        B = _cantilever(12, {"type": kind, "elements": 2}).basis
        assert np.abs(B - fem_basis(_cantilever(12), 2, degree)).max() < 1e-14
    assert ref.basis is None and ref.coordinate_names == ()


def test_per_mode_orders_and_coordinate_names():
    mech = _cantilever(8, {"type": "legendre", "order": {"bending_y": 3, "bending_z": 1}})
    assert mech.basis.shape == (16, 6)
    assert mech.coordinate_names == tuple(f"backbone/rod/bending_y/{j}" for j in range(4)) + (
        "backbone/rod/bending_z/0", "backbone/rod/bending_z/1")


@pytest.mark.parametrize("basis, field", [
    ({"type": "spline", "order": 2}, "strain_basis.type"),
    ({"type": "legendre", "order": -1}, "strain_basis.order"),
    ({"type": "legendre", "order": 13}, "strain_basis.order"),
    ({"type": "legendre", "order": 2.0}, "strain_basis.order"),
    ({"type": "legendre", "order": {"torsion": 1, "bending_y": 1, "bending_z": 1}}, "strain_basis.order.torsion"),
    ({"type": "legendre", "order": {"bending_y": 1}}, "strain_basis.order"),
    ({"type": "fem_cubic", "elements": 0}, "strain_basis.elements"),
    ({"type": "fem_linear", "order": 2}, "strain_basis.order"),
    ({"type": "legendre", "order": 9}, "strain_basis: 8 sections cannot carry 10"),
    ("legendre", "strain_basis: expected a mapping"),
])
def test_bad_bases_are_refused_naming_the_field(basis, field):
    with pytest.raises(ModelError, match=f"segments\\[0\\].{field}"):
        _cantilever(8, basis)


def test_a_mask_that_frees_nothing_is_refused():
    with pytest.raises(ModelError, match=r"segments\[0\].free_modes: at least one free mode"):
        _cantilever(8, {"type": "legendre", "order": 1}, free=[])


def _tree_dict(control="effort"):
    return {"name": "gvs_tree", "bodies": [
        {"name": "pan", "type": "link", "mass": 0.1, "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0],
         "joint": {"name": "pan", "type": "revolute", "axis": [0, 0, 1], "control": control}},
        {"name": "arm", "type": "member", "parent": "pan",
         "segments": [{**benchmark_cantilever_dict(8, "bending")["segments"][0],
                       "strain_basis": {"type": "legendre", "order": 2}},
                      {**benchmark_cantilever_dict(4, "bending")["segments"][0], "name": "pcs", "length": 0.1}]}]}


def test_a_tree_members_segment_takes_a_basis_the_rest_keeps_its_coordinates():
    mech = mechanism_from_dict(_tree_dict())
    B, tree = mech.basis, mech.tree
    assert B.shape == (1 + 16 + 8, 1 + 6 + 8)
    assert mech.coordinate_names[0] == "pan/0" and mech.coordinate_names[1] == "arm/rod/bending_y/0"
    assert mech.coordinate_names[-1].startswith("arm_")         # the PCS segment's joints: their own coordinates
    assert np.all(B[0] == np.eye(15)[0]) and np.abs(B[17:, 7:] - np.eye(8)).max() == 0
    assert np.abs(B[1:17, 1:7] - legendre_basis(_cantilever(8), 2)).max() < 1e-14
    assert tree.nv == 25


def test_a_free_flying_gvs_member_moves_as_the_pcs_one():
    """A soft arm on a floating base (quaternion coordinates: identity
    columns of the basis, moving on their group), bent and spun in zero
    gravity: with a full basis the reduced step flies, turns and bends as
    the engine's O(n) step, and the strains stay on the basis."""
    out = []
    for order in (None, 5):
        seg = {**benchmark_cantilever_dict(6, "bending_torsion")["segments"][0], "length": 0.3}
        if order is not None:
            seg["strain_basis"] = {"type": "legendre", "order": order}
        mech = mechanism_from_dict({"name": "flyer", "gravity": [0, 0, 0], "base": {"motion": "floating"},
                                    "bodies": [{"name": "arm", "type": "member", "segments": [seg]}]})
        q, v = mech.tree.q0.copy(), np.zeros(mech.tree.nv)
        q[7:] += 2.0 * (np.arange(len(q) - 7) % 3 == 1)            # bent: 2 rad/m about y
        v[3:6] = [0.5, -1.0, 2.0]                                   # spinning
        sim = MechanismSimulator(mech, 1e-4, 0.5, q=q, v=v, tol=1e-12, max_iterations=60)
        sim.step(n=200)
        out.append(sim.q.copy())
    assert np.abs(out[0][3:7] - [0, 0, 0, 1]).max() > 1e-2          # it turned
    assert np.abs(out[0] - out[1]).max() < 1e-8


# --------------------------------------------------- a constant basis is one section

@pytest.fixture(scope="module")
def one_and_six():
    """One PCS section, and six sections with the order-0 basis (precurved,
    all six modes free, exact quadrature: 12 Gauss points a section)."""
    def mech(n, basis):
        d = benchmark_cantilever_dict(n, "all")
        d["quadrature_points"] = 12
        d["segments"][0]["reference_strain"] = [1, 0, 0, 0.3, 0.5, -0.2]
        if basis:
            d["segments"][0]["strain_basis"] = {"type": "legendre", "order": 0}
        return from_robot_model(model_from_dict(d))
    return mech(1, False), mech(6, True)


def test_a_constant_basis_is_one_pcs_section_fk_m_rnea_statics(one_and_six):
    one, six = one_and_six
    B = six.basis
    rng = np.random.default_rng(1)
    w1, w6 = Workspace(one.tree), Workspace(six.tree)
    for _ in range(3):
        z = rng.normal(size=6) * np.array([0.01, 0.02, 0.02, 0.5, 1.0, 1.0])
        v, a = rng.normal(size=6), rng.normal(size=6)
        q1, q6 = one.tree.q0 + z, six.tree.q0 + B @ z
        T1 = alg.forward_kinematics(one.tree, w1, q1)[1][-1].copy()
        assert np.abs(T1 - alg.forward_kinematics(six.tree, w6, q6)[1][-1]).max() < 1e-12
        M1 = alg.crba(one.tree, w1, q1).copy()
        assert np.abs(M1 - B.T @ alg.crba(six.tree, w6, q6) @ B).max() < 1e-12 * np.abs(M1).max()
        t1 = alg.rnea(one.tree, w1, q1, v, a).copy()
        assert np.abs(t1 - B.T @ alg.rnea(six.tree, w6, q6, B @ v, B @ a)).max() < 1e-12 * np.abs(t1).max()
    e1, e6 = solve_equilibrium(one, tol=1e-13), solve_equilibrium(six, tol=1e-13)
    assert np.abs(e1.q - one.tree.q0).max() > 0.1                    # it sags
    assert np.abs(six.tree.q0 + B @ (e1.q - one.tree.q0) - e6.q).max() < 1e-12


def test_a_constant_basis_is_one_pcs_section_for_1_s_of_dynamics(one_and_six):
    """Released under gravity, no damping, 400 steps of the implicit
    midpoint rule: the reduced step and the engine's O(n) step agree to
    their Newton tolerance (1e-13), amplified over the run."""
    one, six = one_and_six
    out = []
    for mech in (one, six):
        sim = MechanismSimulator(mech, 2.5e-3, 0.5, tol=1e-13, max_iterations=60)
        sim.step(n=400)
        out.append((sim.q - mech.tree.q0, sim.v))
    z6 = np.linalg.lstsq(six.basis, out[1][0], rcond=None)[0]
    assert np.abs(out[0][0]).max() > 0.3
    assert np.abs(out[0][0] - z6).max() < 1e-10
    assert np.abs(six.basis @ z6 - out[1][0]).max() < 1e-13          # the state stays on the basis


# ----------------------------------------------------------------- statics

@pytest.mark.parametrize("basis, columns", [
    ({"type": "legendre", "order": 3}, lambda m: legendre_basis(m, 3)),
    ({"type": "fem_cubic", "elements": 2}, lambda m: fem_basis(m, 2, 3)),
])
def test_statics_in_the_robot_files_basis_is_the_reduced_galerkin_solve(basis, columns):
    """solve_equilibrium on the robot with a basis equals solve_reduced
    (solve.strain_basis: its own basis function and Newton) on the PCS
    robot, under gravity and a tip force."""
    from soft_twin_core.engine.loads import Loads, PointLoad
    loads = Loads(point=(PointLoad(0.5, (0.0, 0.02, 0.05, 0.0, 0.0, 0.0)),))
    gvs, pcs = _cantilever(24, basis), _cantilever(24)
    eq = solve_equilibrium(gvs, loads=loads)
    q_ref, _, _ = solve_reduced(free_problem(pcs, make_inputs(pcs, loads=loads)), columns(pcs), pcs.tree.q0,
                                load_steps=4)
    assert np.abs(eq.q - pcs.tree.q0).max() > 0.5
    assert np.abs(eq.q - q_ref).max() < 1e-9
    assert eq.stable


# ----------------------------------------------------------------- dynamics

def _energy(mech, q, v):
    from soft_twin_core.solve.constrained import dense_stiffness_damping
    K, _ = dense_stiffness_damping(mech.tree)
    M = alg.crba(mech.tree, Workspace(mech.tree), q)
    dq = q - mech.tree.q0
    return 0.5 * v @ M @ v + 0.5 * dq @ K @ dq


def test_free_vibration_at_the_projected_eigenfrequency_and_energy_at_second_order():
    """No gravity, no damping: the cantilever, Legendre order 3 on 24
    sections, released from a small bend in its first mode shape (an
    eigenvector of ``B^T K B x = w^2 B^T M B x``), vibrates at the lowest
    frequency of modal_frequencies (that eigen-solve) to 0.2 %; with large
    swings the midpoint rule's energy error falls about 4x a halving of dt."""
    from scipy.linalg import eigh
    from soft_twin_core.engine.loads import Loads, PointLoad
    from soft_twin_core.solve.constrained import dense_stiffness_damping
    gvs = _cantilever(24, {"type": "legendre", "order": 3}, gravity=[0.0, 0.0, 0.0])
    B = gvs.basis
    f1 = modal_frequencies(_cantilever(24, gravity=[0.0, 0.0, 0.0]), B, count=1)[0]
    K, _ = dense_stiffness_damping(gvs.tree)
    M = alg.crba(gvs.tree, Workspace(gvs.tree), gvs.tree.q0)
    shape = eigh(B.T @ K @ B, B.T @ M @ B)[1][:, 0]
    dq = B @ shape
    dq *= 1e-3 / np.abs(dq).max()
    dt = 1.0 / f1 / 200
    sim = MechanismSimulator(gvs, dt, 0.5, q=gvs.tree.q0 + dq, tol=1e-12)
    k = int(np.argmax(np.abs(dq)))
    y = []
    for _ in range(600):                   # three periods
        sim.step()
        y.append(sim.q[k] - gvs.tree.q0[k])
    y = np.array(y)
    up = np.flatnonzero((y[:-1] < 0) & (y[1:] >= 0))
    t_up = (up + y[up] / (y[up] - y[up + 1])) * dt   # upward zero crossings, interpolated
    period = np.diff(t_up).mean()
    assert len(t_up) >= 2 and abs(1.0 / period / f1 - 1) < 2e-3, (1 / period, f1)
    q_big = solve_equilibrium(gvs, loads=Loads(point=(PointLoad(0.5, (0, 0, 5e-3, 0, 0, 0)),))).q
    drift = []
    for h in (2e-3, 1e-3):
        sim = MechanismSimulator(gvs, h, 0.5, q=q_big, tol=1e-12)
        e0 = _energy(gvs, sim.q, sim.v)
        worst = 0.0
        for _ in range(int(round(0.2 / h))):
            sim.step()
            worst = max(worst, abs(_energy(gvs, sim.q, sim.v) - e0))
        drift.append(worst / e0)
    assert drift[0] < 1e-2 and 3.0 < drift[0] / drift[1] < 5.0, drift


def test_a_start_off_the_basis_is_refused():
    gvs = _cantilever(8, {"type": "legendre", "order": 1})
    q = gvs.tree.q0.copy()
    q[5] += 0.3
    with pytest.raises(ValueError, match="q: not a configuration of the robot's variable-strain segments"):
        MechanismSimulator(gvs, 1e-3, q=q)


# ----------------------------------------------------------------- the filter

def _tracked_arm(sections, order=None):
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for seg in d["segments"]:
        seg["sections"] = sections
        if order is not None:
            seg["strain_basis"] = {"type": "legendre", "order": order}
    return from_robot_model(model_from_dict(d))


def assert_gvs_linearisation(ekf, q_eq, extra, u):
    """At rest at q_eq (with ``extra``: the offsets and the wrench) the
    filter's step keeps the state, and its analytic Phi and Gamma_u equal
    central differences of that step, in the errors' layout (z, its rate,
    extra), the state mapped through the basis."""
    mech = ekf.mech
    B, q0, n, nz = mech.basis, mech.tree.q0, ekf.n, ekf.nr
    z0 = np.linalg.lstsq(B, q_eq - q0, rcond=None)[0]
    x0 = np.concatenate([z0, np.zeros(nz), extra])
    ekf.x = np.concatenate([q_eq, np.zeros(n), extra])
    ekf.lam = ekf._rest_multipliers()
    lam0 = ekf.lam.copy()

    def step(x, u):
        ekf.x = np.concatenate([q0 + B @ x[:nz], B @ x[nz:2 * nz], x[2 * nz:]])
        ekf.a, ekf.lam = np.zeros(n), lam0.copy()
        ekf.predict(u)
        return np.concatenate([np.linalg.lstsq(B, ekf.x[:n] - q0, rcond=None)[0],
                               np.linalg.lstsq(B, ekf.x[n:2 * n], rcond=None)[0], ekf.x[2 * n:]])
    assert np.abs(step(x0, u) - x0).max() < 1e-8
    ekf.x, ekf.lam = np.concatenate([q_eq, np.zeros(n), extra]), lam0.copy()
    Phi, Gamma = ekf.linearisation()
    h, hu = 1e-6, 1e-4
    Phi_fd = np.stack([(step(x0 + h * e, u) - step(x0 - h * e, u)) / (2 * h) for e in np.eye(len(x0))], axis=1)
    assert np.abs(Phi - Phi_fd).max() <= 1e-5 * np.abs(Phi_fd).max()
    if len(u):
        Gamma_fd = np.stack([(step(x0, u + hu * e) - step(x0, u - hu * e)) / (2 * hu) for e in np.eye(len(u))],
                            axis=1)
        assert np.abs(Gamma - Gamma_fd).max() <= 1e-5 * np.abs(Gamma_fd).max()


def test_the_filters_process_jacobian_in_the_basis_is_its_steps_linearisation():
    """At an equilibrium under tendons and a tip wrench, the filter's
    analytic Phi and Gamma_u (the Galerkin projection of the engine's
    derivatives) equal central differences of its mean step, whose state
    has 2 nz + 6 entries in the errors (nz = 12 coordinates for 48
    strains)."""
    from soft_twin_core.engine.loads import Loads, PointLoad
    mech = _tracked_arm(8, 1)
    u = np.array([12.0, 2.0, 6.0, 1.0])
    w = np.array([0.3, -0.2, -0.5, 0.01, 0.02, -0.015])
    eq = solve_equilibrium(mech, u, loads=Loads(point=(PointLoad(0.4, tuple(w)),)))
    sensors = [sn.PoseSensor("em", 1e-3, 0.01, s=0.4)]
    ekf = es.EKF(mech, sensors, 0.01, wrench="wrench", actuation=u, q_init=eq.q)
    assert ekf.P.shape == (2 * 12 + 6, 2 * 12 + 6)
    assert_gvs_linearisation(ekf, eq.q, w, u)


def test_the_filters_process_jacobian_with_rigid_joints_and_a_closed_chain_in_a_basis():
    """The same check on the pan-tilt arm on springs (its rigid joints
    identity columns of the basis) and on the parallel robot (the loop's
    reactions in the step, its covariance conditioned on G B)."""
    import copy
    from soft_twin_core.solve.constrained import FrameLoad
    d = copy.deepcopy(read_yaml_file(find_file("pan_tilt_arm", "robots")))
    for b in d["bodies"]:
        j = b.get("joint", {})
        if j.get("type") == "revolute":
            j["control"], j["stiffness"] = "passive", 2.0
        if b.get("type") == "member":
            for seg in b["segments"]:
                seg["sections"], seg["strain_basis"] = 6, {"type": "legendre", "order": 2}
    sprung = mechanism_from_dict(d, str(find_file("pan_tilt_arm", "robots").parent))
    u = np.array([5.0, 1.0, 2.0, 0.5])
    w = np.array([0.2, -0.1, -0.3, 0.004, 0.01, -0.006])
    eq = solve_equilibrium(sprung, u, point_loads=[FrameLoad("tool", w)]).q
    ekf = es.EKF(sprung, [sn.PoseSensor("em", 1e-3, 0.01, frame="tool")], 0.01, wrench="wrench", actuation=u,
                 q_init=eq)
    assert ekf.nr == 2 + 2 * 9
    assert_gvs_linearisation(ekf, eq, w, u)
    d = read_yaml_file(find_file("planar_parallel_robot", "robots"))
    for b in d["bodies"]:
        for seg in b.get("segments", []):
            seg["strain_basis"] = {"type": "legendre", "order": 3}
    par = mechanism_from_dict(d, str(find_file("planar_parallel_robot", "robots").parent))
    eq = solve_equilibrium(par)                          # (the filter's process model: gravity alone)
    ekf = es.EKF(par, [sn.PoseSensor("em", 1e-3, 0.01, frame="platform")], 0.01, q_init=eq.q)
    assert ekf.lam.size == 6 and ekf.nr < par.tree.nv
    assert_gvs_linearisation(ekf, eq.q, np.zeros(0), np.zeros(0))


def test_the_gvs_filter_tracks_as_the_pcs_filter_on_the_same_sections_with_a_fifth_of_the_state():
    """The tracked arm (8 + 8 sections) through tendon swings, observed by
    three pose sensors (1 mm): the filter on Legendre order 2 segments (18
    coordinates; its noise the PCS filter's projected on the basis) has the
    PCS filter's tip error (96 strains) within 5 %, and below 1 % of the
    length. With the same noise per coordinate as a section's (a
    coordinate moves the whole segment) it tracks the readings' noise and
    is 28 % worse: the projection is what makes the two filters alike."""
    truth = _tracked_arm(8)
    sensors = [sn.PoseSensor(f"em{i}", 1e-3, 0.01, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]
    tip = sn.PoseSensor("tip", 1.0, 1.0, s=0.4)

    def inputs(t):
        return np.array([10 * (1 - np.cos(np.pi * t)), 0.0, 8 * (1 - np.cos(1.6 * np.pi * t)), 0.0])
    sim = MechanismSimulator(truth, 0.002, q=solve_equilibrium(truth).q, tol=1e-9, max_iterations=30)
    rng = np.random.default_rng(7)
    data = []
    for _ in range(150):
        for _ in range(5):
            sim.step(inputs(sim.t + 0.001))
        data.append(({s.name: sn.simulate_measurement(s, sn.sensor_pose(truth, sim.q, s), rng) for s in sensors},
                      sn.sensor_pose(truth, sim.q, tip)[:3, 3]))
    med = {}
    for label, mech in (("pcs", truth), ("gvs", _tracked_arm(8, 2))):
        ekf = es.EKF(mech, sensors, 0.01, wrench="force")
        err = []
        for k, (readings, p) in enumerate(data):
            ekf.predict(inputs((k + 0.5) * 0.01))
            ekf.update(readings)
            err.append(np.linalg.norm(ekf.tip_pose()[:3, 3] - p))
        med[label] = np.median(err[20:]), ekf.P.shape[0]
    assert med["pcs"][1] == 2 * 48 + 3 and med["gvs"][1] == 2 * 18 + 3
    assert med["gvs"][0] < 0.004 and abs(med["gvs"][0] / med["pcs"][0] - 1) < 0.05, med


# ------------------------------------- a full basis: the same robot in other coordinates

def _with_full_bases(name, order=None):
    """The robot file ``name`` and the same file with every segment on a
    Legendre basis of order sections - 1: as many functions as sections,
    an invertible change of coordinates (the same physics, solved in z);
    ``order``: that order instead (at most sections - 1), a reduced basis."""
    from soft_twin_core.robot.mechanism import is_tree_file, load_mechanism
    import copy
    import yaml
    path = find_file(name, "robots")
    d = read_yaml_file(path)
    g = copy.deepcopy(d)
    segments = [s for b in g.get("bodies", []) if b.get("type") == "member" for s in b["segments"]] \
        if is_tree_file(g) else g["segments"]
    for seg in segments:
        full = int(seg.get("sections", 1)) - 1
        seg["strain_basis"] = {"type": "legendre", "order": full if order is None else min(order, full)}
    load = (lambda m: mechanism_from_dict(m, str(path.parent))) if is_tree_file(d) else \
        (lambda m: from_robot_model(model_from_dict(m), m, str(path.parent)))
    assert yaml.safe_dump(g)                     # (a plain mapping, as a file would give)
    return load_mechanism(path), load(g)


def _platform_load(inputs):
    """The scenario's 2 N across and 3 N down on the parallel robot's platform."""
    from soft_twin_core.solve.constrained import FrameLoad
    if inputs.get("point_loads") == "platform":
        return {**inputs, "point_loads": (FrameLoad("platform", np.array([2.0, 0.0, -3.0, 0.0, 0.0, 0.0]), "world"),)}
    return inputs


def _same_config(gvs, q, pcs_q):
    B = gvs.basis
    assert B.shape[0] == B.shape[1] and np.linalg.matrix_rank(B) == B.shape[0]
    return np.abs(q - pcs_q).max()


@pytest.mark.parametrize("name, inputs", [
    ("pan_tilt_arm", dict(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4, "tilt": -0.3})),
    ("planar_parallel_robot", dict(point_loads="platform")),
    ("tendon_arm_on_table", dict(actuation=[0.0, 0.0, 0.0, 1.5])),
])
def test_statics_with_position_joints_closed_chains_and_contact_in_full_bases(name, inputs):
    """Position-controlled joints and their efforts, a closed chain's
    reactions, contact with a table: the KKT Newton in z gives the PCS
    robot's equilibrium (a full basis is a change of coordinates)."""
    pcs, gvs = _with_full_bases(name)
    inputs = _platform_load(inputs)
    a, b = solve_equilibrium(pcs, **inputs), solve_equilibrium(gvs, **inputs)
    assert np.abs(a.q - pcs.tree.q0).max() > 1e-2
    assert _same_config(gvs, b.q, a.q) < 1e-8
    assert np.abs(a.lam - b.lam).max(initial=0) <= 1e-7 * max(1.0, np.abs(a.lam).max(initial=0))
    for k, v in a.joint_efforts.items():
        assert abs(b.joint_efforts[k] - v) < 1e-7


@pytest.mark.parametrize("name, inputs, steps", [
    ("pan_tilt_arm", dict(actuation=[2.0, 0.0, 1.0, 0.0], positions="ramp"), 200),
    ("planar_parallel_robot", dict(point_loads="platform"), 100),
    ("tendon_arm_on_table", dict(actuation=[0.0, 0.0, 0.0, 1.5]), 200),
    ("soft_gripper_lift", dict(actuation=[6.0, 6.0], positions={"lift": 0.0}), 200),    # a loose cylinder held
    ("catheter_in_vessel", dict(), 100),                  # a prescribed base, in a tube
])
def test_dynamics_with_position_joints_closed_chains_and_contact_in_full_bases(name, inputs, steps):
    """The engine's compiled steps in z (the reduced step; with constraint
    rows or contacts the closed-chain and contact steps with the Galerkin
    inverse) against its steps on the PCS robot: the same trajectory to
    the Newton tolerances."""
    pcs, gvs = _with_full_bases(name)
    inputs = _platform_load(inputs)
    out = []
    for mech in (pcs, gvs):
        sim = MechanismSimulator(mech, 2e-3, 0.5, tol=1e-12, constraint_tol=1e-12, max_iterations=60)
        if inputs.get("positions") == "ramp":        # the joints' commands in a smooth ramp, as a twin shapes them
            for k in range(steps):
                s = min(1.0, (k + 1) / 150)
                s = s * s * (3 - 2 * s)
                sim.step(**{**inputs, "positions": {"pan": 0.4 * s, "tilt": -0.3 * s}})
        else:
            sim.step(n=steps, **inputs)
        out.append(sim.q.copy())
    assert np.abs(out[0] - pcs.tree.q0).max() > 1e-3
    assert _same_config(gvs, out[1], out[0]) < 1e-7


def _pan_tilt_gvs(sections=8, order=2):
    from soft_twin_core.robot.mechanism import load_mechanism
    path = find_file("pan_tilt_arm", "robots")
    d = read_yaml_file(path)
    arm = next(b for b in d["bodies"] if b.get("type") == "member")
    for seg in arm["segments"]:
        seg["sections"] = sections
        seg["strain_basis"] = {"type": "legendre", "order": order}
    return mechanism_from_dict(d, str(path.parent)), load_mechanism(path)


@pytest.mark.parametrize("name, order, inputs, steps, kernel", [
    ("planar_parallel_robot", 2, dict(point_loads="platform"), 100, "closed"),         # a loop's rows
    ("tendon_arm_on_table", 0, dict(actuation=[0.0, 0.0, 0.0, 1.5]), 200, "contact"),   # contacts (2 sections)
    ("catheter_in_vessel", 2, dict(), 100, "contact"),           # a prescribed base's clamp and contacts
])
def test_reduced_bases_in_the_compiled_steps_as_in_the_python_kkt_step(name, order, inputs, steps, kernel):
    """Legendre order 0 or 2 on every segment (fewer coordinates than sections):
    the compiled closed-chain and contact steps with the Galerkin inverse
    ``B (B^T A B)^-1 B^T`` and the residual ``B^T R`` give the Python KKT
    step's trajectory, which solves for z with ``T^T A T`` and ``G T``
    (solve_factored), to the Newton tolerances; the velocities stay on the
    basis."""
    _, gvs = _with_full_bases(name, order=order)
    B = gvs.basis
    assert B.shape[1] < B.shape[0]
    inputs = _platform_load(inputs)
    out = []
    for compiled in (True, False):
        sim = MechanismSimulator(gvs, 2e-3, 0.5, tol=1e-12, constraint_tol=1e-12, max_iterations=60,
                                 compiled=compiled)
        used = sim._use_closed_step if kernel == "closed" else sim._use_compiled_step
        assert used == compiled and sim._theta_integrator is None
        sim.step(n=steps, **inputs)
        w = np.linalg.lstsq(B, sim.v, rcond=None)[0]
        assert np.abs(B @ w - sim.v).max() <= 1e-10 * np.abs(sim.v).max()
        out.append((sim.q.copy(), sim.v.copy(), sim.lam.copy()))
    (q1, v1, l1), (q2, v2, l2) = out
    assert np.abs(q1 - gvs.tree.q0).max() > 1e-3
    assert np.abs(q1 - q2).max() < 1e-8
    assert np.abs(v1 - v2).max() < 1e-6 * np.abs(v2).max()
    assert np.abs(l1 - l2).max(initial=0) <= 1e-6 * max(1.0, np.abs(l2).max(initial=0))


def test_a_position_controlled_arm_with_a_reduced_basis_balances_on_the_basis_only():
    """The pan-tilt arm, 8 sections a segment on Legendre order 2 (6 of
    its 16 strain coordinates a segment): at the KKT Newton's equilibrium
    the virtual work of the forces on the basis vanishes (``B^T R = 0``,
    R the engine's full residual with the joints' efforts), the joints sit
    at their commands, and R itself does not vanish (a PCS equilibrium
    would need strains off the basis). Its dynamics, damped, settles there
    (the Python KKT step in z, another path)."""
    gvs, _ = _pan_tilt_gvs()
    inputs = dict(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4, "tilt": -0.3})
    eq = solve_equilibrium(gvs, **inputs)
    from soft_twin_core.solve.constrained import _Equilibrium
    pb = _Equilibrium(gvs, eq.inputs)
    pb.T = None                                           # the full residual, for the check
    R, phi, _ = pb.residual(eq.q, eq.lam)
    scale = np.abs(pb.K @ (eq.q - gvs.tree.q0)).max()
    assert np.abs(gvs.basis.T @ R).max() < 1e-9 * scale
    assert np.abs(R).max() > 1e-4 * scale
    assert np.abs(phi).max() < 1e-10
    sim = MechanismSimulator(gvs, 5e-3, 1.0, tol=1e-10)
    sim.step(n=1200, **inputs)                            # 6 s: the first modes are damped 12-15 %
    assert np.abs(sim.q - eq.q).max() < 1e-4 * np.abs(eq.q - gvs.tree.q0).max()


def test_the_filters_jacobian_of_a_free_flying_gvs_arm_is_the_pcs_filters_in_other_coordinates():
    """A free-flying arm (its base's quaternion stepped on its group) with
    a full basis T: the filter's Phi is the PCS filter's (checked against
    differences in test_free_base_estimation) seen in the coordinates z,
    ``Phi_z = S^-1 Phi_q S`` with S = diag(T, T, I)."""
    ekfs = []
    for order in (None, 5):
        seg = {**benchmark_cantilever_dict(6, "bending_torsion")["segments"][0], "length": 0.3}
        if order is not None:
            seg["strain_basis"] = {"type": "legendre", "order": order}
        mech = mechanism_from_dict({"name": "flyer", "gravity": [0, 0, -9.81], "base": {"motion": "floating"},
                                    "bodies": [{"name": "arm", "type": "member", "segments": [seg]}]})
        ekf = es.EKF(mech, [sn.PoseSensor("em", 1e-3, 0.01, s=0.3)], 0.01, wrench="force")
        q, v = mech.tree.q0.copy(), np.zeros(mech.tree.nv)
        q[7:] += 2.0 * (np.arange(len(q) - 7) % 3 == 1)            # bent
        v[:6] = [0.1, 0.0, -0.2, 0.5, -1.0, 2.0]                    # moving and spinning
        ekf.x[:ekf.nq], ekf.x[ekf.nq:ekf.nq + ekf.n] = q, v
        ekfs.append(ekf)
    (pcs, gvs), T = ekfs, ekfs[1].mech.basis
    n = T.shape[0]
    S = np.eye(2 * n + 3)
    S[:n, :n] = S[n:2 * n, n:2 * n] = T
    Phi_q, Phi_z = pcs.linearisation()[0], gvs.linearisation()[0]
    assert np.abs(Phi_q[:6, :6] - np.eye(6)).max() > 1e-3                 # the group step is not the identity
    assert np.abs(Phi_z - np.linalg.solve(S, Phi_q @ S)).max() < 1e-9 * np.abs(Phi_q).max()


def test_the_command_lines_runs_report_the_coordinates(tmp_path):
    """soft-twin-sim statics and dynamics on a scenario of the GVS arm:
    the JSON carries the coordinates z with their names, and each row's
    section strains are ``f0 + B z``."""
    import json
    from soft_twin_core.cli import main as cli_main
    from soft_twin_core.robot.mechanism import load_mechanism
    robot = find_file("gvs_arm", "robots")
    mech = load_mechanism(robot)
    (tmp_path / "s.yaml").write_text(f"robot: {robot}\ngravity: true\nactuation: {{tendon_y_pos: 2.0}}\n")
    assert cli_main(["statics", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "st.json")]) == 0
    assert cli_main(["dynamics", str(tmp_path / "s.yaml"), "--duration", "0.05", "-o",
                     str(tmp_path / "dy.json")]) == 0
    st, dy = (json.loads((tmp_path / f).read_text()) for f in ("st.json", "dy.json"))
    for d, rows in ((st, [(st["coordinates"], st["strains"])]), (dy, zip(dy["coordinates"], dy["strains"]))):
        assert d["coordinate_names"] == list(mech.coordinate_names) and len(d["coordinate_names"]) == 27
        for z, strains in rows:
            q = mech.tree.q0 + mech.basis @ np.array(z)
            xi = np.reshape(strains, (-1, 6))
            got = np.concatenate([xi[k, mech.tree.joints[j].section.modes]
                                  for k, j in enumerate(mech.members[0].joints)])
            assert np.abs(got - q).max() < 1e-12
    assert len(dy["coordinates"]) == len(dy["time"]) > 10 and np.abs(st["coordinates"]).max() > 0.1


def test_a_custom_basis_from_a_python_callable():
    """with_strain_basis(mech, member, CustomBasis(f)): Legendre P_0..P_2
    given as a callable spans what the robot file's order 2 does (the same
    B), and solves the same statics; a callable of the wrong shape, with
    non-finite values, or an unknown member are refused, naming them."""
    from soft_twin_core.robot.mechanism import with_strain_basis
    from soft_twin_core.robot.strain_bases import CustomBasis

    def legendre2(x):
        t = 2 * x - 1
        return np.array([np.ones_like(t), t, 0.5 * (3 * t * t - 1)])
    file_basis, pcs = _cantilever(12, {"type": "legendre", "order": 2}), _cantilever(12)
    custom = with_strain_basis(pcs, "backbone", CustomBasis(legendre2))
    assert np.abs(custom.basis - file_basis.basis).max() < 1e-14
    assert np.abs(solve_equilibrium(custom).q - solve_equilibrium(file_basis).q).max() < 1e-12
    assert pcs.basis is None                                   # the original is untouched
    with pytest.raises(ModelError, match=r"shape \(k >= 1, 12\)"):
        with_strain_basis(pcs, "backbone", CustomBasis(lambda x: x))
    with pytest.raises(ModelError, match="finite"):
        with_strain_basis(pcs, "backbone", CustomBasis(lambda x: np.array([np.full_like(x, np.inf)])))
    with pytest.raises(ModelError, match="12 sections cannot carry 13"):
        with_strain_basis(pcs, "backbone", CustomBasis(lambda x: np.array([x ** j for j in range(13)])))
    with pytest.raises(ModelError, match="member: no member named 'arm'"):
        with_strain_basis(pcs, "arm", CustomBasis(legendre2))


def test_position_controlled_joints_eliminated_in_the_reduced_step_as_in_the_kkt_step():
    """The pan-tilt arm on Legendre order 2, its joints following a smooth
    command: the reduced step with the joints eliminated (their end
    positions prescribed, their efforts the residual's rows) and the Python
    KKT step (their efforts multipliers) give the same trajectory and
    efforts."""
    gvs, _ = _pan_tilt_gvs(6, 2)
    out = []
    for compiled in (True, False):
        sim = MechanismSimulator(gvs, 2e-3, 0.5, tol=1e-12, max_iterations=60, compiled=compiled)
        assert (sim._theta_integrator is not None) == compiled
        for k in range(300):
            s = min(1.0, (k + 1) / 200)
            s = s * s * (3 - 2 * s)
            sim.step(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4 * s, "tilt": -0.3 * s})
        out.append((sim.q.copy(), sim.joint_efforts()))
    assert abs(out[0][0][0] - 0.4) < 1e-12 and abs(out[0][1]["tilt"]) > 0.1
    assert np.abs(out[0][0] - out[1][0]).max() < 1e-9
    assert all(abs(out[0][1][j] - out[1][1][j]) < 1e-9 for j in ("pan", "tilt"))


@pytest.mark.parametrize("name, order", [
    ("pan_tilt_arm", 2),                 # rigid joints: identity columns
    ("planar_parallel_robot", 2),        # three members, a platform
    ("catheter_in_vessel", 2),           # a prescribed base: a free joint, its quaternion
    ("soft_gripper_lift", 1),            # a loose cylinder on a free joint, a lift
])
def test_the_mass_matrix_in_z_is_the_projected_crba(name, order):
    """:func:`passes.projected_mass_pass` (the kinetic energy's sum over the
    mass points, their twists per coordinate by a forward recursion)
    equals ``B^T M B`` with M by CRBA, at a random configuration on the
    basis, to round-off."""
    from soft_twin_core.engine.integrators import integrate_pass
    from soft_twin_core.engine.kernels import passes
    _, gvs = _with_full_bases(name, order=order)
    tree, B = gvs.tree, np.ascontiguousarray(gvs.basis)
    ws = Workspace(tree)
    q = np.empty(tree.nq)
    integrate_pass(ws.m, tree.q0.copy(), B @ (0.3 * np.random.default_rng(2).standard_normal(B.shape[1])), 1.0, q)
    expect = B.T @ alg.crba(tree, ws, q) @ B
    out = np.empty((B.shape[1], B.shape[1]))
    passes.forward_pass(ws.m, ws.w, q, np.zeros(tree.nv), np.zeros(tree.nv), passes.POSES)
    passes.projected_mass_pass(ws.m, ws.w, B, out)
    assert np.abs(out - expect).max() < 1e-13 * np.abs(expect).max()


def test_the_compiled_newton_matrix_is_the_projected_one_with_the_held_joints_eliminated():
    """reduced_step.basis_newton_matrix's inverse against the definition,
    ``(B^T (M + th D + th^2 K) B)^-1`` from the dense CRBA, on the
    pan-tilt arm on Legendre order 2 in a bent pose: its position-controlled
    joints' rows and columns the identity's, the rest the inverse of the
    free block; a non-finite pose makes no matrix."""
    from soft_twin_core.engine.reduced_step import basis_newton_matrix
    gvs, _ = _pan_tilt_gvs(6, 2)
    sim = MechanismSimulator(gvs, 2e-3, 0.5)
    integ, tree, B = sim._theta_integrator, gvs.tree, gvs.basis
    rng = np.random.default_rng(5)
    q = tree.q0 + B @ (0.2 * rng.normal(size=B.shape[1]))
    th = 0.5 * 2e-3
    M = alg.crba(tree, Workspace(tree), q)
    A = B.T @ (M + th * sim.D + th * th * sim.K) @ B
    fixed, fz = integ.arrays.fixed, integ._fz
    assert fixed.sum() == 2 and np.abs(A[np.ix_(fixed, fz)]).max() > 1e-3 * np.abs(A).max()   # coupled: eliminated
    assert basis_newton_matrix(sim.ws.m, sim.ws.w, q, th, integ.arrays, np.zeros(tree.nv))
    Ainv = integ.arrays.Ainv
    ref = np.linalg.inv(A[np.ix_(fz, fz)])
    assert np.abs(Ainv[np.ix_(fz, fz)] - ref).max() <= 1e-10 * np.abs(ref).max()
    assert np.array_equal(Ainv[np.ix_(fixed, fixed)], np.eye(2)) and not Ainv[np.ix_(fixed, fz)].any()
    q[3] = np.nan
    assert not basis_newton_matrix(sim.ws.m, sim.ws.w, q, th, integ.arrays, np.zeros(tree.nv))


@pytest.mark.parametrize("case", ["free cantilever", "held joints", "fallbacks"])
def test_many_reduced_steps_in_one_call_are_the_single_steps(case):
    """sim.step(n=k) runs the converged steps of the call in one compiled
    call (its Newton matrix held and refreshed inside it); k calls of one
    step carry the same matrix and refresh rule through the integrator:
    the same states, iterations and efforts to the bit. ``fallbacks``: the
    pan-tilt arm's joints jump at once (160 rad/s in one step), so
    steps fail in the compiled call and go on through the integrator's
    fallbacks (a fresh start from v0, full Newton, halves)."""
    from soft_twin_core.engine.reduced_step import ReducedThetaIntegrator
    if case == "free cantilever":
        mech, kw, inputs = _cantilever(16, {"type": "legendre", "order": 3}, free="all"), {}, {}
    else:
        mech, _ = _pan_tilt_gvs(6, 2)
        kw = dict(max_iterations=10)
        jump = case == "fallbacks"          # (else held where they start, the tendons swinging the arm)
        inputs = dict(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4 * jump, "tilt": -0.3 * jump})
    runs = []
    for calls in ((40,), (1,) * 40):
        sim = MechanismSimulator(mech, 2.5e-3, 0.5, tol=1e-8, **kw)
        assert isinstance(sim._theta_integrator, ReducedThetaIntegrator)
        tried = []
        step = sim._theta_integrator.step
        sim._theta_integrator.step = (lambda state, failed=None, log=tried:
                                      log.append(failed is not None) or step(state, failed))
        for n in calls:
            sim.step(n=n, **inputs)
        runs.append((sim.q, sim.v, sim.newton_iterations, sim.factorisations, sim.lam, tried))
    (q1, v1, it1, f1, lam1, tried1), (q2, v2, it2, f2, lam2, tried2) = runs
    assert np.array_equal(q1, q2) and np.array_equal(v1, v2) and np.array_equal(lam1, lam2)
    assert (it1, f1) == (it2, f2)
    assert f1 > 1                           # a matrix refreshed on the way
    if case == "held joints":
        assert q1[0] == 0.0 and np.abs(lam1).max() > 1e-3
    assert (tried1 != []) == (case == "fallbacks") and all(tried1)


def test_a_jumping_joint_command_in_a_full_basis_follows_the_compiled_step():
    """The pan-tilt arm's joints commanded 0.4 and -0.3 rad at once (400
    rad/s in one 2 ms step, the arm whipped): after the violent first step
    the last acceleration extrapolates far off; the reduced step then
    starts again from v0 (and would fall back on full Newton) instead of
    splitting the step, and follows the engine's compiled step on the PCS
    arm (a full basis) to 1e-6 over 200 steps."""
    pcs, gvs = _with_full_bases("pan_tilt_arm")
    inputs = dict(actuation=[2.0, 0.0, 1.0, 0.0], positions={"pan": 0.4, "tilt": -0.3})
    sims = [MechanismSimulator(m, 2e-3, 0.5, tol=1e-12, max_iterations=60) for m in (pcs, gvs)]
    for _ in range(200):
        for sim in sims:
            sim.step(**inputs)
        assert abs(sims[0].t - sims[1].t) < 1e-12
    assert np.abs(sims[0].q - pcs.tree.q0).max() > 0.3
    assert _same_config(gvs, sims[1].q, sims[0].q) < 1e-6


def test_the_reduced_steps_full_newton_matrix_is_the_derivative_of_its_residual():
    """The fallback's matrix ``B^T (M + theta h dtau/dv + (theta h)^2
    dtau/dq) B`` equals central differences of ``h B^T R`` in the end
    velocity's coordinates w1 (R the theta step's residual, gravity and
    the sections' stiffness and damping, a moving bent state), and the
    held matrix (no velocity products, no gravity terms) does not."""
    from soft_twin_core.engine.integrators import integrate_pass, residual_pass
    from soft_twin_core.engine.kernels.data import empty_loads
    mech = _cantilever(12, {"type": "legendre", "order": 3}, free="all")
    sim = MechanismSimulator(mech, 2e-3, 0.5)
    integ, tree, B = sim._theta_integrator, mech.tree, mech.basis
    rng = np.random.default_rng(3)
    q0 = tree.q0 + B @ (0.3 * rng.normal(size=B.shape[1]) * np.repeat([0.01, 0.01, 0.01, 1, 1, 1], 4))
    v0 = B @ (5.0 * rng.normal(size=B.shape[1]))
    h, th = 2e-3, 0.5
    g = np.array(tree.gravity, dtype=float)
    coef = np.zeros(len(sim.act.joint))

    def hR(w1):
        vt = (1 - th) * v0 + th * (B @ w1)
        qt, R = np.empty_like(q0), np.empty(tree.nv)
        integrate_pass(sim.ws.m, q0, vt, th * h, qt)
        residual_pass(sim.ws.m, sim.ws.w, sim.act, empty_loads(), g, coef, np.zeros(tree.nv), qt, vt,
                      (B @ w1 - v0) / h, R, False)
        return h * (B.T @ R), qt, vt
    w1 = np.linalg.lstsq(B, v0, rcond=None)[0] + rng.normal(size=B.shape[1])
    _, qt, vt = hR(w1)
    A = integ.full_matrix(qt, vt, (B @ w1 - v0) / h, g, h)
    eps = 1e-6
    fd = np.stack([(hR(w1 + eps * e)[0] - hR(w1 - eps * e)[0]) / (2 * eps) for e in np.eye(len(w1))], axis=1)
    assert np.abs(A - fd).max() <= 1e-6 * np.abs(fd).max()
    assert np.abs(integ.newton_matrix(qt, h) - fd).max() > 1e-4 * np.abs(fd).max()
