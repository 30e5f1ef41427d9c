"""Physics of the implicit theta-method (soft_twin_core.engine.integrators.ThetaIntegrator)
on hybrid soft-rigid trees:

* the reference potential energy is the potential of the engine's static
  forces (its gradient is RNEA at rest), so the energy checks below test the
  engine and not the reference;
* theta = 1/2 (implicit midpoint) conserves the energy of undamped trees to
  second order (the error shrinks 4x when dt halves), spherical joints
  included; a constant joint effort enters through its work;
* a torque-free rigid body on a free joint keeps its kinetic energy (exactly:
  V_t^T ad(V_t)^T I V_t = 0 in the midpoint residual) and its world-frame
  spatial momentum to second order; a free-floating base with a soft arm
  keeps its momentum and energy to second order; quaternions stay unit;
* damped motion (implicit Euler) settles on the static equilibrium that an
  independent Newton solve of R(q) = RNEA(q, 0, 0) - effort = 0 finds;
* a step that cannot converge reports it and leaves the state unchanged, and
  a step that needs sub-steps equals the same number of smaller steps.

Two engine defects these tests found are fixed: a non-finite update once
passed newton_step's check (max() dropped the NaN), and the second step's
predictor extrapolated from the initial zero acceleration.
"""

import types

import numpy as np
import pytest

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import actuator_arrays
from soft_twin_core.engine.integrators import ThetaIntegrator
from soft_twin_core.engine.joint_kinds import FREE, SOFT, SPHERICAL
from soft_twin_core.engine.kernels.data import empty_loads, kernel_array
from soft_twin_core.engine.multibody import ModelBuilder, spatial_inertia
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.reference import joints as jnt
from soft_twin_core.reference import multibody as reference

from test_multibody import _placement, _section, gripper, pan_tilt_arm

BEND_TORSION = (False, False, False, True, True, True)


# ----------------------------------------------------------------------------
# Models
# ----------------------------------------------------------------------------

def undamped_arm():
    """pan_tilt_arm without joint damping (the pan spring stays: conservative)."""
    b = ModelBuilder("undamped_arm", gravity=(0.2, -0.1, -9.81))
    pan = b.add_joint("pan", "revolute", -1, _placement(p=(0, 0, 0.1)), axis=(0, 0, 1),
                      inertia=spatial_inertia(0.8, (0.01, 0, 0.03), np.diag([2e-3, 2e-3, 1e-3])),
                      stiffness=0.5)
    tilt = b.add_joint("tilt", "revolute", pan, _placement(p=(0, 0, 0.06)), axis=(0, 1, 0),
                       inertia=spatial_inertia(0.3, (0.02, 0.0, 0.0), np.diag([4e-4, 5e-4, 5e-4])))
    secs = [_section(0.1, f0=(1, 0, 0, 0.1 * k, 0, 2.0)) for k in range(4)]
    js = b.add_soft_chain("arm", secs, tilt, _placement(rpy=(0.1, -0.3, 0.2), p=(0.04, 0, 0)))
    b.add_path("arm", js)
    return b.build()


def damped_arm():
    """The pan-tilt arm with viscous sections and damped springs on both
    rigid joints (a unique, stable static equilibrium; slowest mode decays at
    ~2.3/s)."""
    b = ModelBuilder("damped_arm", gravity=(0.2, -0.1, -9.81))
    pan = b.add_joint("pan", "revolute", -1, _placement(p=(0, 0, 0.1)), axis=(0, 0, 1),
                      inertia=spatial_inertia(0.8, (0.01, 0, 0.03), np.diag([2e-3, 2e-3, 1e-3])),
                      stiffness=0.5, damping=0.1)
    tilt = b.add_joint("tilt", "revolute", pan, _placement(p=(0, 0, 0.06)), axis=(0, 1, 0),
                       inertia=spatial_inertia(0.3, (0.02, 0.0, 0.0), np.diag([4e-4, 5e-4, 5e-4])),
                       stiffness=1.0, damping=0.3, q_ref=0.2)
    secs = [_section(0.1, f0=(1, 0, 0, 0.1 * k, 0, 2.0), visc=2e5) for k in range(4)]
    js = b.add_soft_chain("arm", secs, tilt, _placement(rpy=(0.1, -0.3, 0.2), p=(0.04, 0, 0)))
    b.add_path("arm", js)
    return b.build()


def ball_arm():
    """A rigid link on a spherical joint, a soft arm (bending + torsion)
    hanging from it and a rigid hand on a revolute wrist."""
    b = ModelBuilder("ball_arm", gravity=(0.0, 0.3, -9.81))
    ball = b.add_joint("ball", "spherical", -1, _placement(p=(0, 0, 0.5)),
                       inertia=spatial_inertia(0.2, (0.01, 0.0, -0.05), np.diag([1e-4, 2e-4, 1.5e-4])))
    secs = [_section(0.08, free=BEND_TORSION, f0=(1, 0, 0, 0.2, -1.0, 0.5)) for _ in range(2)]
    js = b.add_soft_chain("arm", secs, ball, _placement(rpy=(0, np.pi / 2, 0), p=(0, 0, -0.1)))
    b.add_path("arm", js)
    b.add_joint("wrist", "revolute", js[-1], _placement(p=(0.01, 0, 0)), axis=(0, 1, 0),
                inertia=spatial_inertia(0.05, (0.02, 0.0, 0.0), np.diag([1e-5, 2e-5, 2e-5])))
    return b.build()


def spinning_body():
    """One rigid body on a free joint (centre of mass off the frame origin,
    non-diagonal rotational inertia), no gravity."""
    b = ModelBuilder("spinning_body", gravity=(0.0, 0.0, 0.0))
    Ic = np.array([[3e-3, 2e-4, -1e-4], [2e-4, 5e-3, 3e-4], [-1e-4, 3e-4, 8e-3]])
    b.add_joint("base", "free", -1, inertia=spatial_inertia(1.2, (0.05, -0.02, 0.03), Ic))
    return b.build()


def floating_arm():
    """A free-floating rigid base carrying a soft arm (bending + torsion) and
    a tool mass, no gravity."""
    b = ModelBuilder("floating_arm", gravity=(0.0, 0.0, 0.0))
    base = b.add_joint("base", "free", -1,
                       inertia=spatial_inertia(0.5, (0.01, 0.0, 0.02), np.diag([1e-3, 2e-3, 1.5e-3])))
    secs = [_section(0.08, free=BEND_TORSION, f0=(1, 0, 0, 0.3, 1.0, -0.5)) for _ in range(2)]
    js = b.add_soft_chain("arm", secs, base, _placement(rpy=(0.2, 0.1, 0.0), p=(0.05, 0, 0)))
    b.add_path("arm", js)
    b.add_joint("tool", "fixed", js[-1], _placement(p=(0.01, 0, 0)),
                inertia=spatial_inertia(0.02, (0.01, 0, 0), np.diag([2e-6, 4e-6, 4e-6])))
    return b.build()


# ----------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------

def _integrator(model, dt, theta=0.5, loads=None, effort=None, **kw):
    """A ThetaIntegrator of a model without actuators and constant inputs;
    ``effort`` may also be a callable of t."""
    ws = Workspace(model)
    act = actuator_arrays(model)
    assert act.joint.shape == (0,)
    loads = empty_loads() if loads is None else loads
    coef = np.zeros(0)
    g = kernel_array(model.gravity)       # (writable, as the twin's own inputs: the model's is frozen)
    if callable(effort):
        def inputs(t):
            return loads, g, coef, np.ascontiguousarray(effort(t), dtype=float)
    else:
        eff = np.zeros(model.nv) if effort is None else np.asarray(effort, dtype=float)

        def inputs(t):
            return loads, g, coef, eff
    return ThetaIntegrator(model, ws, act, inputs, dt, theta, **kw), ws


def _state(q, v):
    return types.SimpleNamespace(q=np.array(q, dtype=float), qdot=np.array(v, dtype=float), t=0.0)


def _energy(model, ws, q, v):
    """Kinetic (0.5 v^T M v, CRBA) plus potential (reference: elastic + gravity)."""
    return 0.5 * v @ alg.crba(model, ws, q) @ v + reference.potential_energy(model, q)


def _gentle_start(model, seed, amp):
    """q0 with the angular strains of the soft sections perturbed by +-amp
    [rad/m] (linear strains left at f0: their modes are stiff) and a random
    unit quaternion tilt of amp/4 for spherical joints."""
    rng = np.random.default_rng(seed)
    q = model.q0.copy()
    for i, j in enumerate(model.joints):
        a = model.idx_q[i]
        if j.kind == SOFT:
            m = j.section.modes
            q[a:a + j.nq] += np.where(m < 3, 0.0, amp * rng.uniform(-1, 1, j.nq))
        elif j.kind == SPHERICAL:
            dv = np.zeros(model.nv)
            dv[model.idx_v[i]:model.idx_v[i] + 3] = 0.25 * amp * rng.uniform(-1, 1, 3)
            q = jnt.integrate(model, q, dv)
    return q


def _energy_errors(model, q0, v0, dt, T, samples=10, effort=None, joint=None):
    """max |E(t) - E(0) - W(t)| over ``samples`` equally spaced times in (0, T]
    (W: the work of a constant effort on the 1-dof ``joint``)."""
    integ, ws = _integrator(model, dt, 0.5, effort=effort, tol=1e-12)
    st = _state(q0, v0)
    E0 = _energy(model, ws, st.q, st.qdot)
    n = int(round(T / dt))
    every = n // samples
    errs = []
    for k in range(1, n + 1):
        info = integ.step(st)
        assert info.converged, f"step {k} at dt={dt} did not converge"
        if k % every == 0:
            work = 0.0
            if effort is not None:
                iq, iv = model.idx_q[joint], model.idx_v[joint]
                work = effort[iv] * (st.q[iq] - q0[iq])
            errs.append(_energy(model, ws, st.q, st.qdot) - E0 - work)
    return np.max(np.abs(errs)), E0


def _orders(errors):
    return [errors[k] / errors[k + 1] for k in range(len(errors) - 1)]


# ----------------------------------------------------------------------------
# 0. The reference potential is the engine's static force potential
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("make", [pan_tilt_arm, gripper, ball_arm, undamped_arm])
def test_potential_energy_gradient_is_rnea_at_rest(make):
    """dV/dq along each velocity coordinate (q (+) eps e_k, central
    differences; right-trivialised on spherical joints) equals RNEA at v = a = 0:
    gravity plus K (q - q0)."""
    model = make()
    ws = Workspace(model)
    q = jnt.random_configuration(model, np.random.default_rng(4), 0.5)
    eps = 1e-6
    grad = np.array([(reference.potential_energy(model, jnt.integrate(model, q, eps * e))
                      - reference.potential_energy(model, jnt.integrate(model, q, -eps * e))) / (2 * eps)
                     for e in np.eye(model.nv)])
    tau = alg.rnea(model, ws, q, None, None).copy()
    assert np.max(np.abs(grad - tau)) < 1e-7 * max(1.0, np.max(np.abs(tau)))
    # and the kinetic energy of the reference is 0.5 v^T M v of CRBA
    v = np.random.default_rng(5).standard_normal(model.nv)
    ke = reference.kinetic_energy(model, q, v)
    assert abs(0.5 * v @ alg.crba(model, ws, q) @ v - ke) < 1e-12 * max(1.0, ke)


# ----------------------------------------------------------------------------
# 1. Energy conservation at second order (implicit midpoint)
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("with_effort", [False, True])
def test_midpoint_energy_error_is_second_order_hybrid_tree(with_effort):
    model = undamped_arm()
    q0 = _gentle_start(model, 0, 0.2)
    v0 = np.zeros(model.nv)
    v0[:2] = [2.0, -1.5]
    effort = None
    if with_effort:
        effort = np.zeros(model.nv)
        effort[0] = 0.05          # constant torque on the pan joint: E - tau (q_pan - q_pan(0)) is conserved
    errs = []
    for dt in (1e-3, 5e-4, 2.5e-4):
        e, E0 = _energy_errors(model, q0, v0, dt, 0.2, effort=effort, joint=0)
        errs.append(e)
    ratios = _orders(errs)
    assert errs[0] < 1e-4 * abs(E0), errs
    assert min(ratios) > 3.0, (errs, ratios)


def test_midpoint_energy_error_is_second_order_spherical_joint():
    model = ball_arm()
    q0 = _gentle_start(model, 1, 2.0)
    v0 = np.zeros(model.nv)
    v0[:3] = [1.5, -1.0, 2.0]            # body angular velocity of the ball joint
    v0[-1] = 3.0                          # wrist
    errs = []
    for dt in (1e-3, 5e-4, 2.5e-4):
        e, E0 = _energy_errors(model, q0, v0, dt, 0.3, samples=15)
        errs.append(e)
    ratios = _orders(errs)
    assert errs[0] < 1e-3 * abs(E0), errs
    assert min(ratios) > 3.0, (errs, ratios)


# ----------------------------------------------------------------------------
# 2. Lie-group joints: free and spherical joints
# ----------------------------------------------------------------------------

def _world_momentum(model, q, v):
    """Spatial momentum [linear; angular about the world origin] of the free
    body in world axes: Ad(g^-1)^T I V."""
    g = reference.placements(model, q)[1][0]
    return lie.Ad(lie.se3_inv(g)).T @ (model.joints[0].inertia @ v)


def test_free_body_spins_torque_free():
    model = spinning_body()
    assert model.kinds[0] == FREE
    q0 = model.q0.copy()
    q0[:3] = [0.1, 0.2, 0.3]
    u = np.array([0.3, -0.5, 0.2, 0.8])
    q0[3:7] = u / np.linalg.norm(u)
    v0 = np.array([0.3, -0.2, 0.1, 2.0, -6.0, 3.0])      # body twist [v; w]: tumbling
    I = model.joints[0].inertia
    ke0 = 0.5 * v0 @ I @ v0
    h0 = _world_momentum(model, q0, v0)
    T = 0.5
    ke_err, h_err = [], []
    for dt in (4e-3, 2e-3, 1e-3):
        integ, ws = _integrator(model, dt, 0.5, tol=1e-12)
        st = _state(q0, v0)
        kmax = hmax = 0.0
        for k in range(int(round(T / dt))):
            assert integ.step(st).converged
            assert abs(np.linalg.norm(st.q[3:7]) - 1.0) < 1e-14
            kmax = max(kmax, abs(0.5 * st.qdot @ I @ st.qdot - ke0))
            hmax = max(hmax, np.max(np.abs(_world_momentum(model, st.q, st.qdot) - h0)))
        ke_err.append(kmax / ke0)
        h_err.append(hmax / np.max(np.abs(h0)))
        # M is the constant body inertia on a free joint: the engine agrees
        assert np.max(np.abs(alg.crba(model, ws, st.q) - I)) < 1e-14
    # midpoint: (V1 - V0)^T I V_t = h V_t^T ad(V_t)^T I V_t = 0, kinetic energy
    # is conserved up to the Newton tolerance at every step size
    assert max(ke_err) < 1e-8 and max(ke_err) < 1e-3 * min(h_err), (ke_err, h_err)
    # momentum (a Lie-group, not a quadratic, invariant): second order
    ratios = _orders(h_err)
    assert h_err[0] < 1e-2, h_err
    assert min(ratios) > 3.0, (h_err, ratios)


def _tree_momentum(model, q, v):
    """World-frame spatial momentum of every mass point, explicit Jacobians
    (reference): sum Ad(g_p^-1)^T I_p J_p v."""
    frames = reference.placements(model, q)
    h = np.zeros(6)
    for i, x, g, I in reference.mass_points(model, q, frames):
        h += lie.Ad(lie.se3_inv(g)).T @ (I @ (reference.point_jacobian(model, q, i, x, None, frames) @ v))
    return h


def test_floating_hybrid_tree_conserves_momentum_and_energy():
    """Free-floating base + soft arm without gravity: the world momentum of
    the whole tree and its energy (kinetic + elastic) are conserved to second
    order (the arm's bending modes are fast: dt <= 0.2 ms to be asymptotic)."""
    model = floating_arm()
    q0 = _gentle_start(model, 0, 2.0)
    q0[:3] = [0.1, -0.2, 0.3]
    v0 = np.zeros(model.nv)
    v0[:6] = [0.2, -0.1, 0.3, 1.0, -2.0, 1.5]
    h0 = _tree_momentum(model, q0, v0)
    T = 0.1
    h_err, e_err = [], []
    for dt in (2e-4, 1e-4, 5e-5):
        integ, ws = _integrator(model, dt, 0.5, tol=1e-12)
        st = _state(q0, v0)
        E0 = _energy(model, ws, q0, v0)
        n = int(round(T / dt))
        hmax = emax = 0.0
        for k in range(1, n + 1):
            assert integ.step(st).converged
            assert abs(np.linalg.norm(st.q[3:7]) - 1.0) < 1e-14
            if k % (n // 10) == 0:
                hmax = max(hmax, np.max(np.abs(_tree_momentum(model, st.q, st.qdot) - h0)))
                emax = max(emax, abs(_energy(model, ws, st.q, st.qdot) - E0))
        h_err.append(hmax / np.max(np.abs(h0)))
        e_err.append(emax / E0)
    assert h_err[0] < 1e-5 and e_err[0] < 1e-5, (h_err, e_err)
    assert min(_orders(h_err)) > 3.0, (h_err, _orders(h_err))
    assert min(_orders(e_err)) > 3.0, (e_err, _orders(e_err))


def test_spherical_joint_quaternion_stays_unit():
    model = ball_arm()
    q0 = _gentle_start(model, 2, 2.0)
    v0 = np.zeros(model.nv)
    v0[:3] = [5.0, -3.0, 4.0]
    integ, _ = _integrator(model, 2e-3, 0.5)
    st = _state(q0, v0)
    for _ in range(200):
        assert integ.step(st).converged
        assert abs(np.linalg.norm(st.q[:4]) - 1.0) < 1e-14
    # and the ball has moved through a large rotation
    R0, R1 = jnt.quat_to_rot(q0[:4]), jnt.quat_to_rot(st.q[:4])
    assert np.linalg.norm(lie.log_so3(R0.T @ R1)) > 0.3


# ----------------------------------------------------------------------------
# 3. Damped motion settles on the static equilibrium
# ----------------------------------------------------------------------------

def _newton_statics(model, ws, residual, q, tol=1e-13, max_it=50):
    """Independent equilibrium: Newton on R(q) = 0 with a central-difference
    tangent along the velocity coordinates and a backtracking line search."""
    n = model.nv
    for _ in range(max_it):
        r0 = residual(q)
        J = np.column_stack([(residual(jnt.integrate(model, q, 1e-7 * e))
                              - residual(jnt.integrate(model, q, -1e-7 * e))) / 2e-7 for e in np.eye(n)])
        dq = -np.linalg.solve(J, r0)
        s = 1.0
        while (np.linalg.norm(residual(jnt.integrate(model, q, s * dq))) > (1 - 0.5 * s) * np.linalg.norm(r0)
               and s > 1e-3):
            s *= 0.5
        q = jnt.integrate(model, q, s * dq)
        if np.max(np.abs(s * dq)) < tol:
            return q, J
    raise AssertionError("Newton statics did not converge")


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_damped_motion_settles_on_the_static_equilibrium(theta):
    """Under gravity, a dead tip load and constant joint efforts. Implicit
    Euler damps every mode: run until max |v| < 1e-9. The midpoint rule lets
    the fast overdamped modes (real eigenvalues with |lambda| h >> 1, mapped
    near -1) ring at a small amplitude: run a fixed 10 s and check the
    configuration only."""
    model = damped_arm()
    js = model.soft_joints[-1]
    loads = alg.make_loads(model, [js], [-1.0], [[0.0, 0.03, -0.05, 0.0, 0.0, 0.002]], [True])
    effort = np.zeros(model.nv)
    effort[:2] = [0.05, -0.02]
    integ, ws = _integrator(model, 5e-3, theta, loads=loads, effort=effort)
    st = _state(model.q0, np.r_[1.0, -1.0, np.zeros(model.nv - 2)])
    if theta == 1.0:
        while np.max(np.abs(st.qdot)) > 1e-9:
            assert integ.step(st).converged
            assert st.t < 15.0, f"not settled after {st.t} s: max |v| = {np.max(np.abs(st.qdot))}"
    else:
        for _ in range(2000):
            assert integ.step(st).converged

    def residual(q):
        return alg.rnea(model, ws, q, None, None, loads).copy() - effort

    # static residual at the settled state, relative to the forces in balance
    R = residual(st.q)
    grav = alg.rnea(model, ws, st.q, None, None, loads, elastic=False).copy()
    elast = reference.elastic_force(model, st.q, np.zeros(model.nv))
    scale = max(np.max(np.abs(grav)), np.max(np.abs(elast)), np.max(np.abs(effort)))
    assert np.max(np.abs(R)) < (1e-9 if theta == 1.0 else 1e-7) * scale
    # the same equilibrium as an independent Newton solve started from q0
    q_eq, J = _newton_statics(model, ws, residual, model.q0.copy())
    assert np.max(np.abs(residual(q_eq))) < 1e-12 * scale
    assert np.all(np.linalg.eigvalsh(0.5 * (J + J.T)) > 0)      # a stable one
    assert np.max(np.abs(jnt.difference(model, q_eq, st.q))) < 1e-8 * max(1.0, np.max(np.abs(q_eq)))


# ----------------------------------------------------------------------------
# 4. Sub-stepping and failure
# ----------------------------------------------------------------------------

def _hard_start(model):
    """A violent initial configuration (axial and shear strains off by ~1%)
    whose first step of 0.5 ms needs more than 10 iterations at tol 1e-9."""
    return jnt.random_configuration(model, np.random.default_rng(0), 0.1)


def test_a_failed_step_leaves_the_state_unchanged():
    model = pan_tilt_arm()
    q0 = _hard_start(model)
    v0 = np.zeros(model.nv)
    # without sub-steps the 0.5 ms step does not converge
    integ, _ = _integrator(model, 5e-4, max_substep_levels=0, full_newton=False)
    st = _state(q0, v0)
    q_obj, v_obj = st.q, st.qdot
    info = integ.step(st)
    assert not info.converged
    assert st.q is q_obj and st.qdot is v_obj and st.t == 0.0
    assert np.array_equal(st.q, q0) and np.array_equal(st.qdot, v0)
    assert np.array_equal(integ.last_a, np.zeros(model.nv))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_non_finite_effort_fails_the_step(bad):
    model = pan_tilt_arm()
    v0 = np.zeros(model.nv)
    effort = np.zeros(model.nv)
    effort[1] = bad
    integ, _ = _integrator(model, 1e-3, effort=effort)
    st = _state(model.q0, v0)
    info = integ.step(st)
    assert np.all(np.isfinite(st.q)) and np.all(np.isfinite(st.qdot))
    assert not info.converged
    assert np.array_equal(st.q, model.q0) and np.array_equal(st.qdot, v0) and st.t == 0.0


def test_failure_in_a_later_sub_step_rolls_back_the_whole_step():
    """A violent effort (100 N m on pan and tilt) from 0.4 dt on: the full
    step (inputs at t + dt/2) fails, its first half converges, the second
    half fails; the step fails as a whole and the state stays. With the
    effort back to normal the next attempt equals a fresh integrator's step."""
    model = pan_tilt_arm()
    dt = 1e-3
    q0 = _gentle_start(model, 3, 0.5)
    v0 = np.zeros(model.nv)
    v0[0] = 1.0
    flag = {"bad": True}
    asked = []

    def effort(t):
        asked.append(t)
        e = np.zeros(model.nv)
        e[0] = 0.1
        if flag["bad"] and t > 0.4 * dt:
            e[:2] = [100.0, -100.0]
        return e

    integ, _ = _integrator(model, dt, effort=effort, max_substep_levels=1, full_newton=False)
    st = _state(q0, v0)
    assert not integ.step(st).converged
    assert np.any(np.isclose(asked, 0.75 * dt))          # the second half was tried: the first converged
    assert np.array_equal(st.q, q0) and np.array_equal(st.qdot, v0) and st.t == 0.0
    assert np.array_equal(integ.last_a, np.zeros(model.nv))
    flag["bad"] = False
    assert integ.step(st).converged
    fresh, _ = _integrator(model, dt, effort=effort, full_newton=False)
    st2 = _state(q0, v0)
    assert fresh.step(st2).converged
    assert np.max(np.abs(st.qdot - st2.qdot)) < 1e-7 * np.max(np.abs(st2.qdot))
    assert np.max(np.abs(st.q - st2.q)) < 1e-10
    assert st.t == st2.t == dt


def test_sub_steps_equal_smaller_steps():
    """A step whose Newton iteration fails at dt is split into two halves:
    the result is that of two steps of dt/2."""
    model = pan_tilt_arm()
    q0 = _hard_start(model)
    v0 = np.zeros(model.nv)
    dt = 5e-4
    integ, _ = _integrator(model, dt, max_substep_levels=1, full_newton=False, tol=1e-9)
    st = _state(q0, v0)
    info = integ.step(st)
    assert info.converged and info.iterations > integ.max_iterations
    assert st.t == dt
    # each half from the previous step's acceleration (zero here), as the
    # sub-steps do: one fresh integrator per half step
    st2 = _state(q0, v0)
    for _ in range(2):
        half, _ = _integrator(model, dt / 2, max_substep_levels=0, full_newton=False, tol=1e-9)
        assert half.step(st2).converged
    assert np.max(np.abs(st.qdot - st2.qdot)) < 1e-7 * np.max(np.abs(st2.qdot))
    assert np.max(np.abs(jnt.difference(model, st2.q, st.q))) < 1e-9
    # last_a is the mean acceleration over the whole step
    assert np.allclose(integ.last_a, (st.qdot - v0) / dt)


def test_a_step_the_compiled_run_gave_up_on_goes_straight_to_its_halves():
    """run() hands a step whose O(n) iteration failed (fresh factorisation,
    max_iterations) to the sub-steps without trying the same iteration
    again: the repeat (what step() alone does) would take the same iterates
    to the same failure, so the states are bit for bit those of the repeat,
    with one failed O(n) attempt fewer for each such step."""
    model = pan_tilt_arm()
    q0 = _hard_start(model)
    runs = []
    for skip in (True, False):
        integ, _ = _integrator(model, 5e-4, max_substep_levels=2, full_newton=False, tol=1e-9)
        tried = []
        newton = integ._newton
        integ._newton = lambda *a: tried.append(a[3]) or newton(*a)
        if not skip:                      # step() as before: its own attempt at the whole step first
            step = integ.step
            integ.step = lambda state, failed=None: step(state)
        st = _state(q0, np.zeros(model.nv))
        assert integ.run(st, 4).converged
        runs.append((st, tried))
    (a, tried_a), (b, tried_b) = runs
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qdot, b.qdot) and a.t == b.t
    whole = [h for h in tried_b if h == 5e-4]                 # the repeated attempts at the whole step
    assert whole and len(tried_a) == len(tried_b) - len(whole) and 5e-4 not in tried_a


def test_second_step_predictor_does_not_extrapolate_from_the_initial_zero_acceleration():
    model = pan_tilt_arm()
    integ, _ = _integrator(model, 2.5e-4, max_substep_levels=0)
    st = _state(_hard_start(model), np.zeros(model.nv))
    assert integ.step(st).converged           # from the guess v0
    assert integ.step(st).converged           # from v1 + h a_pred


def test_full_newton_fallback_rescues_large_strain_rates():
    """From a violent start (axial/shear strains +-3 %, strain rates ~1e3/s)
    the O(n) iteration, which leaves out the geometric terms, fails; the
    fallback with the analytic derivatives of inverse dynamics integrates
    without sub-steps, and the undamped energy stays near its start."""
    model = pan_tilt_arm()
    q0 = jnt.random_configuration(model, np.random.default_rng(0), 0.3)
    plain, _ = _integrator(model, 2.5e-4, max_substep_levels=0, full_newton=False)
    assert not plain.step(_state(q0, np.zeros(model.nv))).converged
    integ, ws = _integrator(model, 2.5e-4, max_substep_levels=0)
    st = _state(q0, np.zeros(model.nv))
    e0 = _energy(model, ws, st.q, st.qdot)
    drift = 0.0
    for _ in range(200):
        assert integ.step(st).converged
        drift = max(drift, abs(_energy(model, ws, st.q, st.qdot) - e0))
    print(f"energy {e0:.4g} J, max drift {drift:.3g} J")
    assert drift < 1e-3 * abs(e0)


def test_compiled_multi_step_run_equals_single_steps():
    """ThetaIntegrator.run (n steps in one compiled call, constant inputs)
    takes the same steps as n calls of step(): equal to the Newton
    tolerance, same time (it may reuse a factorisation where step() takes a
    fresh one every step: test_run_reuses_factorisations_...)."""
    model = pan_tilt_arm()
    q0 = _gentle_start(model, 2, 0.5)
    a, _ = _integrator(model, 1e-3, tol=1e-12)
    b, _ = _integrator(model, 1e-3, tol=1e-12)
    sa, sb = _state(q0, np.zeros(model.nv)), _state(q0, np.zeros(model.nv))
    assert a.run(sa, 50).converged
    for _ in range(50):
        assert b.step(sb).converged
    assert np.max(np.abs(sa.q - sb.q)) < 1e-9 and np.max(np.abs(sa.qdot - sb.qdot)) < 1e-7
    assert sa.t == pytest.approx(sb.t, abs=1e-15)
