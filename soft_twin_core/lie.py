"""SO(3) and SE(3): hat maps, adjoints, exp/log, tangent operators, Cayley map.

Conventions (docs/CONVENTIONS.md; the seed lecture slides, part B "The exponential map on SO(3)/SE(3)"):

* A twist / strain / wrench 6-vector is ``x = [u; w]`` = [linear; angular].
* ``hat(w)`` is the 3x3 skew matrix, ``hat6(x) = [[hat(w), u], [0, 0]]`` (the
  slides' tilde on R^6), ``ad(x) = [[hat(w), hat(u)], [0, hat(w)]]`` (the
  slides' hat on R^6), ``Ad(H) = [[R, hat(p) R], [0, R]]``.
* ``exp_se3(x) = expm(hat6(x))``; ``log_se3`` is its inverse for angles < pi.
* Tangent operators are **right-trivialised**, as in the slides:
  ``T(x) = sum_i (-ad(x))^i / (i+1)!`` so that
  ``d/dt exp(x(t)) = exp(x) hat6(T(x) xdot)``. The translation of
  ``exp_se3(x)`` is ``T_so3(w).T @ u``.
* Cayley map ``cay(x) = (I - hat6(x)/2)^-1 (I + hat6(x)/2)``.

Every function accepts a stack: inputs of shape (..., 3) / (..., 6) /
(..., 3, 3) / (..., 4, 4) and returns the matching (..., ) shapes. All maps
but the logarithms are written with analytic operations only (no abs, no
norm), so they accept complex input and can be differentiated by the
complex-step method.

Near theta = 0 the scalar coefficient functions switch to Taylor series whose
coefficients are generated exactly in :mod:`soft_twin_core._series`.
"""

import numpy as np

from soft_twin_core import _series

__all__ = [
    "hat", "vee", "hat6", "vee6", "ad", "coad", "Ad", "Ad_inv", "se3_inv",
    "se3_from_rp", "exp_so3", "log_so3", "T_so3", "T_so3_inv", "exp_se3",
    "log_se3", "T_se3", "T_se3_inv", "T_se3_dot", "cay_so3", "cay_se3",
    "T_cay_se3", "T_cay_se3_inv", "cayley_coordinates", "checked_rigid_transform",
]

# Below these angles the Taylor branches are used. Chosen so that the direct
# formulas, whose cancellation error grows like eps/theta^k, stay near 1e-14
# above them, while the (factorially decaying) series truncation is < 1e-20.
_SMALL = 0.25
_SMALL_DERIV = 0.5
_N_TERMS = 10
_N_TERMS_DERIV = 14


def _poly(coeffs):
    return np.array(coeffs[::-1])  # highest power first, for Horner


_P_A = _poly(_series.even_coefficients(_series.SERIES_A, _N_TERMS))
_P_B = _poly(_series.even_coefficients(_series.SERIES_B, _N_TERMS))
_P_C = _poly(_series.even_coefficients(_series.SERIES_C, _N_TERMS))
_P_D = _poly(_series.even_coefficients(_series.SERIES_D, _N_TERMS))
_P_T_OVER_SIN = _poly(_series.even_coefficients(_series.SERIES_T_OVER_SIN, _N_TERMS))
_P_BETA = tuple(_poly(_series.even_coefficients(b, _N_TERMS)) for b in _series.SERIES_BETA)
_P_DBETA = tuple(_poly(_series.even_coefficients(b, _N_TERMS_DERIV))
                 for b in _series.SERIES_DBETA)


def _horner(p, t2):
    out = np.full_like(t2, p[0])
    for c in p[1:]:
        out = out * t2 + c
    return out


def _theta(t2, limit):
    """(theta, small mask, safe theta) from theta^2; safe theta is 1 where small."""
    small = np.real(t2) < limit * limit
    t2_safe = np.where(small, 1.0, t2)
    return small, np.sqrt(t2_safe)


def _as_array(x, last, name):
    x = np.asarray(x)
    if x.dtype.kind not in "fc":
        x = x.astype(float)
    if x.shape[-1:] != (last,):
        raise ValueError(f"{name}: expected an array of shape (..., {last}), got {x.shape}")
    return x


def _as_matrices(m, n, name):
    m = np.asarray(m)
    if m.dtype.kind not in "fc":
        m = m.astype(float)
    if m.shape[-2:] != (n, n):
        raise ValueError(f"{name}: expected an array of shape (..., {n}, {n}), got {m.shape}")
    return m


def _sq(w):
    return np.sum(w * w, axis=-1)


# ----------------------------------------------------------------------------
# hat / vee / adjoints
# ----------------------------------------------------------------------------

def hat(w):
    """so(3) hat: (..., 3) -> (..., 3, 3) skew matrix with hat(a) @ b = a x b."""
    w = _as_array(w, 3, "hat")
    out = np.zeros(w.shape + (3,), dtype=w.dtype)
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee(W):
    """Inverse of :func:`hat`: (..., 3, 3) -> (..., 3) (uses the skew part)."""
    W = _as_matrices(W, 3, "vee")
    return 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2],
                           W[..., 0, 2] - W[..., 2, 0],
                           W[..., 1, 0] - W[..., 0, 1]], axis=-1)


def hat6(x):
    """se(3) tilde: (..., 6) [u; w] -> (..., 4, 4) [[hat(w), u], [0, 0]]."""
    x = _as_array(x, 6, "hat6")
    out = np.zeros(x.shape[:-1] + (4, 4), dtype=x.dtype)
    out[..., :3, :3] = hat(x[..., 3:])
    out[..., :3, 3] = x[..., :3]
    return out


def vee6(X):
    """Inverse of :func:`hat6`: (..., 4, 4) -> (..., 6) [u; w]."""
    X = _as_matrices(X, 4, "vee6")
    return np.concatenate([X[..., :3, 3], vee(X[..., :3, :3])], axis=-1)


def ad(x):
    """Adjoint of se(3) (the slides' hat on R^6): ad(x) y = vee6([hat6(x), hat6(y)]).

    ``ad(x) = [[hat(w), hat(u)], [0, hat(w)]]``, shape (..., 6, 6).
    """
    x = _as_array(x, 6, "ad")
    out = np.zeros(x.shape[:-1] + (6, 6), dtype=x.dtype)
    W = hat(x[..., 3:])
    out[..., :3, :3] = W
    out[..., 3:, 3:] = W
    out[..., :3, 3:] = hat(x[..., :3])
    return out


def coad(x):
    """Co-adjoint ``ad(x).T`` acting on wrenches [force; moment], shape (..., 6, 6)."""
    return np.swapaxes(ad(x), -1, -2)


def Ad(H):
    """Adjoint of SE(3): ``Ad(H) = [[R, hat(p) R], [0, R]]``, maps body twists
    at H to twists in the frame H is expressed in. (..., 4, 4) -> (..., 6, 6)."""
    H = _as_matrices(H, 4, "Ad")
    R, p = H[..., :3, :3], H[..., :3, 3]
    out = np.zeros(H.shape[:-2] + (6, 6), dtype=H.dtype)
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat(p) @ R
    return out


def Ad_inv(H):
    """``Ad(H)^-1 = Ad(H^-1) = [[R^T, -R^T hat(p)], [0, R^T]]`` without inversion."""
    H = _as_matrices(H, 4, "Ad_inv")
    Rt = np.swapaxes(H[..., :3, :3], -1, -2)
    p = H[..., :3, 3]
    out = np.zeros(H.shape[:-2] + (6, 6), dtype=H.dtype)
    out[..., :3, :3] = Rt
    out[..., 3:, 3:] = Rt
    out[..., :3, 3:] = -Rt @ hat(p)
    return out


def se3_inv(H):
    """Inverse of a homogeneous transform, ``[[R^T, -R^T p], [0, 1]]``."""
    H = _as_matrices(H, 4, "se3_inv")
    Rt = np.swapaxes(H[..., :3, :3], -1, -2)
    out = np.zeros_like(H)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, H[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def checked_rigid_transform(T, what, atol=1e-6):
    """``T`` as a float 4x4 rigid transform (a proper rotation to ``atol``,
    a finite position [m], the row [0, 0, 0, 1]); ValueError naming
    ``what`` else. The rotation is used as given (not re-orthonormalised)."""
    try:
        H = np.array(T, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected a 4x4 rigid transform, got {str(T)[:200]}") from None
    if H.shape != (4, 4) or not np.all(np.isfinite(H)):
        raise ValueError(f"{what}: expected a finite 4x4 rigid transform (rotation, position [m]), got "
                         f"{'shape ' + str(H.shape) if H.shape != (4, 4) else 'non-finite entries'}")
    R = H[:3, :3]
    if not np.allclose(H[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=atol) \
            or np.linalg.det(R) < 0:
        raise ValueError(f"{what}: not a rigid transform (its rotation is not orthonormal with determinant 1 "
                         f"to {atol:g}, or its last row is not [0, 0, 0, 1])")
    return H


def se3_from_rp(R, p):
    """Homogeneous transform from rotation (..., 3, 3) and position (..., 3)."""
    R = _as_matrices(R, 3, "se3_from_rp R")
    p = _as_array(p, 3, "se3_from_rp p")
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    out = np.zeros(shape + (4, 4), dtype=np.result_type(R, p))
    out[..., :3, :3] = R
    out[..., :3, 3] = p
    out[..., 3, 3] = 1.0
    return out


# ----------------------------------------------------------------------------
# SO(3)
# ----------------------------------------------------------------------------

def _so3_coeffs(t2):
    """a = sin t/t, b = (1-cos t)/t^2, c = (t - sin t)/t^3 with Taylor branches."""
    small, t = _theta(t2, _SMALL)
    s, co = np.sin(t), np.cos(t)
    a = np.where(small, _horner(_P_A, t2), s / t)
    b = np.where(small, _horner(_P_B, t2), (1.0 - co) / (t * t))
    c = np.where(small, _horner(_P_C, t2), (t - s) / (t * t * t))
    return a, b, c


def exp_so3(w):
    """Rodrigues: ``expm(hat(w)) = I + a W + b W^2``, (..., 3) -> (..., 3, 3)."""
    w = _as_array(w, 3, "exp_so3")
    W = hat(w)
    a, b, _ = _so3_coeffs(_sq(w))
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def T_so3(w):
    """Right tangent operator of SO(3): ``sum_i (-hat(w))^i/(i+1)! = I - b W + c W^2``.

    ``d/dt exp_so3(w) = exp_so3(w) hat(T_so3(w) wdot)``; ``T_so3(w).T`` is the
    left Jacobian (translation part of ``exp_se3``).
    """
    w = _as_array(w, 3, "T_so3")
    W = hat(w)
    _, b, c = _so3_coeffs(_sq(w))
    return np.eye(3) - b[..., None, None] * W + c[..., None, None] * (W @ W)


def _d_coeff(t2):
    """d = (1 - gamma)/t^2 with gamma = (t/2) cot(t/2); Taylor near 0."""
    small, t = _theta(t2, _SMALL)
    gamma = 0.5 * t * np.cos(0.5 * t) / np.sin(0.5 * t)
    return np.where(small, _horner(_P_D, t2), (1.0 - gamma) / (t * t))


def T_so3_inv(w):
    """Inverse of :func:`T_so3`: ``I + W/2 + d W^2``, d = (1 - (t/2)cot(t/2))/t^2.

    Defined for |w| < 2 pi."""
    w = _as_array(w, 3, "T_so3_inv")
    W = hat(w)
    d = _d_coeff(_sq(w))
    return np.eye(3) + 0.5 * W + d[..., None, None] * (W @ W)


def log_so3(R):
    """Inverse of :func:`exp_so3`: rotation vector with angle in [0, pi].

    theta = atan2(|vee(R)|, (tr R - 1)/2) (no arccos, accurate near 0 and pi);
    near pi the axis comes from the symmetric part ``(R + R^T)/2 = cos I +
    (1 - cos) n n^T``, with its sign taken from vee(R). Real input only.
    """
    R = _as_matrices(R, 3, "log_so3")
    s_vec = vee(R)                                   # sin(theta) * axis
    cos_t = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sin_t = np.sqrt(_sq(s_vec))
    theta = np.arctan2(sin_t, cos_t)
    t2 = theta * theta
    small = t2 < _SMALL * _SMALL
    factor = np.where(small, _horner(_P_T_OVER_SIN, t2), theta / np.where(small, 1.0, sin_t))
    w = factor[..., None] * s_vec
    near_pi = cos_t < -0.5
    if np.any(near_pi):
        S = 0.5 * (R + np.swapaxes(R, -1, -2)) - cos_t[..., None, None] * np.eye(3)
        k = np.argmax(np.diagonal(S, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(S, np.broadcast_to(k[..., None, None], S.shape[:-1] + (1,)),
                                 axis=-1)[..., 0]
        n = col / np.sqrt(_sq(col))[..., None]
        sign = np.where(np.sum(n * s_vec, axis=-1) < 0, -1.0, 1.0)
        w = np.where(near_pi[..., None], (sign * theta)[..., None] * n, w)
    return w


# ----------------------------------------------------------------------------
# SE(3)
# ----------------------------------------------------------------------------

def exp_se3(x):
    """``expm(hat6(x))`` in closed form: ``[[exp_so3(w), T_so3(w).T u], [0, 1]]``."""
    x = _as_array(x, 6, "exp_se3")
    u, w = x[..., :3], x[..., 3:]
    W = hat(w)
    W2 = W @ W
    a, b, c = _so3_coeffs(_sq(w))
    a, b, c = a[..., None, None], b[..., None, None], c[..., None, None]
    eye = np.eye(3)
    out = np.zeros(x.shape[:-1] + (4, 4), dtype=x.dtype)
    out[..., :3, :3] = eye + a * W + b * W2
    V = eye + b * W + c * W2                         # T_so3(w).T
    out[..., :3, 3] = np.einsum("...ij,...j->...i", V, u)
    out[..., 3, 3] = 1.0
    return out


def log_se3(H):
    """Inverse of :func:`exp_se3` for rotation angles in [0, pi]:
    ``[T_so3_inv(w).T p; w]`` with ``w = log_so3(R)``."""
    H = _as_matrices(H, 4, "log_se3")
    w = log_so3(H[..., :3, :3])
    Vinv_T = np.swapaxes(T_so3_inv(w), -1, -2)
    u = np.einsum("...ij,...j->...i", Vinv_T, H[..., :3, 3])
    return np.concatenate([u, w], axis=-1)


def _beta(t2):
    """Coefficients of T_se3 = I - b1 ad + b2 ad^2 - b3 ad^3 + b4 ad^4."""
    small, t = _theta(t2, _SMALL)
    s, c = np.sin(t), np.cos(t)
    direct = ((4.0 - t * s - 4.0 * c) / (2 * t**2),
              (4.0 * t - 5.0 * s + t * c) / (2 * t**3),
              (2.0 - t * s - 2.0 * c) / (2 * t**4),
              (2.0 * t - 3.0 * s + t * c) / (2 * t**5))
    return tuple(np.where(small, _horner(p, t2), d) for p, d in zip(_P_BETA, direct))


def _dbeta_over_theta(t2):
    """(d beta_k / d theta) / theta, k = 1..4."""
    small, t = _theta(t2, _SMALL_DERIV)
    s, c = np.sin(t), np.cos(t)
    N = (4.0 - t * s - 4.0 * c, 4.0 * t - 5.0 * s + t * c,
         2.0 - t * s - 2.0 * c, 2.0 * t - 3.0 * s + t * c)
    dN = (3.0 * s - t * c, 4.0 - 4.0 * c - t * s, s - t * c, 2.0 - 2.0 * c - t * s)
    out = []
    for k, (n, dn, p) in enumerate(zip(N, dN, _P_DBETA)):
        m = k + 2
        direct = (t * dn - m * n) / (2 * t ** (m + 2))
        out.append(np.where(small, _horner(p, t2), direct))
    return tuple(out)


def T_se3(x):
    """Right tangent operator of SE(3), ``sum_i (-ad(x))^i/(i+1)!``, (..., 6, 6).

    ``d/dt exp_se3(x) = exp_se3(x) hat6(T_se3(x) xdot)``. Closed form as a
    quartic in ad(x) (ad satisfies ad^5 + 2 t^2 ad^3 + t^4 ad = 0; Mueller,
    "Review of the exponential and Cayley map on SE(3)", 2021). The diagonal
    blocks equal T_so3(w).
    """
    x = _as_array(x, 6, "T_se3")
    A = ad(x)
    A2 = A @ A
    b1, b2, b3, b4 = (b[..., None, None] for b in _beta(_sq(x[..., 3:])))
    return np.eye(6) - b1 * A + b2 * A2 - b3 * (A2 @ A) + b4 * (A2 @ A2)


def T_se3_inv(x):
    """Inverse of :func:`T_se3`: ``[[Ti, -Ti Tuw Ti], [0, Ti]]``, Ti = T_so3_inv(w)."""
    x = _as_array(x, 6, "T_se3_inv")
    T = T_se3(x)
    Ti = T_so3_inv(x[..., 3:])
    out = np.zeros_like(T)
    out[..., :3, :3] = Ti
    out[..., 3:, 3:] = Ti
    out[..., :3, 3:] = -Ti @ T[..., :3, 3:] @ Ti
    return out


def T_se3_dot(x, xdot):
    """Time derivative of ``T_se3(x(t))`` given ``xdot = dx/dt``, (..., 6, 6).

    Differentiates the quartic form term by term:
    ``sum_k (+-)[beta_k' thetadot ad^k + beta_k sum_j ad^j ad(xdot) ad^(k-1-j)]``
    with ``beta_k' thetadot = (beta_k'/theta) (w . wdot)``.
    """
    x = _as_array(x, 6, "T_se3_dot x")
    xdot = _as_array(xdot, 6, "T_se3_dot xdot")
    A, Ad_ = ad(x), ad(xdot)
    A2 = A @ A
    A3 = A2 @ A
    t2 = _sq(x[..., 3:])
    wwd = np.sum(x[..., 3:] * xdot[..., 3:], axis=-1)
    betas = _beta(t2)
    dbetas = _dbeta_over_theta(t2)
    # derivatives of ad^k
    dA1 = Ad_
    dA2 = Ad_ @ A + A @ Ad_
    dA3 = dA2 @ A + A2 @ Ad_
    dA4 = dA3 @ A + A3 @ Ad_
    powers = (A, A2, A3, A2 @ A2)
    dpowers = (dA1, dA2, dA3, dA4)
    out = np.zeros(np.broadcast_shapes(A.shape, Ad_.shape), dtype=np.result_type(x, xdot))
    for k in range(4):
        sign = -1.0 if k % 2 == 0 else 1.0
        out = out + sign * ((dbetas[k] * wwd)[..., None, None] * powers[k]
                            + betas[k][..., None, None] * dpowers[k])
    return out


# ----------------------------------------------------------------------------
# Cayley map
# ----------------------------------------------------------------------------

def _inv_I_minus_half(w):
    """(I - hat(w)/2)^-1 = I + (2 W + W^2)/(4 + t^2)."""
    W = hat(w)
    k = 1.0 / (4.0 + _sq(w))[..., None, None]
    return np.eye(3) + k * (2.0 * W + W @ W)


def cay_so3(w):
    """Cayley map on SO(3): ``(I - W/2)^-1 (I + W/2) = I + 4/(4+t^2) (W + W^2/2)``."""
    w = _as_array(w, 3, "cay_so3")
    W = hat(w)
    k = (4.0 / (4.0 + _sq(w)))[..., None, None]
    return np.eye(3) + k * (W + 0.5 * (W @ W))


def cay_se3(x):
    """Cayley map on SE(3): ``(I - hat6(x)/2)^-1 (I + hat6(x)/2)``
    = ``[[cay_so3(w), (I - W/2)^-1 u], [0, 1]]``. Agrees with exp to 2nd order."""
    x = _as_array(x, 6, "cay_se3")
    out = np.zeros(x.shape[:-1] + (4, 4), dtype=x.dtype)
    out[..., :3, :3] = cay_so3(x[..., 3:])
    out[..., :3, 3] = np.einsum("...ij,...j->...i", _inv_I_minus_half(x[..., 3:]), x[..., :3])
    out[..., 3, 3] = 1.0
    return out


def T_cay_se3(x):
    """Right tangent operator of the Cayley map: ``d/dt cay(x) = cay(x) hat6(T xdot)``.

    From ``cay(X)^-1 dcay = (I + X/2)^-1 dX (I - X/2)^-1``:
    ``T = [[P, -P hat(Q u / 2)], [0, 4/(4+t^2) (I - W/2)]]`` with
    ``P = (I + W/2)^-1`` and ``Q = (I - W/2)^-1``.
    """
    x = _as_array(x, 6, "T_cay_se3")
    u, w = x[..., :3], x[..., 3:]
    P = _inv_I_minus_half(-w)
    Q = _inv_I_minus_half(w)
    k = (4.0 / (4.0 + _sq(w)))[..., None, None]
    out = np.zeros(x.shape[:-1] + (6, 6), dtype=x.dtype)
    out[..., :3, :3] = P
    out[..., :3, 3:] = -P @ hat(0.5 * np.einsum("...ij,...j->...i", Q, u))
    out[..., 3:, 3:] = k * (np.eye(3) - 0.5 * hat(w))
    return out


def T_cay_se3_inv(x):
    """Inverse of :func:`T_cay_se3`, exact block inverse:
    ``[[I + W/2, hat(Q u/2) Dinv], [0, Dinv]]`` with
    ``Dinv = I + W/2 + w w^T/4`` (inverse of ``4/(4+t^2) (I - W/2)``)."""
    x = _as_array(x, 6, "T_cay_se3_inv")
    u, w = x[..., :3], x[..., 3:]
    W = hat(w)
    eye = np.eye(3)
    D_inv = eye + 0.5 * W + 0.25 * np.einsum("...i,...j->...ij", w, w)
    q = 0.5 * np.einsum("...ij,...j->...i", _inv_I_minus_half(w), u)
    out = np.zeros(x.shape[:-1] + (6, 6), dtype=x.dtype)
    out[..., :3, :3] = eye + 0.5 * W
    out[..., 3:, 3:] = D_inv
    out[..., :3, 3:] = hat(q) @ D_inv
    return out


def cayley_coordinates(f):
    """Strain coordinates ``zeta`` with ``cay_se3(zeta) == exp_se3(f)`` exactly.

    Slides part C: ``zeta_w = lambda f_w`` with ``lambda = 2 tan(t/2)/t`` and
    ``zeta_u = (I - hat(zeta_w)/2) T_so3(f_w).T f_u`` (the slides' garbled
    ``tau lambda'`` term written out). Valid for rotation angles t < pi.
    """
    f = _as_array(f, 6, "cayley_coordinates")
    u, w = f[..., :3], f[..., 3:]
    t2 = _sq(w)
    small, t = _theta(t2, _SMALL)
    # 2 tan(t/2)/t = 1 + t^2/12 + t^4/120 + 17 t^6/20160 + 31 t^8/362880 + ...
    lam_series = 1.0 + t2 * (1 / 12 + t2 * (1 / 120 + t2 * (17 / 20160 + t2 * (31 / 362880
                             + t2 * (691 / 79833600)))))
    lam = np.where(small, lam_series, 2.0 * np.tan(0.5 * t) / t)
    zw = lam[..., None] * w
    V = np.swapaxes(T_so3(w), -1, -2)
    p = np.einsum("...ij,...j->...i", V, u)
    zu = p - 0.5 * np.cross(zw, p)
    return np.concatenate([zu, zw], axis=-1)


def rotation_with_z(z):
    """A rotation matrix whose third column is the unit vector z (its x axis
    normal to z and to world x, or to world y when z is near x)."""
    z = np.asarray(z, dtype=float)
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])
