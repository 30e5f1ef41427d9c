"""Inverse kinematics: closed forms (one section, constant curvature) and a
general damped least-squares (Levenberg-Marquardt) solver over the free
strain modes (slides part B "Inverse kinematics", part C "Soft continuum arm
with constant curvature").
"""

from dataclasses import dataclass

import numpy as np

from . import kinematics as kin
from . import lie


def one_section_strain(H_start, H_end, length):
    """Strain f [1/m] of one section taking H_start to H_end over ``length`` m:
    ``f = log_se3(H_start^-1 H_end) / L`` (rotation angle below pi)."""
    return lie.log_se3(lie.se3_inv(H_start) @ H_end) / length


def constant_curvature_from_tip(p_base):
    """Arc parameters of the constant-curvature arc from the base origin,
    tangent to the base x axis, through the point ``p_base`` (base frame, m).

    Returns (kappa [1/m], phi [rad], arc_length [m], bending [w_x, w_y, w_z]
    per unit length) with the bending plane at angle phi from the y axis
    about x: tip = [sin(k s)/k, cos(phi)(1-cos(k s))/k, sin(phi)(1-cos(k s))/k],
    w = kappa [0, -sin(phi), cos(phi)].
    """
    p = np.asarray(p_base, dtype=float)
    r = np.hypot(p[1], p[2])
    if r < 1e-15:
        if p[0] <= 0:
            raise ValueError(f"p_base: {p} is not reachable by an arc tangent to +x")
        return 0.0, 0.0, float(p[0]), np.zeros(3)
    phi = np.arctan2(p[2], p[1])
    rho = (p[0] ** 2 + r**2) / (2 * r)          # radius of the circle
    kappa = 1.0 / rho
    angle = np.arctan2(p[0], rho - r)           # subtended angle in (0, 2 pi)
    if angle < 0:
        angle += 2 * np.pi
    arc = rho * angle
    w = kappa * np.array([0.0, -np.sin(phi), np.cos(phi)])
    return float(kappa), float(phi), float(arc), w


def _fast_tip(model):
    """The compiled tip pose + spatial Jacobian, if numba is available."""
    if model.kinematic_map != "exponential":
        return None
    try:
        from . import _fast
    except ImportError:
        return None
    return _fast.tip_and_spatial_jacobian


@dataclass
class IKResult:
    """q: free-mode strains found; success: both errors within tolerance;
    position_error [m], orientation_error [rad] of the achieved tip;
    iterations; achieved_pose (4x4 world); message."""
    q: np.ndarray
    success: bool
    position_error: float
    orientation_error: float
    iterations: int
    achieved_pose: np.ndarray
    message: str


def _errors(g, target):
    dp = target[:3, 3] - g[:3, 3]
    dR = lie.log_so3(g[:3, :3].T @ target[:3, :3])
    return float(np.sqrt(dp @ dp)), float(np.sqrt(dR @ dR))


def solve_ik(model, target, q_init=None, *, position_only=False, weights=None,
             lower=None, upper=None, tol_position=1e-8, tol_orientation=1e-8,
             max_iterations=200, initial_damping=1e-3):
    """Tip inverse kinematics by Levenberg-Marquardt on the SE(3) log error.

    target: world pose (4x4) of the tip, or a 3-vector position with
    ``position_only``. Full pose error ``e = log(g^-1 g_target)`` (tip body
    frame) with Jacobian ``-T_se3_inv(-e) J_body``; position error
    ``p_target - p`` with ``-R J_v``. weights: 6 (or 3) non-negative weights
    of the error components. lower/upper: bounds on q (projected). Never
    raises for unreachable targets: returns the best pose, success False.
    """
    target = np.asarray(target, dtype=float)
    if position_only and target.shape == (3,):
        T = np.eye(4)
        T[:3, 3] = target
        target = T
    if target.shape != (4, 4) or not np.all(np.isfinite(target)):
        raise ValueError(f"target: expected a finite 4x4 pose (or 3-vector with position_only), "
                         f"got shape {target.shape}")
    q = model.q0.copy() if q_init is None else model.check_q(np.array(q_init, dtype=float), "q_init")
    m = 3 if position_only else 6
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (m,) or np.any(w < 0):
        raise ValueError(f"weights: expected {m} non-negative numbers, got {weights!r}")
    lo = -np.inf if lower is None else np.asarray(lower, dtype=float)
    hi = np.inf if upper is None else np.asarray(upper, dtype=float)
    q = np.clip(q, lo, hi)

    fast = _fast_tip(model)

    def residual(q):
        if fast is not None:
            g, Js = fast(model, q)
        else:
            ch = kin.chain(model, q)
            g = ch.g_tip
            Wt = np.swapaxes(ch.W, -3, -2)
            Js = Wt.reshape(6, 6 * model.n_sections)[:, model.free_index]
        if position_only:
            e = target[:3, 3] - g[:3, 3]
        else:
            e = lie.log_se3(lie.se3_inv(g) @ target)
        return g, e, Js

    def jac(g, e, Js):
        Jb = lie.Ad_inv(g) @ Js
        if position_only:
            return -g[:3, :3] @ Jb[:3]
        return -lie.T_se3_inv(-e) @ Jb

    g, e, ch = residual(q)
    cost = float(e @ (w * e))
    lam = initial_damping
    it = 0
    message = "max iterations reached"
    for it in range(1, max_iterations + 1):
        pe, oe = _errors(g, target)
        if pe <= tol_position and (position_only or oe <= tol_orientation):
            it -= 1
            message = "converged"
            break
        Je = jac(g, e, ch)
        A = Je.T @ (w[:, None] * Je)
        b = -Je.T @ (w * e)
        improved = False
        for _ in range(12):
            step = np.linalg.solve(A + lam * (np.diag(np.diag(A)) + 1e-9 * np.eye(len(q))), b)
            q_new = np.clip(q + step, lo, hi)
            g_new, e_new, ch_new = residual(q_new)
            cost_new = float(e_new @ (w * e_new))
            if np.isfinite(cost_new) and cost_new < cost:
                q, g, e, ch, cost = q_new, g_new, e_new, ch_new, cost_new
                lam = max(lam / 5.0, 1e-12)
                improved = True
                break
            lam *= 8.0
        if not improved:
            message = "stalled: no step reduces the error (target unreachable or at a bound)"
            break
    pe, oe = _errors(g, target)
    success = pe <= tol_position and (position_only or oe <= tol_orientation)
    if success:
        message = "converged"
    return IKResult(q, success, pe, oe, it, g, message)


@dataclass
class ActuationIKResult:
    """u: actuator inputs found (N / Pa); q: the equilibrium they produce;
    success, position_error [m], orientation_error [rad], iterations,
    achieved_pose, message (as IKResult)."""
    u: np.ndarray
    q: np.ndarray
    success: bool
    position_error: float
    orientation_error: float
    iterations: int
    achieved_pose: np.ndarray
    message: str


def solve_actuation_ik(model, target, u_init=None, q_init=None, *, loads=None, position_only=False,
                       weights=None, u_max=None, tol_position=1e-8, tol_orientation=1e-8,
                       max_iterations=50):
    """Inverse kinematics over the actuator inputs, through statics: find
    u (tendon tensions >= 0, chamber pressures) whose static equilibrium
    under ``loads`` (default gravity) puts the tip at ``target``.

    Levenberg-Marquardt on the tip error e(q(u)) with the sensitivity of the
    equilibrium ``dq/du = Kt^-1 B`` (Kt: statics tangent, B = d tau / d u,
    exact since tau is linear in u). Each evaluation is a warm-started
    statics solve. Targets the actuators cannot reach return the closest
    equilibrium found with success False.
    """
    from . import statics as st
    from .loads import Loads, actuation_force
    loads = Loads() if loads is None else loads
    n_act = len(model.actuators)
    if n_act == 0:
        raise ValueError("solve_actuation_ik: this robot has no actuators")
    target = np.asarray(target, dtype=float)
    if position_only and target.shape == (3,):
        T = np.eye(4)
        T[:3, 3] = target
        target = T
    if target.shape != (4, 4) or not np.all(np.isfinite(target)):
        raise ValueError(f"target: expected a finite 4x4 pose (or 3-vector with position_only), "
                         f"got shape {target.shape}")
    lo = np.array([0.0 if a.kind == "tendon" else -np.inf for a in model.actuators])
    hi = np.full(n_act, np.inf) if u_max is None else np.broadcast_to(np.asarray(u_max, float), (n_act,))
    u = np.zeros(n_act) if u_init is None else st.actuation_vector(model, u_init).copy()
    u = np.clip(u, lo, hi)
    m_err = 3 if position_only else 6
    w = np.ones(m_err) if weights is None else np.asarray(weights, dtype=float)

    def evaluate(u, q_start):
        r = st.solve_statics(model, u, loads, q_init=q_start)
        g = r.tip_pose
        e = target[:3, 3] - g[:3, 3] if position_only else lie.log_se3(lie.se3_inv(g) @ target)
        return r.q, g, e

    q, g, e = evaluate(u, q_init)
    cost = float(e @ (w * e))
    lam, it, message = 1e-3, 0, "max iterations reached"
    for it in range(1, max_iterations + 1):
        pe, oe = _errors(g, target)
        if pe <= tol_position and (position_only or oe <= tol_orientation):
            it -= 1
            break
        ch = kin.chain(model, q)
        B = np.stack([actuation_force(model, ch, ek) for ek in np.eye(n_act)], axis=1)
        Kt = st._fast_tangent(model, q, u, loads)
        dq_du = np.linalg.solve(Kt, B)
        Jb = kin.tip_jacobian(model, q)
        Je = (-g[:3, :3] @ Jb[:3]) if position_only else (-lie.T_se3_inv(-e) @ Jb)
        Ju = Je @ dq_du
        A = Ju.T @ (w[:, None] * Ju)
        b = -Ju.T @ (w * e)
        scale_u = np.maximum(np.abs(np.diag(A)), 1e-300)
        improved = False
        for _ in range(12):
            step = np.linalg.solve(A + lam * np.diag(scale_u), b)
            u_new = np.clip(u + step, lo, hi)
            try:
                q_new, g_new, e_new = evaluate(u_new, q)
            except st.StaticsError:
                lam *= 8.0
                continue
            cost_new = float(e_new @ (w * e_new))
            if cost_new < cost:
                u, q, g, e, cost = u_new, q_new, g_new, e_new, cost_new
                lam = max(lam / 5.0, 1e-12)
                improved = True
                break
            lam *= 8.0
        if not improved:
            message = "stalled: the actuators cannot bring the tip closer (target not reachable by actuation)"
            break
    pe, oe = _errors(g, target)
    success = pe <= tol_position and (position_only or oe <= tol_orientation)
    return ActuationIKResult(u, q, success, pe, oe, it, g, "converged" if success else message)
