"""One theta-method step of a tree with contacts, compiled: the step of
:meth:`soft_twin_core.solve.constrained.MechanismSimulator._step` for a
mechanism without multipliers (no constraint rows, no position-controlled
joints), whose Python glue cost five times the passes it drove.

Modified Newton on the step's mean velocity as there: the residual
``ID(q_t, v_t, a) + K (q_t - q_ref) + D v_t - tau_act - effort`` with the
contacts' mean forces of the step (:func:`kernels.contact.step_contacts`)
as dead point loads at the backbone points; the Newton matrix
``(M + theta h D_t + (theta h)^2 K_t) / h`` (K_t: the static tangent of the
elastic forces, loads, tendons and the contacts' ``-J^T dF/dp J``; D_t: with
``-J^T dF/dv J``) inverted at the first iterate, or the caller's from an
earlier step while the same points touch, and again when an update shrinks
less than fourfold. Dense (nv^3 a factorisation), which for the arms the
twin runs (up to ~100 dof) costs less than the glue it replaces."""

import numpy as np

from soft_twin_core.engine.forces import actuation_tangent_pass
from soft_twin_core.engine.integrators import integrate_pass, residual_after_forward
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.contact import step_contacts
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.frames import point_poses, world_point_jacobians
from soft_twin_core.engine.kernels.spatial import _jit, _jit_inline
from soft_twin_core.engine.kernels.tangent import static_tangent_pass


@_jit_inline
def _with_contact_loads(ld, pj, px, idx, F, M, c):
    """The loads ``ld`` and the c contacts' forces F and moments M as dead
    point loads at their backbone points."""
    L = ld.joint.shape[0]
    joint = np.empty(L + c, np.int64)
    x = np.empty(L + c)
    wr = np.empty((L + c, 6))
    world = np.empty(L + c, np.bool_)
    for k in range(L):
        joint[k], x[k], world[k] = ld.joint[k], ld.x[k], ld.world[k]
        for r in range(6):
            wr[k, r] = ld.wrench[k, r]
    for k in range(c):
        joint[L + k], x[L + k], world[L + k] = pj[idx[k]], px[idx[k]], True
        for r in range(3):
            wr[L + k, r] = F[k, r]
            wr[L + k, 3 + r] = M[k, r]
    return LoadArrays(joint, x, wr, world)


@_jit_inline
def _positions(m, w, q, v, a, level, pj, px, G, out):
    """The points' positions at q (a forward pass to ``level``: v and a too)."""
    passes.forward_pass(m, w, q, v, a, level)
    point_poses(m, w, pj, px, G)
    for p in range(pj.shape[0]):
        for r in range(3):
            out[p, r] = G[p, r, 3]


@_jit_inline
def _newton_inverse(m, w, act, ldc, g, coef, K, D, qt, h, theta, pj, px, idx, dF, dV, c, zeros, Ainv):
    """Ainv = ((M + th h D_t + (th h)^2 K_t) / h)^-1 at q_t; False if singular."""
    nv = K.shape[0]
    passes.forward_pass(m, w, qt, zeros, zeros, 0)
    A = np.zeros((nv, nv))
    passes.crba_pass(m, w, A)
    passes.rnea_pass(m, w, ldc, g, np.empty(nv), True)
    Kt = K.copy()
    static_tangent_pass(m, w, ldc, g, Kt)
    actuation_tangent_pass(m, w, act, coef, Kt)
    Dt = D.copy()
    if c > 0:
        G = np.empty((c, 4, 4))
        J = np.empty((c, 6, nv))
        world_point_jacobians(m, w, pj[idx[:c]], px[idx[:c]], G, J)
        for k in range(c):
            Jl = np.ascontiguousarray(J[k, :3, :])
            KJ = dF[k] @ Jl
            DJ = dV[k] @ Jl
            JT = np.ascontiguousarray(Jl.T)
            Kt -= JT @ KJ
            Dt -= JT @ DJ
    th = theta * h
    for i in range(nv):
        for j in range(nv):
            A[i, j] = (A[i, j] + th * Dt[i, j] + th * th * Kt[i, j]) / h
            if not np.isfinite(A[i, j]):
                return False
    try:
        inv = np.linalg.inv(A)
    except Exception:           # singular to machine precision
        return False
    ok = True
    for i in range(nv):
        for j in range(nv):
            if not np.isfinite(inv[i, j]):
                ok = False
            Ainv[i, j] = inv[i, j]
    return ok


@_jit
def contact_step(m, w, act, ld, g, coef, effort, K, D, q_ref, elastic_noise, q0, v0, h, theta, tol, floor,
                 max_it, pj, px, prad, pmod, pw, obs, obs0, moving, Ainv, key, reuse,
                 v1, q1, pt, idx, ob_of, n_out, gap, F, dF, dV, M, slip):
    """One step from (q0, v0) (guess v1, updated in place; q1 receives the
    end configuration, pt the contact points' positions at the theta point
    of the last iterate). Contact points (joint pj, abscissa px, radius,
    modulus, weight); obstacles ``obs`` (``obs0`` at the step's start for
    the ``moving`` ones). ``Ainv``: the inverse Newton matrix, reused at the
    first iterate if ``reuse`` and the contacts there are ``key``
    (``key[0]`` of them, then obstacle * P + point each), else made anew
    (key updated). Returns (iterations, status, contacts, factorised):
    status 0 converged, 1 not in max_it, 3 non-finite, 4 singular; the
    contacts (those of the last iterate) in the output arrays."""
    nv, nq, P = v0.shape[0], q0.shape[0], pj.shape[0]
    zeros = np.zeros(nv)
    G = np.empty((P, 4, 4))
    J = np.empty((P, 6, nv))
    passes.forward_pass(m, w, q0, zeros, zeros, 0)
    world_point_jacobians(m, w, pj, px, G, J)
    p0 = np.empty((P, 3))
    pv0 = np.zeros((P, 3))
    for p in range(P):
        for r in range(3):
            p0[p, r] = G[p, r, 3]
            for k in range(nv):
                pv0[p, r] += J[p, r, k] * v0[k]
    p1 = np.empty((P, 3))
    qt = np.empty(nq)
    vt = np.empty(nv)
    acc = np.empty(nv)
    R = np.empty(nv)
    th = theta * h
    refactor, factorised = True, 0
    prev, first, Rs, noise = np.inf, 0.0, 1e-300, 0.0
    c = 0
    for it in range(1, max_it + 1):
        for k in range(nv):
            vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
            acc[k] = (v1[k] - v0[k]) / h
        integrate_pass(m, q0, vt, th, qt)
        integrate_pass(m, q0, vt, h, q1)
        _positions(m, w, q1, zeros, zeros, 0, pj, px, G, p1)
        _positions(m, w, qt, vt, acc, 2, pj, px, G, pt)          # (the residual's forward pass too)
        c = step_contacts(prad, pmod, pw, obs, obs0, moving, p0, p1, pt, h, theta, pv0, True,
                          idx, ob_of, n_out, gap, F, dF, dV, M, slip)
        ldc = _with_contact_loads(ld, pj, px, idx, F, M, c)
        if refactor:
            same = reuse and it == 1 and key[0] == c
            if same:
                for k in range(c):
                    if key[1 + k] != ob_of[k] * P + idx[k]:
                        same = False
            if not same:
                if not _newton_inverse(m, w, act, ldc, g, coef, K, D, qt, h, theta, pj, px, idx, dF, dV, c,
                                       zeros, Ainv):
                    return it, 4, c, factorised
                passes.forward_pass(m, w, qt, vt, acc, 2)             # (it posed the workspace at rest)
                factorised += 1
                key[0] = c
                for k in range(c):
                    key[1 + k] = ob_of[k] * P + idx[k]
            refactor = False
        residual_after_forward(m, w, act, ldc, g, coef, effort, qt, vt, R, False)
        nR = 0.0
        for k in range(nv):
            if not np.isfinite(R[k]):
                return it, 3, c, factorised
            nR = max(nR, abs(R[k]))
        if it == 1:
            Rs = max(nR, 1e-300)
            if elastic_noise:
                # round-off of the forces: the elastic ones (a robot resting on obstacles steps from an
                # equilibrium whose residual is this noise)
                for i in range(nv):
                    s = 0.0
                    for j in range(nv):
                        s += K[i, j] * (qt[j] - q_ref[j])
                    noise = max(noise, 1e-9 * abs(s))
            if nR <= noise:
                break
        elif nR <= max(tol * Rs, noise):
            break
        ndv, vmax = 0.0, 0.0
        for i in range(nv):
            s = 0.0
            for j in range(nv):
                s -= Ainv[i, j] * R[j]
            v1[i] += s
            ndv = max(ndv, abs(s))
            vmax = max(vmax, abs(v1[i]), abs(v0[i]))
        if not np.isfinite(ndv):
            return it, 3, c, factorised
        if it == 1:
            first = ndv
        vs = max(vmax, first, 1e-300)
        if ndv <= max(tol * vs, floor) or (it > 2 and ndv <= 1e-6 * vs and ndv >= 0.5 * prev):
            break
        refactor = it > 1 and ndv > 0.25 * prev
        prev = ndv
    else:
        return max_it, 1, c, factorised
    for k in range(nv):
        vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
    integrate_pass(m, q0, vt, h, q1)
    return it, 0, c, factorised
