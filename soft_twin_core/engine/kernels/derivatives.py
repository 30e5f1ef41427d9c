"""Analytic partial derivatives of inverse dynamics, d tau/d q and d tau/d v
(numba), by differentiating the RNEA passes (tangent-linear recursion).

For each column (a unit velocity e of joint k; q moves on the joint's group,
right-trivialised: q (+) eps e, the convention of Pinocchio's
computeRNEADerivatives) the forward pass propagates the derivatives of the
body twists, accelerations and frame displacements through the subtree of
k, and the backward pass those of the wrenches through the subtree and up
to the root. At the perturbed joint, with zeta = S_k e (the output frame's
displacement), ``dAd(Jq^-1) = -ad(zeta) Ad(Jq^-1)``,

    dV_k = -ad(zeta) (V_k - S v) + dS v
    dA_k = -ad(zeta) (A_k - S a - c_k) + dS a + dc_k,
    dc_k = ad(dV_k) S v + ad(V_k) dS v + d(Sdot v)

(soft section: dS = L^2 Tdot(L f)[e] B, d(Sdot v) = L^3 D^2T(L f)[e, fdot] fdot,
:func:`spatial._T_d2_into`; the same at each quadrature point with x for L);
below it ``dV_i = Ad(X_i^-1) dV_parent``, ``dA_i = Ad(X_i^-1) dA_parent + ad(dV_i) S_i v_i``,
and gravity seen from a frame turned by delta: ``d(R^T g) = -delta_w x R^T g``.
The wrenches follow ``df = I dA' - ad(dV)^T I V - ad(V)^T I dV``, ``dtau = S^T df
(+ dS^T f)``, ``df_in = Ad(Jq^-1)^T df (- Ad(Jq^-1)^T ad(zeta)^T f)``. The
velocity derivative is the same recursion with dV_k = S_k e and no
displacement. Stiffness and damping add their blocks. Gravity only (no
external loads); exponential-map sections. O(n) per column.
"""

import numpy as np

from soft_twin_core.engine.kernels.spatial import TRUE, _T_d2_into, _T_dot_into, _ad_vec, _jit, _jit_inner

from soft_twin_core.engine.joint_kinds import SOFT


@_jit_inner
def _adT(x, y, out):
    """out = ad(x)^T y."""
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    a0, a1, a2, b0, b1, b2 = y[0], y[1], y[2], y[3], y[4], y[5]
    out[0] = -(w1 * a2 - w2 * a1)
    out[1] = -(w2 * a0 - w0 * a2)
    out[2] = -(w0 * a1 - w1 * a0)
    out[3] = -(u1 * a2 - u2 * a1) - (w1 * b2 - w2 * b1)
    out[4] = -(u2 * a0 - u0 * a2) - (w2 * b0 - w0 * b2)
    out[5] = -(u0 * a1 - u1 * a0) - (w0 * b1 - w1 * b0)


@_jit_inner
def _mv(A, x, out):
    for r in range(6):
        acc = 0.0
        for c in range(6):
            acc += A[r, c] * x[c]
        out[r] = acc


@_jit_inner
def _mtv(A, x, out):
    for r in range(6):
        acc = 0.0
        for c in range(6):
            acc += A[c, r] * x[c]
        out[r] = acc


@_jit_inner
def _Scol(S, nv, vec, iv, out):
    for r in range(6):
        acc = 0.0
        for c in range(nv):
            acc += S[r, c] * vec[iv + c]
        out[r] = acc


@_jit_inner
def _dwrench(I6, mc, diag, scale, dA, dl, R, g, V, dV, out, t1, t2, t3):
    """out = scale (I (dA + [dl_w x R^T g; 0]) - ad(dV)^T I V - ad(V)^T I dV)."""
    for r in range(3):
        t1[r] = R[0, r] * g[0] + R[1, r] * g[1] + R[2, r] * g[2]      # R^T g
    c0 = dl[4] * t1[2] - dl[5] * t1[1]
    c1 = dl[5] * t1[0] - dl[3] * t1[2]
    c2 = dl[3] * t1[1] - dl[4] * t1[0]
    t1[0], t1[1], t1[2] = dA[0] + c0, dA[1] + c1, dA[2] + c2
    t1[3], t1[4], t1[5] = dA[3], dA[4], dA[5]
    if diag:
        for r in range(6):
            out[r] = mc[r] * t1[r]
            t2[r] = mc[r] * V[r]
            t3[r] = mc[r] * dV[r]
    else:
        _mv(I6, t1, out)
        _mv(I6, V, t2)
        _mv(I6, dV, t3)
    _adT(dV, t2, t1)
    for r in range(6):
        out[r] -= t1[r]
    _adT(V, t3, t1)
    for r in range(6):
        out[r] = scale * (out[r] - t1[r])


@_jit_inner
def _perturbed_frame(x, strain, rate, fa, e_full, V, A, Sv, Sa, Ad_in, Ain, zeta, wrt_q, soft,
                     dV, dA, tmp):
    """dV, dA of a frame moved by its own joint's coordinate (zeta = S e):
    the joint's output frame (x = L) or a soft cross-section at x."""
    x6, xd6, c, dSv, dSa, t1, t2, t3 = tmp[0], tmp[1], tmp[2], tmp[3], tmp[4], tmp[5], tmp[6], tmp[7]
    P = tmp[8:13]
    for r in range(6):
        x6[r] = x * strain[r]
    # c = A - Ad Ain - S a
    _mv(Ad_in, Ain, t1)
    for r in range(6):
        c[r] = A[r] - t1[r] - Sa[r]
        dSv[r] = 0.0
        dSa[r] = 0.0
    if wrt_q:
        if soft:
            for r in range(6):
                xd6[r] = x * e_full[r]
            _T_dot_into(x6, xd6, rate, dSv, P, t1, t2, t3)
            _T_dot_into(x6, xd6, fa, dSa, P, t1, t2, t3)
            for r in range(6):
                dSv[r] *= x
                dSa[r] *= x
        # dV = -ad(zeta)(V - Sv) + dSv
        for r in range(6):
            t1[r] = V[r] - Sv[r]
        _ad_vec(zeta, t1, t2)
        for r in range(6):
            dV[r] = -t2[r] + dSv[r]
        # dc = ad(dV) Sv + ad(V) dSv + x^3 D2T[e, fd] fd
        _ad_vec(dV, Sv, t1)
        _ad_vec(V, dSv, t2)
        for r in range(6):
            dA[r] = t1[r] + t2[r]
        if soft:
            _T_d2_into(x6, e_full, rate, rate, t3)
            for r in range(6):
                dA[r] += x * x * x * t3[r]
        # dA = -ad(zeta)(A - Sa - c) + dSa + dc
        for r in range(6):
            t1[r] = A[r] - Sa[r] - c[r]
        _ad_vec(zeta, t1, t2)
        for r in range(6):
            dA[r] += -t2[r] + dSa[r]
    else:
        for r in range(6):
            dV[r] = zeta[r]
        _ad_vec(dV, Sv, t1)
        _ad_vec(V, zeta, t2)
        for r in range(6):
            dA[r] = t1[r] + t2[r]
        if soft:
            for r in range(6):
                xd6[r] = x * e_full[r]
            _T_dot_into(x6, xd6, rate, t1, P, t2, t3, dSv)
            for r in range(6):
                xd6[r] = x * rate[r]
            _T_dot_into(x6, xd6, e_full, t2, P, t3, dSa, dSv)
            for r in range(6):
                dA[r] += x * (t1[r] + t2[r])


@_jit_inner
def _dS_T_f(x, strain, e_full, modes, nv, f, out, tmp):
    """out[a] = (x^2 Tdot(x f)[e] e_(m_a)) . f: d(S^T f)/dq at fixed f."""
    x6, xd6, y, col, t1, t2, t3 = tmp[0], tmp[1], tmp[2], tmp[3], tmp[5], tmp[6], tmp[7]
    P = tmp[8:13]
    for r in range(6):
        x6[r] = x * strain[r]
        xd6[r] = x * e_full[r]
    for a in range(nv):
        for r in range(6):
            y[r] = 0.0
        y[modes[a]] = 1.0
        _T_dot_into(x6, xd6, y, col, P, t1, t2, t3)
        acc = 0.0
        for r in range(6):
            acc += x * col[r] * f[r]
        out[a] = acc


@_jit
def rnea_derivatives_pass(m, w, g, q, v, a, dtau_dq, dtau_dv):
    """d tau/d q and d tau/d v (nv, nv) of ``tau = M a + C v + g + K (q - q0) + D v``
    after forward_pass(level 2) and rnea_pass at (q, v, a) without loads."""
    n = m.parent.shape[0]
    P = m.px.shape[1]
    dV = np.zeros((n, 6))
    dA = np.zeros((n, 6))
    dl = np.zeros((n, 6))
    dVp = np.zeros((n, P, 6))
    dAp = np.zeros((n, P, 6))
    dlp = np.zeros((n, P, 6))
    dfacc = np.zeros((n, 6))
    insub = np.zeros(n, np.bool_)
    tmp = np.zeros((16, 6))
    Sv = np.empty(6)
    Sa = np.empty(6)
    zeta = np.empty(6)
    e_full = np.zeros(6)
    fa = np.zeros(6)
    dVin = np.empty(6)
    dAin = np.empty(6)
    dlin = np.empty(6)
    t1 = np.empty(6)
    t2 = np.empty(6)
    t3 = np.empty(6)
    df = np.empty(6)
    dfin = np.empty(6)
    col = np.empty(6)
    R = np.empty((3, 3))
    z6 = np.zeros(6)
    for wrt in range(2):
        wrt_q = wrt == 0
        out = dtau_dq if wrt_q else dtau_dv
        for k in range(n):
            nvk, ivk = m.nv[k], m.iv[k]
            soft_k = m.kind[k] == SOFT
            for b in range(nvk):
                cidx = ivk + b
                for r in range(6):
                    zeta[r] = w.S[k, r, b]
                    e_full[r] = 0.0
                    fa[r] = 0.0
                if soft_k:
                    e_full[m.modes[k, b]] = 1.0
                    for c in range(nvk):
                        fa[m.modes[k, c]] = a[ivk + c]
                for i in range(n):
                    insub[i] = False
                    for r in range(6):
                        dfacc[i, r] = 0.0
                # ---- forward: the subtree of k ----
                for i in range(k, n):
                    par = m.parent[i]
                    if i == k:
                        insub[i] = True
                        _Scol(w.S[i], nvk, v, ivk, Sv)
                        _Scol(w.S[i], nvk, a, ivk, Sa)
                        _perturbed_frame(m.length[i] if soft_k else 1.0, w.strain[i], w.strain_rate[i], fa,
                                         e_full, w.V[i], w.A[i], Sv, Sa, w.Ad_J_inv[i], w.Ain[i], zeta, wrt_q,
                                         soft_k, dV[i], dA[i], tmp)
                        for r in range(6):
                            dl[i, r] = zeta[r] if wrt_q else 0.0
                        if soft_k:
                            for p in range(m.npt[i]):
                                for r in range(6):
                                    t3[r] = w.Sp[i, p, r, b]
                                _Scol(w.Sp[i, p], nvk, v, ivk, Sv)
                                _Scol(w.Sp[i, p], nvk, a, ivk, Sa)
                                _perturbed_frame(m.px[i, p], w.strain[i], w.strain_rate[i], fa, e_full,
                                                 w.Vp[i, p], w.Ap[i, p], Sv, Sa, w.Ad_p_inv[i, p], w.Ain[i], t3,
                                                 wrt_q, TRUE, dVp[i, p], dAp[i, p], tmp)
                                for r in range(6):
                                    dlp[i, p, r] = t3[r] if wrt_q else 0.0
                        continue
                    if par < 0 or not insub[par]:
                        continue
                    insub[i] = True
                    nv, iv = m.nv[i], m.iv[i]
                    _mv(m.Ad_pl_inv[i], dV[par], dVin)
                    _mv(m.Ad_pl_inv[i], dA[par], dAin)
                    _mv(m.Ad_pl_inv[i], dl[par], dlin)
                    _mv(w.Ad_J_inv[i], dVin, dV[i])
                    _mv(w.Ad_J_inv[i], dlin, dl[i])
                    _Scol(w.S[i], nv, v, iv, Sv)
                    _ad_vec(dV[i], Sv, t1)
                    _mv(w.Ad_J_inv[i], dAin, dA[i])
                    for r in range(6):
                        dA[i, r] += t1[r]
                    if m.kind[i] == SOFT:
                        for p in range(m.npt[i]):
                            _mv(w.Ad_p_inv[i, p], dVin, dVp[i, p])
                            _mv(w.Ad_p_inv[i, p], dlin, dlp[i, p])
                            _Scol(w.Sp[i, p], nv, v, iv, Sv)
                            _ad_vec(dVp[i, p], Sv, t1)
                            _mv(w.Ad_p_inv[i, p], dAin, dAp[i, p])
                            for r in range(6):
                                dAp[i, p, r] += t1[r]
                # ---- backward: the subtree, then the ancestors ----
                for i in range(n - 1, -1, -1):
                    nv, iv = m.nv[i], m.iv[i]
                    if i >= k and insub[i]:
                        for r in range(6):
                            df[r] = dfacc[i, r]
                        if m.rigid_mass[i]:
                            _dwrench(m.inertia[i], m.mc[i], False, 1.0, dA[i], dl[i], w.g_out[i], g, w.V[i],
                                     dV[i], t1, t2, t3, dfin)
                            for r in range(6):
                                df[r] += t1[r]
                        for c in range(nv):
                            acc = 0.0
                            for r in range(6):
                                acc += w.S[i, r, c] * df[r]
                            out[iv + c, cidx] = acc
                        _mtv(w.Ad_J_inv[i], df, dfin)
                        if i == k and wrt_q:
                            if soft_k:
                                _dS_T_f(m.length[i], w.strain[i], e_full, m.modes[i], nv, w.f[i], col, tmp)
                                for c in range(nv):
                                    out[iv + c, cidx] += col[c]
                            _adT(zeta, w.f[i], t1)
                            _mtv(w.Ad_J_inv[i], t1, t2)
                            for r in range(6):
                                dfin[r] -= t2[r]
                        if m.kind[i] == SOFT:
                            for p in range(m.npt[i]):
                                for r in range(3):
                                    for c in range(3):
                                        acc = 0.0
                                        for s in range(3):
                                            acc += w.g_in[i, r, s] * w.gp[i, p, s, c]
                                        R[r, c] = acc
                                _dwrench(m.inertia[i], m.mc[i], True, m.pw[i, p], dAp[i, p], dlp[i, p], R, g,
                                         w.Vp[i, p], dVp[i, p], t1, t2, t3, col)
                                for c in range(nv):
                                    acc = 0.0
                                    for r in range(6):
                                        acc += w.Sp[i, p, r, c] * t1[r]
                                    out[iv + c, cidx] += acc
                                _mtv(w.Ad_p_inv[i, p], t1, t2)
                                for r in range(6):
                                    dfin[r] += t2[r]
                                if i == k and wrt_q:
                                    _dS_T_f(m.px[i, p], w.strain[i], e_full, m.modes[i], nv, w.fp[i, p], col, tmp)
                                    for c in range(nv):
                                        out[iv + c, cidx] += col[c]
                                    for r in range(6):
                                        t3[r] = w.Sp[i, p, r, b]
                                    _adT(t3, w.fp[i, p], t1)
                                    _mtv(w.Ad_p_inv[i, p], t1, t2)
                                    for r in range(6):
                                        dfin[r] -= t2[r]
                    elif i < k and _is_ancestor(m.parent, i, k):
                        for r in range(6):
                            df[r] = dfacc[i, r]
                        for c in range(nv):
                            acc = 0.0
                            for r in range(6):
                                acc += w.S[i, r, c] * df[r]
                            out[iv + c, cidx] = acc
                        _mtv(w.Ad_J_inv[i], df, dfin)
                    else:
                        for c in range(nv):
                            out[iv + c, cidx] = 0.0
                        continue
                    par = m.parent[i]
                    if par >= 0:
                        _mtv(m.Ad_pl_inv[i], dfin, t1)
                        for r in range(6):
                            dfacc[par, r] += t1[r]
        # stiffness and damping blocks
        for i in range(n):
            if m.kind[i] == 3 or m.kind[i] == 4:
                continue
            nv, iv = m.nv[i], m.iv[i]
            for r in range(nv):
                for c in range(nv):
                    out[iv + r, iv + c] += m.Kb[i, r, c] if wrt_q else m.Db[i, r, c]
        _field_blocks(m, wrt_q, out)


@_jit_inner
def _field_blocks(m, wrt_q, out):
    """out[ef_v, ef_v] += P^T K P (``wrt_q``) or P^T D P: the elastic
    fields' stiffness or damping (passes.field_forces)."""
    nz, nr = m.ef_P.shape
    C = m.ef_K if wrt_q else m.ef_D
    for a in range(nr):
        for b in range(nr):
            acc = 0.0
            for c in range(nz):
                pa = m.ef_P[c, a]
                if pa != 0.0:
                    for k in range(nz):
                        acc += pa * C[c, k] * m.ef_P[k, b]
            out[m.ef_v[a], m.ef_v[b]] += acc


@_jit_inner
def _is_ancestor(parent, j, k):
    i = parent[k]
    while i >= 0:
        if i == j:
            return True
        i = parent[i]
    return False
