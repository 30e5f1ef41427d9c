"""The recursive passes over the kinematic tree (numba), one function each.

Every pass takes the model's packed arrays ``m`` (:class:`data.ModelArrays`)
and the workspace arrays ``w`` (:class:`data.WorkArrays`) and writes into
``w``. Joints are in topological order, so a forward loop meets a parent
before its children and a backward loop the children first. Notation (see
:mod:`soft_twin_core.engine.multibody`): joint i maps its parent's output frame to
its input frame by the fixed placement, and its input frame to its output
frame by Jq_i(q_i); S_i is its motion subspace in the output frame; a soft
section carries quadrature points p at pose gp = exp(x_p f) from its input
frame, with subspace Sp = x_p T(x_p f) B.

* :func:`forward_pass`: poses; body twists V_i = Ad(X_i^-1) V_parent + S_i v_i;
  accelerations A_i = Ad(X_i^-1) A_parent + S_i a_i + ad(V_i) S_i v_i + Sdot_i v_i;
  the same for soft points.
* :func:`rnea_pass`: inverse dynamics; the wrench f_i at each output frame
  (everything beyond it) and f_in_i transmitted through the joint.
* :func:`crba_pass`: the joint-space mass matrix from composite inertias.
* :func:`aba_factor` / :func:`aba_solve`: articulated-body factorisation of
  ``M + cD D + cK K`` (joint-space damping and stiffness folded into each
  joint's block) and the O(n) solve with it.
"""

import numpy as np

from soft_twin_core.engine.joint_kinds import FIXED, FREE, PRISMATIC, REVOLUTE, SOFT, SPHERICAL  # noqa: F401
from soft_twin_core.engine.kernels.spatial import (FALSE, TRUE, _Ad_into, _ad_t, _ad_vec, _exp_into, _jit,
                                                   _jit_inner, _jit_inline, _map_into, _T_dot_along,
                                                   _tangent_dot_into, _tangent_into)

# forward_pass's levels, as numpy integers: a literal 0 or 2 from compiled code
# would compile the pass once more for each value (a Literal[int] signature).
POSES, TWISTS, ACCELERATIONS = np.int64(0), np.int64(1), np.int64(2)


@_jit_inner
def _quat_into(qx, qy, qz, qw, g):
    g[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    g[0, 1] = 2 * (qx * qy - qz * qw)
    g[0, 2] = 2 * (qx * qz + qy * qw)
    g[1, 0] = 2 * (qx * qy + qz * qw)
    g[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    g[1, 2] = 2 * (qy * qz - qx * qw)
    g[2, 0] = 2 * (qx * qz - qy * qw)
    g[2, 1] = 2 * (qy * qz + qx * qw)
    g[2, 2] = 1 - 2 * (qx * qx + qy * qy)


@_jit_inner
def _eye4(g):
    for r in range(4):
        for c in range(4):
            g[r, c] = 1.0 if r == c else 0.0


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
def _mv6(A, x, out):
    for r in range(6):
        acc = 0.0
        for k in range(6):
            acc += A[r, k] * x[k]
        out[r] = acc


@_jit_inner
def _mtv6(A, x, out):
    for r in range(6):
        acc = 0.0
        for k in range(6):
            acc += A[k, r] * x[k]
        out[r] = acc


@_jit_inner
def _Sv(S, nv, v, iv, out):
    """out = S[:, :nv] v[iv:iv+nv]."""
    for r in range(6):
        acc = 0.0
        for k in range(nv):
            acc += S[r, k] * v[iv + k]
        out[r] = acc


@_jit_inner
def _joint_transform(kind, kmap, iq, nv, axis, length, f0, modes, q, J, S, strain, x6, T, S3, subspace):
    """Joint transform J (input -> output frame), subspace S (output frame;
    a soft joint's only if ``subspace``, else zeros) and, for a soft joint,
    its strain."""
    S[:, :] = 0.0
    _eye4(J)
    if kind == SOFT:
        for a in range(6):
            strain[a] = f0[a]
        for a in range(nv):
            strain[modes[a]] = q[iq + a]
        for a in range(6):
            x6[a] = length * strain[a]
        _map_into(kmap, x6, J)
        if not subspace:
            return
        _tangent_into(kmap, x6, T, S3)
        for a in range(nv):
            for r in range(6):
                S[r, a] = length * T[r, modes[a]]
    elif kind == REVOLUTE:
        for a in range(3):
            x6[a] = 0.0
            x6[3 + a] = axis[a] * q[iq]
            S[3 + a, 0] = axis[a]
        _exp_into(x6, J)
    elif kind == PRISMATIC:
        for a in range(3):
            J[a, 3] = axis[a] * q[iq]
            S[a, 0] = axis[a]
    elif kind == SPHERICAL:
        _quat_into(q[iq], q[iq + 1], q[iq + 2], q[iq + 3], J)
        for a in range(3):
            S[3 + a, a] = 1.0
    elif kind == FREE:
        _quat_into(q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6], J)
        for a in range(3):
            J[a, 3] = q[iq + a]
        for a in range(6):
            S[a, a] = 1.0


@_jit_inner
def _soft_point(kmap, x, strain, modes, nv, gp, Ad_p_inv, Sp, x6, T, S3):
    """Pose gp = exp(x f), Ad(gp^-1) and subspace Sp = x T(x f) B of the
    cross-section at abscissa x of a soft section with strain f."""
    for a in range(6):
        x6[a] = x * strain[a]
    _map_into(kmap, x6, gp)
    _Ad_into(gp, Ad_p_inv, TRUE)
    _tangent_into(kmap, x6, T, S3)
    Sp[:, :] = 0.0
    for a in range(nv):
        for r in range(6):
            Sp[r, a] = x * T[r, modes[a]]


@_jit_inner
def _soft_bias(kmap, x, strain, rate, V, Sv, out, vs, P):
    """ad(V) S v + x Tdot(x f, x fdot) fdot: the velocity-product acceleration
    of the cross-section at abscissa x of a soft section (strain f, rate
    fdot, body twist V, S v = Sv); vs: (>= 5, 6) scratch, P: (5, 6)."""
    if kmap == 0:
        X = (x * strain[0], x * strain[1], x * strain[2], x * strain[3], x * strain[4], x * strain[5])
        Y = (rate[0], rate[1], rate[2], rate[3], rate[4], rate[5])
        d = _T_dot_along(x, X, Y)
        e = _ad_t((V[0], V[1], V[2], V[3], V[4], V[5]), (Sv[0], Sv[1], Sv[2], Sv[3], Sv[4], Sv[5]))
        for a in range(6):
            out[a] = x * d[a] + e[a]
        return
    x6, xd6, tmp, tmp2, acc = vs[0], vs[1], vs[2], vs[3], vs[4]
    for a in range(6):
        x6[a] = x * strain[a]
        xd6[a] = x * rate[a]
    _tangent_dot_into(kmap, x6, xd6, rate, out, P, tmp, tmp2, acc)
    _ad_vec(V, Sv, tmp)
    for a in range(6):
        out[a] = x * out[a] + tmp[a]


@_jit_inner
def _place_joint(m, w, i, q, T, S3, subspace):
    """Joint i's transform, strain (and subspace if ``subspace``) at q, and
    its frames' poses g_in, g_out from its parent's (a pass in topological
    order)."""
    par = m.parent[i]
    _joint_transform(m.kind[i], m.kmap[i], m.iq[i], m.nv[i], m.axis[i], m.length[i], m.f0[i], m.modes[i], q, w.Jq[i],
                     w.S[i], w.strain[i], w.vscratch[0], T, S3, subspace)
    if par < 0:
        for r in range(4):
            for cc in range(4):
                w.g_in[i, r, cc] = m.placement[i, r, cc]
    else:
        _mm4(w.g_out[par], m.placement[i], w.g_in[i])
    _mm4(w.g_in[i], w.Jq[i], w.g_out[i])


@_jit_inline
def poses_pass(m, w, q):
    """The joints' transforms, strains and frames' poses (Jq, strain, g_in,
    g_out) alone: what point positions need (frames.point_poses), at a
    third of :func:`forward_pass`'s level 0 (no subspaces, no quadrature
    points). The workspace's other arrays are not of q (S: zeros for soft
    joints): a forward pass before anything that reads them."""
    T = w.scratch[0]
    S3 = np.empty((7, 3, 3))
    for i in range(m.parent.shape[0]):
        _place_joint(m, w, i, q, T, S3, FALSE)


@_jit
def forward_pass(m, w, q, v, a, level):
    """level 0: poses and subspaces; 1: + twists; 2: + accelerations (a may
    be zeros: the velocity-product accelerations alone)."""
    n = m.parent.shape[0]
    T = w.scratch[0]
    S3 = np.empty((7, 3, 3))
    Sv = w.vscratch[5]
    c = w.vscratch[6]
    t6 = w.vscratch[7]
    P5 = w.scratch[15][:5]
    for i in range(n):
        par = m.parent[i]
        _place_joint(m, w, i, q, T, S3, TRUE)
        _Ad_into(w.Jq[i], w.Ad_J_inv[i], TRUE)
        soft = m.kind[i] == SOFT
        nv, iv = m.nv[i], m.iv[i]
        if soft:
            for b in range(6):
                w.strain_rate[i, b] = 0.0
            if level >= 1:
                for b in range(nv):
                    w.strain_rate[i, m.modes[i, b]] = v[iv + b]
            for p in range(m.npt[i]):
                _soft_point(m.kmap[i], m.px[i, p], w.strain[i], m.modes[i], nv, w.gp[i, p], w.Ad_p_inv[i, p], w.Sp[i, p],
                            w.vscratch[0], T, S3)
        if level < 1:
            continue
        if par < 0:
            for b in range(6):
                w.Vin[i, b] = 0.0
        else:
            _mv6(m.Ad_pl_inv[i], w.V[par], w.Vin[i])
        _mv6(w.Ad_J_inv[i], w.Vin[i], t6)
        _Sv(w.S[i], nv, v, iv, Sv)
        for b in range(6):
            w.V[i, b] = t6[b] + Sv[b]
        if soft:
            for p in range(m.npt[i]):
                _mv6(w.Ad_p_inv[i, p], w.Vin[i], t6)
                _Sv(w.Sp[i, p], nv, v, iv, c)
                for b in range(6):
                    w.Vp[i, p, b] = t6[b] + c[b]
        if level < 2:
            continue
        if par < 0:
            for b in range(6):
                w.Ain[i, b] = 0.0
        else:
            _mv6(m.Ad_pl_inv[i], w.A[par], w.Ain[i])
        if soft:
            _soft_bias(m.kmap[i], m.length[i], w.strain[i], w.strain_rate[i], w.V[i], Sv, c, w.vscratch, P5)
        else:
            _ad_vec(w.V[i], Sv, c)
        _mv6(w.Ad_J_inv[i], w.Ain[i], t6)
        for b in range(6):
            w.A[i, b] = t6[b] + c[b]
        _Sv(w.S[i], nv, a, iv, t6)
        for b in range(6):
            w.A[i, b] += t6[b]
        if soft:
            for p in range(m.npt[i]):
                _Sv(w.Sp[i, p], nv, v, iv, Sv)
                _soft_bias(m.kmap[i], m.px[i, p], w.strain[i], w.strain_rate[i], w.Vp[i, p], Sv, c, w.vscratch, P5)
                _mv6(w.Ad_p_inv[i, p], w.Ain[i], t6)
                _Sv(w.Sp[i, p], nv, a, iv, Sv)
                for b in range(6):
                    w.Ap[i, p, b] = t6[b] + Sv[b] + c[b]


@_jit_inner
def _inertial_wrench(I6, mc, diag, A, V, R, g, scale, out, tmp, tmp2):
    """out = scale (I (A - [R^T g; 0]) - ad(V)^T I V): inertial minus
    gravitational body wrench of a rigid inertia I6 (or diagonal mc); R:
    the body's rotation (its upper-left 3x3 block is read) in the frame
    where g is given."""
    for a in range(3):
        tmp[a] = A[a] - (R[0, a] * g[0] + R[1, a] * g[1] + R[2, a] * g[2])
        tmp[a + 3] = A[a + 3]
    if diag:
        for a in range(6):
            out[a] = mc[a] * tmp[a]
            tmp2[a] = mc[a] * V[a]
    else:
        _mv6(I6, tmp, out)
        _mv6(I6, V, tmp2)
    # - ad(V)^T y = [w x yu; u x yu + w x yw]  (y = I V)
    u0, u1, u2, w0, w1, w2 = V[0], V[1], V[2], V[3], V[4], V[5]
    y0, y1, y2, z0, z1, z2 = tmp2[0], tmp2[1], tmp2[2], tmp2[3], tmp2[4], tmp2[5]
    out[0] += w1 * y2 - w2 * y1
    out[1] += w2 * y0 - w0 * y2
    out[2] += w0 * y1 - w1 * y0
    out[3] += u1 * y2 - u2 * y1 + w1 * z2 - w2 * z1
    out[4] += u2 * y0 - u0 * y2 + w2 * z0 - w0 * z2
    out[5] += u0 * y1 - u1 * y0 + w0 * z1 - w1 * z0
    for a in range(6):
        out[a] *= scale


@_jit_inner
def _load_wrench(m, w, ld, l, T, S3, Wb, pose):
    """Body wrench Wb of load l at its point, and the point's pose in the
    joint's input frame (soft) or output frame (rigid: identity)."""
    i = ld.joint[l]
    x = ld.x[l]
    if x >= 0.0 and m.kind[i] == SOFT:
        x6 = w.vscratch[0]
        for a in range(6):
            x6[a] = x * w.strain[i, a]
        _map_into(m.kmap[i], x6, pose)
        R = np.empty((3, 3))
        for r in range(3):
            for c in range(3):
                acc = 0.0
                for k in range(3):
                    acc += w.g_in[i, r, k] * pose[k, c]
                R[r, c] = acc
    else:
        _eye4(pose)
        R = w.g_out[i, :3, :3]
    if ld.world[l]:
        for a in range(3):
            Wb[a] = R[0, a] * ld.wrench[l, 0] + R[1, a] * ld.wrench[l, 1] + R[2, a] * ld.wrench[l, 2]
            Wb[a + 3] = R[0, a] * ld.wrench[l, 3] + R[1, a] * ld.wrench[l, 4] + R[2, a] * ld.wrench[l, 5]
    else:
        for a in range(6):
            Wb[a] = ld.wrench[l, a]


@_jit
def rnea_pass(m, w, ld, g, tau, at_rest):
    """Inverse dynamics after :func:`forward_pass` (level 2; level 0 with
    ``at_rest``: v = a = 0): tau = M a + C v + g(q) - J^T F_ext (no
    stiffness, damping or actuation: see :func:`joint_forces`). Fills w.f
    (output frames) and w.f_in (input frames): the wrench the parent side
    exerts on the subtree."""
    z6 = np.zeros(6)
    gin = np.empty(3)
    n = m.parent.shape[0]
    t1, t2, t3, Wb = w.vscratch[8], w.vscratch[9], w.vscratch[10], w.vscratch[11]
    T = w.scratch[0]
    S3 = np.empty((7, 3, 3))
    pose = np.empty((4, 4))
    Ad = w.scratch[1]
    for i in range(n):
        for b in range(6):
            w.f[i, b] = 0.0
            w.f_in[i, b] = 0.0
    for k in range(tau.shape[0]):
        tau[k] = 0.0
    # external loads: output-frame loads into f, soft-point loads into tau and f_in
    for l in range(ld.joint.shape[0]):
        i = ld.joint[l]
        _load_wrench(m, w, ld, l, T, S3, Wb, pose)
        if ld.x[l] >= 0.0 and m.kind[i] == SOFT:
            x = ld.x[l]
            x6 = w.vscratch[0]
            for a in range(6):
                x6[a] = x * w.strain[i, a]
            _tangent_into(m.kmap[i], x6, T, S3)
            for a in range(m.nv[i]):
                acc = 0.0
                for r in range(6):
                    acc += x * T[r, m.modes[i, a]] * Wb[r]
                tau[m.iv[i] + a] -= acc
            _Ad_into(pose, Ad, TRUE)
            _mtv6(Ad, Wb, t1)
            for b in range(6):
                w.f_in[i, b] -= t1[b]
        else:
            for b in range(6):
                w.f[i, b] -= Wb[b]
    for i in range(n - 1, -1, -1):
        # literal flags (not TRUE/FALSE): a copy of _inertial_wrench per case, 8 % faster RNEA than one with the branch
        if m.rigid_mass[i]:
            _inertial_wrench(m.inertia[i], m.mc[i], False, z6 if at_rest else w.A[i], z6 if at_rest else w.V[i],
                             w.g_out[i], g, 1.0, t1, t2, t3)
            for b in range(6):
                w.f[i, b] += t1[b]
        nv, iv = m.nv[i], m.iv[i]
        for a in range(nv):
            acc = 0.0
            for r in range(6):
                acc += w.S[i, r, a] * w.f[i, r]
            tau[iv + a] += acc
        _mtv6(w.Ad_J_inv[i], w.f[i], t1)
        for b in range(6):
            w.f_in[i, b] += t1[b]
        if m.kind[i] == SOFT:
            # gravity in the input frame; at a point, R_p^T of it
            for a in range(3):
                gin[a] = w.g_in[i, 0, a] * g[0] + w.g_in[i, 1, a] * g[1] + w.g_in[i, 2, a] * g[2]
            for p in range(m.npt[i]):
                fp = w.fp[i, p]
                _inertial_wrench(m.inertia[i], m.mc[i], True, z6 if at_rest else w.Ap[i, p],
                                 z6 if at_rest else w.Vp[i, p], w.gp[i, p], gin, m.pw[i, p], fp, t2, t3)
                for a in range(nv):
                    acc = 0.0
                    for r in range(6):
                        acc += w.Sp[i, p, r, a] * fp[r]
                    tau[iv + a] += acc
                _mtv6(w.Ad_p_inv[i, p], fp, t1)
                for b in range(6):
                    w.f_in[i, b] += t1[b]
        par = m.parent[i]
        if par >= 0:
            _mtv6(m.Ad_pl_inv[i], w.f_in[i], t1)
            for b in range(6):
                w.f[par, b] += t1[b]


@_jit_inline
def joint_forces(m, q, v, out):
    """out += Kb (q - q0) + Db v joint by joint (stiffness and damping),
    then the elastic fields' forces (:func:`field_forces`)."""
    n = m.parent.shape[0]
    for i in range(n):
        nv, iv, iq = m.nv[i], m.iv[i], m.iq[i]
        if m.kind[i] == SPHERICAL or m.kind[i] == FREE:
            continue
        for a in range(nv):
            acc = 0.0
            for b in range(nv):
                acc += m.Kb[i, a, b] * (q[iq + b] - m.q0[iq + b]) + m.Db[i, a, b] * v[iv + b]
            out[iv + a] += acc
    field_forces(m, q, v, out)


@_jit_inner
def field_forces(m, q, v, out):
    """out += P^T (K z + D zdot), z = P (q - q0), zdot = P v over the
    elastic fields' coordinates (multibody.ElasticField; packed as ef_*)."""
    nz, nr = m.ef_P.shape
    if nz == 0:
        return
    z = np.zeros(nz)
    zd = np.zeros(nz)
    for c in range(nz):
        for r in range(nr):
            p = m.ef_P[c, r]
            if p != 0.0:
                z[c] += p * (q[m.ef_q[r]] - m.q0[m.ef_q[r]])
                zd[c] += p * v[m.ef_v[r]]
    f = np.zeros(nz)
    for c in range(nz):
        acc = 0.0
        for k in range(nz):
            acc += m.ef_K[c, k] * z[k] + m.ef_D[c, k] * zd[k]
        f[c] = acc
    for r in range(nr):
        acc = 0.0
        for c in range(nz):
            acc += m.ef_P[c, r] * f[c]
        out[m.ef_v[r]] += acc


@_jit_inner
def _congruence_add(X, I, out, tmp):
    """out += X^T I X (6x6, I symmetric) for an adjoint X = Ad(g^-1), whose
    lower-left 3x3 block is zero: the products skip it and only the upper
    triangle is summed (mirrored)."""
    for r in range(6):
        for c in range(6):
            acc = 0.0
            for k in range(3 if c < 3 else 6):
                acc += I[r, k] * X[k, c]
            tmp[r, c] = acc
    for r in range(6):
        kr = 3 if r < 3 else 6
        for c in range(r, 6):
            acc = 0.0
            for k in range(kr):
                acc += X[k, r] * tmp[k, c]
            out[r, c] += acc
            if c != r:
                out[c, r] += acc


@_jit_inner
def _diag_congruence_add(X, d, wgt, out):
    """out += wgt X^T diag(d) X for an adjoint X (zero lower-left block)."""
    for r in range(6):
        for c in range(r, 6):
            acc = 0.0
            for k in range(3 if r < 3 else 6):
                acc += X[k, r] * d[k] * X[k, c]
            out[r, c] += wgt * acc
            if c != r:
                out[c, r] += wgt * acc


@_jit_inner
def _joint_blocks(soft, nv, npt, pw, mc, X, S, Ad_p_inv, Sp_all, IA, F, Dm, Ic, tmp, IS):
    """For joint i with the inertia IA (output frame) of everything beyond
    its output frame: F = Ad(Jq^-1)^T IA S + sum_p Ad(gp^-1)^T Ip Sp (6 x nv,
    input frame), Dm = S^T IA S + sum_p Sp^T Ip Sp, and Ic = Ad(Jq^-1)^T IA
    Ad(Jq^-1) + sum_p Ad(gp^-1)^T Ip Ad(gp^-1) (input frame). The adjoints'
    zero lower-left blocks and the symmetry of Dm and Ic are used."""
    for r in range(6):
        for c in range(6):
            Ic[r, c] = 0.0
    _congruence_add(X, IA, Ic, tmp)
    for r in range(6):
        for a in range(nv):
            acc = 0.0
            for k in range(6):
                acc += IA[r, k] * S[k, a]
            IS[r, a] = acc
    for r in range(6):
        for a in range(nv):
            acc = 0.0
            for k in range(3 if r < 3 else 6):
                acc += X[k, r] * IS[k, a]
            F[r, a] = acc
    for a in range(nv):
        for b in range(a, nv):
            acc = 0.0
            for k in range(6):
                acc += S[k, a] * IS[k, b]
            Dm[a, b] = acc
            Dm[b, a] = acc
    if not soft:
        return
    for p in range(npt):
        Xp = Ad_p_inv[p]
        Sp = Sp_all[p]
        wg = pw[p]
        _diag_congruence_add(Xp, mc, wg, Ic)
        for k in range(6):
            for a in range(nv):
                tmp[k, a] = wg * mc[k] * Sp[k, a]
        for r in range(6):
            for a in range(nv):
                acc = 0.0
                for k in range(3 if r < 3 else 6):
                    acc += Xp[k, r] * tmp[k, a]
                F[r, a] += acc
        for a in range(nv):
            for b in range(a, nv):
                acc = 0.0
                for k in range(6):
                    acc += Sp[k, a] * tmp[k, b]
                Dm[a, b] += acc
                if b != a:
                    Dm[b, a] += acc


@_jit_inner
def _twist_map(X, Jin, S, nv, Bi, out):
    """out = X Jin + S Bi (6, nz): a frame's twist per coordinate z from
    its joint's input frame's (Jin) through the adjoint X, plus the joint's
    own motion (its subspace S (6, nv) times its rows Bi (nv, nz) of B)."""
    nz = Jin.shape[1]
    for r in range(6):
        for c in range(nz):
            acc = 0.0
            for k in range(6):
                acc += X[r, k] * Jin[k, c]
            for a in range(nv):
                acc += S[r, a] * Bi[a, c]
            out[r, c] = acc


@_jit_inner
def _add_kinetic(J, I, diag, scale, IJ, out):
    """out += scale J^T I J (upper triangle; J (6, nz), I the inertia (6,
    6) or, ``diag``, its diagonal in I[0])."""
    nz = J.shape[1]
    for r in range(6):
        for c in range(nz):
            if diag:
                IJ[r, c] = scale * I[0, r] * J[r, c]
            else:
                acc = 0.0
                for k in range(6):
                    acc += I[r, k] * J[k, c]
                IJ[r, c] = scale * acc
    for a in range(nz):
        for b in range(a, nz):
            acc = 0.0
            for r in range(6):
                acc += J[r, a] * IJ[r, b]
            out[a, b] += acc


@_jit
def projected_mass_pass(m, w, B, out):
    """out = B^T M B (nz, nz) after :func:`forward_pass` (level 0): the
    mass matrix of coordinates z with v = B z, as the kinetic energy's sum
    over the mass points, ``sum_p J_p^T I_p J_p``, J_p the point's body
    twist per coordinate z by one forward recursion (frame by frame, as
    :func:`forward_pass` propagates V). O(n nz (6 + nz)) where CRBA and
    the projection B^T (M B) cost O(nv^2 nz)."""
    n = m.parent.shape[0]
    nz = B.shape[1]
    Jz = np.zeros((n, 6, nz))
    Jin = np.zeros((6, nz))
    Jp = np.empty((6, nz))
    IJ = np.empty((6, nz))
    mc = np.empty((1, 6))
    for a in range(nz):
        for b in range(nz):
            out[a, b] = 0.0
    for i in range(n):
        nv, iv, par = m.nv[i], m.iv[i], m.parent[i]
        if par >= 0:
            _twist_map(m.Ad_pl_inv[i], Jz[par], w.S[i], 0, B[iv:iv + nv], Jin)
        else:
            Jin[:, :] = 0.0
        _twist_map(w.Ad_J_inv[i], Jin, w.S[i], nv, B[iv:iv + nv], Jz[i])
        if m.rigid_mass[i]:
            _add_kinetic(Jz[i], m.inertia[i], False, 1.0, IJ, out)
        if m.kind[i] == SOFT:
            mc[0, :] = m.mc[i]
            for p in range(m.npt[i]):
                if m.pw[i, p] != 0.0:
                    _twist_map(w.Ad_p_inv[i, p], Jin, w.Sp[i, p], nv, B[iv:iv + nv], Jp)
                    _add_kinetic(Jp, mc, True, m.pw[i, p], IJ, out)
    for a in range(nz):
        for b in range(a):
            out[a, b] = out[b, a]


@_jit
def crba_pass(m, w, M):
    """Joint-space mass matrix M (nv, nv) after :func:`forward_pass` (level 0)."""
    n = m.parent.shape[0]
    F = w.scratch[4]
    Dm = w.scratch[5]
    Ic = w.scratch[6]
    G = w.scratch[7]
    tmp = w.scratch[8]
    for i in range(n):
        for r in range(6):
            for c in range(6):
                w.IA[i, r, c] = m.inertia[i, r, c] if m.rigid_mass[i] else 0.0
    for i in range(n - 1, -1, -1):
        nv, iv = m.nv[i], m.iv[i]
        _joint_blocks(m.kind[i] == SOFT, nv, m.npt[i], m.pw[i], m.mc[i], w.Ad_J_inv[i], w.S[i], w.Ad_p_inv[i],
                      w.Sp[i], w.IA[i], F, Dm, Ic, w.scratch[2], w.scratch[3])
        for a in range(nv):
            for b in range(nv):
                M[iv + a, iv + b] = Dm[a, b]
        # walk up the ancestors with F (input frame of the current joint)
        child = i
        j = m.parent[i]
        while j >= 0 and nv > 0:
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for k in range(6):
                        acc += m.Ad_pl_inv[child, k, r] * F[k, a]
                    G[r, a] = acc            # at j's output frame
            for b in range(m.nv[j]):
                for a in range(nv):
                    acc = 0.0
                    for k in range(6):
                        acc += w.S[j, k, b] * G[k, a]
                    M[m.iv[j] + b, iv + a] = acc
                    M[iv + a, m.iv[j] + b] = acc
            for r in range(6):
                for a in range(nv):
                    acc = 0.0
                    for k in range(6):
                        acc += w.Ad_J_inv[j, k, r] * G[k, a]
                    F[r, a] = acc            # at j's input frame
            child = j
            j = m.parent[j]
        par = m.parent[i]
        if par >= 0:
            _congruence_add(m.Ad_pl_inv[i], Ic, w.IA[par], tmp)


@_jit_inner
def spd_inverse(A, n, out):
    """Inverse of a small symmetric positive definite A[:n, :n] (Cholesky:
    a joint's block in the ABA, a basis's Newton matrix) into out[:n, :n];
    returns False if A is not positive definite (or not finite)."""
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    # inverse of L (lower), then out = L^-T L^-1
    Li = np.zeros((n, n))
    for j in range(n):
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * Li[k, j]
            Li[i, j] = s / L[i, i]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(max(i, j), n):
                s += Li[k, i] * Li[k, j]
            out[i, j] = s
    return True


@_jit_inline
def aba_factor(m, w, cD, cK):
    """Articulated-body factorisation of M + cD D + cK K after
    :func:`forward_pass` (level 0). Returns False if a joint block is not
    positive definite."""
    n = m.parent.shape[0]
    Dm = w.scratch[5]
    Ic = w.scratch[6]
    tmp = w.scratch[8]
    UD = w.scratch[9]
    for i in range(n):
        for r in range(6):
            for c in range(6):
                w.IA[i, r, c] = m.inertia[i, r, c] if m.rigid_mass[i] else 0.0
    for i in range(n - 1, -1, -1):
        nv = m.nv[i]
        U = w.U[i]
        for r in range(6):
            for c in range(6):
                w.Sf[i, r, c] = w.S[i, r, c]
                w.Xf[i, r, c] = w.Ad_J_inv[i, r, c]
        _joint_blocks(m.kind[i] == SOFT, nv, m.npt[i], m.pw[i], m.mc[i], w.Ad_J_inv[i], w.S[i], w.Ad_p_inv[i],
                      w.Sp[i], w.IA[i], U, Dm, Ic, w.scratch[2], w.scratch[3])
        if nv > 0:
            for a in range(nv):
                for b in range(nv):
                    Dm[a, b] += cD * m.Db[i, a, b] + cK * m.Kb[i, a, b]
            if not spd_inverse(Dm, nv, w.Dinv[i]):
                return False
            # Ic -= U Dinv U^T (symmetric)
            for r in range(6):
                for b in range(nv):
                    acc = 0.0
                    for k in range(nv):
                        acc += U[r, k] * w.Dinv[i, k, b]
                    UD[r, b] = acc
            for r in range(6):
                for c in range(r, 6):
                    acc = 0.0
                    for k in range(nv):
                        acc += UD[r, k] * U[c, k]
                    Ic[r, c] -= acc
                    if c != r:
                        Ic[c, r] -= acc
        par = m.parent[i]
        if par >= 0:
            _congruence_add(m.Ad_pl_inv[i], Ic, w.IA[par], tmp)
    return True


@_jit_inline
def aba_solve(m, w, rhs, x):
    """x = (M + cD D + cK K)^-1 rhs with the factors of :func:`aba_factor`
    (which keeps its own copies of S and Ad(Jq^-1): later passes at other
    configurations do not disturb it)."""
    n = m.parent.shape[0]
    t1 = w.vscratch[12]
    t2 = w.vscratch[13]
    for i in range(n):
        for b in range(6):
            w.pA[i, b] = 0.0
    for i in range(n - 1, -1, -1):
        nv, iv = m.nv[i], m.iv[i]
        for a in range(nv):
            acc = rhs[iv + a]
            for r in range(6):
                acc -= w.Sf[i, r, a] * w.pA[i, r]
            w.u[i, a] = acc
        par = m.parent[i]
        if par < 0:
            continue
        _mtv6(w.Xf[i], w.pA[i], t1)
        for a in range(nv):
            acc = 0.0
            for b in range(nv):
                acc += w.Dinv[i, a, b] * w.u[i, b]
            t2[a] = acc
        for r in range(6):
            acc = t1[r]
            for a in range(nv):
                acc += w.U[i, r, a] * t2[a]
            t1[r] = acc
        _mtv6(m.Ad_pl_inv[i], t1, t2)
        for r in range(6):
            w.pA[par, r] += t2[r]
    for i in range(n):
        nv, iv = m.nv[i], m.iv[i]
        par = m.parent[i]
        if par < 0:
            for r in range(6):
                t1[r] = 0.0
        else:
            _mv6(m.Ad_pl_inv[i], w.As[par], t1)
        for a in range(nv):
            acc = w.u[i, a]
            for r in range(6):
                acc -= w.U[i, r, a] * t1[r]
            t2[a] = acc
        for a in range(nv):
            acc = 0.0
            for b in range(nv):
                acc += w.Dinv[i, a, b] * t2[b]
            x[iv + a] = acc
        _mv6(w.Xf[i], t1, t2)
        for r in range(6):
            acc = t2[r]
            for a in range(nv):
                acc += w.Sf[i, r, a] * x[iv + a]
            w.As[i, r] = acc
