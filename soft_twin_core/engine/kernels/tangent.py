"""The static tangent: d tau / d q of the applied-force part of inverse
dynamics at rest (v = a = 0), in one O(n^2) pass (numba).

At rest, with the RNEA wrenches F (minus the applied loads: gravity, dead
and follower loads) as spatial wrenches (world axes, about the origin) and
the spatial subspaces Sw = Ad(g) S of every joint (output frame) and soft
point (its cross-section),

    tau_i = Sw_i^T F_beyond(i) + sum_{p in i} Sw_p^T F_p.

Moving joint k by dq_k moves everything beyond it rigidly with the spatial
twist xi = Sw_k dq_k (a soft point p of k with its own Sw_p dq_k). Per load
at world position p: a dead wrench (f, m) changes as ``dF = [0; (v + w x p) x f]``,
a follower wrench as ``dF = -ad(xi)^T F``; a subspace carried along changes
as ``ad(xi) Sw``, and a soft section's own subspace as ``x Tdot(x f)[x df]``.
Summed per moving set:

* k beyond joint i (descendant): ``Sw_i^T Y_k``,
  ``Y_k = sum_sets (Lam(dead) + Psi(follower)) Sw_set``,
  ``Lam = [[0, 0], [-hat(fs), Phi^T - tr(Phi) I]]``, ``Psi(F) = [[0, -hat(f)], [-hat(f), -hat(n)]]``;
* k an ancestor of i: ``Z_i Omega_k`` (Omega: the angular rows of Sw_k),
  ``Z_i = sum_sets Sw_set^T Gam(dead)``, ``Gam = [hat(fs); Phi - tr(Phi) I + hat(ms)]``
  (follower loads turn with the subspaces: no change);
* k = i: ``sum_sets Sw_set^T Gam Omega_set + x^2 [Tdot(x f)[e_b]^T f_body]_a``,

with fs, ms the summed dead forces and moments of the set and
``Phi = sum f p^T``. Checked against central differences in the tests.
"""

import numpy as np

from soft_twin_core.engine.kernels.spatial import (FALSE, _Ad_into, _T_cay_dot_into, _betas_dbetas, _jit,
                                                   _jit_inner, _map_into, _tangent_into)

from soft_twin_core.engine.joint_kinds import SOFT


@_jit_inner
def _adT_vec(x, y, out):
    """out = ad(x)^T y = [-w x yu; -u x yu - w x yw]."""
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    a0, a1, a2, b0, b1, b2 = y[0], y[1], y[2], y[3], y[4], y[5]
    out[0] = -(w1 * a2 - w2 * a1)
    out[1] = -(w2 * a0 - w0 * a2)
    out[2] = -(w0 * a1 - w1 * a0)
    out[3] = -(u1 * a2 - u2 * a1) - (w1 * b2 - w2 * b1)
    out[4] = -(u2 * a0 - u0 * a2) - (w2 * b0 - w0 * b2)
    out[5] = -(u0 * a1 - u1 * a0) - (w0 * b1 - w1 * b0)


@_jit_inner
def _Tdot_T_columns(kmap, x, f, out):
    """out[:, b] = (d/dx T(x)[e_b])^T f, b = 0..5 (the transposed directional
    derivatives of the tangent operator applied to a wrench f)."""
    if kmap == 1:
        col = np.empty(6)
        e = np.zeros(6)
        y = np.zeros(6)
        for b in range(6):
            e[:] = 0.0
            e[b] = 1.0
            for a in range(6):
                y[:] = 0.0
                y[a] = 1.0
                _T_cay_dot_into(x, e, y, col)
                acc = 0.0
                for r in range(6):
                    acc += col[r] * f[r]
                out[a, b] = acc
        return
    # T^T f = f - b1 ad^T f + b2 (ad^T)^2 f - b3 (ad^T)^3 f + b4 (ad^T)^4 f
    t2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5]
    bb, dd = _betas_dbetas(t2)
    P = np.empty((5, 6))
    for a in range(6):
        P[0, a] = f[a]
    for k in range(1, 5):
        _adT_vec(x, P[k - 1], P[k])
    e = np.zeros(6)
    acc = np.empty(6)
    tmp = np.empty(6)
    tmp2 = np.empty(6)
    for b in range(6):
        e[:] = 0.0
        e[b] = 1.0
        wwd = x[b] if b >= 3 else 0.0                 # w . e_b
        _adT_vec(e, P[0], acc)                        # Q_1 = ad(e)^T f
        for a in range(6):
            out[a, b] = -(dd[0] * wwd * P[1, a] + bb[0] * acc[a])
        for k in range(2, 5):
            sign = 1.0 if k % 2 == 0 else -1.0
            _adT_vec(e, P[k - 1], tmp)
            _adT_vec(x, acc, tmp2)
            for a in range(6):
                acc[a] = tmp[a] + tmp2[a]
                out[a, b] += sign * (dd[k - 1] * wwd * P[k, a] + bb[k - 1] * acc[a])


@_jit_inner
def _spatial_subspace(g, S, nv, Sw, Ad):
    _Ad_into(g, Ad, FALSE)
    for r in range(6):
        for a in range(nv):
            acc = 0.0
            for k in range(6):
                acc += Ad[r, k] * S[k, a]
            Sw[r, a] = acc


@_jit_inner
def _add_set(nv, Sw, fs, Ph, ms, Ff, Y, Z, D, Om, with_diag):
    """Y += (Lam + Psi) Sw, Z += Sw^T Gam, D += Sw^T Gam Om (with_diag) for
    a moving set with dead sums (fs, Ph, ms) and follower sum Ff."""
    tr = Ph[0, 0] + Ph[1, 1] + Ph[2, 2]
    G = np.empty((6, 3))
    # Gam = [hat(fs); Ph - tr I + hat(ms)]
    G[0, 0], G[0, 1], G[0, 2] = 0.0, -fs[2], fs[1]
    G[1, 0], G[1, 1], G[1, 2] = fs[2], 0.0, -fs[0]
    G[2, 0], G[2, 1], G[2, 2] = -fs[1], fs[0], 0.0
    for r in range(3):
        for c in range(3):
            G[3 + r, c] = Ph[r, c] - (tr if r == c else 0.0)
    G[3, 1] -= ms[2]
    G[3, 2] += ms[1]
    G[4, 0] += ms[2]
    G[4, 2] -= ms[0]
    G[5, 0] -= ms[1]
    G[5, 1] += ms[0]
    # L = Lam + Psi (6x6)
    L = np.zeros((6, 6))
    f0, f1, f2 = Ff[0], Ff[1], Ff[2]
    n0, n1, n2 = Ff[3], Ff[4], Ff[5]
    Hf = ((0.0, -f2, f1), (f2, 0.0, -f0), (-f1, f0, 0.0))
    Hn = ((0.0, -n2, n1), (n2, 0.0, -n0), (-n1, n0, 0.0))
    Hs = ((0.0, -fs[2], fs[1]), (fs[2], 0.0, -fs[0]), (-fs[1], fs[0], 0.0))
    for r in range(3):
        for c in range(3):
            L[r, 3 + c] = -Hf[r][c]
            L[3 + r, c] = -Hf[r][c] - Hs[r][c]
            L[3 + r, 3 + c] = -Hn[r][c] + Ph[c, r] - (tr if r == c else 0.0)
    for r in range(6):
        for a in range(nv):
            acc = 0.0
            for k in range(6):
                acc += L[r, k] * Sw[k, a]
            Y[r, a] += acc
    SG = np.empty((6, 3))
    for a in range(nv):
        for c in range(3):
            acc = 0.0
            for k in range(6):
                acc += Sw[k, a] * G[k, c]
            SG[a, c] = acc
            Z[a, c] += acc
    if with_diag:
        for a in range(nv):
            for b in range(nv):
                D[a, b] += SG[a, 0] * Om[3, b] + SG[a, 1] * Om[4, b] + SG[a, 2] * Om[5, b]


@_jit_inner
def _dead_point(fd, md, p0, p1, p2, fs, Ph, ms):
    """Dead sums of one wrench (fd, md) at world position (p0, p1, p2)
    (accumulated; the position as numbers, so that callers holding it in a
    vector or in a pose's column share one compilation)."""
    for r in range(3):
        fs[r] += fd[r]
        ms[r] += md[r]
        Ph[r, 0] += fd[r] * p0
        Ph[r, 1] += fd[r] * p1
        Ph[r, 2] += fd[r] * p2


@_jit_inner
def _own_term(kmap, x, strain, modes, nv, fb, D, tmp6):
    """D[a, b] += x^2 [(d/dx T(x f)[e_mb])^T fb]_ma: the change of the own
    subspace x T(x f) B of a soft cross-section carrying the body wrench fb."""
    x6 = np.empty(6)
    for a in range(6):
        x6[a] = x * strain[a]
    _Tdot_T_columns(kmap, x6, fb, tmp6)
    for a in range(nv):
        for b in range(nv):
            D[a, b] += x * x * tmp6[modes[a], modes[b]]


@_jit
def static_tangent_pass(m, w, ld, g, Kt):
    """Kt += d tau_rnea / dq at rest, after forward_pass (level >= 0) and
    rnea_pass at v = a = 0 (w.f, w.fp hold the RNEA wrenches)."""
    n = m.parent.shape[0]
    Sw = np.zeros((n, 6, 6))
    Y = np.zeros((n, 6, 6))
    Z = np.zeros((n, 6, 3))
    D = np.zeros((n, 6, 6))
    # dead sums and follower sum of everything beyond each joint's output frame
    fs = np.zeros((n, 3))
    Ph = np.zeros((n, 3, 3))
    ms = np.zeros((n, 3))
    Ff = np.zeros((n, 6))
    Ad = np.empty((6, 6))
    gp = np.empty((4, 4))
    pose = np.empty((4, 4))
    Swp = np.zeros((6, 6))
    tmp6 = np.empty((6, 6))
    fd = np.empty(3)
    md = np.zeros(3)
    z3 = np.zeros(3)
    pfs = np.zeros(3)
    pPh = np.zeros((3, 3))
    pms = np.zeros(3)
    pFf = np.zeros(6)
    fb = np.empty(6)
    for i in range(n):
        _spatial_subspace(w.g_out[i], w.S[i], m.nv[i], Sw[i], Ad)
    # rigid bodies' gravity and output-frame loads
    for i in range(n):
        if m.rigid_mass[i]:
            I6 = m.inertia[i]
            mass = I6[0, 0]
            c = (I6[5, 1] / mass, I6[3, 2] / mass, I6[4, 0] / mass)
            pw = np.empty(3)
            for r in range(3):
                pw[r] = w.g_out[i, r, 3] + w.g_out[i, r, 0] * c[0] + w.g_out[i, r, 1] * c[1] \
                    + w.g_out[i, r, 2] * c[2]
                fd[r] = -mass * g[r]
            _dead_point(fd, z3, pw[0], pw[1], pw[2], fs[i], Ph[i], ms[i])
    for l in range(ld.joint.shape[0]):
        i = ld.joint[l]
        if ld.x[l] >= 0.0 and m.kind[i] == SOFT:
            continue
        _add_load(ld, l, w.g_out[i], fs[i], Ph[i], ms[i], Ff[i], fb, Ad)
    for i in range(n - 1, -1, -1):
        nv = m.nv[i]
        soft = m.kind[i] == SOFT
        if soft:
            # quadrature points (gravity) and loads inside the section: own moving sets
            for p in range(m.npt[i] + ld.joint.shape[0]):
                if p < m.npt[i]:
                    x = m.px[i, p]
                    _mm4(w.g_in[i], w.gp[i, p], gp)
                    Sp = w.Sp[i, p]
                    pfs[:] = 0.0
                    pPh[:, :] = 0.0
                    pms[:] = 0.0
                    pFf[:] = 0.0
                    mass = m.pw[i, p] * m.mc[i, 0]
                    for r in range(3):
                        fd[r] = -mass * g[r]
                    _dead_point(fd, z3, gp[0, 3], gp[1, 3], gp[2, 3], pfs, pPh, pms)
                    for a in range(6):
                        fb[a] = w.fp[i, p, a]
                else:
                    l = p - m.npt[i]
                    if ld.joint[l] != i or ld.x[l] < 0.0:
                        continue
                    x = ld.x[l]
                    x6 = np.empty(6)
                    for a in range(6):
                        x6[a] = x * w.strain[i, a]
                    _map_into(m.kmap[i], x6, pose)
                    _mm4(w.g_in[i], pose, gp)
                    _point_subspace(m.kmap[i], x6, x, m.modes[i], nv, Swp)
                    Sp = Swp
                    pfs[:] = 0.0
                    pPh[:, :] = 0.0
                    pms[:] = 0.0
                    pFf[:] = 0.0
                    _add_load(ld, l, gp, pfs, pPh, pms, pFf, fb, Ad)
                _spatial_subspace(gp, Sp, nv, tmp6, Ad)
                _add_set(nv, tmp6, pfs, pPh, pms, pFf, Y[i], Z[i], D[i], tmp6, True)
                _own_term(m.kmap[i], x, w.strain[i], m.modes[i], nv, fb, D[i], Ad)
                # the point's loads join what lies beyond the parent (not beyond i's output)
                par = m.parent[i]
                if par >= 0:
                    for r in range(3):
                        fs[par, r] += pfs[r]
                        ms[par, r] += pms[r]
                        for c in range(3):
                            Ph[par, r, c] += pPh[r, c]
                    for r in range(6):
                        Ff[par, r] += pFf[r]
        # the set beyond the output frame
        _add_set(nv, Sw[i], fs[i], Ph[i], ms[i], Ff[i], Y[i], Z[i], D[i], Sw[i], True)
        if soft:
            _own_term(m.kmap[i], m.length[i], w.strain[i], m.modes[i], nv, w.f[i], D[i], Ad)
        par = m.parent[i]
        if par >= 0:
            for r in range(3):
                fs[par, r] += fs[i, r]
                ms[par, r] += ms[i, r]
                for c in range(3):
                    Ph[par, r, c] += Ph[i, r, c]
            for r in range(6):
                Ff[par, r] += Ff[i, r]
    # assemble
    for k in range(n):
        nk, ik = m.nv[k], m.iv[k]
        for a in range(nk):
            for b in range(nk):
                Kt[ik + a, ik + b] += D[k, a, b]
        j = m.parent[k]
        while j >= 0:
            nj, ij = m.nv[j], m.iv[j]
            for a in range(nj):
                for b in range(nk):
                    acc = 0.0
                    for r in range(6):
                        acc += Sw[j, r, a] * Y[k, r, b]
                    Kt[ij + a, ik + b] += acc
            for a in range(nk):
                for b in range(nj):
                    Kt[ik + a, ij + b] += Z[k, a, 0] * Sw[j, 3, b] + Z[k, a, 1] * Sw[j, 4, b] \
                        + Z[k, a, 2] * Sw[j, 5, b]
            j = m.parent[j]


@_jit_inner
def _mm4(A, B, out):
    for r in range(3):
        for c in range(4):
            acc = A[r, 3] if c == 3 else 0.0
            for k in range(3):
                acc += A[r, k] * B[k, c]
            out[r, c] = acc
    out[3, 0] = 0.0
    out[3, 1] = 0.0
    out[3, 2] = 0.0
    out[3, 3] = 1.0


@_jit_inner
def _point_subspace(kmap, x6, x, modes, nv, Sp):
    T = np.empty((6, 6))
    S3 = np.empty((7, 3, 3))
    _tangent_into(kmap, x6, T, S3)
    for a in range(nv):
        for r in range(6):
            Sp[r, a] = x * T[r, modes[a]]


@_jit_inner
def _add_load(ld, l, g, fs, Ph, ms, Ff, fb, Ad):
    """Sums of load l (RNEA sign: minus the applied wrench) at world pose g;
    fb receives its body wrench."""
    W = ld.wrench[l]
    if ld.world[l]:
        fd = np.empty(3)
        md = np.empty(3)
        for r in range(3):
            fd[r] = -W[r]
            md[r] = -W[3 + r]
        _dead_point(fd, md, g[0, 3], g[1, 3], g[2, 3], fs, Ph, ms)
        for a in range(3):
            fb[a] = -(g[0, a] * W[0] + g[1, a] * W[1] + g[2, a] * W[2])
            fb[3 + a] = -(g[0, a] * W[3] + g[1, a] * W[4] + g[2, a] * W[5])
    else:
        for a in range(6):
            fb[a] = -W[a]
        # spatial: Ad(g)^-T fb = [R fu; p x R fu + R fw]
        Rf = np.empty(3)
        Rm = np.empty(3)
        for r in range(3):
            Rf[r] = g[r, 0] * fb[0] + g[r, 1] * fb[1] + g[r, 2] * fb[2]
            Rm[r] = g[r, 0] * fb[3] + g[r, 1] * fb[4] + g[r, 2] * fb[5]
        p = g[:3, 3]
        Ff[0] += Rf[0]
        Ff[1] += Rf[1]
        Ff[2] += Rf[2]
        Ff[3] += p[1] * Rf[2] - p[2] * Rf[1] + Rm[0]
        Ff[4] += p[2] * Rf[0] - p[0] * Rf[2] + Rm[1]
        Ff[5] += p[0] * Rf[1] - p[1] * Rf[0] + Rm[2]
