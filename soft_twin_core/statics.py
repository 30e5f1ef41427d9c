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
from .errors import StaticsError


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
    Exact to machine precision (reference; see :func:`_fast_tangent`)."""
    n = model.n_dof
    qc = q[None, :] + 1j * h * np.eye(n)
    return (residual(model, qc, u, loads).imag / h).T


class _Problem:
    """The equilibrium problem of a robot description under inputs u and
    loads, bound to the multibody engine and one workspace:
    ``R(q) = K (q - q0) + tau_rnea(q; loads, gravity) - tau_act(q, u)``
    (:func:`integrators.residual_pass` at rest) and its analytic tangent
    (:func:`kernels.tangent.static_tangent_pass` plus the stiffness blocks
    and the tendons' :func:`forces.actuation_tangent_pass`)."""

    def __init__(self, model, u, loads):
        from .forces import actuator_arrays, gravity_of, load_arrays
        from .workspace import Workspace
        tree = model.tree
        self.tree, self.ws = tree, Workspace(tree)
        self.act = _actuators(model)
        self.loads = load_arrays(tree, loads, u)
        # point-moment tendons are internal: the support's reaction excludes them
        self.loads_ext = load_arrays(tree, loads) if u.size and any(
            a.tendon_model == "point_moment" for a in model.actuators) else self.loads
        self.g = gravity_of(tree, loads)
        self.coef = np.ascontiguousarray(self.act.unit @ u) if u.size else np.zeros(len(self.act.joint))
        self.zeros = np.zeros(tree.nv)
        self.K = _stiffness_blocks(model)
        self.absK = np.abs(self.K)            # for the round-off level of the residual
        self.n_tangents = 0                    # tangents computed (Newton's and tangent()'s)

    def residual(self, q, loads=None):
        """R(q); the workspace then holds the forward pass and the RNEA
        wrenches at rest under ``loads`` (default the problem's): what
        :meth:`tangent` and :meth:`result` read (one compiled kernel for
        all three, so a new process loads or compiles one kernel less)."""
        from .integrators import residual_pass
        out = np.empty(self.tree.nv)
        q = np.ascontiguousarray(q, dtype=float)
        residual_pass(self.ws.m, self.ws.w, self.act, self.loads if loads is None else loads, self.g, self.coef,
                      self.zeros, q, self.zeros, self.zeros, out, True)
        return out

    def result(self, model, q, iterations, R, steps):
        """StaticsResult at the solution q: the tip pose and the support's
        reaction (the wrench the root joint transmits, from the RNEA at rest:
        tendons are internal) from the engine."""
        self.residual(q, self.loads_ext)            # poses and RNEA wrenches at rest
        w = self.ws.work
        g_base = w.g_in[0]
        f_in = w.f_in[0]
        R_base = g_base[:3, :3]
        base = np.concatenate([R_base @ f_in[:3], R_base @ f_in[3:]])
        scale = _scale(model, q, R)
        return StaticsResult(
            q=q, strains=model.strains(q), tip_pose=w.g_out[self.tree.n_joints - 1].copy(),
            base_wrench_world=base, iterations=iterations, residual=float(np.abs(R).max() / scale),
            residual_abs=float(np.abs(R).max()), converged=True, load_steps=steps)

    def tangent(self, q):
        """dR/dq, analytic: one forward pass, one RNEA pass (those of the
        residual) and one O(n^2) tangent pass."""
        from .forces import actuation_tangent_pass
        from .kernels.tangent import static_tangent_pass
        m, w = self.ws.m, self.ws.w
        self.n_tangents += 1
        self.residual(q)                            # poses and RNEA wrenches at rest
        Kt = self.K.copy()
        static_tangent_pass(m, w, self.loads, self.g, Kt)
        actuation_tangent_pass(m, w, self.act, self.coef, Kt)
        return Kt


def _actuators(model):
    a = model.__dict__.get("_actuator_arrays")
    if a is None:
        from .forces import actuator_arrays
        a = actuator_arrays(model.tree)
        object.__setattr__(model, "_actuator_arrays", a)
    return a


def _stiffness_blocks(model):
    return model.K_q


def _residual_fast(model, q, u, loads):
    """R(q) on the compiled engine."""
    return _Problem(model, np.asarray(u, dtype=float), loads).residual(q)


def _fast_tangent(model, q, u, loads):
    """dR/dq, analytic on the compiled engine (checked in the tests against
    the complex step of the numpy reference :func:`tangent`)."""
    return _Problem(model, np.asarray(u, dtype=float), loads).tangent(q)


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


def _scale(model, q, R):
    """A force scale for the relative residual: the largest of the elastic
    force K (q - q0) and the applied force Q + tau = K (q - q0) - R."""
    Kq = model.K_q @ (q - model.q0)
    return max(np.abs(Kq).max(initial=0), np.abs(Kq - R).max(initial=0), 1e-300)


def is_stable(model, q, u, loads, Kt=None):
    """Static stability: every eigenvalue of the tangent dR/dq has a positive
    real part (no divergence mode). Newton may converge to an unstable
    equilibrium (e.g. an arm curled up against gravity); the solver rejects
    those and follows the loaded path from the start point instead. ``Kt``:
    a tangent already at hand (Newton's last one, evaluated next to q)."""
    if Kt is None:
        Kt = _fast_tangent(model, q, u, loads)
    scale = np.abs(Kt).max()
    if np.abs(Kt - Kt.T).max() <= 1e-10 * scale:
        # conservative loads: a symmetric tangent, stable iff positive definite
        try:
            np.linalg.cholesky(Kt + 1e-9 * scale * np.eye(len(Kt)))
            return True
        except np.linalg.LinAlgError:
            return False
    ev = np.linalg.eigvals(Kt)
    return bool(np.all(ev.real > -1e-9 * np.abs(ev).max()))


# Up to this many free strains the compiled Newton (one call per solve) is
# used; above, the numpy loop, whose LAPACK solve is blocked: measured, the
# compiled elimination takes 73 / 491 / 7662 us at 60 / 120 / 240 unknowns,
# numpy 51 / 192 / 857 us, while the compiled loop saves ~0.1 ms of Python per
# iteration.
COMPILED_NEWTON_MAX_DOF = 96


def _newton(model, pb, q, tol, max_iterations, Kt_hint=None):
    """Newton with line search on the problem ``pb`` (:class:`_Problem`).
    With ``Kt_hint`` (a tangent from a nearby state) the first steps reuse
    it (modified Newton) while each step cuts the residual at least
    tenfold; then fresh tangents are computed; a converged solve takes one
    more (polish) step with the last tangent when it lowers |R|. Compiled
    (:func:`kernels.static_newton.static_newton`) up to
    ``COMPILED_NEWTON_MAX_DOF`` unknowns, else :func:`_newton_numpy` (the
    same iterates). Returns (q, R, iterations, converged, the last tangent
    used: the hint object itself, a fresh array, or None)."""
    n = model.n_dof
    if n > COMPILED_NEWTON_MAX_DOF:
        return _newton_numpy(model, pb, np.array(q, dtype=float), tol, max_iterations, Kt_hint)
    from .kernels.static_newton import static_newton
    use_hint = Kt_hint is not None and Kt_hint.shape == (n, n)
    q = np.array(q, dtype=float)
    Kt, R = np.empty((n, n)), np.empty(n)
    hint = np.ascontiguousarray(Kt_hint, dtype=float) if use_hint else Kt
    it, ok, which, n_tangents = static_newton(pb.ws.m, pb.ws.w, pb.act, pb.loads, pb.g, pb.coef, pb.K, pb.absK,
                                              model.q0, q, float(tol), int(max_iterations), hint, use_hint, Kt, R)
    pb.n_tangents += n_tangents
    return q, R, int(it), bool(ok), (None, Kt_hint, Kt)[which]


def _converged(model, pb, q, R, scale, tol):
    """|R| <= tol scale + the round-off level 64 eps |K| (|q| + |q0|) of the
    stiff axial/shear modes (K (q - q0) cancels terms of size |K| |q|)."""
    roundoff = 64 * np.finfo(float).eps * (pb.absK @ (np.abs(q) + np.abs(model.q0)))
    return bool(np.all(np.abs(R) <= tol * scale + roundoff))


def _newton_numpy(model, pb, q, tol, max_iterations, Kt_hint=None):
    """:func:`_newton` as a numpy loop (LAPACK solves): for large models,
    and the tests' reference of the compiled kernel."""
    R = pb.residual(q)
    scale = _scale(model, q, R)
    it, Kt = 0, None
    reuse = Kt_hint is not None and Kt_hint.shape == (model.n_dof, model.n_dof)
    for it in range(1, max_iterations + 1):
        if _converged(model, pb, q, R, scale, tol):
            if Kt is not None:
                try:
                    q_p = q + np.linalg.solve(Kt, -R)
                    R_p = pb.residual(q_p)
                    if np.all(np.isfinite(R_p)) and np.linalg.norm(R_p) < np.linalg.norm(R):
                        q, R = q_p, R_p
                except np.linalg.LinAlgError:
                    pass
            return q, R, it - 1, True, Kt
        Kt = Kt_hint if reuse else pb.tangent(q)
        try:
            dq = np.linalg.solve(Kt, -R)
        except np.linalg.LinAlgError:
            if reuse:
                reuse = False
                continue
            return q, R, it, False, None
        step, r0 = 1.0, np.linalg.norm(R)
        for _ in range(20):
            q_try = q + step * dq
            R_try = pb.residual(q_try)
            if np.all(np.isfinite(R_try)) and np.linalg.norm(R_try) < (1 - 1e-4 * step) * r0:
                break
            step *= 0.5
        else:
            if reuse:              # the stale tangent gives no descent: take a fresh one
                reuse = False
                continue
            return q, R, it, _converged(model, pb, q, R, scale, tol), Kt
        if reuse and (step < 1.0 or np.linalg.norm(R_try) > 0.1 * r0):
            reuse = False          # slow: fresh tangents from now on
        q, R = q_try, R_try
        scale = max(scale, _scale(model, q, R))
    return q, R, it, _converged(model, pb, q, R, scale, tol), Kt


def solve_statics(model, actuation=None, loads=None, q_init=None, *, tol=1e-10,
                  max_iterations=50, max_load_steps=64, check_stability=True, tangent_hint=None):
    """Static equilibrium under actuation (dict name -> tension N / pressure
    Pa, or a vector) and loads (:class:`Loads`, default: gravity only).

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
    with one_blas_thread():
        return _solve(model, u, loads, q, tol, max_iterations, max_load_steps, check_stability, tangent_hint)


def _solve(model, u, loads, q, tol, max_iterations, max_load_steps, check_stability, tangent_hint):
    total_it = 0
    pb = _Problem(model, u, loads)
    q1, R, it, ok, Kt = _newton(model, pb, q, tol, max_iterations, tangent_hint)
    total_it += it
    steps = 1
    fallback = None           # a converged but unstable equilibrium
    if Kt is tangent_hint:
        Kt = None             # judge stability (and hand on) a tangent of this state, not the hint
    if ok and check_stability:
        if Kt is None:
            Kt = pb.tangent(q1)
        if not is_stable(model, q1, u, loads, Kt):
            ok, fallback = False, (q1, R)
    if not ok:
        # continuation from the start point in the load factor lam
        lam, dlam, steps = 0.0, 0.25, 0
        q_c = q.copy()
        while lam < 1.0:
            target = min(1.0, lam + dlam)
            q_try, R, it, ok, Kt = _newton(model, _Problem(model, target * u, loads.scaled(target)), q_c, tol,
                                           max_iterations)
            total_it += it
            steps += 1
            if ok and check_stability and not is_stable(model, q_try, target * u, loads.scaled(target), Kt):
                ok = False
            if ok:
                lam, q_c = target, q_try
                dlam = min(2 * dlam, 1.0)
            else:
                dlam *= 0.5
                if dlam < 1.0 / max_load_steps / 64 or steps > 4 * max_load_steps:
                    if fallback is not None:
                        # no stable path: report the equilibrium Newton found, flagged
                        res = pb.result(model, fallback[0], total_it, fallback[1], steps)
                        res.stable = False
                        return res
                    raise StaticsError(f"statics did not converge: reached load fraction {lam:.4f}; "
                                       f"the load or actuation may exceed what the model can carry, "
                                       f"or the rod buckles (try a different q_init)")
        q1 = q_c
        R = pb.residual(q1)
    res = pb.result(model, q1, total_it, R, steps)
    res.tangent = Kt
    return res


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
