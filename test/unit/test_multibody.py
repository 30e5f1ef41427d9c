"""The multibody engine on hybrid soft-rigid trees: the compiled recursive
passes against the explicit-Jacobian reference (soft_twin_core.reference.multibody),
the old chain dynamics, the Newton-Euler balance and passivity. Rigid-only
trees are checked against Pinocchio in test_multibody_pinocchio.py."""

from pathlib import Path

import numpy as np
import pytest

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.loads import Loads
from soft_twin_core.engine.multibody import ModelBuilder, SoftSection, spatial_inertia
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.reference import dynamics as dy
from soft_twin_core.reference import joints as jnt
from soft_twin_core.reference import multibody as reference
from soft_twin_core.robot.model import load_model, model_from_dict, section_matrices, CrossSection, Material

TOL = 1e-10
TENDON_ARM = str(Path(__file__).resolve().parents[2] / "config" / "robots" / "tendon_arm.yaml")


def _section(length, radius=0.01, free=(True,) * 6, f0=(1, 0, 0, 0, 0, 0), E=2e6, visc=0.0, kmap="exponential"):
    K, D, M = section_matrices(CrossSection.solid_circle(radius), Material(E, E / 3, 1100.0, visc))
    return SoftSection(length, K, D, M, np.array(f0, float), np.array(free, bool), kmap)


def _placement(rpy=(0, 0, 0), p=(0, 0, 0)):
    from scipy.spatial.transform import Rotation
    H = np.eye(4)
    H[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    H[:3, 3] = p
    return H


def pan_tilt_arm(kmap="exponential"):
    """A soft arm (4 sections, all six modes) on a 2-joint rigid pan-tilt."""
    b = ModelBuilder("pan_tilt_arm", gravity=(0.2, -0.1, -9.81))
    pan = b.add_joint("pan", "revolute", -1, _placement(p=(0, 0, 0.1)), axis=(0, 0, 1),
                      inertia=spatial_inertia(0.8, (0.01, 0, 0.03), np.diag([2e-3, 2e-3, 1e-3])),
                      stiffness=0.5, damping=0.01)
    tilt = b.add_joint("tilt", "revolute", pan, _placement(p=(0, 0, 0.06)), axis=(0, 1, 0),
                       inertia=spatial_inertia(0.3, (0.02, 0.0, 0.0), np.diag([4e-4, 5e-4, 5e-4])))
    secs = [_section(0.1, f0=(1, 0, 0, 0.1 * k, 0, 2.0), kmap=kmap) for k in range(4)]
    js = b.add_soft_chain("arm", secs, tilt, _placement(rpy=(0.1, -0.3, 0.2), p=(0.04, 0, 0)))
    b.add_path("arm", js)
    return b.build()


def gripper():
    """A rigid palm on a prismatic lift with three soft fingers of 3 sections
    (bending + torsion, one finger with all modes) and a fixed tool mass."""
    b = ModelBuilder("gripper")
    lift = b.add_joint("lift", "prismatic", -1, _placement(rpy=(0, np.pi / 2, 0)), axis=(1, 0, 0),
                       inertia=spatial_inertia(0.5, (0.0, 0.0, 0.01), np.diag([1e-3, 1e-3, 2e-3])))
    for k in range(3):
        ang = 2 * np.pi * k / 3
        free = (True,) * 6 if k == 0 else (False, False, False, True, True, True)
        secs = [_section(0.05, 0.006, free=free, f0=(1, 0, 0, 0, 0.5, -1.0)) for _ in range(3)]
        js = b.add_soft_chain(f"finger{k}", secs, lift,
                              _placement(rpy=(ang, 0, 0.3), p=(0.02, 0.03 * np.cos(ang), 0.03 * np.sin(ang))))
        b.add_path(f"finger{k}", js)
    b.add_joint("tool", "fixed", 3, _placement(p=(0.01, 0, 0)),
                inertia=spatial_inertia(0.05, (0.005, 0, 0), np.diag([1e-5, 1e-5, 1e-5])))
    return b.build()


HYBRID = {"pan_tilt_arm": pan_tilt_arm, "gripper": gripper,
          "pan_tilt_arm_cayley": lambda: pan_tilt_arm("cayley")}


def _state(model, seed):
    rng = np.random.default_rng(seed)
    q = jnt.random_configuration(model, rng, 0.5)
    return q, rng.standard_normal(model.nv), rng.standard_normal(model.nv)


def _rel(a, b):
    return np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))


@pytest.mark.parametrize("name", HYBRID)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hybrid_recursions_match_reference(name, seed):
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, a = _state(model, seed)
    M = reference.mass_matrix(model, q)
    assert _rel(alg.crba(model, ws, q), M) < TOL
    tau = reference.inverse_dynamics(model, q, v, a)
    assert _rel(alg.rnea(model, ws, q, v, a), tau) < TOL
    # forward dynamics in O(n) inverts inverse dynamics (M is ill-conditioned: relative to a)
    acc = alg.forward_dynamics(model, ws, q, v, tau)
    assert np.max(np.abs(acc - a)) < 1e-8 * np.linalg.cond(M) ** 0.5
    g_in, g_out = alg.forward_kinematics(model, ws, q)
    assert _rel(g_out, reference.placements(model, q)[1]) < 1e-13


@pytest.mark.parametrize("name", HYBRID)
def test_folded_factorisation_solves_the_block_system(name):
    """factor(cD, cK) solves (M + cD D + cK K) x = r: the implicit
    integrator's Newton matrix, in O(n)."""
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, _ = _state(model, 5)
    M = reference.mass_matrix(model, q)
    # D and K columns from the reference elastic force (linear in q - q0 and v)
    n = model.nv
    K = np.column_stack([reference.elastic_force(model, _unit_q(model, k), np.zeros(n)) for k in range(n)])
    D = np.column_stack([reference.elastic_force(model, model.q0, np.eye(n)[k]) for k in range(n)])
    r = np.random.default_rng(1).standard_normal(n)
    alg.factor(model, ws, q, 0.02, 3e-4)
    x = alg.solve(model, ws, r)
    assert _rel(x, np.linalg.solve(M + 0.02 * D + 3e-4 * K, r)) < 1e-9


def _unit_q(model, k):
    """q0 displaced by 1 along velocity coordinate k (no spherical/free joints here)."""
    dv = np.zeros(model.nv)
    dv[k] = 1.0
    return jnt.integrate(model, model.q0, dv)


@pytest.mark.parametrize("name", HYBRID)
def test_root_wrench_is_the_newton_euler_balance(name):
    """f_in of the root joint = sum over every mass point of its inertial
    minus gravitational wrench, moved to the root's input frame (explicit
    Jacobians), minus the loads."""
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, a = _state(model, 7)
    frames = reference.placements(model, q)
    g_root = frames[0][0]
    total = np.zeros(6)
    for i, x, g_p, I in reference.mass_points(model, q, frames):
        J = reference.point_jacobian(model, q, i, x, None, frames)
        Jd = reference.point_jacobian_dot(model, q, v, i, x, None, frames)
        V, A = J @ v, J @ a + Jd @ v
        h = I @ (A - np.r_[g_p[:3, :3].T @ model.gravity, 0, 0, 0]) - lie.ad(V).T @ I @ V
        total += lie.Ad(lie.se3_inv(g_p) @ g_root).T @ h
    # a dead and a follower point load on the last soft joint
    js = model.soft_joints[-1]
    sec = model.joints[js].section
    loads = alg.make_loads(model, [js, js], [0.3 * sec.length, -1.0],
                           [[0.1, -0.2, 0.3, 0.01, 0.0, -0.02], [0.0, 0.05, 0.0, 0.0, 0.003, 0.0]], [True, False])
    for k, world in enumerate([True, False]):
        g_p = reference.point_pose(model, q, js, [0.3 * sec.length, None][k], None, frames)
        W = loads.wrench[k]
        Wb = np.r_[g_p[:3, :3].T @ W[:3], g_p[:3, :3].T @ W[3:]] if world else W
        total -= lie.Ad(lie.se3_inv(g_p) @ g_root).T @ Wb
    alg.rnea(model, ws, q, v, a, loads)
    assert _rel(ws.work.f_in[0], total) < TOL


@pytest.mark.parametrize("name", HYBRID)
def test_loads_enter_as_minus_jacobian_transpose(name):
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, a = _state(model, 3)
    frames = reference.placements(model, q)
    js = model.soft_joints[1]
    x = 0.7 * model.joints[js].section.length
    W = np.array([0.3, -0.1, 0.2, 0.02, -0.01, 0.005])
    for world in (True, False):
        tau0 = alg.rnea(model, ws, q, v, a).copy()
        tau1 = alg.rnea(model, ws, q, v, a, alg.make_loads(model, [js], [x], [W], [world])).copy()
        g_p = reference.point_pose(model, q, js, x, None, frames)
        Wb = np.r_[g_p[:3, :3].T @ W[:3], g_p[:3, :3].T @ W[3:]] if world else W
        J = reference.point_jacobian(model, q, js, x, None, frames)
        assert _rel(tau1 - tau0, -J.T @ Wb) < TOL


@pytest.mark.parametrize("name", HYBRID)
def test_passivity_mdot_minus_2c(name):
    """v^T (Mdot - 2 C) v = 0: Mdot by a central difference of CRBA along v,
    C v from RNEA without gravity, acceleration or elasticity."""
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, _ = _state(model, 11)
    h = 1e-6
    Mp = alg.crba(model, ws, jnt.integrate(model, q, h * v)).copy()
    Mm = alg.crba(model, ws, jnt.integrate(model, q, -h * v)).copy()
    Mdot = (Mp - Mm) / (2 * h)
    Cv = alg.rnea(model, ws, q, v, None, gravity=np.zeros(3), elastic=False)
    lhs = v @ Mdot @ v
    assert abs(lhs - 2 * v @ Cv) < 1e-7 * max(1.0, abs(lhs))


def test_soft_chain_equals_the_chain_dynamics():
    """The default robot as a tree: M and the forces equal the (tested) chain
    dynamics of soft_twin_core.reference.dynamics."""
    robot = load_model(TENDON_ARM)
    model = robot.tree
    ws = Workspace(model)
    rng = np.random.default_rng(0)
    q = robot.q0 + 0.4 * rng.standard_normal(robot.n_dof)
    v = rng.standard_normal(robot.n_dof)
    M, f = dy.dynamics_terms(robot, q, v, np.zeros(len(robot.actuators)), Loads())
    assert _rel(alg.crba(model, ws, q), M) < TOL
    # f = -(C v + g + K (q - q0) + D v)
    assert _rel(-alg.rnea(model, ws, q, v, None), f) < TOL


def test_benchmark_cantilever_offsets_and_workspace_checks():
    robot = model_from_dict({"name": "x", "segments": [
        {"length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
         "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1000},
         "offset_to_next": {"position": [0, 0, 0.01], "rpy": [0, 0, 1.0]}},
        {"length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
         "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1000}}]})
    model = robot.tree
    ws = Workspace(model)
    with pytest.raises(ValueError, match=r"q: expected shape \(24,\)"):
        alg.crba(model, ws, np.zeros(5))
    with pytest.raises(ValueError, match="another model"):
        alg.crba(pan_tilt_arm(), ws, np.zeros(24))
    q = robot.q0 + 0.1
    assert _rel(alg.crba(model, ws, q), dy.mass_matrix(robot, q)) < TOL


def _complex_step_id(model, q, v, a, wrt, h=1e-30):
    """d/dq or d/dv of the reference inverse dynamics by the complex step
    (exact to round-off; additive coordinates only: no spherical/free joints)."""
    n = model.nv
    out = np.zeros((n, n))
    for k in range(n):
        e = np.zeros(n, complex)
        e[k] = 1j * h
        args = (q + e, v, a) if wrt == "q" else (q, v + e, a)
        out[:, k] = reference.inverse_dynamics(model, *args).imag / h
    return out


@pytest.mark.parametrize("name", ["pan_tilt_arm", "gripper"])
def test_rnea_derivatives_hybrid(name):
    """Analytic d tau/d q and d tau/d v on hybrid trees against the complex
    step of the explicit-Jacobian reference (1e-10), and against central
    differences of the engine's own RNEA (the issue's 1e-7)."""
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, a = _state(model, 4)
    dq, dv = alg.rnea_derivatives(model, ws, q, v, a)
    assert _rel(dq, _complex_step_id(model, q, v, a, "q")) < TOL
    assert _rel(dv, _complex_step_id(model, q, v, a, "v")) < TOL
    h = 1e-6
    for k in range(model.nv):
        e = np.zeros(model.nv)
        e[k] = h
        plus = alg.rnea(model, ws, q + e, v, a, elastic=False).copy()
        col = (plus - alg.rnea(model, ws, q - e, v, a, elastic=False)) / (2 * h)
        K_col = np.array([reference.elastic_force(model, _unit_q(model, k), np.zeros(model.nv))]).ravel()
        assert np.max(np.abs(dq[:, k] - K_col - col)) <= 1e-7 * max(1.0, np.max(np.abs(dq)))


def _static_residual_and_tangent(model, ld, act, coef):
    from soft_twin_core.engine.forces import actuation_tangent_pass
    from soft_twin_core.engine.integrators import residual_pass
    from soft_twin_core.engine.kernels import passes
    from soft_twin_core.engine.kernels.tangent import static_tangent_pass
    ws = Workspace(model)
    z = np.zeros(model.nv)
    g = model.gravity.copy()

    def R(q):
        out = np.empty(model.nv)
        residual_pass(ws.m, ws.w, act, ld, g, coef, z, np.ascontiguousarray(q), z, z, out, True)
        return out

    def Kt(q):
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q), z, z, 0)
        passes.rnea_pass(ws.m, ws.w, ld, g, np.empty(model.nv), True)
        K = np.zeros((model.nv, model.nv))
        for i in range(model.n_joints):
            b, k = model.idx_v[i], model.joints[i].nv
            K[b:b + k, b:b + k] = ws.arrays.Kb[i, :k, :k]
        static_tangent_pass(ws.m, ws.w, ld, g, K)
        actuation_tangent_pass(ws.m, ws.w, act, coef, K)
        return K
    return R, Kt


@pytest.mark.parametrize("name", HYBRID)
def test_static_tangent_is_the_derivative_of_the_static_residual(name):
    """The analytic static tangent (one O(n^2) pass) against central
    differences of the static residual, with dead and follower loads inside
    a section and at output frames (rigid and soft), gravity; and on the
    tendon arm with tendons pulling."""
    from soft_twin_core.engine.forces import actuator_arrays
    model = HYBRID[name]()
    js = model.soft_joints[-1]
    L = model.joints[js].section.length
    ld_ = alg.make_loads(model, [js, js, js, 1], [0.3 * L, -1, 0.8 * L, -1],
                         np.random.default_rng(0).standard_normal((4, 6)), [True, False, False, True])
    act = actuator_arrays(model)
    R, Kt = _static_residual_and_tangent(model, ld_, act, np.zeros(len(act.joint)))
    q = _state(model, 1)[0]
    h = 1e-6
    K_fd = np.column_stack([(R(q + h * e) - R(q - h * e)) / (2 * h) for e in np.eye(model.nv)])
    assert _rel(Kt(q), K_fd) < 1e-8


def test_static_tangent_with_tendons():
    from soft_twin_core.engine.forces import actuator_arrays
    robot = load_model(TENDON_ARM)
    model = robot.tree
    act = actuator_arrays(model)
    R, Kt = _static_residual_and_tangent(model, alg.make_loads(model, [], [], np.zeros((0, 6)), []), act,
                                         act.unit @ np.array([3.0, 0.0, 5.0, 1.0]))
    q = robot.q0 + 0.3 * np.random.default_rng(2).standard_normal(robot.n_dof)
    h = 1e-6
    K_fd = np.column_stack([(R(q + h * e) - R(q - h * e)) / (2 * h) for e in np.eye(model.nv)])
    assert _rel(Kt(q), K_fd) < 1e-8


def test_static_tangent_with_sheath_friction():
    """The friction's lower-triangular coupling (a tendon's tension at s
    depends on every strain before s) in the analytic tangent: the tendon
    arm with sheath friction on straight, converging and helical tendons,
    against central differences."""
    import yaml
    from soft_twin_core.engine.forces import actuator_arrays
    d = yaml.safe_load(Path(TENDON_ARM).read_text())
    d["actuators"] += [
        {"name": "conv", "routing": "converging", "offset": [0.008, 0.002], "offset_end": [0.002, -0.004],
         "start": 0.05, "end": 0.4},
        {"name": "helix", "routing": "helical", "radius": 0.006, "turns_per_meter": 3.0, "end": 0.42}]
    q = None
    tangents = []
    for mu in (0.0, 0.35):
        for a in d["actuators"]:
            a["friction"] = mu
        robot = model_from_dict(d)
        model = robot.tree
        act = actuator_arrays(model)
        R, Kt = _static_residual_and_tangent(model, alg.make_loads(model, [], [], np.zeros((0, 6)), []), act,
                                             act.unit @ np.array([3.0, 0.0, 5.0, 1.0, 2.0, 4.0]))
        if q is None:
            q = robot.q0 + 0.3 * np.random.default_rng(2).standard_normal(robot.n_dof)
        h = 1e-6
        K_fd = np.column_stack([(R(q + h * e) - R(q - h * e)) / (2 * h) for e in np.eye(model.nv)])
        tangents.append(Kt(q))
        assert _rel(tangents[-1], K_fd) < 1e-8
    # the friction's part is there to be checked (also below the diagonal blocks)
    assert np.abs(np.tril(tangents[1] - tangents[0], -3)).max() > 1e-2 * np.abs(tangents[0]).max()


@pytest.mark.parametrize("name", HYBRID)
def test_point_jacobians_and_their_derivatives(name):
    """Compiled point Jacobians (body, world) and their time derivatives
    against the explicit-Jacobian reference, at a rigid joint's output frame,
    a soft section's end and a cross-section inside a section."""
    model = HYBRID[name]()
    ws = Workspace(model)
    q, v, _ = _state(model, 8)
    js = model.soft_joints[1]
    for j, x in ((0, -1.0), (js, -1.0), (js, 0.37 * model.joints[js].section.length)):
        xr = None if x < 0 else x
        g, J = alg.point_jacobian(model, ws, q, j, x, "body")
        assert _rel(g, reference.point_pose(model, q, j, xr)) < 1e-13
        assert _rel(J, reference.point_jacobian(model, q, j, xr)) < 1e-12
        Jd = alg.point_jacobian_dot(model, ws, q, v, j, x, "body")
        assert _rel(Jd, reference.point_jacobian_dot(model, q, v, j, xr)) < 1e-11
        # world frame: d/dt of blockdiag(R, R) J by a central difference along (q, v)
        h = 1e-6
        Jw = lambda qq: alg.point_jacobian(model, ws, qq, j, x, "world")[1].copy()  # noqa: E731
        fd = (Jw(jnt.integrate(model, q, h * v)) - Jw(jnt.integrate(model, q, -h * v))) / (2 * h)
        assert _rel(alg.point_jacobian_dot(model, ws, q, v, j, x, "world"), fd) < 1e-7
