"""Plain numpy reference of the multibody dynamics, by explicit Jacobians.

Independent of the recursive passes (:mod:`soft_twin_core.engine.algorithms`) they
are tested against: every mass point (a rigid body, or a Gauss point of a
soft section with weight w_p) has an explicit body Jacobian

    J_p = [ ... Ad(g_p^-1 g_j) S_j ... ]   (ancestor joints j of the point)

(own column of a point inside a soft section: x T(x f) B), its time
derivative in closed form

    d/dt [Ad(g_p^-1 g_j) S_j] = Ad(g_p^-1 g_j) (ad(V_j) S_j + Sdot_j) - ad(V_p) Ad(g_p^-1 g_j) S_j

(V_j = J_j v, V_p = J_p v), and the Lagrangian equations of motion follow by
summation:

    M = sum_p J_p^T I_p J_p
    C v = sum_p J_p^T (I_p Jdot_p v - ad(V_p)^T I_p V_p)
    g = -sum_p J_p^T I_p [R_p^T g_world; 0]          (gravity)
    tau = M a + C v + g + K (q - q0) + D v - J^T F_ext

Slow (Python loops over points and joints) and readable; the soft-chain
special case also agrees with :mod:`soft_twin_core.reference.dynamics`.
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.joint_kinds import SOFT
from soft_twin_core.reference.joints import joint_transform, point_transform, subspace, subspace_dot


def _qv(model, i, q, v=None):
    j = model.joints[i]
    a, b = model.idx_q[i], model.idx_v[i]
    qi = q[a:a + j.nq]
    return (qi, None) if v is None else (qi, v[b:b + j.nv])


def placements(model, q):
    """World poses of every joint's input and output frame: (g_in, g_out), (n, 4, 4)."""
    n = model.n_joints
    dt = np.result_type(q, float)
    g_in, g_out = np.empty((n, 4, 4), dtype=dt), np.empty((n, 4, 4), dtype=dt)
    for i, j in enumerate(model.joints):
        base = np.eye(4) if j.parent < 0 else g_out[j.parent]
        g_in[i] = base @ j.placement
        g_out[i] = g_in[i] @ joint_transform(j, _qv(model, i, q)[0])
    return g_in, g_out


def point_pose(model, q, i, x=None, local=None, frames=None):
    """World pose of a point on joint i's body: a soft section's cross-section
    at abscissa x (None: the output frame), then the local placement."""
    g_in, g_out = placements(model, q) if frames is None else frames
    local = np.eye(4) if local is None else local
    j = model.joints[i]
    if j.kind == SOFT and x is not None:
        return g_in[i] @ point_transform(j, _qv(model, i, q)[0], x) @ local
    return g_out[i] @ local


def point_jacobian(model, q, i, x=None, local=None, frames=None):
    """Body Jacobian (6, nv) of the point (see :func:`point_pose`)."""
    frames = placements(model, q) if frames is None else frames
    g_p = point_pose(model, q, i, x, local, frames)
    gi = lie.se3_inv(g_p)
    J = np.zeros((6, model.nv), dtype=g_p.dtype)
    for k in model.support(i):
        jk = model.joints[k]
        b = model.idx_v[k]
        qk = _qv(model, k, q)[0]
        if k == i and jk.kind == SOFT and x is not None:
            Pinv = lie.se3_inv(np.eye(4) if local is None else local)
            J[:, b:b + jk.nv] = lie.Ad(Pinv) @ subspace(jk, qk, x)
        else:
            J[:, b:b + jk.nv] = lie.Ad(gi @ frames[1][k]) @ subspace(jk, qk)
    return J


def point_jacobian_dot(model, q, v, i, x=None, local=None, frames=None):
    """Time derivative of :func:`point_jacobian` along (q, v), closed form."""
    frames = placements(model, q) if frames is None else frames
    g_p = point_pose(model, q, i, x, local, frames)
    gi = lie.se3_inv(g_p)
    V_p = point_jacobian(model, q, i, x, local, frames) @ v
    Jd = np.zeros((6, model.nv), dtype=np.result_type(g_p, v, float))
    for k in model.support(i):
        jk = model.joints[k]
        b = model.idx_v[k]
        qk, vk = _qv(model, k, q, v)
        if k == i and jk.kind == SOFT and x is not None:
            Pinv = lie.se3_inv(np.eye(4) if local is None else local)
            Jd[:, b:b + jk.nv] = lie.Ad(Pinv) @ subspace_dot(jk, qk, vk, x)
        else:
            A = lie.Ad(gi @ frames[1][k])
            S = subspace(jk, qk)
            V_k = point_jacobian(model, q, k, None, None, frames) @ v
            Jd[:, b:b + jk.nv] = A @ (lie.ad(V_k) @ S + subspace_dot(jk, qk, vk)) - lie.ad(V_p) @ A @ S
    return Jd


def mass_points(model, q, frames=None):
    """Every mass point: list of (joint, x or None, world pose, 6x6 inertia
    (Gauss weight folded in for soft sections))."""
    frames = placements(model, q) if frames is None else frames
    out = []
    for i, j in enumerate(model.joints):
        if j.kind == SOFT:
            sec = j.section
            xg, wg = np.polynomial.legendre.leggauss(sec.quadrature_points)
            for xs, ws in zip(0.5 * sec.length * (xg + 1), 0.5 * sec.length * wg):
                out.append((i, xs, point_pose(model, q, i, xs, None, frames), ws * sec.Mc))
        elif np.any(j.inertia != 0):
            out.append((i, None, frames[1][i], j.inertia))
    return out


def mass_matrix(model, q):
    frames = placements(model, q)
    M = np.zeros((model.nv, model.nv), dtype=np.result_type(q, float))
    for i, x, g, I in mass_points(model, q, frames):
        J = point_jacobian(model, q, i, x, None, frames)
        M += J.T @ I @ J
    return M


def bias_force(model, q, v):
    """C(q, v) v (Coriolis and centrifugal)."""
    frames = placements(model, q)
    out = np.zeros(model.nv, dtype=np.result_type(q, v, float))
    for i, x, g, I in mass_points(model, q, frames):
        J = point_jacobian(model, q, i, x, None, frames)
        Jd = point_jacobian_dot(model, q, v, i, x, None, frames)
        V = J @ v
        out += J.T @ (I @ (Jd @ v) - lie.ad(V).T @ I @ V)
    return out


def gravity_force(model, q, gravity=None):
    """g(q): the generalised gravity term on the left-hand side (minus the
    generalised force of gravity)."""
    gw = model.gravity if gravity is None else np.asarray(gravity, float)
    frames = placements(model, q)
    out = np.zeros(model.nv, dtype=np.result_type(q, float))
    for i, x, g, I in mass_points(model, q, frames):
        J = point_jacobian(model, q, i, x, None, frames)
        a = np.concatenate([g[:3, :3].T @ gw, np.zeros(3)])
        out -= J.T @ I @ a
    return out


def elastic_force(model, q, v):
    """K (q - q0) + D v, joint by joint (soft sections: B^T L K B and B^T L D B;
    rigid 1-dof joints: their passive spring and damper)."""
    out = np.zeros(model.nv, dtype=np.result_type(q, v, float))
    for i, j in enumerate(model.joints):
        qi, vi = _qv(model, i, q, v)
        b = model.idx_v[i]
        q0i = model.q0[model.idx_q[i]:model.idx_q[i] + j.nq]
        if j.kind == SOFT:
            m = j.section.modes
            L = j.section.length
            out[b:b + j.nv] = L * (j.section.K[np.ix_(m, m)] @ (qi - q0i) + j.section.D[np.ix_(m, m)] @ vi)
        elif j.nv == 1:
            out[b] = j.stiffness * (qi[0] - q0i[0]) + j.damping * vi[0]
    return out


def inverse_dynamics(model, q, v, a, gravity=None):
    """tau = M a + C v + g(q) + K (q - q0) + D v (no external loads)."""
    return (mass_matrix(model, q) @ a + bias_force(model, q, v) + gravity_force(model, q, gravity)
            + elastic_force(model, q, v))


def kinetic_energy(model, q, v):
    return 0.5 * v @ mass_matrix(model, q) @ v


def potential_energy(model, q):
    """Elastic (soft sections and joint springs) plus gravitational [J]."""
    frames = placements(model, q)
    e = 0.0
    for i, x, g, I in mass_points(model, q, frames):
        m = I[0, 0]
        c = np.array([I[5, 1], I[3, 2], I[4, 0]]) / m if m else np.zeros(3)   # I[3:, :3] = m hat(c)
        e -= m * model.gravity @ (g[:3, :3] @ c + g[:3, 3])
    for i, j in enumerate(model.joints):
        qi = _qv(model, i, q)[0]
        q0i = model.q0[model.idx_q[i]:model.idx_q[i] + j.nq]
        if j.kind == SOFT:
            m_ = j.section.modes
            d = qi - q0i
            e += 0.5 * j.section.length * d @ j.section.K[np.ix_(m_, m_)] @ d
        elif j.nv == 1:
            e += 0.5 * j.stiffness * (qi[0] - q0i[0]) ** 2
    return e
