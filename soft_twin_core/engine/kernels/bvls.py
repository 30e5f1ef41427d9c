"""Bounded-variable least squares for the few columns of an actuation IK
step: min |A x - b|^2 subject to lo <= x <= hi (lo <= 0 <= hi), by the
active-set method of Stark and Parker (BVLS, Computational Statistics 1995)
started from x = 0.

Compiled because the planner and the IK service call it once per
Gauss-Newton trial on matrices of a few rows and columns, where the numpy
version spent ~0.4 ms in Python overhead per call (a quarter of an IK
answer). Tested against scipy's ``lsq_linear(method="bvls")``.
"""

import numpy as np

from soft_twin_core.engine.kernels.spatial import _jit, _jit_inner


@_jit_inner
def _free_lstsq(A, b, x, at, F, nf):
    """Least squares over the free columns F[:nf] with the others fixed at x."""
    m, n = A.shape
    r = b.copy()
    for j in range(n):
        if at[j] != 0 and x[j] != 0.0:
            for i in range(m):
                r[i] -= A[i, j] * x[j]
    Af = np.empty((m, nf))
    for t in range(nf):
        for i in range(m):
            Af[i, t] = A[i, F[t]]
    rcond = np.finfo(np.float64).eps * max(m, nf)
    return np.linalg.lstsq(Af, r, rcond)[0]


@_jit
def box_lstsq_kernel(A, b, lo, hi, max_iterations):
    """x (n,) inside the box; A (m, n), b (m,), lo/hi (n,) C-contiguous
    float64 (lo may be -inf, hi +inf)."""
    m, n = A.shape
    x = np.zeros(n)
    at = np.zeros(n, np.int8)            # -1 at lower, +1 at upper, 0 free
    free = np.empty(n, np.bool_)
    for j in range(n):
        free[j] = hi[j] > lo[j]
        if not free[j]:
            at[j] = -1
            x[j] = lo[j]
    F = np.empty(n, np.int64)
    xf = np.empty(n)
    hit_lo = np.empty(n, np.bool_)
    hit_hi = np.empty(n, np.bool_)
    for _ in range(max_iterations):
        nf = 0
        for j in range(n):
            if at[j] == 0:
                F[nf] = j
                nf += 1
        if nf > 0:
            z = _free_lstsq(A, b, x, at, F, nf)
            alpha, k_min, any_viol = np.inf, -1, False
            for t in range(nf):
                j = F[t]
                if z[t] < lo[j] or z[t] > hi[j]:
                    any_viol = True
                    d = z[t] - x[j]
                    s = (lo[j] - x[j]) / d if d < 0 else ((hi[j] - x[j]) / d if d > 0 else np.inf)
                    if s < alpha or k_min < 0:
                        alpha, k_min = s, t
            if any_viol:
                alpha = min(max(alpha, 0.0), 1.0)
                any_hit = False
                for t in range(nf):
                    j = F[t]
                    d = z[t] - x[j]
                    xf[t] = x[j] + alpha * d
                    tol = 1e-14 * max(1.0, abs(xf[t]))
                    hit_lo[t] = xf[t] <= lo[j] + tol and d < 0
                    hit_hi[t] = xf[t] >= hi[j] - tol and d > 0
                    any_hit = any_hit or hit_lo[t] or hit_hi[t]
                if not any_hit:               # round-off: fix the first violator
                    d = z[k_min] - x[F[k_min]]
                    hit_lo[k_min], hit_hi[k_min] = d < 0, d > 0
                for t in range(nf):
                    j = F[t]
                    x[j] = min(max(xf[t], lo[j]), hi[j])
                    if hit_lo[t]:
                        x[j], at[j] = lo[j], -1
                    elif hit_hi[t]:
                        x[j], at[j] = hi[j], 1
                continue
            for t in range(nf):
                x[F[t]] = z[t]
        # minus the gradient w = A^T (b - A x); free the most promising bound variable
        res = b.copy()
        for j in range(n):
            for i in range(m):
                res[i] -= A[i, j] * x[j]
        w = np.zeros(n)
        w_max = 0.0
        for j in range(n):
            for i in range(m):
                w[j] += A[i, j] * res[i]
            w_max = max(w_max, abs(w[j]))
        tol = 1e-12 * max(w_max, 1e-300) if nf > 0 else 0.0
        best, best_w = -1, -1.0
        for j in range(n):
            cand = free[j] and ((at[j] == -1 and w[j] > tol) or (at[j] == 1 and w[j] < -tol))
            if cand and abs(w[j]) > best_w:
                best, best_w = j, abs(w[j])
        if best < 0:
            break
        at[best] = 0
    for j in range(n):
        x[j] = min(max(x[j], lo[j]), hi[j])
    return x


@_jit
def regularised_box_step(Je, e, x, lo, hi, scale, eps, x_ref, lam, dx):
    """dx of :func:`soft_twin_core.planning.planner.bounded_gauss_newton_step`:
    min |Je dx + e|^2 + |eps scale (x + dx - x_ref)|^2 + max(lam, 1e-12) |scale dx|^2
    subject to lo <= x + dx <= hi, the inputs whose box is empty held at
    dx = 0. Returns True when every input is held (dx = 0)."""
    m, n = Je.shape
    rows = m + (n if eps > 0 else 0) + n
    A = np.zeros((rows, n))
    b = np.zeros(rows)
    for i in range(m):
        b[i] = -e[i]
        for j in range(n):
            A[i, j] = Je[i, j]
    r = m
    if eps > 0:
        for j in range(n):
            A[r + j, j] = eps * scale[j]
            b[r + j] = -eps * scale[j] * (x[j] - x_ref[j])
        r += n
    s = np.sqrt(max(lam, 1e-12))
    for j in range(n):
        A[r + j, j] = s * scale[j]
    dlo = np.empty(n)
    dhi = np.empty(n)
    held = True
    for j in range(n):
        dlo[j] = lo[j] - x[j]
        dhi[j] = max(hi[j] - x[j], dlo[j])
        if dhi[j] - dlo[j] > 0:
            held = False
        else:
            dlo[j] = dhi[j] = 0.0
    if held:
        for j in range(n):
            dx[j] = 0.0
        return True
    x = box_lstsq_kernel(A, b, dlo, dhi, 10 * n + 10)
    for j in range(n):                 # a loop, not a slice assignment (static_newton._copy)
        dx[j] = x[j]
    return False
