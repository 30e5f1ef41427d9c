"""One theta-method step of a tree with contacts, compiled: the step of
:meth:`soft_twin_core.solve.constrained.MechanismSimulator._step` for a
mechanism without constraint rows (its position-controlled joints
eliminated: their velocities prescribed), whose Python glue cost five times
the passes it drove.

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

from soft_twin_core.engine.closed_step import (_schur, _with_reactions, constraint_values, factors_fit,
                                               reaction_size, row_scratch, schur_update)
from soft_twin_core.engine.integrators import integrate_pass, residual_after_forward
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.contact import pose_obstacles, step_contacts, transition_fraction
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.frames import (body_point_twists, frame_spins, offset_point_positions,
                                                  relative_point_jacobians, spatial_jacobian)
from soft_twin_core.engine.kernels.spatial import FALSE, _jit, _jit_inline, _jit_inner
from soft_twin_core.engine.step_matrix import (elastic_noise, forces_balanced, free_newton_update,
                                                invert_step_matrix, onto_basis, residual_sizes, step_tangents,
                                                theta_point, update_converged)


@_jit_inline
def _with_contact_loads(w, ld, pj, px, G, pt, idx, ob_of, obody, F, M, c, arm, barm):
    """The loads ``ld`` and the c contacts' forces F and moments M as dead
    loads: on each point's frame (its pose G, after the forward pass at
    the theta point pt), and their reactions -F, -M on the bodies that
    carry the touched obstacles (``obody``: -1 for the world's), about
    those frames' origins; arm and barm receive the lever arms [m] from the
    frames' origins to the points."""
    L = ld.joint.shape[0]
    nb = 0
    for k in range(c):
        if obody[ob_of[k]] >= 0:
            nb += 1
    joint = np.empty(L + c + nb, np.int64)
    x = np.empty(L + c + nb)
    wr = np.empty((L + c + nb, 6))
    world = np.empty(L + c + nb, np.bool_)
    for k in range(L):
        joint[k], x[k], world[k] = ld.joint[k], ld.x[k], ld.world[k]
        for r in range(6):
            wr[k, r] = ld.wrench[k, r]
    e = L + c
    for k in range(c):
        i = idx[k]
        joint[L + k], x[L + k], world[L + k] = pj[i], px[i], True
        for r in range(3):
            arm[k, r] = pt[i, r] - G[i, r, 3]
        b = obody[ob_of[k]]
        for r in range(3):
            barm[k, r] = pt[i, r] - w.g_out[b, r, 3] if b >= 0 else 0.0
        for r in range(3):
            r1, r2 = (r + 1) % 3, (r + 2) % 3
            wr[L + k, r] = F[k, r]
            wr[L + k, 3 + r] = M[k, r] + arm[k, r1] * F[k, r2] - arm[k, r2] * F[k, r1]
        if b >= 0:
            joint[e], x[e], world[e] = b, -1.0, True
            for r in range(3):
                r1, r2 = (r + 1) % 3, (r + 2) % 3
                wr[e, r] = -F[k, r]
                wr[e, 3 + r] = -M[k, r] - (barm[k, r1] * F[k, r2] - barm[k, r2] * F[k, r1])
            e += 1
    return LoadArrays(joint, x, wr, world)


@_jit_inline
def _positions(m, w, q, v, a, level, pj, px, poff, G, out):
    """The points' positions at q (a forward pass to ``level``: v and a too)."""
    passes.forward_pass(m, w, q, v, a, level)
    offset_point_positions(m, w, pj, px, poff, G, out)


@_jit_inline
def _transition_alpha(m, w, pj, px, prad, pt, idx, ob_of, obs, n_out, slip, dv, c):
    """The fraction of the update dv that no frictional contact's slip
    (the surface point's) jumps across its stiction zone with
    (:func:`kernels.contact.transition_fraction`; the workspace posed at
    the theta point)."""
    nv = dv.shape[0]
    Js = np.empty((3, nv))
    alpha = 1.0
    d = np.empty(3)
    for k in range(c):
        o = ob_of[k]
        if obs.friction[o] <= 0.0:
            continue
        i = idx[k]
        _surface_jacobian(m, w, pj[i], px[i], prad[i], obs.body[o], pt[i], n_out[k], Js)
        for r in range(3):
            acc = 0.0
            for j in range(nv):
                acc += Js[r, j] * dv[j]
            d[r] = acc
        dn = d[0] * n_out[k, 0] + d[1] * n_out[k, 1] + d[2] * n_out[k, 2]
        for r in range(3):
            d[r] -= dn * n_out[k, r]
        alpha = min(alpha, transition_fraction(slip[k], d, obs.stiction[o]))
    return alpha


@_jit_inner
def _angular_jacobian(m, w, j, x, body, out):
    """out (3, nv): the Jacobian of the angular velocity of frame (j, x)
    relative to joint ``body``'s output frame (-1: the world), world axes."""
    g = np.empty((4, 4))
    Js = np.empty((6, out.shape[1]))
    spatial_jacobian(m, w, j, x, g, Js)
    for r in range(3):
        for c in range(out.shape[1]):
            out[r, c] = Js[3 + r, c]
    if body >= 0:
        spatial_jacobian(m, w, body, -1.0, g, Js)
        for r in range(3):
            for c in range(out.shape[1]):
                out[r, c] -= Js[3 + r, c]


@_jit_inner
def _surface_jacobian(m, w, j, x, r, body, p, n, out):
    """out (3, nv): the Jacobian of the velocity of the contact surface's
    point, ``-r n`` from the point p of frame (j, x), relative to joint
    ``body``'s output frame: ``J_p + r [n x] J_omega``."""
    nv = out.shape[1]
    Jp = np.empty((1, 3, nv))
    Jb = np.empty((1, 3, nv))
    pp = np.empty((1, 3))
    for q in range(3):
        pp[0, q] = p[q]
    relative_point_jacobians(m, w, np.array([j]), np.array([x]), np.array([body]), pp, Jp, Jb)
    Jw = np.empty((3, nv))
    _angular_jacobian(m, w, j, x, body, Jw)
    for c in range(nv):
        out[0, c] = Jp[0, 0, c] + r * (n[1] * Jw[2, c] - n[2] * Jw[1, c])
        out[1, c] = Jp[0, 1, c] + r * (n[2] * Jw[0, c] - n[0] * Jw[2, c])
        out[2, c] = Jp[0, 2, c] + r * (n[0] * Jw[1, c] - n[1] * Jw[0, c])


@_jit_inner
def _spin_jacobian(m, w, j, x, body, n, out):
    """out (nv,): the Jacobian of the spin about n of frame (j, x) relative
    to joint ``body``'s output frame (-1: the world)."""
    Jw = np.empty((3, out.shape[0]))
    _angular_jacobian(m, w, j, x, body, Jw)
    for c in range(out.shape[0]):
        out[c] = n[0] * Jw[0, c] + n[1] * Jw[1, c] + n[2] * Jw[2, c]


@_jit_inline
def _spin_alpha(m, w, pj, px, idx, ob_of, obs, n_out, spin, dv, c):
    """The fraction of the update dv that no spinning contact's spin jumps
    across its stiction zone with (as the slip of the patch's rim, mu_t
    spin; the workspace posed at the theta point)."""
    alpha = 1.0
    Js = np.empty(dv.shape[0])
    v = np.zeros(3)
    d = np.zeros(3)
    for k in range(c):
        o = ob_of[k]
        mu_t = obs.torsion[o]
        if mu_t <= 0.0:
            continue
        _spin_jacobian(m, w, pj[idx[k]], px[idx[k]], obs.body[o], n_out[k], Js)
        ds = 0.0
        for j in range(dv.shape[0]):
            ds += Js[j] * dv[j]
        v[0], d[0] = mu_t * spin[k], mu_t * ds
        alpha = min(alpha, transition_fraction(v, d, obs.stiction[o]))
    return alpha


@_jit_inline
def _cross_matrix(f):
    """[f x] (3, 3)."""
    X = np.zeros((3, 3))
    X[0, 1], X[0, 2], X[1, 2] = -f[2], f[1], -f[0]
    X[1, 0], X[2, 0], X[2, 1] = f[2], -f[1], f[0]
    return X


@_jit_inner
def _left3(A, J, out):
    """out (3, n) = A (3, 3) J (3, n)."""
    for r in range(3):
        for j in range(J.shape[1]):
            out[r, j] = A[r, 0] * J[0, j] + A[r, 1] * J[1, j] + A[r, 2] * J[2, j]


@_jit_inner
def _subtract_product(T, L, Y):
    """T (n, n) -= L^T Y, L and Y (3, n): a point's stiffness or damping
    brought to the coordinates (loops: no BLAS call compiled into the step)."""
    for i in range(T.shape[0]):
        l0, l1, l2 = L[0, i], L[1, i], L[2, i]
        for j in range(T.shape[1]):
            T[i, j] -= l0 * Y[0, j] + l1 * Y[1, j] + l2 * Y[2, j]


@_jit_inline
def _newton_inverse(m, w, act, ldc, g, coef, arr, qt, h, theta, pj, px, prad, pt, idx, ob_of, obody, F, dF, dV,
                    dFf, dVf, c, zeros, n_out, dW):
    """Ainv = ((M + th h D_t + (th h)^2 K_t) / h)^-1 at q_t, the rows and
    columns of the ``fixed`` (prescribed) velocities replaced by the
    identity's (their rows of the full matrix into Afix; ``arr``'s, a
    :class:`closed_step.ClosedArrays`, as K, D and the basis B); False if
    singular. A contact's stiffness acts through the velocity of its point
    relative to the body carrying the obstacle (the world's: at rest), and
    its force turns with that body: ``dF = dF/dp J_rel dq - [F x] J_w dq``;
    its friction's through the contact surface's point's Jacobian J_s
    (:func:`_surface_jacobian`): ``J_s^T dFf J`` and ``J_s^T dVf J_s``;
    its spin friction's damping through the spin's Jacobian
    (:meth:`soft_twin_core.solve.contact.MemberContact.add_stiffness`).
    With a basis of the velocities B, its Galerkin inverse
    (:func:`step_matrix.invert_step_matrix`)."""
    nv = arr.K.shape[0]
    A, Kt, Dt = step_tangents(m, w, act, ldc, g, coef, arr.K, arr.D, qt, zeros)
    if c > 0:
        J = np.empty((c, 3, nv))
        Jw = np.empty((c, 3, nv))
        body = np.empty(c, np.int64)
        for k in range(c):
            body[k] = obody[ob_of[k]]
        relative_point_jacobians(m, w, pj[idx[:c]], px[idx[:c]], body, pt[idx[:c]], J, Jw)
        KJ = np.empty((3, nv))
        DJ = np.empty((3, nv))
        XJ = np.empty((3, nv))
        for k in range(c):
            Jl = J[k]
            _left3(dF[k], Jl, KJ)
            _left3(dV[k], Jl, DJ)
            if body[k] >= 0:            # a body's shape: the force turns with it, the reaction's lever arm
                X = _cross_matrix(F[k])     # (solve.contact.MemberContact.add_stiffness)
                _left3(X, Jw[k], XJ)
                for r in range(3):
                    for j in range(nv):
                        KJ[r, j] -= XJ[r, j]
                _left3(X, Jl, XJ)
                _subtract_product(Kt, Jw[k], XJ)
            _subtract_product(Kt, Jl, KJ)
            _subtract_product(Dt, Jl, DJ)
        Jsf = np.empty((3, nv))
        for k in range(c):
            fr = False
            for r in range(3):
                for q in range(3):
                    if dFf[k, r, q] != 0.0 or dVf[k, r, q] != 0.0:
                        fr = True
            if fr:
                i = idx[k]
                _surface_jacobian(m, w, pj[i], px[i], prad[i], body[k], pt[i], n_out[k], Jsf)
                _left3(dFf[k], J[k], KJ)
                _subtract_product(Kt, Jsf, KJ)
                _left3(dVf[k], Jsf, DJ)
                _subtract_product(Dt, Jsf, DJ)
        Js = np.empty(nv)
        for k in range(c):
            if dW[k] != 0.0:
                _spin_jacobian(m, w, pj[idx[k]], px[idx[k]], body[k], n_out[k], Js)
                for i in range(nv):
                    for j in range(nv):
                        Dt[i, j] -= dW[k] * Js[i] * Js[j]
    return invert_step_matrix(A, Kt, Dt, h, theta, arr.fixed, arr.Ainv, arr.Afix, arr.B)


@_jit
def contact_step(m, w, act, ld, g, coef, effort, arr, elastic, q0, v0, h, theta, tol, floor, max_it, ctol,
                 lam_force, lam, pj, px, poff, prad, pmod, pw, allowed, obs, obs0, P0, P1, Pt, moving, key, reuse, v1,
                 q1, pt, idx, ob_of, n_out, gap, F, dF, dV, dFf, dVf, M, slip, arm, barm, spin, dW):
    """One step from (q0, v0) (guess v1, updated in place; q1 receives the
    end configuration, pt the contact points' positions at the theta point
    of the last iterate; ``arr``, a :class:`closed_step.ClosedArrays`: R
    the residual there, phi the constraint values at q1). Constraint rows
    (closed chains, a prescribed base's clamp: ``arr``'s constraints, its
    ``rows`` the independent ones; none for an open tree) as in
    :func:`closed_step.closed_step`: the multipliers ``lam`` updated in
    place, the update by the Schur complement on the rows, the constraints
    held to ``ctol`` at q1; ``lam_force``: the multipliers' size as a force.
    The velocities ``fixed``
    (a mask) are prescribed: they keep v1's values, and their residual
    rows, left out of the iteration, are the efforts that hold them
    (position-controlled joints eliminated: the multipliers of
    ``q_j = q_cmd`` are these rows, carried along the last update by the
    Newton matrix's rows ``Afix`` as the KKT step's multiplier update
    does). Contact points (joint pj, abscissa px, offset
    poff, radius, modulus, weight), the ``allowed`` (P, O) pairs; obstacles
    ``obs`` (``obs0`` at the step's start for the ``moving`` ones; those
    the bodies carry, in their frames), posed into P0, P1, Pt
    (:func:`kernels.contact.posable` copies) at the step's start, end and
    theta point. ``Ainv``: the inverse Newton matrix, reused at the
    first iterate if ``reuse`` and the contacts there are ``key``
    (``key[0]`` of them, then obstacle * P + point each), else made anew
    (key updated). Returns (iterations, status, contacts, factorised,
    lam_max): status 0 converged, 1 not in max_it, 3 non-finite, 4
    singular; the contacts (those of the last iterate) in the output
    arrays; lam_max as :func:`closed_step.closed_step`'s."""
    K, q_ref, fixed, Ainv, Afix, R, phi = arr.K, arr.q_ref, arr.fixed, arr.Ainv, arr.Afix, arr.R, arr.phi
    cj, cx, ckind, crows, csize, ctarget = arr.cj, arr.cx, arr.ckind, arr.crows, arr.csize, arr.ctarget
    rows, Z, Sinv, G1f, Gtf = arr.rows, arr.Z, arr.Sinv, arr.G1f, arr.Gtf
    nv, nq, P = v0.shape[0], q0.shape[0], pj.shape[0]
    nr, mr = phi.shape[0], rows.shape[0]
    if not factors_fit(arr, nv):
        return 0, 4, 0, 0, 0.0   # factors not of these rows (no bounds checks below)
    gc, Jc, G1, Gt, phit, rhs, dl = row_scratch(arr, nv)
    th = theta * h
    zeros = np.zeros(nv)
    G = np.empty((P, 4, 4))
    p0 = np.empty((P, 3))
    touching = P > 0 and obs.kind.shape[0] > 0       # else: only the eliminated joints (no positions needed)
    if touching:
        _positions(m, w, q0, zeros, zeros, passes.POSES, pj, px, poff, G, p0)
        pose_obstacles(w, obs0, P0)
    ovel0 = np.full((obs.kind.shape[0], 6), np.nan)
    if moving.any():
        tw = np.empty((obs.kind.shape[0], 6))
        body_point_twists(m, w, obs.body, P0.a, v0, tw)
        for o in range(obs.kind.shape[0]):
            if obs.body[o] >= 0:
                ovel0[o, :] = tw[o, :]
    spins = False                # the points' frames' rotations: torsional friction, friction (rolling)
    for o in range(obs.kind.shape[0]):
        if obs.torsion[o] > 0.0 or obs.friction[o] > 0.0:
            spins = True
    R0 = np.empty((P, 3, 3))
    R1 = np.empty((P, 3, 3))
    w0 = np.zeros((P, 3))
    if spins:                    # the points' frames' rotations and angular velocities at the start
        frame_spins(m, w, pj, px, v0, R0, w0, np.empty((P, 3, nv)))
    J = np.empty((P, 3, nv))
    relative_point_jacobians(m, w, pj, px, np.full(P, -1, np.int64), p0, J, np.empty((P, 3, nv)))
    pv0 = np.zeros((P, 3))
    # the start velocities are given; a run-time bool, not the constant True, so that this call
    # and the Python step's (engine.contact.step_contact_forces) share one compiled specialisation
    given = pv0.shape[0] == P
    for p in range(P):
        for r in range(3):
            for k in range(nv):
                pv0[p, r] += J[p, r, k] * v0[k]
    p1 = np.empty((P, 3))
    qt = np.empty(nq)
    vt = np.empty(nv)
    acc = np.empty(nv)
    refactor, factorised = True, 0
    prev, first, Rs, noise = np.inf, 0.0, 1e-300, 0.0
    dv = np.zeros(nv)
    lastR, halvings = np.inf, 0
    c = 0
    for it in range(1, max_it + 1):
        theta_point(m, q0, v0, v1, h, theta, vt, acc, qt, q1)
        if nr > 0:              # the constraints' Jacobian at q1: the subspaces too
            passes.forward_pass(m, w, q1, zeros, zeros, passes.POSES)
        elif touching:          # the end positions: poses alone (the pass at the theta point follows)
            passes.poses_pass(m, w, q1)
        if touching:
            offset_point_positions(m, w, pj, px, poff, G, p1)
        if spins:
            for p in range(P):
                for r in range(3):
                    for s in range(3):
                        R1[p, r, s] = G[p, r, s]
        if touching:
            pose_obstacles(w, obs, P1)
        if nr > 0:
            constraint_values(m, w, cj, cx, ckind, crows, csize, ctarget, gc, Jc, phi, G1)
        _positions(m, w, qt, vt, acc, passes.ACCELERATIONS, pj, px, poff, G, pt)  # (the residual's forward pass too)
        if touching:
            pose_obstacles(w, obs, Pt)
        c = step_contacts(prad, pmod, pw, allowed, P1, P0, Pt, moving, ovel0, p0, p1, pt, h, theta, pv0, given,
                          R0, R1, w0, idx, ob_of, n_out, gap, F, dF, dV, dFf, dVf, M, slip, spin, dW)
        ldr = _with_reactions(ld, cj, cx, crows, csize, lam) if nr > 0 else ld
        ldc = _with_contact_loads(w, ldr, pj, px, G, pt, idx, ob_of, obs.body, F, M, c, arm, barm)
        if refactor:
            same = reuse and it == 1 and key[0] == c
            if same:
                for k in range(c):
                    if key[1 + k] != ob_of[k] * P + idx[k]:
                        same = False
            if not same:
                if not _newton_inverse(m, w, act, ldc, g, coef, arr, qt, h, theta, pj, px, prad, pt, idx, ob_of,
                                       obs.body, F, dF, dV, dFf, dVf, c, zeros, n_out, dW):
                    return it, 4, c, factorised, 0.0
                if nr > 0:      # (the workspace posed at q_t)
                    constraint_values(m, w, cj, cx, ckind, crows, csize, ctarget, gc, Jc, phit, Gt)
                    if not _schur(Ainv, Gt, G1, rows, th, fixed, Z, Sinv, G1f, Gtf):
                        return it, 4, c, factorised, 0.0
                passes.forward_pass(m, w, qt, vt, acc, passes.ACCELERATIONS)  # (it posed the workspace at rest)
                factorised += 1
                key[0] = c
                for k in range(c):
                    key[1 + k] = ob_of[k] * P + idx[k]
            refactor = False
        residual_after_forward(m, w, act, ldc, g, coef, effort, qt, vt, R, FALSE)
        nphi = 0.0
        for k in range(nv):
            if not np.isfinite(R[k]):
                return it, 3, c, factorised, 0.0
        nR, held = residual_sizes(R, fixed, arr.B)
        for k in range(nr):
            if not np.isfinite(phi[k]):
                return it, 3, c, factorised, 0.0
            nphi = max(nphi, abs(phi[k]))
        phi_ok = nphi <= ctol
        if it == 1:
            # the forces' scale: the residual's, the efforts holding the prescribed joints and the
            # multipliers (the Python step's multipliers' rows); at rest, the residual alone is round-off
            Rs = max(nR, held, lam_force, 1e-300)
            if elastic:       # round-off of the elastic forces (a robot resting on obstacles)
                noise = elastic_noise(K, qt, q_ref)
        if phi_ok and forces_balanced(nR, Rs, tol, noise):
            break
        if it > 1 and nR > lastR and halvings < 4 and (nr == 0 or c > 0):
            # the residual grew: back along the last update (solve.constrained.MechanismSimulator._step;
            # with constraint rows only among contacts: a constraint's correction may rightly raise it)
            for i in range(nv):
                dv[i] *= 0.5
                v1[i] -= dv[i]
            for j in range(mr):
                dl[j] *= 0.5
                lam[rows[j]] -= dl[j]
            halvings += 1
            continue
        free_newton_update(Ainv, R, fixed, dv)
        if mr > 0:              # the constraint rows' part: dv = y + Z dl
            schur_update(G1f, Sinv, Z, phi, rows, th, dv, rhs, dl)
        alpha = _transition_alpha(m, w, pj, px, prad, pt, idx, ob_of, obs, n_out, slip, dv, c)
        if spins:
            alpha = min(alpha, _spin_alpha(m, w, pj, px, idx, ob_of, obs, n_out, spin, dv, c))
        ndv, vmax = 0.0, 0.0
        for i in range(nv):
            dv[i] *= alpha
            v1[i] += dv[i]
            ndv = max(ndv, abs(dv[i]))
            vmax = max(vmax, abs(v1[i]), abs(v0[i]))
        for j in range(mr):
            dl[j] *= alpha
            lam[rows[j]] += dl[j]
        for i in range(nv):
            if fixed[i]:            # the held joints' efforts, linearised along the update
                for j in range(nv):
                    R[i] += Afix[i, j] * dv[j]
                for j in range(mr):
                    R[i] -= Gtf[j, i] * dl[j]
        lastR, halvings = nR, 0
        if not np.isfinite(ndv):
            return it, 3, c, factorised, 0.0
        if it == 1:
            first = ndv
        vs = max(vmax, first, 1e-300)
        if phi_ok and update_converged(ndv, vs, tol, floor, prev, it > 2):
            break
        refactor = it > 1 and ndv > 0.25 * prev
        prev = ndv
    else:
        return max_it, 1, c, factorised, 0.0
    onto_basis(arr.B, arr.P, v1)
    for k in range(nv):
        vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
    integrate_pass(m, q0, vt, h, q1)
    return it, 0, c, factorised, reaction_size(lam, R, fixed)
