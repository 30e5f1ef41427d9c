"""The numpy reference of the generalised external and actuation forces on
the classic rod (slides part B), by Gauss quadrature and the O(n) spatial
sum; the engine's compiled :mod:`soft_twin_core.engine.forces` is held
against it.

Generalised external force (virtual work): ``Q = sum_p J(s_p)^T W_p +
int J(s)^T w(s) ds`` with body wrenches W = [force; moment] acting on the
cross-section at s. It is computed in O(n) from *spatial* wrenches (world
axes, moments about the world origin) ``F = Ad(g)^-T W``:
``Q_j = W_j^T sum_{p distal to section j} F_p + sum_{p in j} own_p^T F_p``.

Dead loads are fixed in the world (force and moment in world axes, acting at
the cross-section's centre line point); follower loads are fixed in the
body frame of the cross-section.

Actuation (frictionless tendons, fluidic chambers) is exact and conservative:
``tau = -sum_a c_a u_a d(ell_a)/dq`` with the tendon path length
``ell = int |f_u + f_w x d + d'| ds`` over the routed span, so
``tau = -sum_a c_a u_a int B^T [t; d x t] ds`` with t the unit tangent of the
tendon path in the cross-section frame (c = 1 for tendons, u = tension [N];
c = -area for chambers, u = pressure [Pa]).
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.loads import Loads, actuator_point_loads
from soft_twin_core.reference import kinematics as kin


# ----------------------------------------------------------------------------
# Quadrature
# ----------------------------------------------------------------------------

def gauss_points(model, start=0.0, end=None):
    """Gauss-Legendre abscissae s (m) and weights (m) over [start, end] with
    ``model.quadrature_points`` per section (restricted to the overlap)."""
    end = model.total_length if end is None else end
    xg, wg = np.polynomial.legendre.leggauss(model.quadrature_points)
    a = np.maximum(model.s_starts, start)
    b = np.minimum(model.s_starts + model.lengths, end)
    keep = b > a
    a, b = a[keep], b[keep]
    s = (0.5 * (a + b))[:, None] + (0.5 * (b - a))[:, None] * xg[None, :]
    w = (0.5 * (b - a))[:, None] * wg[None, :]
    # keep each point inside its section (guards the boundary convention)
    return s.ravel(), w.ravel(), np.flatnonzero(keep).repeat(model.quadrature_points)


# ----------------------------------------------------------------------------
# Spatial wrenches and the O(n) generalised force
# ----------------------------------------------------------------------------

def _spatial(g, W_body):
    """Ad(g)^-T W: body wrench at pose g -> world axes, moment about origin."""
    return np.einsum("...ji,...j->...i", lie.Ad_inv(g), W_body)


def _dead_to_body(g, W_world):
    R = g[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return np.concatenate([Rt @ W_world[..., :3, None], Rt @ W_world[..., 3:, None]], axis=-2)[..., 0]


def _body_wrenches(W, frames, g):
    """Body wrenches from wrenches given in world ("world") or body axes at poses g."""
    W = np.broadcast_to(W, g.shape[:-2] + (6,))
    is_world = np.array([f == "world" for f in frames])
    Wb = np.where(is_world[:, None], _dead_to_body(g, W.astype(g.dtype)), W)
    return Wb


def load_points(model, ch, loads):
    """All load application points for configuration chain ``ch``:
    (s, section index, local x, poses g, body wrenches W) with quadrature
    weights folded into distributed loads and gravity."""
    s_list, W_list, f_list = [], [], []
    grav = float(loads.gravity) if not isinstance(loads.gravity, bool) else (1.0 if loads.gravity else 0.0)
    if grav != 0.0 and np.any(model.gravity != 0):
        sq, wq, sec = gauss_points(model)
        rhoA = np.array([model.sections[i].M[0, 0] for i in sec])
        Ww = np.zeros((len(sq), 6))
        Ww[:, :3] = grav * (rhoA * wq)[:, None] * model.gravity[None, :]
        s_list.append(sq)
        W_list.append(Ww)
        f_list += ["world"] * len(sq)
    for d in loads.distributed:
        sq, wq, _ = gauss_points(model, d.start, d.end)
        s_list.append(sq)
        W_list.append(wq[:, None] * np.asarray(d.wrench, dtype=float)[None, :])
        f_list += [d.frame] * len(sq)
    for p in loads.point:
        s_list.append(np.array([min(max(p.s, 0.0), model.total_length)]))
        W_list.append(np.asarray(p.wrench, dtype=float)[None, :])
        f_list.append(p.frame)
    if not s_list:
        return None
    s = np.concatenate(s_list)
    W = np.concatenate(W_list)
    idx, x, g, own = kin._point_data(model, ch, s)
    Wb = _body_wrenches(W, f_list, g)
    return s, idx, x, g, own, Wb


def generalized_external_force(model, ch, loads):
    """Q (..., n_dof) and the total spatial load wrench (..., 6) (world axes,
    moment about the world origin) for loads at configuration chain ``ch``."""
    pts = load_points(model, ch, loads)
    batch = ch.q.shape[:-1]
    if pts is None:
        return np.zeros(batch + (model.n_dof,), dtype=ch.W.dtype), np.zeros(batch + (6,))
    s, idx, x, g, own, Wb = pts
    F = _spatial(g, Wb)                                              # (..., P, 6)
    n = model.n_sections
    onehot = (idx[:, None] == np.arange(n)[None, :]).astype(float)   # (P, n)
    F_sec = np.einsum("pn,...pi->...ni", onehot, F)                  # loads in each section
    F_distal = np.cumsum(F_sec[..., ::-1, :], axis=-2)[..., ::-1, :] - F_sec   # strictly distal
    Qfull = np.einsum("...nij,...ni->...nj", ch.W, F_distal)
    Qfull = Qfull + np.einsum("pn,...pij,...pi->...nj", onehot, own, F)
    Q = Qfull.reshape(batch + (6 * n,))[..., model.free_index]
    return Q, F.sum(axis=-2)


def actuation_force(model, ch, u):
    """Generalised actuation force tau (..., n_dof) for inputs u (n_actuators,)
    (tensions N for tendons, pressures Pa for chambers)."""
    batch = ch.q.shape[:-1]
    out = np.zeros(batch + (model.n_sections, 6), dtype=ch.strains.dtype)
    pts = actuator_point_loads(model, u)
    extra = 0.0
    if pts:
        extra = generalized_external_force(model, ch, Loads(point=pts, gravity=False))[0]
    for a, val in zip(model.actuators, u):
        if val == 0.0 or a.tendon_model == "point_moment":
            continue
        sq, wq, sec = gauss_points(model, a.start, a.end)
        d, dd = a.offset_at(sq)
        xi = ch.strains[..., sec, :]
        t = xi[..., :3] + np.cross(xi[..., 3:], d) + dd
        t = t / np.sqrt(np.sum(t * t, axis=-1))[..., None]
        dens = np.concatenate([t, np.cross(d, t)], axis=-1) * (wq[:, None] * (-a.force_per_unit_input * val))
        onehot = (sec[:, None] == np.arange(model.n_sections)[None, :]).astype(float)
        out = out + np.einsum("pn,...pi->...ni", onehot, dens)
    return out.reshape(batch + (6 * model.n_sections,))[..., model.free_index] + extra


def tendon_lengths(model, q):
    """Path length [m] of each actuator's routed span (tendon length; for
    chambers, the chamber length), by Gauss quadrature."""
    ch = kin.chain(model, q)
    out = []
    for a in model.actuators:
        sq, wq, sec = gauss_points(model, a.start, a.end)
        d, dd = a.offset_at(sq)
        xi = ch.strains[..., sec, :]
        t = xi[..., :3] + np.cross(xi[..., 3:], d) + dd
        out.append(np.sum(wq * np.sqrt(np.sum(t * t, axis=-1)), axis=-1))
    return np.array(out)
