"""Compiled (numba) kernel of the dynamics: M(q) and the applied-minus-bias
force f(q, qdot, u, loads), for the exponential map.

Same formulas as :func:`soft_twin_core.dynamics.dynamics_terms` (tested
against it to 1e-12), organised as one recursive pass over the sections:

* section ends g_j, spatial Jacobian blocks W_j = Ad(g_j) L_j T(L_j f_j),
  spatial twists V_j = sum_{k<=j} W_k fdot_k and spatial bias accelerations
  A_j = A_{j-1} + ad(V_j) W_j fdot_j + Ad(g_j) L_j Tdot(L_j f_j)[L_j fdot_j] fdot_j;
* at a point p of section i (local x): body Jacobian columns Ad(g_p)^-1 W_j
  (j < i) and x T(x f_i); body bias acceleration Jdot qdot = Ad(g_p)^-1 A_p
  (the ad(eta) eta term vanishes).

numpy's per-call overhead dominates the small arrays of a soft arm (tens of
microseconds per operation); the loops here run in a few microseconds.
"""

import numpy as np
import numba as nb

from . import lie
from .loads import Loads, gauss_points

_SMALL2 = lie._SMALL ** 2
_SMALLD2 = lie._SMALL_DERIV ** 2
P_A, P_B, P_C = lie._P_A, lie._P_B, lie._P_C
P_B1, P_B2, P_B3, P_B4 = lie._P_BETA
P_D1, P_D2, P_D3, P_D4 = lie._P_DBETA

_jit = nb.njit(cache=True, fastmath=False)


@_jit
def _horner(p, t2):
    out = p[0]
    for k in range(1, p.shape[0]):
        out = out * t2 + p[k]
    return out


@_jit
def _ad_vec(x, y, out):
    """out = ad(x) y = [w x yu + u x yw; w x yw]."""
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    a0, a1, a2, b0, b1, b2 = y[0], y[1], y[2], y[3], y[4], y[5]
    out[0] = w1 * a2 - w2 * a1 + u1 * b2 - u2 * b1
    out[1] = w2 * a0 - w0 * a2 + u2 * b0 - u0 * b2
    out[2] = w0 * a1 - w1 * a0 + u0 * b1 - u1 * b0
    out[3] = w1 * b2 - w2 * b1
    out[4] = w2 * b0 - w0 * b2
    out[5] = w0 * b1 - w1 * b0


@_jit
def _ad_mat(x, A):
    A[:, :] = 0.0
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    for o in (0, 3):
        A[o + 0, o + 1] = -w2
        A[o + 0, o + 2] = w1
        A[o + 1, o + 0] = w2
        A[o + 1, o + 2] = -w0
        A[o + 2, o + 0] = -w1
        A[o + 2, o + 1] = w0
    A[0, 4] = -u2
    A[0, 5] = u1
    A[1, 3] = u2
    A[1, 5] = -u0
    A[2, 3] = -u1
    A[2, 4] = u0


@_jit
def _exp_se3(x, g):
    w0, w1, w2 = x[3], x[4], x[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < _SMALL2:
        a, b, c = _horner(P_A, t2), _horner(P_B, t2), _horner(P_C, t2)
    else:
        t = np.sqrt(t2)
        s, co = np.sin(t), np.cos(t)
        a, b, c = s / t, (1.0 - co) / t2, (t - s) / (t2 * t)
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    W2 = W @ W
    g[:, :] = 0.0
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            g[i, j] = e + a * W[i, j] + b * W2[i, j]
        acc = 0.0
        for j in range(3):
            e = 1.0 if i == j else 0.0
            acc += (e + b * W[i, j] + c * W2[i, j]) * x[j]
        g[i, 3] = acc
    g[3, 3] = 1.0


@_jit
def _betas(t2):
    if t2 < _SMALL2:
        return _horner(P_B1, t2), _horner(P_B2, t2), _horner(P_B3, t2), _horner(P_B4, t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    return ((4.0 - t * s - 4.0 * c) / (2 * t2), (4.0 * t - 5.0 * s + t * c) / (2 * t2 * t),
            (2.0 - t * s - 2.0 * c) / (2 * t2 * t2), (2.0 * t - 3.0 * s + t * c) / (2 * t2 * t2 * t))


@_jit
def _dbetas(t2):
    if t2 < _SMALLD2:
        return _horner(P_D1, t2), _horner(P_D2, t2), _horner(P_D3, t2), _horner(P_D4, t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    N1, N2 = 4.0 - t * s - 4.0 * c, 4.0 * t - 5.0 * s + t * c
    N3, N4 = 2.0 - t * s - 2.0 * c, 2.0 * t - 3.0 * s + t * c
    d1, d2 = 3.0 * s - t * c, 4.0 - 4.0 * c - t * s
    d3, d4 = s - t * c, 2.0 - 2.0 * c - t * s
    return ((t * d1 - 2 * N1) / (2 * t ** 4), (t * d2 - 3 * N2) / (2 * t ** 5),
            (t * d3 - 4 * N3) / (2 * t ** 6), (t * d4 - 5 * N4) / (2 * t ** 7))


@_jit
def _T_se3(x, T):
    b1, b2, b3, b4 = _betas(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    A = np.empty((6, 6))
    _ad_mat(x, A)
    A2 = A @ A
    A3 = A2 @ A
    A4 = A2 @ A2
    for i in range(6):
        for j in range(6):
            T[i, j] = (1.0 if i == j else 0.0) - b1 * A[i, j] + b2 * A2[i, j] - b3 * A3[i, j] + b4 * A4[i, j]


@_jit
def _T_dot_vec(x, xd, y, out):
    """out = (d/dt T_se3(x))[xd] y, differentiating the quartic in ad(x)."""
    t2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5]
    wwd = x[3] * xd[3] + x[4] * xd[4] + x[5] * xd[5]
    b = _betas(t2)
    db = _dbetas(t2)
    P = np.empty((5, 6))      # P[m] = ad(x)^m y
    P[0, :] = y
    for m in range(1, 5):
        _ad_vec(x, P[m - 1], P[m])
    # D[k] = d(ad^k) y = sum_j ad^j ad(xd) ad^(k-1-j) y
    tmp = np.empty(6)
    tmp2 = np.empty(6)
    out[:] = 0.0
    for k in range(1, 5):
        sign = -1.0 if k % 2 == 1 else 1.0
        acc = np.zeros(6)
        for j in range(k):
            _ad_vec(xd, P[k - 1 - j], tmp)
            for r in range(j):
                _ad_vec(x, tmp, tmp2)
                tmp[:] = tmp2
            acc += tmp
        out += sign * (db[k - 1] * wwd * P[k] + b[k - 1] * acc)


@_jit
def _Ad(g, A):
    A[:, :] = 0.0
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    P = np.array([[0.0, -p2, p1], [p2, 0.0, -p0], [-p1, p0, 0.0]])
    R = g[:3, :3]
    PR = P @ R
    for i in range(3):
        for j in range(3):
            A[i, j] = R[i, j]
            A[i + 3, j + 3] = R[i, j]
            A[i, j + 3] = PR[i, j]


@_jit
def _Ad_inv(g, A):
    A[:, :] = 0.0
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    P = np.array([[0.0, -p2, p1], [p2, 0.0, -p0], [-p1, p0, 0.0]])
    Rt = g[:3, :3].T.copy()
    RtP = Rt @ P
    for i in range(3):
        for j in range(3):
            A[i, j] = Rt[i, j]
            A[i + 3, j + 3] = Rt[i, j]
            A[i, j + 3] = -RtP[i, j]


@_jit
def _kernel(q, qd, f0, free_index, lengths, base, offsets, pt_sec, pt_x, pt_w, pt_mc, gravity,
            ld_sec, ld_x, ld_W, ld_world, act_sec, act_d, act_dd, act_coef, Kq, Dq, q0):
    n = lengths.shape[0]
    ndof = q.shape[0]
    nfull = 6 * n
    xi = f0.copy().reshape(nfull)
    xid = np.zeros(nfull)
    for k in range(ndof):
        xi[free_index[k]] = q[k]
        xid[free_index[k]] = qd[k]
    xi = xi.reshape((n, 6))
    xid = xid.reshape((n, 6))
    # --- recursive pass over sections -----------------------------------
    g_start = np.empty((n, 4, 4))
    W = np.empty((n, 6, 6))
    V_end = np.empty((n, 6))
    A_end = np.empty((n, 6))
    g = base.copy()
    E = np.empty((4, 4))
    T = np.empty((6, 6))
    Adm = np.empty((6, 6))
    V = np.zeros(6)
    Acc = np.zeros(6)
    tmp = np.empty(6)
    tmp2 = np.empty(6)
    Lx = np.empty(6)
    Lxd = np.empty(6)
    for i in range(n):
        g_start[i] = g
        L = lengths[i]
        for a in range(6):
            Lx[a] = L * xi[i, a]
            Lxd[a] = L * xid[i, a]
        _exp_se3(Lx, E)
        g = g @ E
        _T_se3(Lx, T)
        _Ad(g, Adm)
        W[i] = Adm @ (L * T)
        contrib = W[i] @ xid[i]
        V = V + contrib
        _ad_vec(V, contrib, tmp)
        _T_dot_vec(Lx, Lxd, xid[i], tmp2)
        Acc = Acc + tmp + Adm @ (L * tmp2)
        V_end[i] = V
        A_end[i] = Acc
        if i < n - 1:
            g = g @ offsets[i]
    # --- per point body Jacobian, bias acceleration -----------------------
    M = np.zeros((ndof, ndof))
    f = np.zeros(ndof)
    npts = pt_sec.shape[0]
    nld = ld_sec.shape[0]
    J = np.empty((6, ndof))
    eta = np.empty(6)
    h = np.empty(6)
    xx = np.empty(6)
    xxd = np.empty(6)
    Ai = np.empty((6, 6))
    gp = np.empty((4, 4))
    for p in range(npts + nld):
        if p < npts:
            i, x = pt_sec[p], pt_x[p]
        else:
            i, x = ld_sec[p - npts], ld_x[p - npts]
        for a in range(6):
            xx[a] = x * xi[i, a]
            xxd[a] = x * xid[i, a]
        _exp_se3(xx, E)
        gp[:, :] = g_start[i] @ E
        _Ad_inv(gp, Ai)
        _T_se3(xx, T)
        own = x * T
        for k in range(ndof):
            c = free_index[k]
            j, a = c // 6, c % 6
            if j < i:
                for r in range(6):
                    acc = 0.0
                    for s in range(6):
                        acc += Ai[r, s] * W[j, s, a]
                    J[r, k] = acc
            elif j == i:
                for r in range(6):
                    J[r, k] = own[r, a]
            else:
                for r in range(6):
                    J[r, k] = 0.0
        if p < npts:
            w = pt_w[p]
            mc = pt_mc[p]
            # body twist and bias acceleration
            eta[:] = J @ qd
            # spatial twist of the point and spatial bias acceleration
            _Ad(gp, Adm)
            Vp = Adm @ eta
            if i > 0:
                Ap = A_end[i - 1].copy()
            else:
                Ap = np.zeros(6)
            own_sp = Adm @ (own @ xid[i])
            _ad_vec(Vp, own_sp, tmp)
            _T_dot_vec(xx, xxd, xid[i], tmp2)
            Ap = Ap + tmp + Adm @ (x * tmp2)
            acc_b = Ai @ Ap
            # h = Mc acc - ad(eta)^T Mc eta  (Mc diagonal)
            for a in range(6):
                tmp[a] = mc[a] * eta[a]
            # ad(eta)^T y: [ -w x yu ; -u x yu - w x yw ]
            u0, u1, u2, w0, w1, w2 = eta[0], eta[1], eta[2], eta[3], eta[4], eta[5]
            y0, y1, y2, z0, z1, z2 = tmp[0], tmp[1], tmp[2], tmp[3], tmp[4], tmp[5]
            adT0 = -(w1 * y2 - w2 * y1)
            adT1 = -(w2 * y0 - w0 * y2)
            adT2 = -(w0 * y1 - w1 * y0)
            adT3 = -(u1 * y2 - u2 * y1) - (w1 * z2 - w2 * z1)
            adT4 = -(u2 * y0 - u0 * y2) - (w2 * z0 - w0 * z2)
            adT5 = -(u0 * y1 - u1 * y0) - (w0 * z1 - w1 * z0)
            h[0] = mc[0] * acc_b[0] - adT0
            h[1] = mc[1] * acc_b[1] - adT1
            h[2] = mc[2] * acc_b[2] - adT2
            h[3] = mc[3] * acc_b[3] - adT3
            h[4] = mc[4] * acc_b[4] - adT4
            h[5] = mc[5] * acc_b[5] - adT5
            # gravity: body force w rhoA R^T g
            for a in range(3):
                gb = 0.0
                for r in range(3):
                    gb += gp[r, a] * gravity[r]
                h[a] -= mc[0] * gb
            for k in range(ndof):
                acc = 0.0
                for a in range(6):
                    acc += J[a, k] * h[a]
                f[k] -= w * acc
            for k in range(ndof):
                for l in range(k, ndof):
                    acc = 0.0
                    for a in range(6):
                        acc += J[a, k] * mc[a] * J[a, l]
                    M[k, l] += w * acc
        else:
            l_ = p - npts
            Wl = ld_W[l_]
            if ld_world[l_]:
                for a in range(3):
                    fb = 0.0
                    mb = 0.0
                    for r in range(3):
                        fb += gp[r, a] * Wl[r]
                        mb += gp[r, a] * Wl[r + 3]
                    tmp[a] = fb
                    tmp[a + 3] = mb
            else:
                tmp[:] = Wl
            for k in range(ndof):
                acc = 0.0
                for a in range(6):
                    acc += J[a, k] * tmp[a]
                f[k] += acc
    for k in range(ndof):
        for l in range(k):
            M[k, l] = M[l, k]
    # --- actuation (exact tendon/chamber forces) -------------------------
    tau = np.zeros((n, 6))
    for p in range(act_sec.shape[0]):
        if act_coef[p] == 0.0:
            continue
        i = act_sec[p]
        d = act_d[p]
        t0 = xi[i, 0] + xi[i, 4] * d[2] - xi[i, 5] * d[1] + act_dd[p, 0]
        t1 = xi[i, 1] + xi[i, 5] * d[0] - xi[i, 3] * d[2] + act_dd[p, 1]
        t2 = xi[i, 2] + xi[i, 3] * d[1] - xi[i, 4] * d[0] + act_dd[p, 2]
        nt = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        t0, t1, t2 = t0 / nt, t1 / nt, t2 / nt
        c = act_coef[p]
        tau[i, 0] += c * t0
        tau[i, 1] += c * t1
        tau[i, 2] += c * t2
        tau[i, 3] += c * (d[1] * t2 - d[2] * t1)
        tau[i, 4] += c * (d[2] * t0 - d[0] * t2)
        tau[i, 5] += c * (d[0] * t1 - d[1] * t0)
    tauf = tau.reshape(nfull)
    for k in range(ndof):
        f[k] += tauf[free_index[k]]
    f -= Kq @ (q - q0) + Dq @ qd
    return M, f


# ----------------------------------------------------------------------------
# Python-side packing (cached per model / loads object)
# ----------------------------------------------------------------------------

_MODEL_CACHE = {}
_LOADS_CACHE = {}


def supports(model):
    return model.kinematic_map == "exponential"


def _pack_model(model):
    key = id(model)
    hit = _MODEL_CACHE.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    s, w, sec = gauss_points(model)
    x = s - model.s_starts[sec]
    mc = np.array([np.diag(model.sections[i].M) for i in sec])
    # actuator quadrature: geometry fixed, coefficient = -c_a u_a w
    a_sec, a_d, a_dd, a_map = [], [], [], []
    for k, a in enumerate(model.actuators):
        sq, wq, sc = gauss_points(model, a.start, a.end)
        d, dd = a.offset_at(sq)
        a_sec.append(sc)
        a_d.append(d)
        a_dd.append(dd)
        row = np.zeros((len(sq), len(model.actuators)))
        row[:, k] = -a.force_per_unit_input * wq
        a_map.append(row)
    packed = dict(
        f0=np.ascontiguousarray(model.f0), free_index=model.free_index.astype(np.int64),
        lengths=np.ascontiguousarray(model.lengths), base=np.ascontiguousarray(model.base_pose),
        offsets=np.ascontiguousarray(model.offsets), pt_sec=sec.astype(np.int64), pt_x=x, pt_w=w,
        pt_mc=mc, Kq=np.ascontiguousarray(model.K_q), Dq=np.ascontiguousarray(model.D_q),
        q0=np.ascontiguousarray(model.q0),
        act_sec=np.concatenate(a_sec).astype(np.int64) if a_sec else np.zeros(0, np.int64),
        act_d=np.concatenate(a_d) if a_d else np.zeros((0, 3)),
        act_dd=np.concatenate(a_dd) if a_dd else np.zeros((0, 3)),
        act_map=np.concatenate(a_map) if a_map else np.zeros((0, 0)),
    )
    _MODEL_CACHE[key] = (model, packed)
    return packed


def _pack_loads(model, loads):
    key = (id(model), id(loads))
    hit = _LOADS_CACHE.get(key)
    if hit is not None and hit[0] is loads:
        return hit[1]
    grav = loads.gravity
    gscale = (1.0 if grav else 0.0) if isinstance(grav, bool) else float(grav)
    s_l, W_l, world_l = [], [], []
    for d in loads.distributed:
        sq, wq, _ = gauss_points(model, d.start, d.end)
        s_l.append(sq)
        W_l.append(wq[:, None] * np.asarray(d.wrench, dtype=float)[None, :])
        world_l += [d.frame == "world"] * len(sq)
    for p in loads.point:
        s_l.append(np.array([min(max(p.s, 0.0), model.total_length)]))
        W_l.append(np.asarray(p.wrench, dtype=float)[None, :])
        world_l.append(p.frame == "world")
    if s_l:
        s = np.concatenate(s_l)
        sec, x = model.locate(s)
        packed = (gscale * model.gravity, sec.astype(np.int64), x, np.concatenate(W_l),
                  np.array(world_l, dtype=np.bool_))
    else:
        packed = (gscale * model.gravity, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)),
                  np.zeros(0, dtype=np.bool_))
    if len(_LOADS_CACHE) > 64:
        _LOADS_CACHE.clear()
    _LOADS_CACHE[key] = (loads, packed)
    return packed


def dynamics_terms(model, q, qdot, u, loads):
    """Compiled equivalent of :func:`soft_twin_core.dynamics.dynamics_terms`."""
    pm = _pack_model(model)
    gravity, ld_sec, ld_x, ld_W, ld_world = _pack_loads(model, Loads() if loads is None else loads)
    u = np.asarray(u, dtype=float)
    coef = pm["act_map"] @ u if u.size else np.zeros(pm["act_sec"].shape[0])
    return _kernel(np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(qdot, dtype=float),
                   pm["f0"], pm["free_index"], pm["lengths"], pm["base"], pm["offsets"],
                   pm["pt_sec"], pm["pt_x"], pm["pt_w"], pm["pt_mc"], gravity,
                   ld_sec, ld_x, ld_W, ld_world, pm["act_sec"], pm["act_d"], pm["act_dd"], coef,
                   pm["Kq"], pm["Dq"], pm["q0"])
