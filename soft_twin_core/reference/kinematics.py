"""PCS forward kinematics, soft geometric Jacobian and its time derivative.

Slides part B, "Kinematics - multiple elements": the pose of the cross-section
at arc length s in section i, local abscissa x, is the product of exponentials

    g(s) = g_base  prod_{j<i} [exp(L_j f_j) O_j]  exp(x f_i)

(O_j: rigid offset after section j, identity inside a segment). With the
Cayley map selected, ``cay`` replaces ``exp``.

Jacobian (body frame at s, 6 x n_dof) maps free strain rates to the body
twist eta = [v; w] of the cross-section: ``eta(s) = J(s) qdot``. It is built
from spatial column blocks ``W_j = Ad(g_j) L_j T(L_j f_j) B_j`` (g_j: frame
at the end of section j) so that ``J(s) = Ad(g(s))^-1 [W_1 .. W_{i-1},
Ad(g(s)) x T(x f_i) B_i, 0 ..]``. The world-frame Jacobian is
``blockdiag(R, R) J`` (velocity of the section origin and angular velocity,
both expressed in world axes).

All functions take q of shape (..., n_dof) (a stack of configurations is
allowed) and arc lengths s of shape (P,) in metres.
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import thread_workspace


def _maps(model):
    if model.kinematic_map == "cayley":
        return lie.cay_se3, lie.T_cay_se3
    return lie.exp_se3, lie.T_se3


def _tangent_dot(model, x, xdot):
    if model.kinematic_map == "cayley":
        # T_cay is rational in x: the complex step is exact to machine precision
        h = 1e-30
        return lie.T_cay_se3(x + 1j * h * xdot).imag / h
    return lie.T_se3_dot(x, xdot)


@dataclass
class Chain:
    """Per-configuration data shared by kinematic queries (no model data).

    strains (..., n, 6); g_start, g_end (..., n, 4, 4) world poses of each
    section's start and end (before any rigid offset); W (..., n, 6, 6)
    spatial Jacobian column blocks of each whole section (all six modes):
    ``W_j = Ad(g_end_j) L_j T(L_j f_j)``."""
    q: np.ndarray
    strains: np.ndarray
    g_start: np.ndarray
    g_end: np.ndarray
    W: np.ndarray
    g_tip: np.ndarray


def chain(model, q):
    """Section frames and spatial Jacobian blocks for configuration(s) q."""
    q = model.check_q(q)
    xi = model.strains(q)
    expmap, tangent = _maps(model)
    L = model.lengths[:, None]
    E = expmap(L * xi)                                  # (..., n, 4, 4)
    S = model.lengths[:, None, None] * tangent(L * xi)  # (..., n, 6, 6)
    n = model.n_sections
    g_start = np.empty(E.shape, dtype=E.dtype)
    g_end = np.empty(E.shape, dtype=E.dtype)
    g = np.broadcast_to(model.base_pose, E.shape[:-3] + (4, 4))
    for i in range(n):
        g_start[..., i, :, :] = g
        g = g @ E[..., i, :, :]
        g_end[..., i, :, :] = g
        if i < n - 1 and model.has_offsets:
            g = g @ model.offsets[i]
    W = lie.Ad(g_end) @ S
    return Chain(q, xi, g_start, g_end, W, g)


def _point_data(model, ch, s):
    idx, x = model.locate(s)
    expmap, tangent = _maps(model)
    xi_p = ch.strains[..., idx, :]                      # (..., P, 6)
    g0 = ch.g_start[..., idx, :, :]
    g = g0 @ expmap(x[:, None] * xi_p)
    own = lie.Ad(g) @ (x[:, None, None] * tangent(x[:, None] * xi_p))
    return idx, x, g, own


def _assemble(model, blocks, own, idx):
    """Spatial J (..., P, 6, n_dof) from section blocks (..., n, 6, 6) before the
    point's section and the point's own block (..., P, 6, 6)."""
    n = model.n_sections
    sec = np.arange(n)
    before = (sec[None, :] < idx[:, None]).astype(float)          # (P, n)
    at = (sec[None, :] == idx[:, None]).astype(float)
    Wt = np.swapaxes(blocks, -3, -2)                              # (..., 6, n, 6)
    J = before[:, None, :, None] * Wt[..., None, :, :, :] \
        + at[:, None, :, None] * own[..., :, :, None, :]
    J = J.reshape(J.shape[:-2] + (6 * n,))
    return J[..., model.free_index]


def poses(model, q, s):
    """World poses (..., P, 4, 4) of the cross-sections at arc lengths s [m]."""
    ch = chain(model, q)
    return _point_data(model, ch, np.atleast_1d(np.asarray(s, dtype=float)))[2]


def tip_pose(model, q):
    """World pose (..., 4, 4) of the tip cross-section."""
    return chain(model, q).g_tip


def backbone_abscissae(model, points_per_section=10):
    """Arc lengths [m] sampling every section at ``points_per_section`` equal
    steps, plus the tip (n * points_per_section + 1 values)."""
    k = np.arange(points_per_section) / points_per_section
    s = (model.s_starts[:, None] + model.lengths[:, None] * k[None, :]).ravel()
    return np.append(s, model.total_length)


def backbone(model, q, points_per_section=10):
    """(s, poses): arc lengths (N,) and world poses (..., N, 4, 4) along the backbone.
    A single real q of an exponential-map model uses the compiled kernel."""
    s = backbone_abscissae(model, points_per_section)
    q = model.check_q(q)
    if q.ndim == 1 and not np.iscomplexobj(q):
        return s, _engine_poses(model, q, s)
    return s, poses(model, q, s)


def _engine_poses(model, q, s):
    """World poses at arc lengths s on the multibody engine (one real q)."""
    tree = model.tree
    joints, x = tree.path("backbone").locate(s)
    return alg.point_poses(tree, thread_workspace(tree), q, joints, x)


def jacobian(model, q, s, frame="body"):
    """Soft geometric Jacobian at arc lengths s: (..., P, 6, n_dof).

    frame="body": body twist [v; w] of the cross-section in its own axes.
    frame="world": the same twist with both parts expressed in world axes
    (v is the world velocity of the centre-line point).
    """
    ch = chain(model, q)
    s = np.atleast_1d(np.asarray(s, dtype=float))
    idx, _, g, own = _point_data(model, ch, s)
    J = lie.Ad_inv(g) @ _assemble(model, ch.W, own, idx)
    if frame == "body":
        return J
    if frame == "world":
        return _rotate_to_world(g, J)
    raise ValueError(f"frame: expected 'body' or 'world', got {frame!r}")


def _rotate_to_world(g, J):
    R = g[..., :3, :3]
    return np.concatenate([R @ J[..., :3, :], R @ J[..., 3:, :]], axis=-2)


def tip_jacobian(model, q, frame="body"):
    """Jacobian (..., 6, n_dof) of the tip (all blocks are whole sections);
    on the multibody engine for a single real q."""
    q = model.check_q(q)
    g, Js = None, None
    if q.ndim == 1 and not np.iscomplexobj(q):
        g, Js = tip_and_spatial_jacobian(model, q)
    if g is None:
        ch = chain(model, q)
        Wt = np.swapaxes(ch.W, -3, -2)
        g = ch.g_tip
        Js = Wt.reshape(Wt.shape[:-2] + (6 * model.n_sections,))[..., model.free_index]
    J = lie.Ad_inv(g) @ Js
    if frame == "world":
        return _rotate_to_world(g, J)
    return J


def tip_and_spatial_jacobian(model, q):
    """(tip pose 4x4, spatial tip Jacobian 6 x n_dof) for one real q, on the
    multibody engine (:func:`algorithms.point_jacobian`); the body Jacobian
    is ``Ad(g_tip)^-1 Js``."""
    tree = model.tree
    return alg.point_jacobian(tree, thread_workspace(tree), q, tree.n_joints - 1, -1.0, "spatial")


def _full_rates(model, qdot):
    qd = np.zeros(qdot.shape[:-1] + (6 * model.n_sections,), dtype=qdot.dtype)
    qd[..., model.free_index] = qdot
    return qd.reshape(qdot.shape[:-1] + (model.n_sections, 6))


def jacobian_and_derivative(model, q, qdot, s):
    """Body Jacobian J(s) and its time derivative dJ/dt along (q, qdot).

    Returns (g, J, Jdot, eta): poses (..., P, 4, 4), J and Jdot
    (..., P, 6, n_dof), body twists eta = J qdot (..., P, 6).
    Jdot: spatial blocks W_j evolve as ``ad(V_j) W_j + Ad(g_j) dS_j/dt``
    (V_j spatial twist of the section end g_j) and ``d/dt Ad(g)^-1 = -ad(eta) Ad(g)^-1``.
    """
    ch = chain(model, q)
    qdot = model.check_q(qdot, "qdot")
    s = np.atleast_1d(np.asarray(s, dtype=float))
    idx, x, g, own = _point_data(model, ch, s)
    xid = _full_rates(model, qdot)                                   # (..., n, 6)
    L = model.lengths[:, None]
    # spatial twists of section ends: V_end_j = sum_{k<=j} W_k xid_k
    contrib = np.einsum("...nij,...nj->...ni", ch.W, xid)
    V_end = np.cumsum(contrib, axis=-2)
    Sdot = model.lengths[:, None, None] * _tangent_dot(model, L * ch.strains, L * xid)
    Wdot = lie.ad(V_end) @ ch.W + lie.Ad(ch.g_end) @ Sdot
    # own block: spatial twist of the point = V_start_i + own xid_i
    Vp = (V_end - contrib)[..., idx, :] + np.einsum("...pij,...pj->...pi", own, xid[..., idx, :])
    own_dot = lie.ad(Vp) @ own + lie.Ad(g) @ (
        x[:, None, None] * _tangent_dot(model, x[:, None] * ch.strains[..., idx, :],
                                        x[:, None] * xid[..., idx, :]))
    Js = _assemble(model, ch.W, own, idx)
    Jsdot = _assemble(model, Wdot, own_dot, idx)
    Ainv = lie.Ad_inv(g)
    J = Ainv @ Js
    eta = np.einsum("...ij,...j->...i", J, qdot[..., None, :])
    Jdot = Ainv @ Jsdot - lie.ad(eta) @ J
    return g, J, Jdot, eta


def point_motion(model, q, qdot, qddot, s):
    """Velocities and accelerations of backbone points.

    Returns a dict with body twists ``eta`` and their derivative ``eta_dot``
    (..., P, 6), world positions ``p_world``, world linear velocity
    ``v_world`` = R v and acceleration ``a_world`` = R (vdot + w x v) of the
    centre-line points, and world angular velocity/acceleration.
    """
    qddot = model.check_q(qddot, "qddot")
    g, J, Jdot, eta = jacobian_and_derivative(model, q, qdot, s)
    eta_dot = np.einsum("...ij,...j->...i", J, qddot[..., None, :]) \
        + np.einsum("...ij,...j->...i", Jdot, np.asarray(qdot)[..., None, :])
    R = g[..., :3, :3]
    v, w = eta[..., :3], eta[..., 3:]
    vd, wd = eta_dot[..., :3], eta_dot[..., 3:]
    rot = lambda a: np.einsum("...ij,...j->...i", R, a)  # noqa: E731
    return {
        "eta": eta, "eta_dot": eta_dot, "p_world": g[..., :3, 3],
        "v_world": rot(v), "a_world": rot(vd + np.cross(w, v)),
        "omega_world": rot(w), "alpha_world": rot(wd),
    }


# ----------------------------------------------------------------------------
# Helix geometry of a section (slides part B "Physical meaning: Helix!")
# ----------------------------------------------------------------------------

def helix_parameters(f):
    """Curvature kappa, torsion tau [1/m] and Frenet frame of the helix traced
    by a constant strain f = [f_u; f_w] (per unit length).

    kappa = |f_w x f_u| / |f_u|^3 ... for |f_u| = 1 the slides' |d_w x d_u|/L^2;
    tau = (f_w . f_u)/|f_u|^2; the Frenet frame at s = 0 in the section frame
    is t = f_u/|f_u|, n = (f_w x f_u)/|f_w x f_u|, b = t x n (n, b undefined
    when kappa = 0: returned as NaN).
    """
    f = np.asarray(f, dtype=float)
    fu, fw = f[..., :3], f[..., 3:]
    nu = np.linalg.norm(fu, axis=-1)
    c = np.cross(fw, fu)
    nc = np.linalg.norm(c, axis=-1)
    kappa = nc / nu**2
    tau = np.sum(fw * fu, axis=-1) / nu**2
    t = fu / nu[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        n = c / nc[..., None]
    b = np.cross(t, n)
    return kappa, tau, np.stack([t, n, b], axis=-1)
