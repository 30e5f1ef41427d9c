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
from .loads import Loads, actuator_point_loads, gauss_points

from .kernels.spatial import (_Ad_into, _T_dot_into, _T_into, _ad_vec, _exp_into, _jit, _mm, _mtm,
                              _mtv, _mv)

@_jit
def _kernel(q, qd, f0, free_index, lengths, base, offsets, pt_sec, pt_x, pt_w, pt_mc, gravity,
            ld_sec, ld_x, ld_W, ld_world, act_sec, act_d, act_dd, act_coef, Kq, Dq, q0, need_mass,
            qdd, n_act_pts):
    """(M, f, F): M and f = Q + tau - K(q - q0) - D qd - C qd as in
    dynamics.dynamics_terms, and F the total spatial wrench (world axes,
    about the origin) of the external loads minus the inertial wrenches at
    (q, qd, qdd) (qdd used only with need_mass), for the base reaction; the
    last ``n_act_pts`` load points are actuator point moments (internal)."""
    n = lengths.shape[0]
    ndof = q.shape[0]
    # --- strains and rates ---------------------------------------------------
    xi = np.empty((n, 6))
    xid = np.zeros((n, 6))
    for i in range(n):
        for a in range(6):
            xi[i, a] = f0[i, a]
    for k in range(ndof):
        c = free_index[k]
        xi[c // 6, c % 6] = q[k]
        xid[c // 6, c % 6] = qd[k]
    # --- scratch -----------------------------------------------------------
    E = np.empty((4, 4))
    g = np.empty((4, 4))
    gtmp = np.empty((4, 4))
    T = np.empty((6, 6))
    A1 = np.empty((6, 6))
    A2 = np.empty((6, 6))
    A3 = np.empty((6, 6))
    A4 = np.empty((6, 6))
    Adm = np.empty((6, 6))
    Ai = np.empty((6, 6))
    own = np.empty((6, 6))
    MA = np.empty((6, 6))
    tmp6 = np.empty((6, 6))
    Pm = np.empty((5, 6))
    S3 = np.empty((7, 3, 3))
    v1 = np.empty(6)
    v2 = np.empty(6)
    v3 = np.empty(6)
    v4 = np.empty(6)
    vacc = np.empty(6)
    Lx = np.empty(6)
    Lxd = np.empty(6)
    eta = np.empty(6)
    accb = np.empty(6)
    Fb = np.empty(6)
    Fs = np.empty(6)
    # --- recursive pass over sections ----------------------------------------
    g_start = np.empty((n, 4, 4))
    W = np.empty((n, 6, 6))
    V_end = np.zeros((n + 1, 6))     # V_end[i + 1]: spatial twist at the end of section i
    A_end = np.zeros((n + 1, 6))
    for r in range(4):
        for c in range(4):
            g[r, c] = base[r, c]
    for i in range(n):
        for r in range(4):
            for c in range(4):
                g_start[i, r, c] = g[r, c]
        L = lengths[i]
        for a in range(6):
            Lx[a] = L * xi[i, a]
            Lxd[a] = L * xid[i, a]
        _exp_into(Lx, E)
        _mm(g, E, gtmp)
        _T_into(Lx, T, S3)
        _Ad_into(gtmp, Adm, False)
        _mm(Adm, T, tmp6)
        for r in range(6):
            for c in range(6):
                W[i, r, c] = L * tmp6[r, c]
        _mv(W[i], xid[i], v1)                     # contrib
        for a in range(6):
            V_end[i + 1, a] = V_end[i, a] + v1[a]
        _ad_vec(V_end[i + 1], v1, v2)
        _T_dot_into(Lx, Lxd, xid[i], v3, Pm, v4, vacc, eta)
        _mv(Adm, v3, v4)
        for a in range(6):
            A_end[i + 1, a] = A_end[i, a] + v2[a] + L * v4[a]
        if i < n - 1:
            _mm(gtmp, offsets[i], g)
        else:
            for r in range(4):
                for c in range(4):
                    g[r, c] = gtmp[r, c]
    # --- per-point quantities accumulated per section --------------------------
    Isec = np.zeros((n, 6, 6))      # sum w Ai^T Mc Ai (spatial inertia)
    Ysec = np.zeros((n, 6, 6))      # sum w Ai^T Mc own
    Mown = np.zeros((n, 6, 6))      # sum w own^T Mc own
    Fsec = np.zeros((n, 6))         # spatial wrench (applied - inertial bias)
    Ftot = np.zeros(6)              # the same, all sections, without actuator points
    fown = np.zeros((n, 6))         # own-mode generalised force
    npts = pt_sec.shape[0]
    nld = ld_sec.shape[0]
    for p in range(npts + nld):
        is_q = p < npts
        if is_q:
            i, x = pt_sec[p], pt_x[p]
        else:
            i, x = ld_sec[p - npts], ld_x[p - npts]
        for a in range(6):
            Lx[a] = x * xi[i, a]
            Lxd[a] = x * xid[i, a]
        _exp_into(Lx, E)
        _mm(g_start[i], E, gtmp)
        _Ad_into(gtmp, Ai, True)
        _T_into(Lx, T, S3)
        for r in range(6):
            for c in range(6):
                own[r, c] = x * T[r, c]
        if is_q and not need_mass and gravity[0] == 0.0 and gravity[1] == 0.0 and gravity[2] == 0.0 \
                and V_end[n, 0] == 0.0 and V_end[n, 1] == 0.0 and V_end[n, 2] == 0.0 \
                and V_end[n, 3] == 0.0 and V_end[n, 4] == 0.0 and V_end[n, 5] == 0.0:
            continue            # statics without gravity: quadrature points carry nothing
        if is_q:
            w = pt_w[p]
            mc = pt_mc[p]
            # body twist eta = Ai V_start + own xid_i
            _mv(Ai, V_end[i], v1)
            _mv(own, xid[i], v2)
            for a in range(6):
                eta[a] = v1[a] + v2[a]
            # body bias acceleration = Ai A_start + ad(eta) own xid + x Tdot xid
            _mv(Ai, A_end[i], v1)
            _ad_vec(eta, v2, v3)
            _T_dot_into(Lx, Lxd, xid[i], v4, Pm, accb, vacc, Fs)
            for a in range(6):
                accb[a] = v1[a] + v3[a] + x * v4[a]
            # inertial bias wrench h = Mc accb - ad(eta)^T Mc eta - rhoA [R^T g; 0]
            u0, u1, u2, w0, w1, w2 = eta[0], eta[1], eta[2], eta[3], eta[4], eta[5]
            y0, y1, y2 = mc[0] * u0, mc[1] * u1, mc[2] * u2
            z0, z1, z2 = mc[3] * w0, mc[4] * w1, mc[5] * w2
            Fb[0] = mc[0] * accb[0] + (w1 * y2 - w2 * y1)
            Fb[1] = mc[1] * accb[1] + (w2 * y0 - w0 * y2)
            Fb[2] = mc[2] * accb[2] + (w0 * y1 - w1 * y0)
            Fb[3] = mc[3] * accb[3] + (u1 * y2 - u2 * y1) + (w1 * z2 - w2 * z1)
            Fb[4] = mc[4] * accb[4] + (u2 * y0 - u0 * y2) + (w2 * z0 - w0 * z2)
            Fb[5] = mc[5] * accb[5] + (u0 * y1 - u1 * y0) + (w0 * z1 - w1 * z0)
            for a in range(3):
                gb = gtmp[0, a] * gravity[0] + gtmp[1, a] * gravity[1] + gtmp[2, a] * gravity[2]
                Fb[a] -= mc[0] * gb
            for a in range(6):
                Fb[a] = -w * Fb[a]               # applied minus inertial bias
            if not need_mass:
                _mtv(Ai, Fb, Fs)
                _mtv(own, Fb, v1)
                for a in range(6):
                    Fsec[i, a] += Fs[a]
                    fown[i, a] += v1[a]
                    Ftot[a] += Fs[a]
                continue
            # inertia accumulators; spatial inertia Ai^T Mc Ai of the point
            if mc[0] == mc[1] and mc[1] == mc[2]:
                # isotropic linear inertia m: [[m I, -m P], [m P, -m P P + R Jd R^T]], P = hat(p)
                mw = w * mc[0]
                p0, p1, p2 = gtmp[0, 3], gtmp[1, 3], gtmp[2, 3]
                P = ((0.0, -p2, p1), (p2, 0.0, -p0), (-p1, p0, 0.0))
                for r in range(3):
                    Isec[i, r, r] += mw
                    for c in range(3):
                        Isec[i, r, c + 3] -= mw * P[r][c]
                        Isec[i, r + 3, c] += mw * P[r][c]
                        pp = P[r][0] * P[0][c] + P[r][1] * P[1][c] + P[r][2] * P[2][c]
                        rjr = (gtmp[r, 0] * mc[3] * gtmp[c, 0] + gtmp[r, 1] * mc[4] * gtmp[c, 1]
                               + gtmp[r, 2] * mc[5] * gtmp[c, 2])
                        Isec[i, r + 3, c + 3] += w * rjr - mw * pp
            else:
                for r in range(6):
                    for c in range(6):
                        MA[r, c] = mc[r] * Ai[r, c]
                _mtm(Ai, MA, tmp6)
                for r in range(6):
                    for c in range(6):
                        Isec[i, r, c] += w * tmp6[r, c]
            for r in range(6):
                for c in range(6):
                    MA[r, c] = mc[r] * own[r, c]
            _mtm(Ai, MA, tmp6)
            for r in range(6):
                for c in range(6):
                    Ysec[i, r, c] += w * tmp6[r, c]
            _mtm(own, MA, tmp6)
            for r in range(6):
                for c in range(6):
                    Mown[i, r, c] += w * tmp6[r, c]
        else:
            l_ = p - npts
            if ld_world[l_]:
                for a in range(3):
                    Fb[a] = gtmp[0, a] * ld_W[l_, 0] + gtmp[1, a] * ld_W[l_, 1] + gtmp[2, a] * ld_W[l_, 2]
                    Fb[a + 3] = gtmp[0, a] * ld_W[l_, 3] + gtmp[1, a] * ld_W[l_, 4] + gtmp[2, a] * ld_W[l_, 5]
            else:
                for a in range(6):
                    Fb[a] = ld_W[l_, a]
        _mtv(Ai, Fb, Fs)
        _mtv(own, Fb, v1)
        internal = (not is_q) and (p - npts >= nld - n_act_pts)
        for a in range(6):
            Fsec[i, a] += Fs[a]
            fown[i, a] += v1[a]
            if not internal:
                Ftot[a] += Fs[a]
    # --- suffix sums, generalised force and mass matrix (CRBA-like) ----------
    Ic = np.zeros((6, 6))
    Fd = np.zeros(6)
    Z = np.empty((n, 6, 6))
    ffull = np.empty((n, 6))
    Mdiag = np.empty((n, 6, 6))
    for k in range(n - 1, -1, -1):
        # Ic, Fd: strictly distal to section k
        _mtv(W[k], Fd, v1)
        for a in range(6):
            ffull[k, a] = v1[a] + fown[k, a]
        _mm(Ic, W[k], tmp6)
        for r in range(6):
            for c in range(6):
                Z[k, r, c] = tmp6[r, c] + Ysec[k, r, c]
        _mtm(W[k], tmp6, A1)
        for r in range(6):
            for c in range(6):
                Mdiag[k, r, c] = A1[r, c] + Mown[k, r, c]
        for r in range(6):
            Fd[r] += Fsec[k, r]
            for c in range(6):
                Ic[r, c] += Isec[k, r, c]
    M = np.zeros((ndof, ndof)) if need_mass else np.zeros((0, 0))
    f = np.empty(ndof)
    for a in range(ndof):
        ca = free_index[a]
        j, al = ca // 6, ca % 6
        f[a] = ffull[j, al]
        if not need_mass:
            continue
        for b in range(a, ndof):
            cb = free_index[b]
            k, be = cb // 6, cb % 6
            if j == k:
                val = Mdiag[j, al, be]
            else:
                acc = 0.0
                for r in range(6):
                    acc += W[j, r, al] * Z[k, r, be]
                val = acc
            M[a, b] = val
            M[b, a] = val
    # --- actuation (exact tendon/chamber forces) -----------------------------
    for p in range(act_sec.shape[0]):
        c = act_coef[p]
        if c == 0.0:
            continue
        i = act_sec[p]
        d = act_d[p]
        t0 = xi[i, 0] + xi[i, 4] * d[2] - xi[i, 5] * d[1] + act_dd[p, 0]
        t1 = xi[i, 1] + xi[i, 5] * d[0] - xi[i, 3] * d[2] + act_dd[p, 1]
        t2 = xi[i, 2] + xi[i, 3] * d[1] - xi[i, 4] * d[0] + act_dd[p, 2]
        nt = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        t0, t1, t2 = t0 / nt, t1 / nt, t2 / nt
        vacc[0], vacc[1], vacc[2] = c * t0, c * t1, c * t2
        vacc[3] = c * (d[1] * t2 - d[2] * t1)
        vacc[4] = c * (d[2] * t0 - d[0] * t2)
        vacc[5] = c * (d[0] * t1 - d[1] * t0)
        for a in range(ndof):
            ca = free_index[a]
            if ca // 6 == i:
                f[a] += vacc[ca % 6]
    # --- elastic and viscous forces -----------------------------------------
    for a in range(ndof):
        acc = 0.0
        for b in range(ndof):
            acc += Kq[a, b] * (q[b] - q0[b]) + Dq[a, b] * qd[b]
        f[a] -= acc
    # --- inertial wrench of the accelerations qdd (base reaction) -----------
    if need_mass:
        xidd = np.zeros((n, 6))
        for k in range(ndof):
            c = free_index[k]
            xidd[c // 6, c % 6] = qdd[k]
        Aq = np.zeros(6)                 # sum_{j < i} W_j xidd_j (spatial)
        for i in range(n):
            _mv(Isec[i], Aq, v1)
            _mv(Ysec[i], xidd[i], v2)
            _mv(W[i], xidd[i], v3)
            for a in range(6):
                Ftot[a] -= v1[a] + v2[a]
                Aq[a] += v3[a]
    return M, f, Ftot


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
        if a.tendon_model == "point_moment":
            continue            # applied as a follower point load (see dynamics_terms)
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


def _loads_with_actuators(model, loads, u):
    packed = _pack_loads(model, Loads() if loads is None else loads)
    pts = actuator_point_loads(model, u) if model.actuators else ()
    if not pts:
        return packed
    gravity, ld_sec, ld_x, ld_W, ld_world = packed
    sec, x = model.locate(np.array([p.s for p in pts]))
    return (gravity, np.concatenate([ld_sec, sec.astype(np.int64)]), np.concatenate([ld_x, x]),
            np.concatenate([ld_W, np.array([p.wrench for p in pts], dtype=float)]),
            np.concatenate([ld_world, np.zeros(len(pts), dtype=np.bool_)]))


def _call(model, q, qdot, u, loads, need_mass, qdd):
    pm = _pack_model(model)
    u = np.asarray(u, dtype=float)
    packed = _loads_with_actuators(model, loads, u)
    gravity, ld_sec, ld_x, ld_W, ld_world = packed
    n_act = packed[1].shape[0] - _pack_loads(model, Loads() if loads is None else loads)[1].shape[0]
    coef = pm["act_map"] @ u if u.size else np.zeros(pm["act_sec"].shape[0])
    return _kernel(np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(qdot, dtype=float),
                   pm["f0"], pm["free_index"], pm["lengths"], pm["base"], pm["offsets"],
                   pm["pt_sec"], pm["pt_x"], pm["pt_w"], pm["pt_mc"], gravity,
                   ld_sec, ld_x, ld_W, ld_world, pm["act_sec"], pm["act_d"], pm["act_dd"], coef,
                   pm["Kq"], pm["Dq"], pm["q0"], need_mass, np.ascontiguousarray(qdd, dtype=float), n_act)


def dynamics_terms(model, q, qdot, u, loads, need_mass=True):
    """Compiled equivalent of :func:`soft_twin_core.dynamics.dynamics_terms`:
    (M, f) with f = Q_ext + tau - K (q - q0) - D qdot - C qdot. With
    ``need_mass=False`` M is skipped (an empty array) and f costs less."""
    M, f, _ = _call(model, q, qdot, u, loads, need_mass, np.zeros(len(q)))
    return M, f


def total_wrench(model, q, qdot, qddot, u, loads):
    """Spatial wrench (world axes, about the world origin) of the external
    loads (gravity included) minus the inertial wrenches at (q, qd, qdd); the
    support's reaction is its negative (see dynamics.base_reaction_dynamic)."""
    return _call(model, q, qdot, u, loads, True, qddot)[2]


@_jit
def _newton_kernel(q0, v0, v1, h, theta, C, tol, floor, max_it,
                   f0, free_index, lengths, base, offsets, pt_sec, pt_x, pt_w, pt_mc, gravity,
                   ld_sec, ld_x, ld_W, ld_world, act_sec, act_d, act_dd, act_coef, Kq, Dq, qref):
    """Modified Newton iteration of one theta-method step (see
    dynamics.Simulator): returns (v1, iterations, status, rate) with status
    0 converged, 1 not converged in max_it, 2 diverging, 3 non-finite."""
    n = q0.shape[0]
    prev = -1.0
    rate = 0.0
    vt = np.empty(n)
    qt = np.empty(n)
    for it in range(1, max_it + 1):
        for k in range(n):
            vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
            qt[k] = q0[k] + theta * h * vt[k]
        M, f, _ = _kernel(qt, vt, f0, free_index, lengths, base, offsets, pt_sec, pt_x, pt_w, pt_mc,
                          gravity, ld_sec, ld_x, ld_W, ld_world, act_sec, act_d, act_dd, act_coef,
                          Kq, Dq, qref, True, vt, 0)
        r = M @ (v1 - v0) - h * f
        dv = np.linalg.solve(M + C, -r)
        upd = 0.0
        vmax = 0.0
        for k in range(n):
            v1[k] += dv[k]
            upd = max(upd, abs(dv[k]))
            vmax = max(vmax, abs(v1[k]), abs(v0[k]))
        if not np.isfinite(upd):
            return v1, it, 3, rate
        goal = max(tol * vmax, floor)
        if upd <= goal:
            return v1, it, 0, rate
        if prev > 0.0:
            r_k = upd / prev
            # Hairer-Wanner stopping rule: the remaining error of a linearly
            # converging iteration is about r/(1 - r) times the last update
            if r_k < 0.5 and r_k / (1.0 - r_k) * upd <= goal:
                return v1, it, 0, rate
            if upd > 100.0 * goal:
                rate = max(rate, r_k)
                if rate > 0.9:
                    return v1, it, 2, rate
        prev = upd
    return v1, max_it, 1, rate


def newton_step(model, q0, v0, v1, h, theta, C, u, loads, tol, floor, max_iterations):
    """Compiled Newton loop of one integrator step (same algorithm as the
    Python loop in dynamics.Simulator._newton)."""
    pm = _pack_model(model)
    u = np.asarray(u, dtype=float)
    gravity, ld_sec, ld_x, ld_W, ld_world = _loads_with_actuators(model, loads, u)
    coef = pm["act_map"] @ u if u.size else np.zeros(pm["act_sec"].shape[0])
    return _newton_kernel(np.ascontiguousarray(q0, dtype=float), np.ascontiguousarray(v0, dtype=float),
                          np.array(v1, dtype=float), float(h), float(theta), np.ascontiguousarray(C),
                          float(tol), float(floor), int(max_iterations),
                          pm["f0"], pm["free_index"], pm["lengths"], pm["base"], pm["offsets"],
                          pm["pt_sec"], pm["pt_x"], pm["pt_w"], pm["pt_mc"], gravity,
                          ld_sec, ld_x, ld_W, ld_world, pm["act_sec"], pm["act_d"], pm["act_dd"], coef,
                          pm["Kq"], pm["Dq"], pm["q0"])


@_jit
def _poses_kernel(q, f0, free_index, lengths, base, offsets, p_sec, p_x):
    n = lengths.shape[0]
    xi = f0.copy()
    for k in range(q.shape[0]):
        c = free_index[k]
        xi[c // 6, c % 6] = q[k]
    g_start = np.empty((n, 4, 4))
    g = base.copy()
    gtmp = np.empty((4, 4))
    E = np.empty((4, 4))
    x6 = np.empty(6)
    for i in range(n):
        g_start[i] = g
        for a in range(6):
            x6[a] = lengths[i] * xi[i, a]
        _exp_into(x6, E)
        _mm(g, E, gtmp)
        if i < n - 1:
            _mm(gtmp, offsets[i], g)
    out = np.empty((p_sec.shape[0], 4, 4))
    for p in range(p_sec.shape[0]):
        i = p_sec[p]
        for a in range(6):
            x6[a] = p_x[p] * xi[i, a]
        _exp_into(x6, E)
        _mm(g_start[i], E, gtmp)
        out[p] = gtmp
    return out


def poses(model, q, s):
    """Compiled :func:`soft_twin_core.kinematics.poses` for one real q."""
    pm = _pack_model(model)
    sec, x = model.locate(np.asarray(s, dtype=float))
    return _poses_kernel(np.ascontiguousarray(q, dtype=float), pm["f0"], pm["free_index"], pm["lengths"],
                         pm["base"], pm["offsets"], sec.astype(np.int64), np.ascontiguousarray(x))


@_jit
def _tip_kernel(q, f0, free_index, lengths, base, offsets):
    """Tip pose and spatial Jacobian (6 x n_dof) columns W_j B_j."""
    n = lengths.shape[0]
    ndof = q.shape[0]
    xi = f0.copy()
    for k in range(ndof):
        c = free_index[k]
        xi[c // 6, c % 6] = q[k]
    g = base.copy()
    gtmp = np.empty((4, 4))
    E = np.empty((4, 4))
    T = np.empty((6, 6))
    A1 = np.empty((6, 6))
    Adm = np.empty((6, 6))
    x6 = np.empty(6)
    S3 = np.empty((7, 3, 3))
    Js = np.zeros((6, ndof))
    for i in range(n):
        for a in range(6):
            x6[a] = lengths[i] * xi[i, a]
        _exp_into(x6, E)
        _mm(g, E, gtmp)
        _T_into(x6, T, S3)
        _Ad_into(gtmp, Adm, False)
        for k in range(ndof):
            c = free_index[k]
            if c // 6 == i:
                a = c % 6
                for r in range(6):
                    acc = 0.0
                    for s in range(6):
                        acc += Adm[r, s] * T[s, a]
                    Js[r, k] = lengths[i] * acc
        if i < n - 1:
            _mm(gtmp, offsets[i], g)
        else:
            g[:, :] = gtmp
    return g, Js


def tip_and_spatial_jacobian(model, q):
    """(tip pose 4x4, spatial tip Jacobian 6 x n_dof) for one real q; the body
    tip Jacobian is Ad(g_tip)^-1 Js (see kinematics.tip_jacobian)."""
    pm = _pack_model(model)
    return _tip_kernel(np.ascontiguousarray(q, dtype=float), pm["f0"], pm["free_index"], pm["lengths"],
                       pm["base"], pm["offsets"])
