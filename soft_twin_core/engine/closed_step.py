"""One theta-method step of a robot with constraint rows (closed chains,
frames clamped, pinned or guided to the world), compiled: the step of
:meth:`soft_twin_core.solve.constrained.MechanismSimulator._step` without
contacts, whose Python glue cost several times the passes it drove.

Modified Newton on the step's mean velocity v and the constraints'
multipliers lambda, on the KKT system of the step

    [ A          -G_t^T ] [dv ]   [ -R    ]
    [ th h G_1    0     ] [dl ] = [ -Phi_1 ]

(A: :func:`step_matrix.invert_step_matrix`'s Newton matrix at the theta
point q_t; G_t, G_1: the constraint rows' Jacobians at q_t and at the end
q_1; R: the residual with the reactions ``G^T lambda`` as dead wrenches at
the constraints' frames; Phi_1: the constraint values at the end of the
step, so that every constraint holds there to ``ctol``: no drift). It is
solved by the Schur complement on the constraint rows (Featherstone,
*Rigid Body Dynamics Algorithms*, 2008, sec. 8.1; Pinocchio's
``constraintDynamics``): with Z = A^-1 G_t^T,

    S dl = -Phi_1 - th h G_1 A^-1 (-R),   S = th h G_1 Z,   dv = -A^-1 R + Z dl,

an nv^3 inverse and an m x m one (m: the independent constraint rows, the
caller's ``rows``: a planar loop closed by a 3-D pin has redundant ones,
whose multipliers stay). A, Z and S^-1 are made at the first iterate and
again when an update shrinks less than fourfold, as the Python step
factorises its KKT matrix. Position-controlled joints are eliminated as
in :mod:`contact_step` (their velocities prescribed, their efforts their
residual rows carried along the update)."""

import numba as nb
import numpy as np
from numba.experimental import structref

from soft_twin_core.engine.integrators import integrate_pass, residual_after_forward
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import ArraysRef, ArraysType, LoadArrays, declare
from soft_twin_core.engine.kernels.frames import world_point_jacobians
from soft_twin_core.engine.kernels.spatial import FALSE, _jit, _jit_inner
from soft_twin_core.engine.kernels.tip_error import _log_so3
from soft_twin_core.engine.step_matrix import (elastic_noise, forces_balanced, free_newton_update,
                                                invert_step_matrix, onto_basis, residual_sizes, step_tangents,
                                                theta_point, update_converged)

CLAMPED = 1        # a constraint kind the kernel tells apart: [dp; log(R_a R_b^T)]; others C[:, :3] dp

# The arrays a robot's steps keep from one step to the next, passed as one structref: typed at a call in
# well under 1 us, where as 19 arguments they cost about 3 us of the four-bar's 20 us step
CLOSED_FIELDS = (
    "K", "D", "q_ref",                                   # stiffness, damping (nv, nv); the elastic forces' q
    "cj", "cx", "ckind", "crows", "csize", "ctarget",    # the constraints (constraint_values)
    "rows",                                              # the independent constraint rows
    "fixed",                                             # (nv,) bool: the prescribed velocities
    "Ainv", "Afix", "Z", "Sinv", "G1f", "Gtf",           # the factors, kept for the next step
    "R", "phi",                                          # out: the residual, the constraint values
    "B", "P",         # a basis of the velocities (nv, nz), (B^T B)^-1 B^T: variable-strain segments; none: nz 0
)


@structref.register
class ClosedArraysType(ArraysType):
    pass


class ClosedArrays(ArraysRef):
    """The arrays of :data:`CLOSED_FIELDS` as :func:`closed_step` takes them."""
    FIELDS = CLOSED_FIELDS


declare(ClosedArrays, ClosedArraysType, CLOSED_FIELDS)


@nb.njit(cache=True)
def _make_closed_ref(K, D, q_ref, cj, cx, ckind, crows, csize, ctarget, rows, fixed, Ainv, Afix, Z, Sinv, G1f, Gtf,
                     R, phi, B, P):
    return ClosedArrays(K, D, q_ref, cj, cx, ckind, crows, csize, ctarget, rows, fixed, Ainv, Afix, Z, Sinv, G1f,
                        Gtf, R, phi, B, P)


ClosedArrays.make = _make_closed_ref


@_jit
def constraint_values(m, w, cj, cx, ckind, crows, csize, ctarget, g, J, phi, G):
    """phi (r,) and G (r, nv) of the constraints at the workspace's pose
    (after :func:`passes.forward_pass`), world axes, as
    :func:`soft_twin_core.solve.constrained.constraint_rows`: constraint k
    ties frame (cj[2k], cx[2k]) to frame (cj[2k+1], cx[2k+1]) (joint -1:
    the world, at ``ctarget[k]``); a clamp's rows are
    ``[p_a - p_b; log(R_a R_b^T)]`` with ``G = J_a - J_b``, the others'
    ``C[:, :3] (p_a - p_b)`` with ``G = C (J_a - J_b)`` (C = crows[k] over
    csize[k] rows). g (2k, 4, 4), J (2k, 6, nv): scratch."""
    world_point_jacobians(m, w, cj, cx, g, J)
    nv = G.shape[1]
    Rr = np.empty((3, 3))
    lg = np.empty(3)
    dp = np.empty(3)
    gb = np.empty((4, 4))
    r = 0
    for k in range(ckind.shape[0]):
        a, b = 2 * k, 2 * k + 1
        for i in range(4):
            for j in range(4):
                gb[i, j] = ctarget[k, i, j] if cj[b] < 0 else g[b, i, j]
        for i in range(3):
            dp[i] = g[a, i, 3] - gb[i, 3]
        if ckind[k] == CLAMPED:
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for l in range(3):
                        s += g[a, i, l] * gb[j, l]
                    Rr[i, j] = s
            _log_so3(Rr, lg)
            for i in range(3):
                phi[r + i] = dp[i]
                phi[r + 3 + i] = lg[i]
            for i in range(6):
                for c in range(nv):
                    G[r + i, c] = J[a, i, c] - J[b, i, c]
        else:
            for i in range(csize[k]):
                s = 0.0
                for l in range(3):
                    s += crows[k, i, l] * dp[l]
                phi[r + i] = s
                for c in range(nv):
                    s = 0.0
                    for l in range(6):
                        s += crows[k, i, l] * (J[a, l, c] - J[b, l, c])
                    G[r + i, c] = s
        r += csize[k]


@_jit_inner
def _with_reactions(ld, cj, cx, crows, csize, lam):
    """The loads ``ld`` and the constraints' reactions: the world wrench
    ``C^T lambda`` on frame a, its opposite on frame b (dead, at the frames'
    origins), as :func:`soft_twin_core.solve.constrained.constraint_loads`."""
    L, nc = ld.joint.shape[0], csize.shape[0]
    n = L
    for k in range(nc):
        n += 2 if cj[2 * k + 1] >= 0 else 1
    joint = np.empty(n, np.int64)
    x = np.empty(n)
    wr = np.zeros((n, 6))
    world = np.ones(n, np.bool_)
    for e in range(L):
        joint[e], x[e], world[e] = ld.joint[e], ld.x[e], ld.world[e]
        for c in range(6):
            wr[e, c] = ld.wrench[e, c]
    e, r = L, 0
    for k in range(nc):
        for i in range(csize[k]):
            for c in range(6):
                wr[e, c] += crows[k, i, c] * lam[r + i]
        joint[e], x[e] = cj[2 * k], cx[2 * k]
        if cj[2 * k + 1] >= 0:
            joint[e + 1], x[e + 1] = cj[2 * k + 1], cx[2 * k + 1]
            for c in range(6):
                wr[e + 1, c] = -wr[e, c]
            e += 1
        e += 1
        r += csize[k]
    return LoadArrays(joint, x, wr, world)


@_jit_inner
def _schur(Ainv, Gt, G1, rows, th, fixed, Z, Sinv, G1f, Gtf):
    """Z = A^-1 G_t^T, S^-1 = (th h G_1 Z)^-1 over the independent ``rows``
    (the fixed velocities' rows of Z zero); G1f, Gtf: those rows of G_1 and
    G_t, kept with them. False if S is singular or not finite."""
    nv, mr = Ainv.shape[0], rows.shape[0]
    for j in range(mr):
        for c in range(nv):
            G1f[j, c] = G1[rows[j], c]
            Gtf[j, c] = Gt[rows[j], c]
    for i in range(nv):
        for j in range(mr):
            s = 0.0
            if not fixed[i]:
                for c in range(nv):
                    if not fixed[c]:
                        s += Ainv[i, c] * Gtf[j, c]
            Z[i, j] = s
    S = np.empty((mr, mr))
    for i in range(mr):
        for j in range(mr):
            s = 0.0
            for c in range(nv):
                s += G1f[i, c] * Z[c, j]
            S[i, j] = th * s
    if mr == 0:
        return True
    try:
        inv = np.linalg.inv(S)
    except Exception:
        return False
    for i in range(mr):
        for j in range(mr):
            if not np.isfinite(inv[i, j]):
                return False
            Sinv[i, j] = inv[i, j]
    return True


@_jit_inner
def schur_update(G1f, Sinv, Z, phi, rows, th, dv, rhs, dl):
    """The KKT system's update from the free one (dv = y = -A^-1 R on
    entry): ``S dl = -Phi_1 - th h G_1 y`` (S^-1, G_1 over the independent
    ``rows``: the factorisation's), then ``dv = y + Z dl`` in place
    (``th``: theta h; rhs: scratch)."""
    nv, mr = dv.shape[0], rows.shape[0]
    for j in range(mr):
        s = 0.0
        for c in range(nv):
            s += G1f[j, c] * dv[c]
        rhs[j] = -phi[rows[j]] - th * s
    for i in range(mr):
        s = 0.0
        for j in range(mr):
            s += Sinv[i, j] * rhs[j]
        dl[i] = s
    for i in range(nv):
        s = 0.0
        for j in range(mr):
            s += Z[i, j] * dl[j]
        dv[i] += s


@_jit_inner
def factors_fit(c, nv):
    """True if the factors of :class:`ClosedArrays` ``c`` are sized for
    its independent rows and nv velocities (the kernels index them without
    bounds checks)."""
    mr = c.rows.shape[0]
    return (c.Z.shape[0] == nv and c.Z.shape[1] == mr and c.Sinv.shape[0] == mr and c.Sinv.shape[1] == mr
            and c.G1f.shape[0] == mr and c.Gtf.shape[0] == mr and c.Ainv.shape[0] == nv and c.Afix.shape[0] == nv)


@_jit_inner
def row_scratch(c, nv):
    """Scratch of a step with the constraints of ``c``: the frames' poses
    and Jacobians (gc, Jc), the rows' Jacobians at q_1 and q_t (G1, Gt),
    their values at q_t (phit), the Schur system's right side and solution
    (rhs, dl)."""
    nc2, nr, mr = c.cj.shape[0], c.phi.shape[0], c.rows.shape[0]
    return (np.empty((nc2, 4, 4)), np.empty((nc2, 6, nv)), np.empty((nr, nv)), np.empty((nr, nv)), np.empty(nr),
            np.empty(mr), np.zeros(mr))


@_jit_inner
def reaction_size(lam, R, fixed):
    """The largest multiplier or held joint's effort (its residual row):
    the next step's constraint forces' scale."""
    out = 0.0
    for k in range(lam.shape[0]):
        out = max(out, abs(lam[k]))
    for k in range(R.shape[0]):
        if fixed[k]:
            out = max(out, abs(R[k]))
    return out


@_jit
def closed_step(m, w, act, ld, g, coef, effort, c, elastic, q0, v0, h, theta, tol, floor, max_it, ctol, lam_force,
                reuse, v1, lam, q1):
    """One step from (q0, v0): v1 (the guess, the fixed velocities
    prescribed) and lam (the constraints' multipliers) updated in place, q1
    the end configuration; ``c`` (:class:`ClosedArrays`): R the residual at
    the last iterate (its fixed rows: the efforts holding those joints), phi
    the constraint values at q1. Constraints as :func:`constraint_values`;
    ``rows``: the independent ones; ``ctol``: the constraint tolerance [m, rad];
    ``lam_force``: the multipliers' size as a force [N] (a floor of the
    residual's scale). ``Ainv, Afix, Z, Sinv, G1f, Gtf``: the
    factors, reused at the first iterate if ``reuse``. Returns (iterations,
    status, factorised, lam_max): status 0 converged, 1 not in max_it, 3
    non-finite, 4 singular; lam_max the largest multiplier or held joint's
    effort at the end (the next step's ``lam_force`` over its length scale;
    0 unless converged)."""
    K, D, q_ref, fixed, rows, R, phi = c.K, c.D, c.q_ref, c.fixed, c.rows, c.R, c.phi
    cj, cx, ckind, crows, csize, ctarget = c.cj, c.cx, c.ckind, c.crows, c.csize, c.ctarget
    Ainv, Afix, Z, Sinv, G1f, Gtf = c.Ainv, c.Afix, c.Z, c.Sinv, c.G1f, c.Gtf
    nv, nq, nr, mr = v0.shape[0], q0.shape[0], phi.shape[0], rows.shape[0]
    if not factors_fit(c, nv):
        return 0, 4, 0, 0.0    # factors not of these rows (no bounds checks below)
    zeros = np.zeros(nv)
    gc, Jc, G1, Gt, phit, rhs, dl = row_scratch(c, nv)
    qt = np.empty(nq)
    vt = np.empty(nv)
    acc = np.empty(nv)
    y = np.empty(nv)
    th = theta * h
    refactor, factorised, fresh = not reuse, 0, False
    prev, first, Rs, noise = np.inf, 0.0, 1e-300, 0.0
    for it in range(1, max_it + 1):
        theta_point(m, q0, v0, v1, h, theta, vt, acc, qt, q1)
        passes.forward_pass(m, w, q1, zeros, zeros, passes.POSES)
        constraint_values(m, w, cj, cx, ckind, crows, csize, ctarget, gc, Jc, phi, G1)
        ldc = _with_reactions(ld, cj, cx, crows, csize, lam)
        if refactor:
            A, Kt, Dt = step_tangents(m, w, act, ldc, g, coef, K, D, qt, zeros)
            constraint_values(m, w, cj, cx, ckind, crows, csize, ctarget, gc, Jc, phit, Gt)   # (posed at q_t)
            if not invert_step_matrix(A, Kt, Dt, h, theta, fixed, Ainv, Afix, c.B):
                return it, 4, factorised, 0.0
            if not _schur(Ainv, Gt, G1, rows, th, fixed, Z, Sinv, G1f, Gtf):
                return it, 4, factorised, 0.0
            factorised += 1
            refactor, fresh = False, True
        passes.forward_pass(m, w, qt, vt, acc, passes.ACCELERATIONS)
        residual_after_forward(m, w, act, ldc, g, coef, effort, qt, vt, R, FALSE)
        nphi = 0.0
        for k in range(nv):
            if not np.isfinite(R[k]):
                return it, 3, factorised, 0.0
        nR = residual_sizes(R, fixed, c.B)[0]
        for k in range(nr):
            if not np.isfinite(phi[k]):
                return it, 3, factorised, 0.0
            nphi = max(nphi, abs(phi[k]))
        phi_ok = nphi <= ctol
        if it == 1:
            Rs = max(nR, lam_force, 1e-300)
            if elastic:
                noise = elastic_noise(K, qt, q_ref)
        if phi_ok and forces_balanced(nR, Rs, tol, noise):
            break              # balanced: forces to tol of their scale, constraints held
        # dv = y + Z dl, y = -A^-1 R;  S dl = -Phi_1 - th h G_1 y (the factorisation's G_1)
        free_newton_update(Ainv, R, fixed, y)
        schur_update(G1f, Sinv, Z, phi, rows, th, y, rhs, dl)          # (y now dv)
        ndv, vmax = 0.0, 0.0
        for i in range(nv):
            v1[i] += y[i]
            ndv = max(ndv, abs(y[i]))
            vmax = max(vmax, abs(v1[i]), abs(v0[i]))
        for i in range(nv):
            if fixed[i]:               # the held joints' efforts, linearised along the update
                s = 0.0
                for j in range(nv):
                    s += Afix[i, j] * y[j]
                for j in range(mr):
                    s -= Gtf[j, i] * dl[j]
                R[i] += s
        for j in range(mr):
            lam[rows[j]] += dl[j]
        if not np.isfinite(ndv):
            return it, 3, factorised, 0.0
        if it == 1:
            first = ndv
        vs = max(vmax, first, 1e-300)
        # converged, or stalled at round-off (with this step's own factors: an earlier step's contract
        # linearly, and stop short of the solution by more than the update)
        if phi_ok and update_converged(ndv, vs, tol, floor, prev, fresh and it > 2):
            break
        refactor = it > 1 and ndv > 0.25 * prev
        prev = ndv
    else:
        return max_it, 1, factorised, 0.0
    onto_basis(c.B, c.P, v1)
    for k in range(nv):
        vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
    integrate_pass(m, q0, vt, h, q1)
    return it, 0, factorised, reaction_size(lam, R, fixed)
