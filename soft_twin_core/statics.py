"""Static equilibrium of the PCS model (slides part B "Statics").

Solves ``R(q) = K (q - q0) - Q_ext(q) - tau_act(q, u) = 0`` by Newton's
method with a backtracking line search. The residual is the multibody
engine's inverse dynamics at rest and the tangent dR/dq its analytic
derivative (one O(n^2) pass, :mod:`soft_twin_core.kernels.tangent`), both
checked in the tests against the numpy reference (:func:`residual`) and its
exact complex-step tangent (:func:`tangent`). Equilibria with
an unstable tangent are rejected in favour of the loaded path from the start
point (continuation in a load factor, also used when a full Newton solve
fails); a previous solution warm-starts the next call.
"""

from dataclasses import dataclass

import numpy as np

from . import kinematics as kin
from ._blas import one_blas_thread
from . import lie
from .loads import (Loads, actuation_force, actuator_point_loads, generalized_external_force, load_points,
                    validate_loads)
from . import equilibrium as eq
from .errors import StaticsError  # noqa: F401  (re-exported: the statics front end raises it)
from .forces import gravity_of, load_arrays


def actuation_vector(model, actuation):
    """Inputs (n_actuators,) from a dict {name: value}, a sequence, or None.
    Tendon tensions must be >= 0 N; every value finite."""
    n = len(model.actuators)
    if actuation is None:
        return np.zeros(n)
    if isinstance(actuation, dict):
        u = np.zeros(n)
        names = model.actuator_names
        for k, v in actuation.items():
            if k not in names:
                raise ValueError(f"actuation: unknown actuator {k!r}; this robot has {list(names)}")
            try:
                u[names.index(k)] = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"actuation: {k} = {v!r} is not a number") from None
    else:
        try:
            u = np.asarray(actuation, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"actuation: expected {n} numbers, got {actuation!r}") from None
        if u.shape != (n,):
            raise ValueError(f"actuation: expected {n} values (one per actuator {list(model.actuator_names)}), "
                             f"got shape {u.shape}")
    for a, val in zip(model.actuators, u):
        if not np.isfinite(val):
            raise ValueError(f"actuation: {a.name} = {val} is not finite")
        if a.kind == "tendon" and val < 0:
            raise ValueError(f"actuation: tendon {a.name} tension must be >= 0 N, got {val}")
    return u


def residual(model, q, u, loads):
    """Equilibrium residual R(q) (..., n_dof) in generalised-force units
    (numpy reference; accepts a stack of complex q for the complex step)."""
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    tau = actuation_force(model, ch, u)
    return np.einsum("ij,...j->...i", model.K_q, ch.q - model.q0) - Q - tau


def tangent(model, q, u, loads, h=1e-30):
    """dR/dq (n_dof, n_dof) by the complex step: column k = Im R(q + i h e_k)/h.
    Exact to machine precision (reference of :meth:`equilibrium.Problem.tangent`)."""
    n = model.n_dof
    qc = q[None, :] + 1j * h * np.eye(n)
    return (residual(model, qc, u, loads).imag / h).T


def _actuators(model):
    """The actuator arrays of a robot's tree, made once per model."""
    a = model.__dict__.get("_actuator_arrays")
    if a is None:
        from .forces import actuator_arrays
        a = actuator_arrays(model.tree)
        object.__setattr__(model, "_actuator_arrays", a)
    return a


def problem(model, u, loads):
    """The :class:`equilibrium.Problem` of a classic robot under inputs u
    and :class:`Loads` (gravity, point and distributed loads by arc length;
    the point-moment tendons' follower moments)."""
    tree = model.tree
    act = _actuators(model)
    u = np.asarray(u, dtype=float)
    coef = np.ascontiguousarray(act.unit @ u) if u.size else np.zeros(len(act.joint))
    return eq.Problem(tree, act, model.K_q, load_arrays(tree, loads, u), gravity_of(tree, loads), coef)


@dataclass
class StaticsResult:
    """Equilibrium: q; strains (n_sections, 6); tip_pose (4x4, world);
    base_wrench_world [f; m] (6,) exerted by the support on the robot, world
    axes, moment about the base origin; iterations; residual (relative,
    ||R||_inf / force scale; converged means <= tol, or at round-off for very
    stiff axial/shear modes); residual_abs; converged; load_steps used;
    stable: False when only an unstable equilibrium (a tangent eigenvalue
    with negative real part) was found."""
    q: np.ndarray
    strains: np.ndarray
    tip_pose: np.ndarray
    base_wrench_world: np.ndarray
    iterations: int
    residual: float
    residual_abs: float
    converged: bool
    load_steps: int
    stable: bool = True
    tangent: object = None       # the last Newton tangent (for tangent_hint)


def _result(model, pb, u, loads, sol):
    """StaticsResult of a solution: the tip pose and the support's reaction
    (the wrench the root joint transmits, from the RNEA at rest: the
    point-moment tendons are internal, so their moments are left out)."""
    q, R = sol.q, sol.R
    internal = u.size and any(a.tendon_model == "point_moment" for a in model.actuators)
    pb.residual(q, load_arrays(model.tree, loads) if internal else None)     # poses and RNEA wrenches at rest
    w = pb.ws.work
    R_base = w.g_in[0][:3, :3]
    f_in = w.f_in[0]
    base = np.concatenate([R_base @ f_in[:3], R_base @ f_in[3:]])
    return StaticsResult(
        q=q, strains=model.strains(q), tip_pose=w.g_out[model.tree.n_joints - 1].copy(), base_wrench_world=base,
        iterations=sol.iterations, residual=float(np.abs(R).max() / eq.force_scale(pb, q, R)),
        residual_abs=float(np.abs(R).max()), converged=True, load_steps=sol.load_steps, stable=sol.stable,
        tangent=sol.tangent)


def solve_statics(model, actuation=None, loads=None, q_init=None, *, tol=1e-10,
                  max_iterations=50, max_load_steps=64, check_stability=True, tangent_hint=None):
    """Static equilibrium under actuation (dict name -> tension N / pressure
    Pa, or a vector) and loads (:class:`Loads`, default: gravity only), by
    :func:`equilibrium.solve` (the solver of every robot without
    constraints).

    q_init warm-starts Newton (default: the rest configuration);
    ``tangent_hint`` (a previous result's ``tangent``) lets the first Newton
    steps skip computing the tangent, which halves a warm solve. If a full
    solve fails or lands on an unstable equilibrium (``check_stability``),
    the loads and actuation are applied in increasing fractions from q_init
    (continuation), bisecting a failed increment. Raises StaticsError with
    the reached load fraction if it cannot converge; never returns NaN.
    """
    loads = Loads() if loads is None else loads
    validate_loads(model, loads)
    u = actuation_vector(model, actuation)
    q = model.q0.copy() if q_init is None else model.check_q(np.array(q_init, dtype=float), "q_init").copy()
    return solve_checked(model, u, loads, q, tol=tol, max_iterations=max_iterations, max_load_steps=max_load_steps,
                         check_stability=check_stability, tangent_hint=tangent_hint)


def solve_checked(model, u, loads, q, **options):
    """:func:`solve_statics` of inputs checked already (u (n_actuators,),
    Loads, q (n_dof,)), e.g. at the node's door: no second check. The
    options are :func:`solve_statics`' (all of them given)."""
    with one_blas_thread():
        pb = problem(model, u, loads)
        sol = eq.solve(pb, q, **options)
        return _result(model, pb, u, loads, sol)


def base_reaction(model, F_total_origin):
    """Support reaction [f; m] in world axes, moment about the base origin,
    balancing the total applied spatial wrench (given about the world origin)."""
    p0 = model.base_pose[:3, 3]
    f = -F_total_origin[..., :3]
    m = -F_total_origin[..., 3:] - np.cross(p0, f)
    return np.concatenate([f, m], axis=-1)


def internal_wrenches(model, q, s, actuation=None, loads=None):
    """Internal wrench (stress resultant) [force; moment] (P, 6) in the body
    frame at arc lengths s: the wrench the distal part exerts on the proximal
    part through the cross-section, from the loads distal to s (strong form,
    cut at s). Tendons anchored distal to s add their tension pulled back
    along the tendon at s. At equilibrium its elastic part approximates
    K (f - f0) (exactly so in the continuum limit)."""
    loads = Loads() if loads is None else loads
    u = actuation_vector(model, actuation)
    s = np.atleast_1d(np.asarray(s, dtype=float))
    ch = kin.chain(model, q)
    act_pts = actuator_point_loads(model, u)
    if act_pts:
        loads = Loads(point=tuple(loads.point) + act_pts, distributed=loads.distributed,
                      gravity=loads.gravity)
    pts = load_points(model, ch, loads)
    idx, x, g, own = kin._point_data(model, ch, s)
    out = np.zeros((len(s), 6))
    if pts is not None:
        sp, _, _, gp, _, Wb = pts
        F = np.einsum("...ji,...j->...i", lie.Ad_inv(gp), Wb)
        distal = sp[None, :] >= s[:, None]          # a load exactly at s counts as distal
        Fd = distal.astype(float) @ F                                   # world, about origin
        out = np.einsum("pji,pj->pi", lie.Ad(g), Fd)                    # Ad(g)^T F: to body at s
    # a tendon crossing the cut pulls the distal free body back along its path
    # with its tension T at offset d: the distal part then pushes the proximal
    # part with the extra wrench -T [t; d x t] (pressure: T = -area * p).
    for a, val in zip(model.actuators, u):
        if val == 0.0 or a.tendon_model == "point_moment":
            continue
        inside = (s >= a.start) & (s < a.end)
        if not np.any(inside):
            continue
        d, dd = a.offset_at(s)
        xi = ch.strains[idx]
        t = xi[:, :3] + np.cross(xi[:, 3:], d) + dd
        t = t / np.linalg.norm(t, axis=-1, keepdims=True)
        w = -a.force_per_unit_input * val * np.concatenate([t, np.cross(d, t)], axis=-1)
        out[inside] += w[inside]
    return out


def actuation_for_shape(model, q, loads=None):
    """Actuation that holds configuration q in equilibrium, where one exists.

    The actuation force is linear in the inputs, ``tau(q, u) = B(q) u``, so
    the inputs solve ``B(q) u = K (q - q0) - Q_ext(q)``: non-negative least
    squares for tendons (tension >= 0), free sign for chamber pressures.
    Returns (u, relative residual ||B u - rhs|| / force scale); a residual
    above ~1e-6 means the actuators cannot hold that shape exactly."""
    from scipy.optimize import lsq_linear
    loads = Loads() if loads is None else loads
    q = model.check_q(np.asarray(q, dtype=float))
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    rhs = model.K_q @ (q - model.q0) - Q
    n = len(model.actuators)
    if n == 0:
        return np.zeros(0), (0.0 if not np.any(rhs) else 1.0)
    B = np.stack([actuation_force(model, ch, e) for e in np.eye(n)], axis=1)
    lo = np.array([0.0 if a.kind == "tendon" else -np.inf for a in model.actuators])
    # scale columns so tensions (N) and pressures (Pa) are comparable
    col = np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    sol = lsq_linear(B / col, rhs, bounds=(lo * col, np.full(n, np.inf)), method="bvls", tol=1e-14)
    u = sol.x / col
    u[lo == 0.0] = np.maximum(u[lo == 0.0], 0.0)
    scale = max(np.linalg.norm(rhs), np.linalg.norm(model.K_q @ (q - model.q0)), np.linalg.norm(Q))
    res = np.linalg.norm(B @ u - rhs) / scale if scale > 0 else 0.0
    return u, float(res)
