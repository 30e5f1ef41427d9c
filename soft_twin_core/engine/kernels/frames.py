"""Poses and Jacobians of points on the tree (numba), after
:func:`passes.forward_pass` (level 0).

A point is (joint j, abscissa x): for a soft joint with x >= 0 the
cross-section at x, pose ``g_in_j exp(x f_j)``; otherwise joint j's output
frame. Its spatial Jacobian (world axes, twist of the body frame through
the origin) has the columns ``Ad(g_out_k) S_k`` of every joint k on the
path from the root, except its own joint's, ``Ad(g_p) x T(x f_j) B`` for a
soft cross-section; the body Jacobian is ``Ad(g_p)^-1`` times it.
"""

import numpy as np

from soft_twin_core.engine.kernels.spatial import (FALSE, TRUE, _Ad_into, _ad_vec, _jit, _jit_inner,
                                                   _map_into, _tangent_dot_into, _tangent_into)


@_jit_inner
def _point_pose(m, w, j, x, out, x6, tmp):
    if x >= 0.0 and m.kind[j] == 5:
        for a in range(6):
            x6[a] = x * w.strain[j, a]
        _map_into(m.kmap[j], x6, tmp)
        for r in range(3):
            for c in range(4):
                acc = w.g_in[j, r, 3] if c == 3 else 0.0
                for k in range(3):
                    acc += w.g_in[j, r, k] * tmp[k, c]
                out[r, c] = acc
        out[3, :3] = 0.0
        out[3, 3] = 1.0
    else:
        for r in range(4):             # a loop, not a slice assignment (static_newton._copy)
            for c in range(4):
                out[r, c] = w.g_out[j, r, c]


@_jit
def point_pose(m, w, j, x, out):
    """out (4x4): world pose of the point (j, x)."""
    _point_pose(m, w, j, x, out, np.empty(6), np.empty((4, 4)))


@_jit
def point_poses(m, w, joint, x, out):
    """out[p] (4x4): world pose of point p = (joint[p], x[p])."""
    x6 = np.empty(6)
    tmp = np.empty((4, 4))
    for p in range(joint.shape[0]):
        _point_pose(m, w, joint[p], x[p], out[p], x6, tmp)


@_jit
def spatial_jacobian(m, w, j, x, g, J):
    """g: world pose of point (j, x); J (6, nv): its spatial Jacobian."""
    x6 = np.empty(6)
    tmp = np.empty((4, 4))
    Ad = np.empty((6, 6))
    T = np.empty((6, 6))
    S3 = np.empty((7, 3, 3))
    _point_pose(m, w, j, x, g, x6, tmp)
    J[:, :] = 0.0
    own = x >= 0.0 and m.kind[j] == 5
    k = j
    while k >= 0:
        nv, iv = m.nv[k], m.iv[k]
        if k == j and own:
            _tangent_into(m.kmap[j], x6, T, S3)
            _Ad_into(g, Ad, FALSE)
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for c in range(6):
                        acc += Ad[r, c] * T[c, m.modes[j, a]]
                    J[r, iv + a] = x * acc
        else:
            _Ad_into(w.g_out[k], Ad, FALSE)
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for c in range(6):
                        acc += Ad[r, c] * w.S[k, c, a]
                    J[r, iv + a] = acc
        k = m.parent[k]


@_jit_inner
def _col_dot(Ad, S, Sd_cols, V, nv, iv, out, tmp, tmp2):
    """out[:, iv:iv+nv] = Ad (ad(V) S + Sdot) column by column."""
    for c in range(nv):
        for r in range(6):
            tmp[r] = S[r, c]
        _ad_vec(V, tmp, tmp2)
        for r in range(6):
            tmp2[r] += Sd_cols[r, c]
        for r in range(6):
            acc = 0.0
            for k in range(6):
                acc += Ad[r, k] * tmp2[k]
            out[r, iv + c] = acc


@_jit
def world_point_jacobians(m, w, joint, x, g, J):
    """For points (joint[p], x[p]) (joint -1: the world origin): g[p] their
    world poses and J[p] (6, nv) the Jacobians of [velocity of the point;
    angular velocity], world axes (the spatial Jacobian shifted to the
    point: v_p = v_o + w x p)."""
    for p in range(joint.shape[0]):
        if joint[p] < 0:
            g[p, :, :] = 0.0
            for a in range(4):
                g[p, a, a] = 1.0
            J[p, :, :] = 0.0
            continue
        spatial_jacobian(m, w, joint[p], x[p], g[p], J[p])
        px, py, pz = g[p, 0, 3], g[p, 1, 3], g[p, 2, 3]
        for c in range(J.shape[2]):
            wx, wy, wz = J[p, 3, c], J[p, 4, c], J[p, 5, c]
            J[p, 0, c] += wy * pz - wz * py
            J[p, 1, c] += wz * px - wx * pz
            J[p, 2, c] += wx * py - wy * px


@_jit
def spatial_jacobian_dot(m, w, j, x, v, Jd):
    """Jd (6, nv): time derivative of the spatial Jacobian of point (j, x)
    after forward_pass (level >= 1). Column of joint k: Ad(g_k) (ad(V_k) S_k
    + Sdot_k) (g_k, V_k: pose and body twist of the frame S_k lives in;
    soft: Sdot = x Tdot(x f)[x fdot] B)."""
    x6 = np.empty(6)
    xd6 = np.empty(6)
    g = np.empty((4, 4))
    tmp4 = np.empty((4, 4))
    Ad = np.empty((6, 6))
    T = np.empty((6, 6))
    S3 = np.empty((7, 3, 3))
    Sx = np.zeros((6, 6))
    Sd = np.zeros((6, 6))
    Vp = np.empty(6)
    e = np.zeros(6)
    col = np.empty(6)
    P = np.empty((5, 6))
    t1 = np.empty(6)
    t2 = np.empty(6)
    t3 = np.empty(6)
    Jd[:, :] = 0.0
    own = x >= 0.0 and m.kind[j] == 5
    k = j
    while k >= 0:
        nv, iv = m.nv[k], m.iv[k]
        soft = m.kind[k] == 5
        xx = x if (k == j and own) else m.length[k]
        Sd[:, :] = 0.0
        if soft:
            for a in range(6):
                x6[a] = xx * w.strain[k, a]
                xd6[a] = xx * w.strain_rate[k, a]
            for c in range(nv):
                e[:] = 0.0
                e[m.modes[k, c]] = 1.0
                _tangent_dot_into(m.kmap[k], x6, xd6, e, col, P, t1, t2, t3)
                for r in range(6):
                    Sd[r, c] = xx * col[r]
        if k == j and own:
            _point_pose(m, w, j, x, g, x6, tmp4)
            for a in range(6):
                x6[a] = x * w.strain[j, a]
            _tangent_into(m.kmap[j], x6, T, S3)
            for c in range(nv):
                for r in range(6):
                    Sx[r, c] = x * T[r, m.modes[j, c]]
            # body twist of the cross-section: Ad(exp(-x f)) V_in + Sx v
            _map_into(m.kmap[j], x6, tmp4)
            _Ad_into(tmp4, Ad, TRUE)
            for r in range(6):
                acc = 0.0
                for c in range(6):
                    acc += Ad[r, c] * w.Vin[j, c]
                for c in range(nv):
                    acc += Sx[r, c] * v[iv + c]
                Vp[r] = acc
            _Ad_into(g, Ad, FALSE)
            _col_dot(Ad, Sx, Sd, Vp, nv, iv, Jd, t1, t2)
        else:
            _Ad_into(w.g_out[k], Ad, FALSE)
            _col_dot(Ad, w.S[k], Sd, w.V[k], nv, iv, Jd, t1, t2)
        k = m.parent[k]


@_jit
def offset_point_positions(m, w, joint, x, offset, G, out):
    """out[p] (3,): world position of the point ``offset[p]`` (3,) in the
    frame of (joint[p], x[p]) (G[p] receives that frame's pose)."""
    point_poses(m, w, joint, x, G)
    for p in range(joint.shape[0]):
        for r in range(3):
            out[p, r] = G[p, r, 3] + G[p, r, 0] * offset[p, 0] + G[p, r, 1] * offset[p, 1] + G[p, r, 2] * offset[p, 2]


@_jit_inner
def _shifted(Js, p, J, sign):
    """J (3, nv) += sign * the velocity at world point p of the body whose
    spatial Jacobian is Js (6, nv): v + w x p."""
    for c in range(J.shape[1]):
        wx, wy, wz = Js[3, c], Js[4, c], Js[5, c]
        J[0, c] += sign * (Js[0, c] + wy * p[2] - wz * p[1])
        J[1, c] += sign * (Js[1, c] + wz * p[0] - wx * p[2])
        J[2, c] += sign * (Js[2, c] + wx * p[1] - wy * p[0])


@_jit
def relative_point_jacobians(m, w, joint, x, body, p, J, Jw):
    """J[k] (3, nv): the Jacobian of the velocity at world point p[k] of the
    frame (joint[k], x[k]) relative to that of joint ``body[k]``'s output
    frame (-1: the world, at rest): of a contact point against an obstacle
    that body carries; Jw[k] (3, nv): that body's angular velocity's (zero
    for the world)."""
    g = np.empty((4, 4))
    Js = np.empty((6, J.shape[2]))
    for k in range(joint.shape[0]):
        J[k, :, :] = 0.0
        Jw[k, :, :] = 0.0
        spatial_jacobian(m, w, joint[k], x[k], g, Js)
        _shifted(Js, p[k], J[k], 1.0)
        if body[k] >= 0:
            spatial_jacobian(m, w, body[k], -1.0, g, Js)
            _shifted(Js, p[k], J[k], -1.0)
            for r in range(3):
                for c in range(J.shape[2]):
                    Jw[k, r, c] = Js[3 + r, c]


@_jit
def body_point_twists(m, w, body, p, v, out):
    """out[k] (6,): [velocity at world point p[k]; angular velocity] of
    joint ``body[k]``'s output frame at joint velocities v (zeros for
    body -1, the world)."""
    g = np.empty((4, 4))
    Js = np.empty((6, v.shape[0]))
    Jp = np.empty((3, v.shape[0]))
    for k in range(body.shape[0]):
        out[k, :] = 0.0
        if body[k] < 0:
            continue
        spatial_jacobian(m, w, body[k], -1.0, g, Js)
        Jp[:, :] = 0.0
        _shifted(Js, p[k], Jp, 1.0)
        for r in range(3):
            for c in range(v.shape[0]):
                out[k, r] += Jp[r, c] * v[c]
                out[k, 3 + r] += Js[3 + r, c] * v[c]


@_jit
def frame_spins(m, w, joint, x, v, R, W, Jw):
    """For frames (joint[k], x[k]) (the workspace posed): R[k] (3, 3) their
    world rotations, W[k] (3,) their angular velocities at joint velocities
    v, Jw[k] (3, nv) the Jacobians of those (world axes)."""
    g = np.empty((4, 4))
    Js = np.empty((6, v.shape[0]))
    for k in range(joint.shape[0]):
        spatial_jacobian(m, w, joint[k], x[k], g, Js)
        for r in range(3):
            acc = 0.0
            for c in range(v.shape[0]):
                Jw[k, r, c] = Js[3 + r, c]
                acc += Js[3 + r, c] * v[c]
            W[k, r] = acc
            for c in range(3):
                R[k, r, c] = g[r, c]
