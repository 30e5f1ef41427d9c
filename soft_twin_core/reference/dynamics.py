"""PCS equations of motion (slides part B "Dynamics"):

    M(q) qddot + C(q, qdot) qdot + D qdot + K (q - q0) = Q(q, t) + tau(q, u(t))

with, by Gauss quadrature over every section (same points everywhere, so the
semi-discrete system is exactly Lagrangian and conserves energy):

    M = int J^T Mc J ds
    C = int J^T (Mc Jdot + (Mc ad(eta) - ad(eta)^T Mc) J) ds,  eta = J qdot

(Mc: cross-section inertia density; the skew middle term makes Mdot - 2C
skew-symmetric; ``C qdot = int J^T (Mc Jdot qdot - ad(eta)^T Mc eta) ds`` is
the body-frame Newton-Euler bias). D and K are the generalised damping and
stiffness ``sum_i L_i B_i^T (D_i, K_i) B_i``; Q the external loads (gravity
included) and tau the actuation of :mod:`soft_twin_core.engine.loads`.

These functions are the readable numpy reference of the chain, kept off the
production paths: every robot's simulator
(:class:`constrained.MechanismSimulator`) runs on the multibody engine
(recursive compiled passes), tested against these and
:mod:`soft_twin_core.reference.multibody`.
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import gravity_of, load_arrays
from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.engine.workspace import thread_workspace
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference.loads import (actuation_force, gauss_points, generalized_external_force,
                                            tendon_lengths)
from soft_twin_core.reference.statics import base_reaction, internal_wrenches
from soft_twin_core.solve.constrained import actuation_vector


def _quadrature(model):
    s, w, sec = gauss_points(model)
    Mc = np.array([model.sections[i].M for i in sec])
    return s, w, Mc


def mass_matrix(model, q):
    """Generalised mass matrix M(q) (n_dof, n_dof), symmetric positive definite."""
    s, w, Mc = _quadrature(model)
    J = kin.jacobian(model, q, s)
    return np.einsum("p,pai,pab,pbj->ij", w, J, Mc, J)


def coriolis_matrix(model, q, qdot):
    """C(q, qdot) (n_dof, n_dof) with Mdot - 2C skew-symmetric."""
    s, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    A = lie.ad(eta)
    Mid = Mc @ A - np.swapaxes(A, -1, -2) @ Mc
    return np.einsum("p,pai,paj->ij", w, J, Mc @ Jdot + Mid @ J)


def bias_force(model, q, qdot):
    """C(q, qdot) qdot = int J^T (Mc Jdot qdot - ad(eta)^T Mc eta) ds."""
    s, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    acc = np.einsum("pij,j->pi", Jdot, qdot)
    h = np.einsum("pab,pb->pa", Mc, acc) - np.einsum("pba,pb->pa", lie.ad(eta), np.einsum("pab,pb->pa", Mc, eta))
    return np.einsum("p,pai,pa->i", w, J, h)


def applied_force(model, q, qdot, u, loads):
    """Everything but inertia: Q_ext + tau_act - K (q - q0) - D qdot."""
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    tau = actuation_force(model, ch, u)
    return Q + tau - model.K_q @ (q - model.q0) - model.D_q @ qdot


def forward_dynamics(model, q, qdot, u=None, loads=None):
    """qddot from M qddot = applied - C qdot."""
    loads = Loads() if loads is None else loads
    u = actuation_vector(model, u)
    rhs = applied_force(model, q, qdot, u, loads) - bias_force(model, q, qdot)
    return np.linalg.solve(mass_matrix(model, q), rhs)


def energy(model, q, qdot, u=None, gravity=True):
    """(kinetic, elastic, gravitational, actuator) energies [J].

    Gravitational energy -int rho A g . p ds uses the same quadrature as the
    dynamics; the actuator potential of constant inputs is sum c_a u_a ell_a
    (tendon tension times path length)."""
    M = mass_matrix(model, q)
    kinetic = 0.5 * qdot @ M @ qdot
    dq = q - model.q0
    elastic = 0.5 * dq @ model.K_q @ dq
    grav = 0.0
    if gravity:
        s, w, Mc = _quadrature(model)
        p = kin.poses(model, q, s)[:, :3, 3]
        grav = -np.sum(w * Mc[:, 0, 0] * (p @ model.gravity))
    act = 0.0
    if u is not None and len(model.actuators):
        u = actuation_vector(model, u)
        c = np.array([a.force_per_unit_input for a in model.actuators])
        act = float(np.sum(c * u * tendon_lengths(model, q)))
    return float(kinetic), float(elastic), float(grav), act


def base_reaction_dynamic(model, q, qdot, qddot, u=None, loads=None):
    """Support reaction [f; m] (world axes, moment about the base origin):
    the wrench the support transmits into the root joint, by the engine's
    inverse dynamics at (q, qdot, qddot) under the loads (actuators are
    internal: their forces close through the base).
    :func:`_base_reaction_reference` is the numpy version."""
    loads = Loads() if loads is None else loads
    tree = model.tree
    ws = thread_workspace(tree)
    alg.rnea(tree, ws, q, qdot, qddot, load_arrays(tree, loads), gravity_of(tree, loads), elastic=False)
    R = ws.work.g_in[0, :3, :3]
    f = ws.work.f_in[0]
    return np.concatenate([R @ f[:3], R @ f[3:]])


def _base_reaction_reference(model, q, qdot, qddot, loads):
    s, w, Mc = _quadrature(model)
    g, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    eta_dot = J @ qddot + Jdot @ qdot
    Wb = w[:, None] * (np.einsum("pab,pb->pa", Mc, eta_dot)
                       - np.einsum("pba,pb->pa", lie.ad(eta), np.einsum("pab,pb->pa", Mc, eta)))
    F_inertia = np.einsum("pji,pj->i", lie.Ad_inv(g), Wb)
    _, F_ext = generalized_external_force(model, kin.chain(model, q), loads)
    return base_reaction(model, F_ext - F_inertia)


def dynamics_terms(model, q, qdot, u, loads):
    """(M, f) with f = Q_ext + tau - K (q - q0) - D qdot - C qdot, sharing one
    kinematic pass (reference implementation of the integrators' kernel)."""
    s, w, Mc = _quadrature(model)
    g, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    M = np.einsum("p,pai,pab,pbj->ij", w, J, Mc, J)
    acc = np.einsum("pij,j->pi", Jdot, qdot)
    h = np.einsum("pab,pb->pa", Mc, acc) - np.einsum("pba,pb->pa", lie.ad(eta),
                                                      np.einsum("pab,pb->pa", Mc, eta))
    bias = np.einsum("p,pai,pa->i", w, J, h)
    return M, applied_force(model, q, qdot, u, loads) - bias


def simulate_ivp(model, t_span, state, actuation=None, loads=None, method="Radau",
                 rtol=1e-8, atol=1e-10, t_eval=None):
    """Adaptive offline integration of the chain with
    scipy.integrate.solve_ivp (Radau or BDF for stiff arms), on the numpy
    equations of motion (:func:`forward_dynamics`): a reference for the
    engine's theta integrator. ``actuation`` (dict or vector) and ``loads``
    are held. The Jacobian of the first-order system [qdot; M^-1 f] is
    supplied by central finite differences of the right-hand side."""
    from scipy.integrate import solve_ivp
    u = actuation_vector(model, actuation)
    n = model.n_dof

    def rhs(t, y):
        return np.concatenate([y[n:], forward_dynamics(model, y[:n], y[n:], u, loads)])

    def jac(t, y):
        eps = 1e-7 * np.maximum(1.0, np.abs(y))
        Jm = np.empty((2 * n, 2 * n))
        for k in range(2 * n):
            e = np.zeros(2 * n)
            e[k] = eps[k]
            Jm[:, k] = (rhs(t, y + e) - rhs(t, y - e)) / (2 * eps[k])
        return Jm

    y0 = np.concatenate([state.q, state.qdot])
    return solve_ivp(rhs, t_span, y0, method=method, rtol=rtol, atol=atol, jac=jac, t_eval=t_eval)


def internal_wrenches_dynamic(model, q, qdot, qddot, s, u=None, loads=None):
    """Internal wrench [force; moment] (P, 6), body frame at arc lengths s,
    in motion: the statics cut (:func:`statics.internal_wrenches`) with the
    d'Alembert inertial wrenches ``-(Mc eta_dot - ad(eta)^T Mc eta)`` of the
    distal quadrature points added as follower loads."""
    loads = Loads() if loads is None else loads
    sq, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, sq)
    eta_dot = J @ qddot + Jdot @ qdot
    h = np.einsum("pab,pb->pa", Mc, eta_dot) - np.einsum("pba,pb->pa", lie.ad(eta),
                                                         np.einsum("pab,pb->pa", Mc, eta))
    inertial = tuple(PointLoad(float(si), tuple(-wi * hi), "body") for si, wi, hi in zip(sq, w, h))
    all_loads = Loads(point=tuple(loads.point) + inertial, distributed=loads.distributed,
                      gravity=loads.gravity)
    return internal_wrenches(model, q, s, u, all_loads)
