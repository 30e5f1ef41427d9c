"""Newton's method on the static equilibrium, compiled (one call per solve).

``R(q) = K (q - q0) + tau_rnea(q; loads, gravity) - tau_act(q, u) = 0``
(:func:`soft_twin_core.engine.integrators.residual_pass` at rest) with its analytic
tangent (:func:`kernels.tangent.static_tangent_pass`, the stiffness and the
tendons' :func:`forces.actuation_tangent_pass`), a backtracking line search
on ``|R|`` and, optionally, a tangent hint from a nearby state reused for
the first steps (modified Newton) while each step cuts the residual at least
tenfold. Convergence: ``|R_k| <= tol * scale + roundoff_k`` for every
component, with the force scale ``max(|K (q - q0)|, |K (q - q0) - R|)``
(the elastic and the applied force) and the round-off level
``64 eps (|K| (|q| + |q0|))`` of the stiff axial/shear modes; a converged
solve takes one more (polish) step with the last tangent when it lowers |R|.

The small dense algebra is written out (the tangent's solve by Gaussian
elimination with partial pivoting, O(n^3/3) for n free strains), so the
kernel needs no BLAS/LAPACK and loads without scipy at start-up.

It is :func:`soft_twin_core.solve.equilibrium.newton_numpy` in one compiled call:
the Python loop around the kernels cost 0.44 of a warm solve's 0.68 ms
(the actuation IK's statics, default robot). The tests check it against
that Python loop (same iterates and iteration counts).
"""

import numpy as np

from soft_twin_core.engine.forces import actuation_tangent_pass
from soft_twin_core.engine.integrators import residual_pass
from soft_twin_core.engine.kernels.spatial import TRUE, _jit, _jit_inline, _jit_inner
from soft_twin_core.engine.kernels.tangent import static_tangent_pass


@_jit_inline
def _residual(m, w, act, ld, g, coef, effort, zeros, q, out):
    residual_pass(m, w, act, ld, g, coef, effort, q, zeros, zeros, out, TRUE)


@_jit_inline
def _tangent(m, w, act, ld, g, coef, K, Kt):
    """dR/dq at the q of the workspace's last residual_pass, whose poses and
    RNEA wrenches at rest it reads (no pass of its own)."""
    for i in range(K.shape[0]):      # element loops, not slice assignment: see _copy
        for j in range(K.shape[1]):
            Kt[i, j] = K[i, j]
    static_tangent_pass(m, w, ld, g, Kt)
    actuation_tangent_pass(m, w, act, coef, Kt)


@_jit_inner
def _scale(K, q, q0, R, floor):
    """max(|K (q - q0)|, |K (q - q0) - R|, floor): the elastic and the applied
    force, at least ``floor`` (:func:`soft_twin_core.solve.equilibrium.load_scale`)."""
    n = q.shape[0]
    s = max(floor, 1e-300)
    for i in range(n):
        kq = 0.0
        for j in range(n):
            kq += K[i, j] * (q[j] - q0[j])
        s = max(s, abs(kq), abs(kq - R[i]))
    return s


@_jit_inner
def _converged(absK, q, q0, R, scale, tol):
    """|R_i| <= tol scale + 64 eps (|K| (|q| + |q0|))_i for every i."""
    n = q.shape[0]
    eps64 = 64 * np.finfo(np.float64).eps
    for i in range(n):
        ro = 0.0
        for j in range(n):
            ro += absK[i, j] * (abs(q[j]) + abs(q0[j]))
        if not abs(R[i]) <= tol * scale + eps64 * ro:
            return False
    return True


@_jit_inner
def _copy(src, dst):
    """dst[:] = src as a loop: numba compiles a slice assignment from an
    array with a shape-mismatch error whose message formatting (str of
    ints, joins) cost about 3 s of the first compile of this kernel."""
    for i in range(src.shape[0]):
        dst[i] = src[i]


@_jit_inner
def _norm(x):
    s = 0.0
    for i in range(x.shape[0]):
        s += x[i] * x[i]
    return np.sqrt(s)


@_jit_inner
def _finite(x):
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    return True


@_jit_inner
def _solve(A, b, out):
    """out = A^-1 b by Gaussian elimination with partial pivoting (no BLAS or
    LAPACK: the kernel loads without scipy); False if A is singular (an
    exactly zero pivot, as LAPACK's gesv) or the result is not finite."""
    n = b.shape[0]
    LU = A.copy()
    x = b.copy()
    for k in range(n):
        p = k
        big = abs(LU[k, k])
        for i in range(k + 1, n):
            if abs(LU[i, k]) > big:
                p, big = i, abs(LU[i, k])
        if big == 0.0:
            return False
        if p != k:
            for j in range(n):
                LU[k, j], LU[p, j] = LU[p, j], LU[k, j]
            x[k], x[p] = x[p], x[k]
        inv = 1.0 / LU[k, k]
        for i in range(k + 1, n):
            f = LU[i, k] * inv
            if f != 0.0:
                for j in range(k + 1, n):
                    LU[i, j] -= f * LU[k, j]
                x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for j in range(i + 1, n):
            acc -= LU[i, j] * out[j]
        out[i] = acc / LU[i, i]
    return _finite(out)


@_jit
def static_newton(m, w, act, ld, g, coef, effort, K, absK, q0, q, tol, floor, max_it, Kt_hint, use_hint, Kt, R):
    """Newton from q (updated in place) to tolerance ``tol``; R receives the
    residual at the returned q, Kt the last fresh tangent. Returns
    (iterations, converged, which, tangents computed); which tangent was the
    last used: 0 none, 1 the hint, 2 the fresh one in Kt. ``effort``: the
    joint efforts (nv,) [N m or N] of effort-controlled joints (zeros for a rod);
    ``floor``: the smallest force scale of the relative residual."""
    n = q.shape[0]
    zeros = np.zeros(n)
    dq = np.empty(n)
    q_try = np.empty(n)
    R_try = np.empty(n)
    _residual(m, w, act, ld, g, coef, effort, zeros, q, R)
    scale = _scale(K, q, q0, R, floor)
    which = 0
    n_tan = 0
    at_q = True                # the workspace holds the passes of the residual at q
    reuse = use_hint
    it = 0
    for it in range(1, max_it + 1):
        if _converged(absK, q, q0, R, scale, tol):
            if which != 0:
                # polish: one more step with the last tangent (one residual call)
                if _solve(Kt_hint if which == 1 else Kt, -R, dq):
                    for i in range(n):
                        q_try[i] = q[i] + dq[i]
                    _residual(m, w, act, ld, g, coef, effort, zeros, q_try, R_try)
                    if _finite(R_try) and _norm(R_try) < _norm(R):
                        _copy(q_try, q)
                        _copy(R_try, R)
            return it - 1, True, which, n_tan
        if reuse:
            which = 1
            ok = _solve(Kt_hint, -R, dq)
        else:
            if not at_q:
                _residual(m, w, act, ld, g, coef, effort, zeros, q, R_try)
            _tangent(m, w, act, ld, g, coef, K, Kt)
            n_tan += 1
            which = 2
            ok = _solve(Kt, -R, dq)
        if not ok:
            if reuse:
                reuse = False
                continue
            return it, False, 0, n_tan
        # backtracking line search on |R|
        step = 1.0
        r0 = _norm(R)
        found = False
        r_try = 0.0
        for _ in range(20):
            for i in range(n):
                q_try[i] = q[i] + step * dq[i]
            _residual(m, w, act, ld, g, coef, effort, zeros, q_try, R_try)
            if _finite(R_try):
                r_try = _norm(R_try)
                if r_try < (1 - 1e-4 * step) * r0:
                    found = True
                    break
            step *= 0.5
        if not found:
            at_q = False          # the line search's residuals were at other points
            if reuse:             # the stale tangent gives no descent: take a fresh one
                reuse = False
                continue
            return it, _converged(absK, q, q0, R, scale, tol), which, n_tan
        if reuse and (step < 1.0 or r_try > 0.1 * r0):
            reuse = False         # slow: fresh tangents from now on
        _copy(q_try, q)
        _copy(R_try, R)
        at_q = True
        scale = max(scale, _scale(K, q, q0, R, floor))
    return it, _converged(absK, q, q0, R, scale, tol), which, n_tan
