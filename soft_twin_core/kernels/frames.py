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

from .spatial import _Ad_into, _jit, _map_into, _tangent_into


@_jit
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
        out[:, :] = w.g_out[j]


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
            _Ad_into(g, Ad, False)
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for c in range(6):
                        acc += Ad[r, c] * T[c, m.modes[j, a]]
                    J[r, iv + a] = x * acc
        else:
            _Ad_into(w.g_out[k], Ad, False)
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for c in range(6):
                        acc += Ad[r, c] * w.S[k, c, a]
                    J[r, iv + a] = acc
        k = m.parent[k]
