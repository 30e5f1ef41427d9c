"""Inverse kinematics of shapes: closed forms (one section, constant
curvature) and a general damped least-squares (Levenberg-Marquardt) solver
over a robot's joint coordinates for any frame (:func:`frame_ik`; the
classic robot's tip: :func:`solve_ik`) (slides part B "Inverse
kinematics", part C "Soft continuum arm with constant curvature"). The IK
through statics, over the actuator inputs and joint commands, is the
planner's sample solve (:class:`planner.TipSolver`).
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core import lie
from soft_twin_core._blas import one_blas_thread
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.frames import spatial_jacobian
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.planning.planner import bounded_gauss_newton_step
from soft_twin_core.robot.mechanism import from_robot_model


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


def _target_pose(target, position_only):
    """4x4 target from a pose, or from a 3-vector with position_only."""
    target = np.asarray(target, dtype=float)
    if position_only and target.shape == (3,):
        T = np.eye(4)
        T[:3, 3] = target
        target = T
    if target.shape != (4, 4) or not np.all(np.isfinite(target)):
        raise ValueError(f"target: expected a finite 4x4 pose (or 3-vector with position_only), "
                         f"got shape {target.shape}")
    return target


def _weights(weights, position_only):
    m = 3 if position_only else 6
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (m,) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError(f"weights: expected {m} non-negative numbers, got {weights!r}")
    return w


def _tip_error(g, target, position_only):
    """Position error p_target - p (world) or the SE(3) log error
    log(g^-1 g_target) (tip body frame)."""
    if position_only:
        return target[:3, 3] - g[:3, 3]
    return lie.log_se3(lie.se3_inv(g) @ target)


def _error_jacobian(g, e, J_body, position_only):
    """d e / d(body twist of the tip): -R J_v, or -T_se3_inv(-e) J_body."""
    if position_only:
        return -g[:3, :3] @ J_body[:3]
    return -lie.T_se3_inv(-e) @ J_body


def _levenberg_marquardt(x, lo, hi, evaluate, jacobian, done, w, max_iterations, lam=1e-3):
    """Bounded Levenberg-Marquardt with Marquardt's diagonal scaling.

    With finite bounds each trial step is the exact minimiser of the damped
    linear model inside the box (the compiled BVLS of the planner,
    :func:`planner.bounded_gauss_newton_step`): a variable at a bound whose
    descent points out of the box is held there and the others are solved
    without it (a merely projected step can fail to descend there). With
    no finite bound, the plain damped normal equations.

    evaluate(x, previous) -> (data, e) (may raise to reject a step);
    jacobian(x, data, e) -> de/dx; done(data) -> bool. Returns
    (x, data, iterations, message)."""
    lo_b = np.broadcast_to(np.asarray(lo, dtype=float), x.shape)
    hi_b = np.broadcast_to(np.asarray(hi, dtype=float), x.shape)
    boxed = bool(np.any(np.isfinite(lo_b)) or np.any(np.isfinite(hi_b)))
    if boxed:
        sw = np.sqrt(w)
    data, e = evaluate(x, None)
    cost = float(e @ (w * e))
    it, message = 0, "max iterations reached"
    for it in range(1, max_iterations + 1):
        if done(data):
            return x, data, it - 1, "converged"
        Je = jacobian(x, data, e)
        A = Je.T @ (w[:, None] * Je)
        b = -Je.T @ (w * e)
        dA = np.maximum(np.diag(A), 1e-12 * max(np.abs(np.diag(A)).max(), 1e-300))
        D = np.diag(dA)
        improved = False
        for _ in range(12):
            if boxed:
                dx, all_held = bounded_gauss_newton_step(sw[:, None] * Je, sw * e, x, lo_b, hi_b, np.sqrt(dA),
                                                         0.0, x, lam)
                if all_held:
                    break
                x_new = np.clip(x + dx, lo, hi)
            else:
                x_new = np.clip(x + np.linalg.solve(A + lam * D, b), lo, hi)
            try:
                data_new, e_new = evaluate(x_new, data)
            except (ArithmeticError, RuntimeError, np.linalg.LinAlgError):
                lam *= 8.0
                continue
            cost_new = float(e_new @ (w * e_new))
            if np.isfinite(cost_new) and cost_new < cost:
                x, data, e, cost = x_new, data_new, e_new, cost_new
                lam = max(lam / 5.0, 1e-12)
                improved = True
                break
            lam *= 8.0
        if not improved:
            message = "stalled: no step reduces the error (target unreachable or at a bound)"
            break
    if done(data):
        message = "converged"
    return x, data, it, message


def solve_ik(model, target, q_init=None, *, position_only=False, weights=None,
             lower=None, upper=None, tol_position=1e-8, tol_orientation=1e-8,
             max_iterations=200, initial_damping=1e-3):
    """Tip inverse kinematics of a classic robot (:class:`model.RobotModel`)
    over its strains: :func:`frame_ik` of its tip.

    target: world pose (4x4) of the tip, or a 3-vector position with
    ``position_only``. Never raises for unreachable targets: returns the
    best pose, success False."""
    mech = model.__dict__.get("_ik_mechanism")
    if mech is None:
        mech = from_robot_model(model)
        object.__setattr__(model, "_ik_mechanism", mech)
    return frame_ik(mech, "tip", target, q_init, position_only=position_only, weights=weights, lower=lower,
                    upper=upper, tol_position=tol_position, tol_orientation=tol_orientation,
                    max_iterations=max_iterations, initial_damping=initial_damping)


# ----------------------------------------------------------------------------
# Shape IK of a frame of any robot (the node's answer for a robot without inputs)
# ----------------------------------------------------------------------------

IK_STATUS = {"at_limit": "a bound blocks (a tension at 0 or its limit, a joint at its limit)",
             "rate_limit": "a rate limit", "out_of_workspace": "outside the workspace of the inputs",
             "statics_failed": "no equilibrium found"}


def frame_ik(mech, frame, target, q_init=None, *, position_only=False, weights=None, lower=None, upper=None,
             tol_position=1e-8, tol_orientation=1e-8, max_iterations=200, initial_damping=1e-3):
    """The shape (every joint coordinate of the robot: strains, joint angles)
    that puts ``frame`` at ``target`` (world pose 4x4, or a position (3,)
    with ``position_only``), by Levenberg-Marquardt on the error: the full
    pose error ``e = log(g^-1 g_target)`` (frame body axes) with Jacobian
    ``-T_se3_inv(-e) J_body``, the position error ``p_target - p`` with
    ``-R J_v`` (J: the frame's Jacobian through every joint on its path).
    weights: 6 (or 3) non-negative weights of the error components;
    lower/upper: bounds on q (projected). Not physical (no statics: it says
    where the robot would have to be, e.g. for a robot without actuators).
    Never raises for unreachable targets: returns the best pose, success
    False (:class:`IKResult`)."""
    tree = mech.tree
    if tree.nq != tree.nv:
        raise ValueError("frame_ik: only robots whose coordinates add (no spherical or free joint)")
    if mech.n_constraint_rows:
        raise ValueError("no shape IK for a closed chain: its constraints fix the shape (and it has no inputs "
                         "to drive it)")
    ref = mech.frame(frame)
    target = _target_pose(target, position_only)
    w = _weights(weights, position_only)
    q = tree.q0.copy() if q_init is None else tree.check_q(np.array(q_init, dtype=float), "q_init")
    lo = -np.inf if lower is None else np.asarray(lower, dtype=float)
    hi = np.inf if upper is None else np.asarray(upper, dtype=float)
    ws = Workspace(tree)

    def evaluate(q, _previous):
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q), ws.zeros_v, ws.zeros_v, 0)
        g, Js = np.empty((4, 4)), np.empty((6, tree.nv))
        spatial_jacobian(ws.m, ws.w, ref.joint, ref.x, g, Js)
        return (g, Js), _tip_error(g, target, position_only)

    def jacobian(q, data, e):
        g, Js = data
        return _error_jacobian(g, e, lie.Ad_inv(g) @ Js, position_only)

    def done(data):
        pe, oe = _errors(data[0], target)
        return pe <= tol_position and (position_only or oe <= tol_orientation)

    with one_blas_thread():
        q, (g, _), it, message = _levenberg_marquardt(np.clip(q, lo, hi), lo, hi, evaluate, jacobian, done, w,
                                                      max_iterations, initial_damping)
    pe, oe = _errors(g, target)
    return IKResult(q, message == "converged", pe, oe, it, g, message)
