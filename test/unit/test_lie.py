"""Lie-group toolkit against its definitions: expm/logm, power series,
finite differences, matrix inverses (issue 3)."""

from math import factorial

import numpy as np
import pytest
import scipy.linalg as sla
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from soft_twin_core import lie

ANGLES = [0.0, 1e-9, 1e-4, 0.1, 0.2499, 0.2501, 0.4999, 0.5001, 1.0, 2.5,
          np.pi - 1e-6]
RNG = np.random.default_rng(1234)


def twist_with_angle(theta, rng=RNG, scale_u=1.0):
    x = rng.normal(size=6)
    x[:3] *= scale_u
    n = np.linalg.norm(x[3:])
    x[3:] *= theta / n
    return x


def power_series_T(x, n=60):
    """T(x) = sum_i (-ad x)^i/(i+1)! by its definition (slides part B)."""
    A = lie.ad(x)
    out, P = np.zeros((6, 6)), np.eye(6)
    for i in range(n):
        out += P / factorial(i + 1)
        P = P @ (-A)
    return out


def central_diff(f, x, y, h=1e-6):
    return (f(x + h * y) - f(x - h * y)) / (2 * h)


finite6 = arrays(np.float64, 6, elements=st.floats(-3, 3, allow_nan=False))
rot_vec = arrays(np.float64, 3, elements=st.floats(-1.8, 1.8, allow_nan=False))


# --- hat / vee / adjoints --------------------------------------------------

def test_hat_is_cross_product_and_vee_inverts():
    a, b = RNG.normal(size=(2, 3))
    assert np.allclose(lie.hat(a) @ b, np.cross(a, b), atol=1e-15)
    assert np.allclose(lie.vee(lie.hat(a)), a)
    x = RNG.normal(size=6)
    assert np.allclose(lie.vee6(lie.hat6(x)), x)


def test_ad_is_lie_bracket():
    x, y = RNG.normal(size=(2, 6))
    X, Y = lie.hat6(x), lie.hat6(y)
    assert np.allclose(lie.hat6(lie.ad(x) @ y), X @ Y - Y @ X, atol=1e-14)
    assert np.allclose(lie.coad(x), lie.ad(x).T)


@settings(max_examples=60, deadline=None)
@given(finite6, finite6, finite6)
def test_Ad_homomorphism_and_conjugation(x1, x2, y):
    H1, H2 = lie.exp_se3(x1), lie.exp_se3(x2)
    assert np.allclose(lie.Ad(H1 @ H2), lie.Ad(H1) @ lie.Ad(H2), atol=1e-10)
    A = lie.Ad(H1)
    assert np.allclose(A @ lie.ad(y) @ np.linalg.inv(A), lie.ad(A @ y), atol=1e-9)
    assert np.allclose(lie.Ad_inv(H1), np.linalg.inv(A), atol=1e-10)
    # Ad is the matrix of conjugation: H hat6(y) H^-1 = hat6(Ad(H) y)
    assert np.allclose(H1 @ lie.hat6(y) @ lie.se3_inv(H1), lie.hat6(A @ y), atol=1e-10)
    assert np.allclose(lie.se3_inv(H1), np.linalg.inv(H1), atol=1e-10)


# --- exp / log ---------------------------------------------------------------

@pytest.mark.parametrize("theta", ANGLES)
def test_exp_se3_equals_expm(theta):
    for _ in range(5):
        x = twist_with_angle(theta)
        assert np.abs(lie.exp_se3(x) - sla.expm(lie.hat6(x))).max() < 1e-12
        assert np.abs(lie.exp_so3(x[3:]) - sla.expm(lie.hat(x[3:]))).max() < 1e-12


@pytest.mark.parametrize("theta", ANGLES)
def test_log_inverts_exp(theta):
    for _ in range(5):
        x = twist_with_angle(theta)
        assert np.abs(lie.log_se3(lie.exp_se3(x)) - x).max() < 1e-12
        assert np.abs(lie.log_so3(lie.exp_so3(x[3:])) - x[3:]).max() < 1e-12


@pytest.mark.parametrize("theta", [1e-4, 0.3, 1.0, 2.5])
def test_log_se3_equals_logm(theta):
    x = twist_with_angle(theta)
    H = lie.exp_se3(x)
    assert np.abs(lie.hat6(lie.log_se3(H)) - sla.logm(H).real).max() < 1e-10


def test_log_near_pi_is_accurate():
    """The arccos formula loses ~sqrt(eps) there; ours must not."""
    for d in [1e-3, 1e-6, 1e-8]:
        x = twist_with_angle(np.pi - d)
        err = np.abs(lie.log_so3(lie.exp_so3(x[3:])) - x[3:]).max()
        assert err < 1e-9, (d, err)
    # at exactly pi the result is a rotation vector of length pi giving back R
    R = lie.exp_so3(np.array([0.0, 0.0, np.pi]))
    w = lie.log_so3(R)
    assert np.isclose(np.linalg.norm(w), np.pi)
    assert np.abs(lie.exp_so3(w) - R).max() < 1e-12


@settings(max_examples=80, deadline=None)
@given(finite6)
def test_exp_log_roundtrip_group(x):
    H = lie.exp_se3(x)
    assert np.abs(lie.exp_se3(lie.log_se3(H)) - H).max() < 1e-10
    if np.linalg.norm(x[3:]) < np.pi - 1e-3:
        assert np.abs(lie.log_se3(H) - x).max() < 1e-10


def test_batched_shapes_match_single():
    xs = RNG.normal(size=(4, 5, 6))
    H = lie.exp_se3(xs)
    assert H.shape == (4, 5, 4, 4)
    assert np.allclose(H[2, 3], lie.exp_se3(xs[2, 3]))
    assert lie.T_se3(xs).shape == (4, 5, 6, 6)
    assert lie.log_se3(H).shape == (4, 5, 6)
    assert lie.Ad(H).shape == (4, 5, 6, 6)
    with pytest.raises(ValueError, match=r"expected an array of shape \(\.\.\., 6\), got \(5,\)"):
        lie.exp_se3(np.zeros(5))


# --- tangent operators ----------------------------------------------------

@pytest.mark.parametrize("theta", ANGLES)
def test_T_se3_equals_power_series_and_inverse(theta):
    for _ in range(5):
        x = twist_with_angle(theta)
        T = lie.T_se3(x)
        assert np.abs(T - power_series_T(x)).max() < 1e-12
        assert np.abs(lie.T_se3_inv(x) @ T - np.eye(6)).max() < 1e-12
        assert np.abs(T[:3, :3] - lie.T_so3(x[3:])).max() < 1e-14
        assert np.abs(lie.T_so3_inv(x[3:]) @ lie.T_so3(x[3:]) - np.eye(3)).max() < 1e-12


@pytest.mark.parametrize("theta", ANGLES)
def test_T_se3_linearises_exp(theta):
    """d/dt exp(x + t y) = exp(x) hat6(T(x) y), central differences."""
    for _ in range(3):
        x = twist_with_angle(theta)
        y = RNG.normal(size=6)
        fd = central_diff(lie.exp_se3, x, y)
        an = lie.exp_se3(x) @ lie.hat6(lie.T_se3(x) @ y)
        assert np.abs(fd - an).max() < 1e-7


@pytest.mark.parametrize("theta", ANGLES)
def test_T_se3_dot_is_derivative_of_T(theta):
    for _ in range(3):
        x = twist_with_angle(theta)
        y = RNG.normal(size=6)
        fd = central_diff(lie.T_se3, x, y)
        assert np.abs(fd - lie.T_se3_dot(x, y)).max() < 1e-7


def test_T_se3_dot_complex_step_exact():
    """Complex step gives machine-precision directional derivatives."""
    for theta in [1e-3, 0.3, 0.7, 2.0]:
        x, y = twist_with_angle(theta), RNG.normal(size=6)
        cs = lie.T_se3(x + 1e-30j * y).imag / 1e-30
        assert np.abs(cs - lie.T_se3_dot(x, y)).max() < 1e-12


def test_taylor_branches_are_continuous():
    """Each side of every switch agrees (catches wrong series coefficients)."""
    from soft_twin_core.lie import _beta, _dbeta_over_theta, _so3_coeffs, _d_coeff
    for limit, fns in [(lie._SMALL, (_beta, _so3_coeffs, lambda t2: (_d_coeff(t2),))),
                       (lie._SMALL_DERIV, (_dbeta_over_theta,))]:
        lo, hi = np.array([(limit * (1 - 1e-13)) ** 2]), np.array([(limit * (1 + 1e-13)) ** 2])
        for fn in fns:
            for a, b in zip(fn(lo), fn(hi)):
                assert np.abs(a - b).max() < 1e-12 * max(1, np.abs(a).max())


# --- Cayley ----------------------------------------------------------------

@pytest.mark.parametrize("theta", ANGLES)
def test_cayley_equals_matrix_definition(theta):
    x = twist_with_angle(theta)
    X = lie.hat6(x)
    ref = np.linalg.inv(np.eye(4) - X / 2) @ (np.eye(4) + X / 2)
    assert np.abs(lie.cay_se3(x) - ref).max() < 1e-12
    W = lie.hat(x[3:])
    ref3 = np.linalg.inv(np.eye(3) - W / 2) @ (np.eye(3) + W / 2)
    assert np.abs(lie.cay_so3(x[3:]) - ref3).max() < 1e-12


def test_cayley_agrees_with_exp_to_third_order():
    """|cay(e x) - exp(e x)| = O(e^3): halving e divides it by 8, to 0.01 in
    the exponent at e = 1e-2 .. 2.5e-3 for every twist (the next term,
    O(e^2) relative, made it 2.89 at e = 0.1 for some). Its own generator:
    the module's draws depend on the tests run before."""
    x = np.random.default_rng(7).normal(size=6)
    errs = [np.abs(lie.cay_se3(e * x) - lie.exp_se3(e * x)).max() for e in (1e-2, 5e-3, 2.5e-3)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(orders - 3.0) < 0.05), orders


@pytest.mark.parametrize("theta", ANGLES)
def test_cayley_tangent_and_inverse(theta):
    x, y = twist_with_angle(theta), RNG.normal(size=6)
    fd = central_diff(lie.cay_se3, x, y)
    an = lie.cay_se3(x) @ lie.hat6(lie.T_cay_se3(x) @ y)
    assert np.abs(fd - an).max() < 1e-7
    assert np.abs(lie.T_cay_se3_inv(x) @ lie.T_cay_se3(x) - np.eye(6)).max() < 1e-12


@pytest.mark.parametrize("theta", ANGLES[:-1] + [3.0])
def test_cayley_coordinates_reproduce_exp_exactly(theta):
    x = twist_with_angle(theta)
    zeta = lie.cayley_coordinates(x)
    tol = 1e-12 * max(1.0, np.linalg.norm(zeta))
    assert np.abs(lie.cay_se3(zeta) - lie.exp_se3(x)).max() < tol


def test_helix_example_strains_cayley_slides():
    """Slides part C: planar bending f = [1,0,0,0,0,K]; exp and cay differ but
    cay of the changed coordinates equals exp."""
    for K in np.linspace(np.pi / 10, np.pi * 0.99, 5):
        f = np.array([1.0, 0, 0, 0, 0, K])
        assert np.abs(lie.cay_se3(lie.cayley_coordinates(f)) - lie.exp_se3(f)).max() < 1e-10


@pytest.mark.parametrize("angle", [0.05, 0.4, 1.3, 3.0])     # Taylor and closed-form branches
def test_compiled_T_dot_along_a_pcs_point_is_the_derivative_of_T(angle):
    """kernels.spatial._T_dot_along(x, X, Y) = d/dt T_se3(X(t)) Y at
    Xdot = x Y (a PCS point: X = x f, Xdot = x fdot, Y = fdot): against a
    central difference of lie.T_se3 and the general compiled _T_dot_into."""
    from soft_twin_core.engine.kernels import spatial as sp
    rng = np.random.default_rng(3)
    x = 0.07
    f = rng.standard_normal(6)
    f[3:] *= angle / (x * np.linalg.norm(f[3:]))
    Y = rng.standard_normal(6) * [0.3, 0.3, 0.3, 4.0, 4.0, 4.0]
    X = x * f
    got = np.array(sp._T_dot_along(x, tuple(X), tuple(Y)))
    h = 1e-6
    fd = (lie.T_se3(X + h * x * Y) - lie.T_se3(X - h * x * Y)) @ Y / (2 * h)
    assert np.abs(got - fd).max() < 1e-7 * max(1.0, np.abs(fd).max())
    general = np.empty(6)
    sp._T_dot_into(X, x * Y, Y, general, np.empty((5, 6)), np.empty(6), np.empty(6), np.empty(6))
    assert np.abs(got - general).max() < 1e-13 * max(1.0, np.abs(general).max())
