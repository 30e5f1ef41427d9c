"""Exact Taylor coefficients of the scalar functions of theta used by the Lie maps.

The closed forms of exp/log/tangent operators divide small differences by
powers of theta and lose accuracy near theta = 0. There we switch to Taylor
series in theta**2. Rather than typing coefficients by hand, they are derived
here once, at import, with exact rational arithmetic from the very numerators
the closed forms use, so the two branches cannot disagree by a typo.
"""

from fractions import Fraction
from math import factorial

_ORDER = 48  # number of coefficients of theta kept in the working series


def _sin():
    return [Fraction((-1) ** ((k - 1) // 2), factorial(k)) if k % 2 else Fraction(0)
            for k in range(_ORDER)]


def _cos():
    return [Fraction((-1) ** (k // 2), factorial(k)) if k % 2 == 0 else Fraction(0)
            for k in range(_ORDER)]


def _theta():
    s = [Fraction(0)] * _ORDER
    s[1] = Fraction(1)
    return s


def _const(c):
    s = [Fraction(0)] * _ORDER
    s[0] = Fraction(c)
    return s


def _add(*terms):
    return [sum(cs, Fraction(0)) for cs in zip(*terms)]


def _scale(a, c):
    return [Fraction(c) * x for x in a]


def _mul(a, b):
    out = [Fraction(0)] * _ORDER
    for i, x in enumerate(a):
        if x:
            for j in range(_ORDER - i):
                out[i + j] += x * b[j]
    return out


def _div(a, b):
    """Series division a / b (b[0] != 0)."""
    out = [Fraction(0)] * _ORDER
    rem = list(a)
    for k in range(_ORDER):
        out[k] = rem[k] / b[0]
        for j in range(k, _ORDER):
            rem[j] -= out[k] * b[j - k]
    return out


def _shift(a, m):
    """Divide by theta**m; the dropped low coefficients must vanish exactly."""
    assert all(x == 0 for x in a[:m]), "numerator does not vanish to the expected order"
    return a[m:] + [Fraction(0)] * m


def _derivative_over_theta(a):
    """Series of f'(theta)/theta for an even series f."""
    d = [Fraction(k) * a[k] for k in range(1, _ORDER)] + [Fraction(0)]
    return _shift(d, 1)


def even_coefficients(a, n_terms):
    """Coefficients c_k of sum_k c_k (theta**2)**k, as floats (lowest first)."""
    assert all(a[k] == 0 for k in range(1, 2 * n_terms, 2)), "series is not even"
    return tuple(float(a[2 * k]) for k in range(n_terms))


S, C, TH = _sin(), _cos(), _theta()
ONE = _const(1)

# SO(3): exp = I + a W + b W^2, T = I - b W + c W^2, T^-1 = I + W/2 + d W^2
SERIES_A = _shift(S, 1)                                            # sin t / t
SERIES_B = _shift(_add(ONE, _scale(C, -1)), 2)                     # (1 - cos t) / t^2
SERIES_C = _shift(_add(TH, _scale(S, -1)), 3)                      # (t - sin t) / t^3
# gamma = (t/2) cot(t/2) = t sin t / (2 (1 - cos t));  d = (1 - gamma) / t^2
_GAMMA = _div(_shift(_mul(TH, S), 2), _scale(_shift(_add(ONE, _scale(C, -1)), 2), 2))
SERIES_GAMMA = _GAMMA
SERIES_D = _shift(_add(ONE, _scale(_GAMMA, -1)), 2)
# log_SO3: theta / sin theta
SERIES_T_OVER_SIN = _div(ONE, SERIES_A)
# derivatives over theta (for time derivatives of the SO(3) tangent operator)
SERIES_DB = _derivative_over_theta(SERIES_B)
SERIES_DC = _derivative_over_theta(SERIES_C)

# SE(3): T(x) = I - b1 ad + b2 ad^2 - b3 ad^3 + b4 ad^4 (right-trivialised,
# T = sum_i (-ad)^i/(i+1)!), numerators N_k over 2 theta^m_k.
_N1 = _add(_const(4), _scale(_mul(TH, S), -1), _scale(C, -4))       # m = 2
_N2 = _add(_scale(TH, 4), _scale(S, -5), _mul(TH, C))                # m = 3
_N3 = _add(_const(2), _scale(_mul(TH, S), -1), _scale(C, -2))       # m = 4
_N4 = _add(_scale(TH, 2), _scale(S, -3), _mul(TH, C))                # m = 5
SERIES_BETA = tuple(_scale(_shift(n, m), Fraction(1, 2))
                    for n, m in ((_N1, 2), (_N2, 3), (_N3, 4), (_N4, 5)))
SERIES_DBETA = tuple(_derivative_over_theta(b) for b in SERIES_BETA)
