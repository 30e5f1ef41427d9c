"""The numpy reference of the classic rod's statics (slides part B
"Statics"), kept off the production paths: the tests hold the engine's
equilibrium solver (:func:`constrained.solve_equilibrium`, every robot)
against it.

* :func:`residual`: ``R(q) = K (q - q0) - Q_ext(q) - tau_act(q, u)`` from
  the chain's kinematics and Gauss quadrature, and :func:`tangent`, its
  exact complex-step derivative (the compiled Newton's residual and
  analytic tangent are checked against both);
* :func:`internal_wrenches`: the stress resultants by the strong form (cut
  at s), and :func:`base_reaction`;
* :func:`actuation_for_shape`: the inputs that hold a shape, by bounded
  least squares on ``B(q) u = K (q - q0) - Q_ext``.
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.loads import Loads, actuator_point_loads
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference.loads import actuation_force, generalized_external_force, load_points
from soft_twin_core.solve.constrained import actuation_vector


def residual(model, q, u, loads):
    """Equilibrium residual R(q) (..., n_dof) in generalised-force units
    (numpy reference; accepts a stack of complex q for the complex step)."""
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    tau = actuation_force(model, ch, u)
    return np.einsum("ij,...j->...i", model.K_q, ch.q - model.q0) - Q - tau


def tangent(model, q, u, loads, h=1e-30):
    """dR/dq (n_dof, n_dof) by the complex step: column k = Im R(q + i h e_k)/h.
    Exact to machine precision (reference of :meth:`equilibrium.Problem.tangent`)."""
    n = model.n_dof
    qc = q[None, :] + 1j * h * np.eye(n)
    return (residual(model, qc, u, loads).imag / h).T


def base_reaction(model, F_total_origin):
    """Support reaction [f; m] in world axes, moment about the base origin,
    balancing the total applied spatial wrench (given about the world origin)."""
    p0 = model.base_pose[:3, 3]
    f = -F_total_origin[..., :3]
    m = -F_total_origin[..., 3:] - np.cross(p0, f)
    return np.concatenate([f, m], axis=-1)


def internal_wrenches(model, q, s, actuation=None, loads=None):
    """Internal wrench (stress resultant) [force; moment] (P, 6) in the body
    frame at arc lengths s: the wrench the distal part exerts on the proximal
    part through the cross-section, from the loads distal to s (strong form,
    cut at s). Tendons anchored distal to s add their tension pulled back
    along the tendon at s. At equilibrium its elastic part approximates
    K (f - f0) (exactly so in the continuum limit)."""
    loads = Loads() if loads is None else loads
    u = actuation_vector(model, actuation)
    s = np.atleast_1d(np.asarray(s, dtype=float))
    ch = kin.chain(model, q)
    act_pts = actuator_point_loads(model, u)
    if act_pts:
        loads = Loads(point=tuple(loads.point) + act_pts, distributed=loads.distributed,
                      gravity=loads.gravity)
    pts = load_points(model, ch, loads)
    idx, x, g, own = kin._point_data(model, ch, s)
    out = np.zeros((len(s), 6))
    if pts is not None:
        sp, _, _, gp, _, Wb = pts
        F = np.einsum("...ji,...j->...i", lie.Ad_inv(gp), Wb)
        distal = sp[None, :] >= s[:, None]          # a load exactly at s counts as distal
        Fd = distal.astype(float) @ F                                   # world, about origin
        out = np.einsum("pji,pj->pi", lie.Ad(g), Fd)                    # Ad(g)^T F: to body at s
    # a tendon crossing the cut pulls the distal free body back along its path
    # with its tension T at offset d: the distal part then pushes the proximal
    # part with the extra wrench -T [t; d x t] (pressure: T = -area * p).
    for a, val in zip(model.actuators, u):
        if val == 0.0 or a.tendon_model == "point_moment":
            continue
        inside = (s >= a.start) & (s < a.end)
        if not np.any(inside):
            continue
        d, dd = a.offset_at(s)
        xi = ch.strains[idx]
        t = xi[:, :3] + np.cross(xi[:, 3:], d) + dd
        t = t / np.linalg.norm(t, axis=-1, keepdims=True)
        w = -a.force_per_unit_input * val * np.concatenate([t, np.cross(d, t)], axis=-1)
        out[inside] += w[inside]
    return out


def actuation_for_shape(model, q, loads=None):
    """Actuation that holds configuration q in equilibrium, where one exists.

    The actuation force is linear in the inputs, ``tau(q, u) = B(q) u``, so
    the inputs solve ``B(q) u = K (q - q0) - Q_ext(q)``: non-negative least
    squares for tendons (tension >= 0), free sign for chamber pressures.
    Returns (u, relative residual ||B u - rhs|| / force scale); a residual
    above ~1e-6 means the actuators cannot hold that shape exactly."""
    from scipy.optimize import lsq_linear
    loads = Loads() if loads is None else loads
    q = model.check_q(np.asarray(q, dtype=float))
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    rhs = model.K_q @ (q - model.q0) - Q
    n = len(model.actuators)
    if n == 0:
        return np.zeros(0), (0.0 if not np.any(rhs) else 1.0)
    B = np.stack([actuation_force(model, ch, e) for e in np.eye(n)], axis=1)
    lo = np.array([0.0 if a.kind == "tendon" else -np.inf for a in model.actuators])
    # scale columns so tensions (N) and pressures (Pa) are comparable
    col = np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    sol = lsq_linear(B / col, rhs, bounds=(lo * col, np.full(n, np.inf)), method="bvls", tol=1e-14)
    u = sol.x / col
    u[lo == 0.0] = np.maximum(u[lo == 0.0], 0.0)
    scale = max(np.linalg.norm(rhs), np.linalg.norm(model.K_q @ (q - model.q0)), np.linalg.norm(Q))
    res = np.linalg.norm(B @ u - rhs) / scale if scale > 0 else 0.0
    return u, float(res)
