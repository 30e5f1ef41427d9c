"""The Newton matrix of an implicit theta step, compiled, shared by the
compiled steps (:mod:`contact_step`, :mod:`closed_step`):

    A = (M + theta h D_t + (theta h)^2 K_t) / h

at the theta point q_t (M: the mass matrix, CRBA; K_t: the static tangent
of the elastic forces, loads and tendons; D_t: the damping), inverted
densely with the rows and columns of the prescribed (``fixed``) velocities
replaced by the identity's: a position-controlled joint is eliminated, its
row of the full matrix kept (``Afix``) to carry its effort along an update.
Dense, nv^3 a factorisation: for the robots the twin runs (up to ~100 dof)
it costs less than the Python glue it replaces."""

import numpy as np

from soft_twin_core.engine.forces import actuation_tangent_pass
from soft_twin_core.engine.integrators import integrate_pass
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.spatial import TRUE, _jit, _jit_inline, _jit_inner
from soft_twin_core.engine.kernels.tangent import static_tangent_pass


@_jit_inline
def step_tangents(m, w, act, ld, g, coef, K, D, qt, zeros):
    """(M, K_t, D_t) at q_t under the dead and follower loads ``ld``, gravity
    g and tendon coefficients ``coef`` (the workspace posed at q_t, at rest)."""
    nv = K.shape[0]
    passes.forward_pass(m, w, qt, zeros, zeros, passes.POSES)
    M = np.zeros((nv, nv))
    passes.crba_pass(m, w, M)
    passes.rnea_pass(m, w, ld, g, np.empty(nv), TRUE)
    Kt = K.copy()
    static_tangent_pass(m, w, ld, g, Kt)
    actuation_tangent_pass(m, w, act, coef, Kt)
    return M, Kt, D.copy()


@_jit_inner
def _project_matrix(A, B):
    """B^T A B (nz, nz), B's zeros skipped (a section's rows of a basis
    are nonzero in its segment's columns only)."""
    nv, nz = B.shape
    AB = np.zeros((nv, nz))
    for k in range(nv):
        for l in range(nv):
            a = A[k, l]
            if a != 0.0:
                for c in range(nz):
                    AB[k, c] += a * B[l, c]
    out = np.zeros((nz, nz))
    for k in range(nv):
        for r in range(nz):
            b = B[k, r]
            if b != 0.0:
                for c in range(nz):
                    out[r, c] += b * AB[k, c]
    return out


@_jit_inner
def _lift_inverse(X, B):
    """B X B^T (nv, nv): the Galerkin inverse from the basis's X = (B^T A B)^-1."""
    nv, nz = B.shape
    BX = np.zeros((nv, nz))
    for k in range(nv):
        for r in range(nz):
            b = B[k, r]
            if b != 0.0:
                for c in range(nz):
                    BX[k, c] += b * X[r, c]
    out = np.empty((nv, nv))
    for i in range(nv):
        for j in range(nv):
            s = 0.0
            for c in range(nz):
                s += BX[i, c] * B[j, c]
            out[i, j] = s
    return out


@_jit_inner
def invert_step_matrix(A, Kt, Dt, h, theta, fixed, Ainv, Afix, B):
    """Ainv = ((A + th h D_t + (th h)^2 K_t) / h)^-1 (A holds M on entry and
    the step matrix on return), the ``fixed`` rows and columns replaced by
    the identity's (their rows of the full matrix into Afix). With a basis
    B (nv, nz; no columns: none), the Galerkin inverse ``B (B^T A B)^-1
    B^T`` instead: an update ``-Ainv R`` is then the basis's Newton update
    mapped to the velocities, and a Schur complement made with it is the
    basis's (the fixed velocities are identity columns of B). False if
    singular or not finite."""
    nv = A.shape[0]
    th = theta * h
    for i in range(nv):
        for j in range(nv):
            A[i, j] = (A[i, j] + th * Dt[i, j] + th * th * Kt[i, j]) / h
            if not np.isfinite(A[i, j]):
                return False
    for i in range(nv):
        if fixed[i]:
            for j in range(nv):
                Afix[i, j] = A[i, j]
                A[i, j] = 0.0
                A[j, i] = 0.0
            A[i, i] = 1.0
    try:
        inv = np.linalg.inv(A if B.shape[1] == 0 else _project_matrix(A, B))
    except Exception:           # singular to machine precision
        return False
    if B.shape[1] > 0:
        inv = _lift_inverse(inv, B)
    ok = True
    for i in range(nv):
        for j in range(nv):
            if not np.isfinite(inv[i, j]):
                ok = False
            Ainv[i, j] = inv[i, j]
    return ok


@_jit_inner
def residual_sizes(R, fixed, B):
    """(nR, held): the largest residual of the free velocities, the
    Newton's unknowns, and the largest of the ``fixed`` ones (the efforts
    holding them). With a basis B (nv, nz; no columns: none) the unknowns
    are its coordinates and their residual ``B^T R`` (the Galerkin
    residual, as the Python KKT step's ``T^T R``); the fixed velocities are
    identity columns of B, whose rows of ``B^T R`` are theirs of R."""
    nv, nz = B.shape
    nR, held = 0.0, 0.0
    for k in range(nv):
        if fixed[k]:
            held = max(held, abs(R[k]))
        elif nz == 0:
            nR = max(nR, abs(R[k]))
    for c in range(nz):
        s = 0.0
        free = True
        for k in range(nv):
            if B[k, c] != 0.0:
                s += B[k, c] * R[k]
                if fixed[k]:
                    free = False
        if free:
            nR = max(nR, abs(s))
    return nR, held


@_jit_inner
def onto_basis(B, P, v):
    """v = B P v in place, P = (B^T B)^-1 B^T (nothing when B has no
    columns): the velocities back on the basis at the end of a step. The
    updates made with the Galerkin inverse lie on it to round-off, but
    nothing pulls a velocity back, so round-off would add up over the
    steps (2e-10 of the speed in 100 steps of the catheter); the identity
    columns' velocities (the fixed ones) come back unchanged."""
    nv, nz = B.shape
    if nz == 0:
        return
    w = np.empty(nz)
    for c in range(nz):
        s = 0.0
        for k in range(nv):
            s += P[c, k] * v[k]
        w[c] = s
    for k in range(nv):
        s = 0.0
        for c in range(nz):
            s += B[k, c] * w[c]
        v[k] = s


@_jit_inner
def elastic_noise(K, qt, q_ref):
    """The round-off of the elastic forces ``K (q_t - q_ref)`` (1e-9 of the
    largest): a robot at rest, or resting on obstacles, steps from an
    equilibrium whose residual is this noise, which a step cannot reduce."""
    nv = K.shape[0]
    noise = 0.0
    for i in range(nv):
        s = 0.0
        for j in range(nv):
            s += K[i, j] * (qt[j] - q_ref[j])
        noise = max(noise, 1e-9 * abs(s))
    return noise


# The stopping rule of every theta step's Newton loop: the compiled closed-chain
# and contact steps here, the Python KKT step of solve.constrained (through
# .py_func: the same source, nothing compiled for it).

@_jit
def forces_balanced(nR, Rs, tol, noise):
    """True when the free velocities' forces balance: their residual
    ``nR = max|R|`` at most ``tol`` times their scale ``Rs`` or the elastic
    forces' round-off ``noise``. Rs is set at the first iterate, the larger
    of its residual and the constraint forces (multipliers, efforts holding
    prescribed joints), and the same test runs at every iterate: a predictor
    balanced to tol of the constraint forces (a robot at rest, or moving
    smoothly) ends the step after one residual, no update."""
    return nR <= max(tol * Rs, noise)


@_jit
def update_converged(ndv, vs, tol, floor, prev, stall_ok):
    """True when the Newton update ``ndv = max|dv|`` is at most ``tol`` of
    the velocities' scale ``vs`` (or at the round-off ``floor``), or, with
    ``stall_ok`` (past the second iterate), when it stalls at round-off: at
    most 1e-6 of the scale and not halving from the last one, ``prev``."""
    return ndv <= max(tol * vs, floor) or (stall_ok and ndv <= 1e-6 * vs and ndv >= 0.5 * prev)


@_jit_inner
def free_newton_update(Ainv, R, fixed, out):
    """out = -A^-1 R over the free velocities (zero on the ``fixed`` ones)."""
    nv = R.shape[0]
    for i in range(nv):
        s = 0.0
        if not fixed[i]:
            for j in range(nv):
                if not fixed[j]:
                    s -= Ainv[i, j] * R[j]
        out[i] = s


@_jit_inner
def theta_point(m, q0, v0, v1, h, theta, vt, acc, qt, q1):
    """The step's mean velocity vt = (1 - theta) v0 + theta v1, its mean
    acceleration acc = (v1 - v0) / h, the theta point qt = q0 (+) theta h vt
    and the end q1 = q0 (+) h vt."""
    for k in range(v0.shape[0]):
        vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
        acc[k] = (v1[k] - v0[k]) / h
    integrate_pass(m, q0, vt, theta * h, qt)
    integrate_pass(m, q0, vt, h, q1)
