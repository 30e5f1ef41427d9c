"""The tip error of an actuation IK and its Jacobian, compiled (numba).

For a tip pose g = (R, p) and a target (R*, p*), with per-axis position
weights ``sw`` and the orientation weight ``swo`` [m/rad]:

    e = [sw * (p* - p);  swo * log(R^T R*)]        (the rotation part only with_rot)

and, for inputs u moving the equilibrium by dq/du (body tip Jacobian J_b),

    de/du = -[sw * (R J_b[:3] dq/du);  swo * T_so3(-e_R)^-1 J_b[3:] dq/du]

(e_R = log(R^T R*): ``d log(R^T R*) = -T_so3(-e_R)^-1 w_body`` for a body
rotation rate w_body of R). Same formulas as :func:`soft_twin_core.lie.log_so3`
and :func:`soft_twin_core.lie.T_so3_inv` (tested against them): one compiled
call replaces a dozen numpy calls on 3x3 arrays, most of the actuation IK's
Python time once its statics was compiled.
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.kernels.spatial import TRUE, _Ad_into, _horner, _jit, _jit_inner

_SMALL2 = lie._SMALL ** 2
P_T_OVER_SIN = lie._P_T_OVER_SIN
P_D = lie._P_D


@_jit_inner
def _log_so3(R, out):
    """out = log(R) (rotation vector, angle in [0, pi]), as lie.log_so3:
    atan2 of the skew part's norm and the trace; near pi the axis from the
    symmetric part, its sign from the skew part."""
    s0 = 0.5 * (R[2, 1] - R[1, 2])
    s1 = 0.5 * (R[0, 2] - R[2, 0])
    s2 = 0.5 * (R[1, 0] - R[0, 1])
    cos_t = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    sin_t = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    theta = np.arctan2(sin_t, cos_t)
    t2 = theta * theta
    f = _horner(P_T_OVER_SIN, t2) if t2 < _SMALL2 else theta / sin_t
    out[0], out[1], out[2] = f * s0, f * s1, f * s2
    if cos_t < -0.5:
        # the column of S = (R + R^T)/2 - cos I = (1 - cos) n n^T with the largest diagonal
        k = 0
        for i in range(1, 3):
            if R[i, i] > R[k, k]:
                k = i
        c0 = 0.5 * (R[0, k] + R[k, 0]) - (cos_t if k == 0 else 0.0)
        c1 = 0.5 * (R[1, k] + R[k, 1]) - (cos_t if k == 1 else 0.0)
        c2 = 0.5 * (R[2, k] + R[k, 2]) - (cos_t if k == 2 else 0.0)
        nrm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        sign = -1.0 if c0 * s0 + c1 * s1 + c2 * s2 < 0 else 1.0
        f = sign * theta / nrm
        out[0], out[1], out[2] = f * c0, f * c1, f * c2


@_jit_inner
def _T_so3_inv(w, out):
    """out = T_so3(w)^-1 = I + W/2 + d W^2, d = (1 - (t/2) cot(t/2)) / t^2."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if t2 < _SMALL2:
        d = _horner(P_D, t2)
    else:
        t = np.sqrt(t2)
        d = (1.0 - 0.5 * t * np.cos(0.5 * t) / np.sin(0.5 * t)) / t2
    W = np.zeros((3, 3))
    W[0, 1], W[0, 2], W[1, 0], W[1, 2], W[2, 0], W[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    for r in range(3):
        for c in range(3):
            acc = 0.0
            for k in range(3):
                acc += W[r, k] * W[k, c]
            out[r, c] = (1.0 if r == c else 0.0) + 0.5 * W[r, c] + d * acc


@_jit
def tip_error(g, target, sw, swo, with_rot, e):
    """e (3, or 6 with_rot) as above; returns (position distance [m],
    weighted position error [m], orientation error [rad], 0 without rot)."""
    pe2 = 0.0
    we2 = 0.0
    for a in range(3):
        d = target[a, 3] - g[a, 3]
        e[a] = sw[a] * d
        pe2 += d * d
        we2 += e[a] * e[a]
    oe = 0.0
    if with_rot:
        Rr = np.empty((3, 3))
        for r in range(3):
            for c in range(3):
                Rr[r, c] = g[0, r] * target[0, c] + g[1, r] * target[1, c] + g[2, r] * target[2, c]
        lg = np.empty(3)
        _log_so3(Rr, lg)
        for a in range(3):
            e[3 + a] = swo * lg[a]
        oe = np.sqrt(lg[0] * lg[0] + lg[1] * lg[1] + lg[2] * lg[2])
    return np.sqrt(pe2), np.sqrt(we2), oe


@_jit
def error_jacobian(g, Js, dq_du, e, sw, swo, with_rot, Je):
    """Je (3 or 6, n_act) = de/du as above, from the spatial tip Jacobian Js
    (6, n_dof) and dq/du (n_dof, n_act)."""
    n_dof, n_act = dq_du.shape[0], dq_du.shape[1]
    Ad = np.empty((6, 6))
    _Ad_into(g, Ad, TRUE)
    # tip twist per input, body axes: Ad(g)^-1 Js dq/du
    JsU = np.zeros((6, n_act))
    for r in range(6):
        for k in range(n_dof):
            x = Js[r, k]
            if x != 0.0:
                for c in range(n_act):
                    JsU[r, c] += x * dq_du[k, c]
    JbU = np.zeros((6, n_act))
    for r in range(6):
        for k in range(6):
            x = Ad[r, k]
            if x != 0.0:
                for c in range(n_act):
                    JbU[r, c] += x * JsU[k, c]
    for r in range(3):
        for c in range(n_act):
            Je[r, c] = -sw[r] * (g[r, 0] * JbU[0, c] + g[r, 1] * JbU[1, c] + g[r, 2] * JbU[2, c])
    if with_rot:
        er = np.zeros(3)
        if swo > 0:
            for a in range(3):
                er[a] = -e[3 + a] / swo
        Ti = np.empty((3, 3))
        _T_so3_inv(er, Ti)
        for r in range(3):
            for c in range(n_act):
                Je[3 + r, c] = -swo * (Ti[r, 0] * JbU[3, c] + Ti[r, 1] * JbU[4, c] + Ti[r, 2] * JbU[5, c])
