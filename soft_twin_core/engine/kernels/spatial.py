"""Compiled (numba) primitives of SE(3) shared by every pass: ad, exp, the
right tangent operator T and its time derivative, adjoints, small dense
products without allocation. Same formulas as :mod:`soft_twin_core.lie`
(tested against it)."""

import numpy as np
import numba as nb

from soft_twin_core import lie

# Floating-point freedoms of every kernel: "contract" lets LLVM fuse a * b + c
# into one FMA instruction, "reassoc" lets it reorder the small fixed-length
# sums (6-vectors, 3x3 and 6x6 products) into vector code. Results move at
# round-off level only; NaN and inf keep their IEEE meaning (no "nnan" /
# "ninf": the finiteness checks of Newton's loops stay). Measured on the
# benchmark cantilever: 8 % less CPU per dynamics step (1 s at 10 sections,
# 2 ms steps: 50-53 against 55-57 ms, interleaved runs).
FASTMATH = {"contract", "reassoc"}

_jit = nb.njit(cache=True, fastmath=FASTMATH, nogil=True)   # nogil: a node service computes while the twin steps

# Flags one kernel passes to another. A literal True / False argument from
# compiled code makes numba compile the callee once per value (a
# Literal[bool] signature, besides the plain bool of a call from Python);
# numpy bools type as plain bool: one compilation serves every caller.
TRUE, FALSE = np.True_, np.False_

# A kernel with one compiled caller (besides Python): numba inlines its IR
# there instead of compiling and linking a separate copy, whose optimisation
# and machine code would be redone in every library above it (the caller's
# library links all its callees' code). Called from Python, it compiles as
# usual. Options as _jit's (nogil as on main) plus the inlining.
_jit_inline = nb.njit(cache=True, fastmath=FASTMATH, nogil=True, inline="always")

# A helper that only compiled code calls: numba generates no Python (and no
# first-class-function) entry point for it, a third of a small helper's
# compile time. One called from Python (a test) keeps _jit.
_jit_inner = nb.njit(cache=True, fastmath=FASTMATH, no_cpython_wrapper=True, no_cfunc_wrapper=True)

_SMALL2 = lie._SMALL ** 2
_SMALLD2 = lie._SMALL_DERIV ** 2
P_A, P_B, P_C = lie._P_A, lie._P_B, lie._P_C
P_B1, P_B2, P_B3, P_B4 = lie._P_BETA
P_D1, P_D2, P_D3, P_D4 = lie._P_DBETA


def _poly_derivative(p):
    """Horner coefficients (highest first) of d/d(t2) of a polynomial in t2."""
    d = len(p) - 1
    return np.array([p[i] * (d - i) for i in range(d)], dtype=float)


# d/d(t2) of (d beta_k / d theta) / theta: Taylor branch below t2 = 1
P_E1, P_E2, P_E3, P_E4 = (_poly_derivative(p) for p in lie._P_DBETA)
_SMALLE2 = 1.0



@_jit_inner
def _horner(p, t2):
    out = p[0]
    for k in range(1, p.shape[0]):
        out = out * t2 + p[k]
    return out


@_jit_inner
def _ad_vec(x, y, out):
    """out = ad(x) y = [w x yu + u x yw; w x yw]."""
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    a0, a1, a2, b0, b1, b2 = y[0], y[1], y[2], y[3], y[4], y[5]
    out[0] = w1 * a2 - w2 * a1 + u1 * b2 - u2 * b1
    out[1] = w2 * a0 - w0 * a2 + u2 * b0 - u0 * b2
    out[2] = w0 * a1 - w1 * a0 + u0 * b1 - u1 * b0
    out[3] = w1 * b2 - w2 * b1
    out[4] = w2 * b0 - w0 * b2
    out[5] = w0 * b1 - w1 * b0


@_jit_inner
def _ad_mat(x, A):
    A[:, :] = 0.0
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    for o in (0, 3):
        A[o + 0, o + 1] = -w2
        A[o + 0, o + 2] = w1
        A[o + 1, o + 0] = w2
        A[o + 1, o + 2] = -w0
        A[o + 2, o + 0] = -w1
        A[o + 2, o + 1] = w0
    A[0, 4] = -u2
    A[0, 5] = u1
    A[1, 3] = u2
    A[1, 5] = -u0
    A[2, 3] = -u1
    A[2, 4] = u0


@_jit_inner
def _betas(t2):
    if t2 < _SMALL2:
        return _horner(P_B1, t2), _horner(P_B2, t2), _horner(P_B3, t2), _horner(P_B4, t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    return ((4.0 - t * s - 4.0 * c) / (2 * t2), (4.0 * t - 5.0 * s + t * c) / (2 * t2 * t),
            (2.0 - t * s - 2.0 * c) / (2 * t2 * t2), (2.0 * t - 3.0 * s + t * c) / (2 * t2 * t2 * t))


@_jit_inner
def _dbetas(t2):
    if t2 < _SMALLD2:
        return _horner(P_D1, t2), _horner(P_D2, t2), _horner(P_D3, t2), _horner(P_D4, t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    N1, N2 = 4.0 - t * s - 4.0 * c, 4.0 * t - 5.0 * s + t * c
    N3, N4 = 2.0 - t * s - 2.0 * c, 2.0 * t - 3.0 * s + t * c
    d1, d2 = 3.0 * s - t * c, 4.0 - 4.0 * c - t * s
    d3, d4 = s - t * c, 2.0 - 2.0 * c - t * s
    return ((t * d1 - 2 * N1) / (2 * t ** 4), (t * d2 - 3 * N2) / (2 * t ** 5),
            (t * d3 - 4 * N3) / (2 * t ** 6), (t * d4 - 5 * N4) / (2 * t ** 7))


@_jit_inner
def _mm(A, B, out):
    """out = A @ B for small dense matrices, no allocation."""
    n, k = A.shape
    m = B.shape[1]
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for r in range(k):
                acc += A[i, r] * B[r, j]
            out[i, j] = acc


@_jit_inner
def _mtm(A, B, out):
    """out = A.T @ B."""
    k, n = A.shape
    m = B.shape[1]
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for r in range(k):
                acc += A[r, i] * B[r, j]
            out[i, j] = acc


@_jit_inner
def _mv(A, x, out):
    for i in range(A.shape[0]):
        acc = 0.0
        for r in range(A.shape[1]):
            acc += A[i, r] * x[r]
        out[i] = acc


@_jit_inner
def _mtv(A, x, out):
    for i in range(A.shape[1]):
        acc = 0.0
        for r in range(A.shape[0]):
            acc += A[r, i] * x[r]
        out[i] = acc


@_jit_inner
def _T_into(x, T, S):
    """T_se3(x) = I - b1 ad + b2 ad^2 - b3 ad^3 + b4 ad^4 from 3x3 blocks:
    ad^k = [[W^k, X_k], [0, W^k]] with X_k = sum_j W^j U W^(k-1-j),
    W^3 = -t^2 W, W^4 = -t^2 W^2. S: (7, 3, 3) scratch (no allocation)."""
    u0, u1, u2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    b1, b2, b3, b4 = _betas(t2)
    W, U, W2, WU, UW, X2, X3 = S[0], S[1], S[2], S[3], S[4], S[5], S[6]
    W[0, 0], W[0, 1], W[0, 2] = 0.0, -w2, w1
    W[1, 0], W[1, 1], W[1, 2] = w2, 0.0, -w0
    W[2, 0], W[2, 1], W[2, 2] = -w1, w0, 0.0
    U[0, 0], U[0, 1], U[0, 2] = 0.0, -u2, u1
    U[1, 0], U[1, 1], U[1, 2] = u2, 0.0, -u0
    U[2, 0], U[2, 1], U[2, 2] = -u1, u0, 0.0
    for i in range(3):
        for j in range(3):
            a2 = 0.0
            a3 = 0.0
            a4 = 0.0
            for k in range(3):
                a2 += W[i, k] * W[k, j]
                a3 += W[i, k] * U[k, j]
                a4 += U[i, k] * W[k, j]
            W2[i, j] = a2
            WU[i, j] = a3
            UW[i, j] = a4
            X2[i, j] = a3 + a4
    # X3 = W^2 U + W U W + U W^2 = W X2 + U W^2 ; X4 = W X3 + U W^3 = W X3 - t2 U W
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += W[i, k] * X2[k, j] + U[i, k] * W2[k, j]
            X3[i, j] = acc
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += W[i, k] * X3[k, j]
            X4 = acc - t2 * UW[i, j]
            D = (1.0 if i == j else 0.0) - (b1 - b3 * t2) * W[i, j] + (b2 - b4 * t2) * W2[i, j]
            T[i, j] = D
            T[i + 3, j + 3] = D
            T[i + 3, j] = 0.0
            T[i, j + 3] = -b1 * U[i, j] + b2 * X2[i, j] - b3 * X3[i, j] + b4 * X4


@_jit_inner
def _betas_dbetas(t2):
    """(_betas(t2), _dbetas(t2)) with one sqrt/sin/cos."""
    if t2 < _SMALLD2:
        return _betas(t2), _dbetas(t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    N1, N2 = 4.0 - t * s - 4.0 * c, 4.0 * t - 5.0 * s + t * c
    N3, N4 = 2.0 - t * s - 2.0 * c, 2.0 * t - 3.0 * s + t * c
    t3 = t2 * t
    t4 = t2 * t2
    t5 = t4 * t
    d1, d2 = 3.0 * s - t * c, 4.0 - 4.0 * c - t * s
    d3, d4 = s - t * c, 2.0 - 2.0 * c - t * s
    return ((N1 / (2 * t2), N2 / (2 * t3), N3 / (2 * t4), N4 / (2 * t5)),
            ((t * d1 - 2 * N1) / (2 * t4), (t * d2 - 3 * N2) / (2 * t5),
             (t * d3 - 4 * N3) / (2 * t4 * t2), (t * d4 - 5 * N4) / (2 * t4 * t3)))


@_jit
def _T_dot_into(x, xd, y, out, P, tmp, tmp2, acc):
    """out = (d/dt T_se3(x))[xd] y (no allocation; P is 5x6 scratch).

    T = I - b1 ad + b2 ad^2 - b3 ad^3 + b4 ad^4 (ad = ad(x)); its derivative
    along xd is sum_k (+-)(b_k' (w . wd) ad^k + b_k d(ad^k)[xd]) with
    d(ad^k)[xd] y = Q_k, Q_1 = ad(xd) y, Q_k = ad(xd) ad^(k-1) y + ad(x) Q_(k-1)
    (11 products ad(.) v instead of the 24 of the expanded sum)."""
    t2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5]
    wwd = x[3] * xd[3] + x[4] * xd[4] + x[5] * xd[5]
    bb, dd = _betas_dbetas(t2)
    b1, b2, b3, b4 = bb
    d1, d2, d3, d4 = dd
    for a in range(6):
        P[0, a] = y[a]
    for m in range(1, 5):
        _ad_vec(x, P[m - 1], P[m])
    # Q_1 = ad(xd) y
    _ad_vec(xd, P[0], acc)
    for a in range(6):
        out[a] = -(d1 * wwd * P[1, a] + b1 * acc[a])
    for k in range(2, 5):
        if k == 2:
            bk, dk, sign = b2, d2, 1.0
        elif k == 3:
            bk, dk, sign = b3, d3, -1.0
        else:
            bk, dk, sign = b4, d4, 1.0
        _ad_vec(xd, P[k - 1], tmp)
        _ad_vec(x, acc, tmp2)
        for a in range(6):
            acc[a] = tmp[a] + tmp2[a]
            out[a] += sign * (dk * wwd * P[k, a] + bk * acc[a])


@_jit_inner
def _ad_t(x, y):
    """ad(x) y on 6-tuples (kept in registers): [w x yu + u x yw; w x yw]."""
    return (x[4] * y[2] - x[5] * y[1] + x[1] * y[5] - x[2] * y[4],
            x[5] * y[0] - x[3] * y[2] + x[2] * y[3] - x[0] * y[5],
            x[3] * y[1] - x[4] * y[0] + x[0] * y[4] - x[1] * y[3],
            x[4] * y[5] - x[5] * y[4],
            x[5] * y[3] - x[3] * y[5],
            x[3] * y[4] - x[4] * y[3])


@_jit
def _T_dot_along(x, X, Y):
    """(d/dt T_se3(X))[x Y] Y for X = x f, Xd = x fdot, Y = fdot: the
    special case of :func:`_T_dot_into` met by a PCS point (the direction
    is parallel to the vector), on tuples. ad(Xd) Y = x ad(Y) Y = 0, so
    Q_1 = 0 and Q_k = x ad(Y) P_(k-1) + ad(X) Q_(k-1) (P_k = ad(X)^k Y):
    9 products ad(.) v instead of 11, no scratch arrays."""
    t2 = X[3] * X[3] + X[4] * X[4] + X[5] * X[5]
    wwd = x * (X[3] * Y[3] + X[4] * Y[4] + X[5] * Y[5])
    bb, dd = _betas_dbetas(t2)
    P1 = _ad_t(X, Y)
    P2 = _ad_t(X, P1)
    P3 = _ad_t(X, P2)
    P4 = _ad_t(X, P3)
    A2 = _ad_t(Y, P1)
    A3 = _ad_t(Y, P2)
    A4 = _ad_t(Y, P3)
    Q2 = (x * A2[0], x * A2[1], x * A2[2], x * A2[3], x * A2[4], x * A2[5])
    B3 = _ad_t(X, Q2)
    Q3 = (x * A3[0] + B3[0], x * A3[1] + B3[1], x * A3[2] + B3[2],
          x * A3[3] + B3[3], x * A3[4] + B3[4], x * A3[5] + B3[5])
    B4 = _ad_t(X, Q3)
    c1, c2, c3, c4 = -dd[0] * wwd, dd[1] * wwd, -dd[2] * wwd, dd[3] * wwd
    b2, b3, b4 = bb[1], -bb[2], bb[3]
    return (c1 * P1[0] + c2 * P2[0] + c3 * P3[0] + c4 * P4[0] + b2 * Q2[0] + b3 * Q3[0] + b4 * (x * A4[0] + B4[0]),
            c1 * P1[1] + c2 * P2[1] + c3 * P3[1] + c4 * P4[1] + b2 * Q2[1] + b3 * Q3[1] + b4 * (x * A4[1] + B4[1]),
            c1 * P1[2] + c2 * P2[2] + c3 * P3[2] + c4 * P4[2] + b2 * Q2[2] + b3 * Q3[2] + b4 * (x * A4[2] + B4[2]),
            c1 * P1[3] + c2 * P2[3] + c3 * P3[3] + c4 * P4[3] + b2 * Q2[3] + b3 * Q3[3] + b4 * (x * A4[3] + B4[3]),
            c1 * P1[4] + c2 * P2[4] + c3 * P3[4] + c4 * P4[4] + b2 * Q2[4] + b3 * Q3[4] + b4 * (x * A4[4] + B4[4]),
            c1 * P1[5] + c2 * P2[5] + c3 * P3[5] + c4 * P4[5] + b2 * Q2[5] + b3 * Q3[5] + b4 * (x * A4[5] + B4[5]))


@_jit_inner
def _exp_into(x, g):
    w0, w1, w2 = x[3], x[4], x[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < _SMALL2:
        a, b, c = _horner(P_A, t2), _horner(P_B, t2), _horner(P_C, t2)
    else:
        t = np.sqrt(t2)
        s, co = np.sin(t), np.cos(t)
        a, b, c = s / t, (1.0 - co) / t2, (t - s) / (t2 * t)
    # W^2 = w w^T - t2 I
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    ww = (w0, w1, w2)
    for i in range(3):
        acc = 0.0
        for j in range(3):
            W2 = ww[i] * ww[j] - (t2 if i == j else 0.0)
            e = 1.0 if i == j else 0.0
            g[i, j] = e + a * W[i][j] + b * W2
            acc += (e + b * W[i][j] + c * W2) * x[j]
        g[i, 3] = acc
        g[3, i] = 0.0
    g[3, 3] = 1.0


@_jit_inner
def _Ad_into(g, A, inverse):
    """A = Ad(g) or Ad(g)^-1 (inverse=True)."""
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    for i in range(6):
        for j in range(6):
            A[i, j] = 0.0
    for i in range(3):
        for j in range(3):
            r = g[j, i] if inverse else g[i, j]
            A[i, j] = r
            A[i + 3, j + 3] = r
    if inverse:
        # -R^T hat(p): column j of hat(p) is p x e_j
        for i in range(3):
            r0, r1, r2 = g[0, i], g[1, i], g[2, i]      # row i of R^T
            # (R^T hat(p))[i, j] = sum_k R[k, i] hat(p)[k, j]
            A[i, 3] = -(r1 * p2 - r2 * p1)
            A[i, 4] = -(r2 * p0 - r0 * p2)
            A[i, 5] = -(r0 * p1 - r1 * p0)
    else:
        # hat(p) R
        for j in range(3):
            c0, c1, c2 = g[0, j], g[1, j], g[2, j]
            A[0, j + 3] = p1 * c2 - p2 * c1
            A[1, j + 3] = p2 * c0 - p0 * c2
            A[2, j + 3] = p0 * c1 - p1 * c0




# ----------------------------------------------------------------------------
# Cayley map (lie.cay_se3, lie.T_cay_se3 and the time derivative of the latter)
# ----------------------------------------------------------------------------

@_jit_inner
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@_jit_inner
def _apply_inv_half(w, v, sign):
    """(I - sign hat(w)/2)^-1 v = v + (2 sign w x v + w x (w x v)) / (4 + t^2)."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    c0, c1, c2 = _cross(w[0], w[1], w[2], v[0], v[1], v[2])
    d0, d1, d2 = _cross(w[0], w[1], w[2], c0, c1, c2)
    k = 1.0 / (4.0 + t2)
    return (v[0] + k * (2 * sign * c0 + d0), v[1] + k * (2 * sign * c1 + d1), v[2] + k * (2 * sign * c2 + d2))


@_jit_inner
def _cay_into(x, g):
    """g = cay_se3(x) = [[I + k (W + W^2/2), (I - W/2)^-1 u], [0, 1]], k = 4/(4 + t^2)."""
    w0, w1, w2 = x[3], x[4], x[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    k = 4.0 / (4.0 + t2)
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    ww = (w0, w1, w2)
    for i in range(3):
        for j in range(3):
            W2 = ww[i] * ww[j] - (t2 if i == j else 0.0)
            g[i, j] = (1.0 if i == j else 0.0) + k * (W[i][j] + 0.5 * W2)
        g[3, i] = 0.0
    p = _apply_inv_half(x[3:], x[:3], 1.0)
    g[0, 3], g[1, 3], g[2, 3] = p[0], p[1], p[2]
    g[3, 3] = 1.0


@_jit_inner
def _T_cay_into(x, T):
    """T = lie.T_cay_se3(x) = [[P, -P hat(Q u/2)], [0, k (I - W/2)]] with
    P = (I + W/2)^-1, Q = (I - W/2)^-1, k = 4/(4 + t^2)."""
    w0, w1, w2 = x[3], x[4], x[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    k = 4.0 / (4.0 + t2)
    kk = 1.0 / (4.0 + t2)
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    ww = (w0, w1, w2)
    Qu = _apply_inv_half(x[3:], x[:3], 1.0)
    h0, h1, h2 = 0.5 * Qu[0], 0.5 * Qu[1], 0.5 * Qu[2]
    H = ((0.0, -h2, h1), (h2, 0.0, -h0), (-h1, h0, 0.0))
    P = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            W2 = ww[i] * ww[j] - (t2 if i == j else 0.0)
            P[i, j] = (1.0 if i == j else 0.0) + kk * (-2.0 * W[i][j] + W2)
            T[i + 3, j + 3] = k * ((1.0 if i == j else 0.0) - 0.5 * W[i][j])
            T[i + 3, j] = 0.0
    for i in range(3):
        for j in range(3):
            T[i, j] = P[i, j]
            T[i, j + 3] = -(P[i, 0] * H[0][j] + P[i, 1] * H[1][j] + P[i, 2] * H[2][j])


@_jit_inner
def _T_cay_dot_into(x, xd, y, out):
    """out = (d/dt T_cay_se3(x))[xd] y: with T y = [P z; k (y_w - w x y_w / 2)],
    z = y_u - (Q u / 2) x y_w, dP = -P hat(wd/2) P, dQ = Q hat(wd/2) Q,
    dk = -8 (w . wd) / (4 + t^2)^2."""
    w = x[3:]
    wd = xd[3:]
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    k = 4.0 / (4.0 + t2)
    dk = -8.0 * (w[0] * wd[0] + w[1] * wd[1] + w[2] * wd[2]) / (4.0 + t2) ** 2
    Qu = _apply_inv_half(w, x[:3], 1.0)
    c = _cross(wd[0], wd[1], wd[2], Qu[0], Qu[1], Qu[2])
    a = _apply_inv_half(w, np.array([0.5 * c[0] + xd[0], 0.5 * c[1] + xd[1], 0.5 * c[2] + xd[2]]), 1.0)
    # a = d(Q u); z and dz
    cz = _cross(Qu[0], Qu[1], Qu[2], y[3], y[4], y[5])
    z = np.array([y[0] - 0.5 * cz[0], y[1] - 0.5 * cz[1], y[2] - 0.5 * cz[2]])
    cdz = _cross(a[0], a[1], a[2], y[3], y[4], y[5])
    Pz = _apply_inv_half(w, z, -1.0)
    e = _cross(wd[0], wd[1], wd[2], Pz[0], Pz[1], Pz[2])
    top = _apply_inv_half(w, np.array([-0.5 * cdz[0] - 0.5 * e[0], -0.5 * cdz[1] - 0.5 * e[1],
                                       -0.5 * cdz[2] - 0.5 * e[2]]), -1.0)
    wy = _cross(w[0], w[1], w[2], y[3], y[4], y[5])
    wdy = _cross(wd[0], wd[1], wd[2], y[3], y[4], y[5])
    for i in range(3):
        out[i] = top[i]
        out[i + 3] = dk * (y[3 + i] - 0.5 * wy[i]) - 0.5 * k * wdy[i]


@_jit_inner
def _map_into(kmap, x, g):
    """Kinematic map of a soft section: exp (kmap 0) or Cayley (1)."""
    if kmap == 1:
        _cay_into(x, g)
    else:
        _exp_into(x, g)


@_jit_inner
def _tangent_into(kmap, x, T, S3):
    if kmap == 1:
        _T_cay_into(x, T)
    else:
        _T_into(x, T, S3)


@_jit_inner
def _tangent_dot_into(kmap, x, xd, y, out, P, tmp, tmp2, acc):
    if kmap == 1:
        _T_cay_dot_into(x, xd, y, out)
    else:
        _T_dot_into(x, xd, y, out, P, tmp, tmp2, acc)


@_jit_inner
def _d2betas(t2):
    """d/d(t2) of the coefficients g_k = (d beta_k/d theta)/theta of
    :func:`_dbetas` (k = 1..4): with g_k = (t N_k' - m N_k)/(2 t^(m+2)),
    m = k + 1, ``dg/dt = (t N'' + (1 - m) N')/(2 t^(m+2)) - (m + 2)(t N' - m N)/(2 t^(m+3))``
    and d/d(t2) = (d/dt)/(2 t); the Taylor series below t2 = 1."""
    if t2 < _SMALLE2:
        return _horner(P_E1, t2), _horner(P_E2, t2), _horner(P_E3, t2), _horner(P_E4, t2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    N = (4.0 - t * s - 4.0 * c, 4.0 * t - 5.0 * s + t * c, 2.0 - t * s - 2.0 * c, 2.0 * t - 3.0 * s + t * c)
    N1 = (3.0 * s - t * c, 4.0 - 4.0 * c - t * s, s - t * c, 2.0 - 2.0 * c - t * s)
    N2 = (2.0 * c + t * s, 3.0 * s - t * c, t * s, s - t * c)
    out = np.empty(4)
    for k in range(4):
        m = k + 2
        dg = (t * N2[k] + (1 - m) * N1[k]) / (2 * t ** (m + 2)) - (m + 2) * (t * N1[k] - m * N[k]) / (2 * t ** (m + 3))
        out[k] = dg / (2 * t)
    return out[0], out[1], out[2], out[3]


@_jit_inner
def _T_d2_into(x, a, b, y, out):
    """out = D^2 T_se3(x)[a, b] y: the second directional derivative of the
    tangent operator (exponential map). With T = sum_k s_k beta_k ad(x)^k,
    g_k = 2 dbeta_k/d(t2), P_k = ad^k y, Q_k(a) = d(ad^k)[a] y
    (Q_1 = ad(a) y, Q_k = ad(a) P_(k-1) + ad(x) Q_(k-1)) and
    R_k = ad(a) Q_(k-1)(b) + ad(b) Q_(k-1)(a) + ad(x) R_(k-1) (R_1 = 0):
    ``sum_k s_k [2 g_k' (w.a)(w.b) P_k + g_k (a_w.b_w) P_k + g_k (w.a) Q_k(b)
    + g_k (w.b) Q_k(a) + beta_k R_k]``."""
    t2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5]
    wa = x[3] * a[3] + x[4] * a[4] + x[5] * a[5]
    wb = x[3] * b[3] + x[4] * b[4] + x[5] * b[5]
    ab = a[3] * b[3] + a[4] * b[4] + a[5] * b[5]
    bb, gg = _betas_dbetas(t2)
    ee = _d2betas(t2)
    P = np.empty((5, 6))
    Qa = np.empty(6)
    Qb = np.empty(6)
    R = np.zeros(6)
    t1 = np.empty(6)
    t2v = np.empty(6)
    t3 = np.empty(6)
    for i in range(6):
        P[0, i] = y[i]
        out[i] = 0.0
    for k in range(1, 5):
        _ad_vec(x, P[k - 1], P[k])
    for k in range(1, 5):
        sign = 1.0 if k % 2 == 0 else -1.0
        if k == 1:
            _ad_vec(a, P[0], Qa)
            _ad_vec(b, P[0], Qb)
        else:
            # R_k uses Q_(k-1): update R before Q
            _ad_vec(a, Qb, t1)
            _ad_vec(b, Qa, t2v)
            _ad_vec(x, R, t3)
            for i in range(6):
                R[i] = t1[i] + t2v[i] + t3[i]
            _ad_vec(a, P[k - 1], t1)
            _ad_vec(x, Qa, t2v)
            for i in range(6):
                Qa[i] = t1[i] + t2v[i]
            _ad_vec(b, P[k - 1], t1)
            _ad_vec(x, Qb, t2v)
            for i in range(6):
                Qb[i] = t1[i] + t2v[i]
        g, e, be = gg[k - 1], ee[k - 1], bb[k - 1]
        for i in range(6):
            out[i] += sign * ((2.0 * e * wa * wb + g * ab) * P[k, i] + g * wa * Qb[i] + g * wb * Qa[i]
                              + be * R[i])
