"""Planner: a tip path (:mod:`soft_twin_core.paths`) to an actuation
sequence (tendon tensions [N], chamber pressures [Pa]) through statics.

Each sample of the path is an actuation IK through the static equilibrium
``R(q, u) = K (q - q0) - Q_ext(q) - B(q) u = 0``:

* **Sensitivity (exact).** The actuation force is linear in the inputs,
  ``tau_act = B(q) u`` (:func:`actuation_matrix`, on the compiled engine),
  so by the implicit function theorem ``dq/du = Kt^-1 B`` with
  ``Kt = dR/dq`` the analytic statics tangent, and the tip twist per input
  is ``J_tip(q) Kt^-1 B(q)`` (:func:`tip_sensitivity`; tested against
  finite differences of full statics solves).
* **Bounds.** Tendon tensions in ``[max(pretension, min), min(limit, max,
  max_tension)]``, chamber pressures in ``[max(-limit, min), min(limit,
  max, max_pressure)]`` (``limit``, ``min``, ``max`` from the robot file,
  :attr:`model.Actuator.lower`/``upper``; unbounded when none is
  declared; ``min: 0`` makes a chamber positive-only); rate limits ``|du/dt| <=
  max_rate`` between consecutive samples turn into a per-sample box around
  the previous sample's inputs. Every planned value lies in its box (a
  projected method: the box is never left, not even by round-off).
* **Redundancy resolution.** Among the inputs that reach a sample, the
  planner takes the one of least ``sum_k ((u_k - lower_k) / s_k)^2``
  (``lower``: the pretension of a tendon; ``s_k``: the input's scale, the
  norm of its tip sensitivity): first Gauss-Newton phases on
  ``|W e|^2 + eps^2 |S (u - lower)|^2`` (``eps = 1e-3``, then ``1e-5``,
  biasing the tip by O(eps^2)) walk along the redundant directions to the
  least such inputs, then a phase on the tip error alone polishes the
  target without moving along them. For
  antagonistic tendons (co-contraction is a direction that leaves the
  shape unchanged) this puts the slack tendon of every pair exactly at the
  pretension and the other at the least tension that holds the pose: the
  **minimum total tension above the pretension**.
* **Continuity.** Each sample is warm-started from the previous one
  (inputs and shape extrapolated linearly from the two previous samples),
  so consecutive samples follow the same branch; rate limits bound the
  jumps when given.
* **Unreachable samples** are flagged (``reached`` False, ``status`` says
  why: ``at_limit`` an actuator bound blocks, ``rate_limit`` the rate limit
  blocks, ``out_of_workspace`` the tip cannot get closer by any small
  change of the inputs), and the plan follows the closest reachable point
  (the minimiser of the weighted tip error within the bounds, locally).

Errors are weighted: ``position_weights`` (3, per world axis, e.g. [0, 1,
1] tracks y and z only) and ``orientation_weight`` [m/rad] when the path
has orientations. A sample is ``reached`` when the weighted position error
is at most ``tolerance`` [m] and the orientation error at most
``tolerance_rad``.
"""

from dataclasses import dataclass, field

import numpy as np

from . import kinematics as kin
from . import lie
from . import equilibrium as eq
from . import statics as st
from ._blas import one_blas_thread
from .loads import Loads
from .kernels.tip_error import error_jacobian, tip_error
from .paths import TipPath
from .errors import PlanError


# ----------------------------------------------------------------------------
# Exact sensitivities
# ----------------------------------------------------------------------------

def actuation_matrix(model, q, ws=None):
    """B(q) (n_dof, n_actuators) with ``tau_act(q, u) = B(q) u`` exactly:
    distributed actuators by the compiled actuation pass with unit inputs,
    point-moment tendons as ``J_body(end)^T [0; d(end) x (-c e_x)]``."""
    from .kernels import passes
    from .workspace import thread_workspace
    ws = thread_workspace(model.tree) if ws is None else ws
    q = np.ascontiguousarray(q, dtype=float)
    passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    return _actuation_columns(model, ws, q)


def _actuation_columns(model, ws, q):
    """:func:`actuation_matrix` on a workspace already posed at q (forward
    pass, level 0)."""
    from . import algorithms as alg
    from .forces import actuation_pass
    tree = model.tree
    B = np.zeros((tree.nv, len(model.actuators)))
    act = st._actuators(model)
    for k, a in enumerate(model.actuators):
        if a.tendon_model != "point_moment":
            actuation_pass(ws.m, ws.w, act, np.ascontiguousarray(act.unit[:, k]), B[:, k])
    for k, a in enumerate(model.actuators):
        if a.tendon_model == "point_moment":
            path = tree.path_of_actuator(k)
            j, x = path.locate(np.array([a.end]))
            _, J = alg.point_jacobian(tree, ws, q, int(j[0]), float(x[0]), "body")
            d, _ = a.offset_at(np.array([a.end]))
            m = np.cross(d[0], -a.force_per_unit_input * np.array([1.0, 0.0, 0.0]))
            B[:, k] = J[3:].T @ m
    return B


@dataclass
class _Eq:
    q: np.ndarray
    tip_pose: np.ndarray
    tangent: object


class _Equilibrium:
    """The statics problem of one model and loads, re-used for many inputs
    u (the engine workspace is made once)."""

    def __init__(self, model, loads):
        self.model, self.loads = model, loads
        self.pb = st.problem(model, np.zeros(len(model.actuators)), loads)
        self.point_moment = any(a.tendon_model == "point_moment" for a in model.actuators)

    def _set(self, u):
        from .forces import load_arrays
        pb = self.pb
        key = getattr(self, "_u", None)
        if key is not None and np.array_equal(key, u):
            return pb
        pb.coef = np.ascontiguousarray(pb.act.unit @ u) if u.size else pb.coef
        if self.point_moment:
            pb.loads = load_arrays(self.model.tree, self.loads, u)
        self._u = np.array(u, dtype=float)
        return pb

    def tangent(self, q, u):
        return self._set(u).tangent(q)

    def tip_pose(self, q):
        """World tip pose (4x4) at q (checked), on this problem's workspace."""
        from .kernels import passes
        from .kernels.frames import point_pose
        ws = self.pb.ws
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
        g = np.empty((4, 4))
        point_pose(ws.m, ws.w, self.model.tree.n_joints - 1, -1.0, g)
        return g

    def sensitivity(self, q, u, Kt=None):
        """(tip pose, spatial tip Jacobian (6, n_dof), dq/du = Kt^-1 B) at the
        equilibrium (q, u) (q contiguous), from one forward pass; ``Kt``: the
        statics tangent if at hand, else computed at q."""
        from .kernels import passes
        from .kernels.frames import spatial_jacobian
        if Kt is None:
            Kt = self.tangent(q, u)
        ws = self.pb.ws
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
        B = _actuation_columns(self.model, ws, q)
        g, Js = np.empty((4, 4)), np.empty((6, self.model.tree.nv))
        spatial_jacobian(ws.m, ws.w, self.model.tree.n_joints - 1, -1.0, g, Js)
        return g, Js, np.linalg.solve(Kt, B)

    def newton(self, q, u, hint=None, tol=1e-12):
        """(q, converged and stable, last tangent): Newton from q under u."""
        pb = self._set(np.asarray(u, dtype=float))
        q1, _, _, ok, Kt = eq.newton(pb, q, tol, 30, hint)
        if ok and Kt is not None and Kt is not hint:
            ok = eq.is_stable(Kt)
        elif ok:
            Kt = None
        return q1, ok, Kt


def tip_sensitivity(model, q, u, loads=None, _eq=None, Kt=None):
    """Exact sensitivities at an equilibrium (q, u): returns
    (tip pose 4x4 world, body tip Jacobian J (6, n_dof), dq/du (n_dof, n_act)),
    so that the body twist of the tip per input is ``J @ dq_du``. ``Kt``:
    the statics tangent if at hand (the equilibrium's last Newton tangent,
    evaluated within Newton's last step of q), else computed at q."""
    loads = Loads() if loads is None else loads
    eq = _Equilibrium(model, loads) if _eq is None else _eq
    g, Js, dq_du = eq.sensitivity(np.ascontiguousarray(q, dtype=float), np.asarray(u, dtype=float), Kt)
    return g, lie.Ad_inv(g) @ Js, dq_du


def tip_position_sensitivity(model, q, u, loads=None):
    """d(tip position, world)/du (3, n_act) = R J_v Kt^-1 B."""
    g, J, dq_du = tip_sensitivity(model, q, u, loads)
    return g[:3, :3] @ J[:3] @ dq_du


def box_lstsq(A, b, lo, hi, max_iterations=None):
    """min |A x - b|^2 subject to lo <= x <= hi (lo <= 0 <= hi), by the
    active-set method of Stark and Parker (BVLS) from x = 0, compiled
    (:func:`soft_twin_core.kernels.bvls.box_lstsq_kernel`; for the few
    columns of an actuation IK step a scipy call costs more than the solve).
    Returns x, always inside the box."""
    from .kernels.bvls import box_lstsq_kernel
    A = np.ascontiguousarray(A, dtype=float)
    n = A.shape[1]
    return box_lstsq_kernel(A, np.ascontiguousarray(b, dtype=float), np.ascontiguousarray(lo, dtype=float),
                            np.ascontiguousarray(hi, dtype=float), int(max_iterations or 10 * n + 10))


def bounded_gauss_newton_step(Je, e, x, lo, hi, scale, eps, x_ref, lam):
    """The step dx of a regularised Gauss-Newton iteration inside the box:
    min |Je dx + e|^2 + |eps scale (x + dx - x_ref)|^2 + lam |scale dx|^2
    subject to lo <= x + dx <= hi (Levenberg-Marquardt damping ``lam``,
    floored at 1e-12; ``eps`` > 0 pulls toward ``x_ref``: the least-input
    resolution of redundancy), by the compiled BVLS
    (:func:`kernels.bvls.regularised_box_step`). Inputs whose box is empty
    stay put. Returns (dx, all_fixed)."""
    from .kernels.bvls import regularised_box_step
    c = np.ascontiguousarray
    dx = np.empty(x.size)
    held = regularised_box_step(c(Je, dtype=float), c(e, dtype=float), c(x, dtype=float), c(lo, dtype=float),
                                c(hi, dtype=float), c(scale, dtype=float), float(eps), c(x_ref, dtype=float),
                                float(lam), dx)
    return dx, bool(held)


# ----------------------------------------------------------------------------
# Options, bounds
# ----------------------------------------------------------------------------

def _per_actuator(model, value, name, default, allow_inf=True):
    """A scalar, a list (one per actuator) or a dict {name: value} -> array."""
    names = model.actuator_names
    n = len(names)
    if value is None:
        return np.full(n, default, dtype=float)
    if isinstance(value, dict):
        out = np.full(n, default, dtype=float)
        for k, v in value.items():
            if k not in names:
                raise PlanError(f"{name}: unknown actuator {k!r}; this robot has {list(names)}")
            out[names.index(k)] = _number(v, f"{name}.{k}", allow_inf)
        return out
    if np.ndim(value) == 0:
        return np.full(n, _number(value, name, allow_inf))
    vals = list(value)
    if len(vals) != n:
        raise PlanError(f"{name}: expected one value per actuator {list(names)}, got {len(vals)}")
    return np.array([_number(v, f"{name}[{i}]", allow_inf) for i, v in enumerate(vals)])


def _number(v, name, allow_inf=True):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise PlanError(f"{name}: expected a number, got {v!r}") from None
    if np.isnan(x) or (not allow_inf and not np.isfinite(x)):
        raise PlanError(f"{name}: expected a {'finite ' if not allow_inf else ''}number, got {v!r}")
    return x


@dataclass
class PlanOptions:
    """position_weights (3,) per world axis (>= 0); orientation_weight [m/rad]
    (used when the path has orientations); tolerance [m] on the weighted
    position error, tolerance_rad [rad]; pretension [N] (tendons' least
    tension; scalar, list or {name: value}); max_tension [N] and
    max_pressure [Pa] (caps on top of each actuator's ``limit``); max_rate
    [N/s or Pa/s] (None: no rate limit); max_iterations per sample; loads
    (default gravity only)."""
    position_weights: tuple = (1.0, 1.0, 1.0)
    orientation_weight: float = 0.1
    tolerance: float = 1e-6
    tolerance_rad: float = 1e-5
    pretension: object = 0.0
    max_tension: object = None
    max_pressure: object = None
    max_rate: object = None
    max_iterations: int = 40
    loads: object = None

    def weights(self):
        w = np.asarray(self.position_weights, dtype=float)
        if w.shape != (3,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
            raise PlanError(f"position_weights: expected 3 non-negative numbers, not all 0, got "
                            f"{self.position_weights!r}")
        wo = _number(self.orientation_weight, "orientation_weight", False)
        if wo < 0:
            raise PlanError(f"orientation_weight: expected a number >= 0 (m/rad), got {wo}")
        for name in ("tolerance", "tolerance_rad"):
            v = _number(getattr(self, name), name, False)
            if v <= 0:
                raise PlanError(f"{name}: expected a number > 0, got {v}")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) \
                or self.max_iterations < 1:
            raise PlanError(f"max_iterations: expected an integer >= 1, got {self.max_iterations!r}")
        return np.sqrt(w), np.sqrt(wo)


def actuator_bounds(model, options=None):
    """(lower, upper) input bounds (n_act,): the robot file's range of each
    actuator ([Actuator.lower, Actuator.upper]: limit, min, max) cut by the
    options: tendons [max(lower, pretension), min(upper, max_tension)],
    chambers [lower, min(upper, max_pressure)]."""
    o = PlanOptions() if options is None else options
    pre = _per_actuator(model, o.pretension, "pretension", 0.0, allow_inf=False)
    tmax = _per_actuator(model, o.max_tension, "max_tension", np.inf)
    pmax = _per_actuator(model, o.max_pressure, "max_pressure", np.inf)
    lo, hi = np.empty(len(model.actuators)), np.empty(len(model.actuators))
    for k, a in enumerate(model.actuators):
        if a.kind == "tendon":
            if pre[k] < 0:
                raise PlanError(f"pretension.{a.name}: a tendon's pretension must be >= 0 N, got {pre[k]}")
            lo[k], hi[k] = max(pre[k], a.lower), min(a.upper, tmax[k])
        else:
            lo[k], hi[k] = a.lower, min(a.upper, pmax[k])
        if not lo[k] <= hi[k]:
            raise PlanError(f"{a.name}: empty input range [{lo[k]}, {hi[k]}] (pretension above the "
                            f"limit or max_tension/max_pressure?)")
    return lo, hi


def rate_limits(model, options):
    """Per-actuator rate limit [unit/s] (inf: none)."""
    r = _per_actuator(model, options.max_rate, "max_rate", np.inf)
    if np.any(r <= 0):
        raise PlanError(f"max_rate: expected values > 0 (per second), got {r.tolist()}")
    return r


# ----------------------------------------------------------------------------
# One sample: bounded Gauss-Newton on the inputs
# ----------------------------------------------------------------------------

@dataclass
class SampleResult:
    """u (n_act,), q (equilibrium), tip pose (4x4 world), position_error [m]
    (3-D distance), weighted_error [m] (with position_weights),
    orientation_error [rad], reached, status ("reached", "at_limit",
    "rate_limit", "out_of_workspace", "statics_failed"), iterations."""
    u: np.ndarray
    q: np.ndarray
    tip_pose: np.ndarray
    position_error: float
    weighted_error: float
    orientation_error: float
    reached: bool
    status: str
    iterations: int
    tangent: object = field(default=None, repr=False)


class TipSolver:
    """Actuation IK of the tip through statics for one model, loads and
    options, re-used sample after sample (warm starts)."""

    EPS_REDUNDANCY = 1e-3

    def __init__(self, model, options=None):
        if not model.actuators:
            raise PlanError("this robot has no actuators: there is nothing to plan")
        self.model = model
        self.options = PlanOptions() if options is None else options
        self.sw, self.swo = self.options.weights()
        self.loads = Loads() if self.options.loads is None else self.options.loads
        self.lower, self.upper = actuator_bounds(model, self.options)
        self.rate = rate_limits(model, self.options)
        self.eq = _Equilibrium(model, self.loads)

    # -- error model ------------------------------------------------------
    def _error(self, g, target, with_rot):
        e = np.empty(6 if with_rot else 3)
        tip_error(np.ascontiguousarray(g, dtype=float), target, self.sw, self.swo, with_rot, e)
        return e

    def _error_jacobian(self, g, e, q, u, with_rot, Kt=None):
        key = getattr(self, "_jac_key", None)
        if key is not None and key[0] is q and np.array_equal(key[1], u) and np.array_equal(key[2], e) \
                and key[3] == with_rot:
            return key[4]
        Je = self._error_jacobian_new(g, e, q, u, with_rot, Kt)
        self._jac_key = (q, np.array(u), np.array(e), with_rot, Je)
        return Je

    def _error_jacobian_new(self, g, e, q, u, with_rot, Kt=None):
        g_, Js, dq_du = self.eq.sensitivity(q, u, Kt)
        self._dq_du = (q, np.array(u), dq_du)
        Je = np.empty((e.size, dq_du.shape[1]))
        error_jacobian(g_, Js, dq_du, e, self.sw, self.swo, with_rot, Je)
        return Je

    def _statics(self, u, q_init, hint=None, q_guess=None):
        """Equilibrium under u from q_init: Newton on the cached problem
        (tangent hint first; from ``q_guess`` first if given), else the full
        solver (continuation, stability). Returns an object with q,
        tip_pose, tangent."""
        for start in ((q_guess, q_init) if q_guess is not None else (q_init,)):
            if start is not None:
                q, ok, Kt = self.eq.newton(np.asarray(start, float), u, hint)
                if ok:
                    return _Eq(q, self.eq.tip_pose(q), Kt)
        return st.solve_statics(self.model, u, self.loads, q_init=q_init, tangent_hint=hint)

    def _predicted(self, q, u, u_new):
        """The equilibrium under u_new to first order from the one at (q, u):
        q + dq/du (u_new - u), with the sensitivity of the last Jacobian
        (None if that was not taken at q)."""
        d = getattr(self, "_dq_du", None)
        if d is None or d[0] is not q or not np.array_equal(d[1], u):
            return None
        return q + d[2] @ (u_new - u)

    def _errors(self, g, target, with_rot):
        """(position distance [m], weighted position error [m], orientation error [rad] or 0)."""
        return tip_error(np.ascontiguousarray(g, dtype=float), np.ascontiguousarray(target, dtype=float), self.sw,
                         self.swo, with_rot, np.empty(6))

    def _reached(self, g, target, with_rot):
        _, we, oe = self._errors(g, target, with_rot)
        return we <= self.options.tolerance and (not with_rot or oe <= self.options.tolerance_rad)

    def held(self, target, u, q):
        """A sample whose statics failed from every start: the inputs and
        equilibrium (u, q) of the sample before are kept, flagged
        ``statics_failed`` (never reached)."""
        with_rot = getattr(self, "_with_rot", False) and self.swo > 0
        g = kin.tip_pose(self.model, q)
        pe, we, oe = self._errors(g, target, with_rot)
        return SampleResult(np.array(u, float), np.array(q, float), g, pe, we, oe, False, "statics_failed", 0)

    # -- the solve ---------------------------------------------------------
    def solve(self, target, u_init, q_init, lower=None, upper=None, rate_box=None, redundancy=True):
        """Inputs whose equilibrium puts the tip at ``target`` (world 4x4; the
        orientation counts when the orientation weight > 0 and
        ``target_has_rotation``), within [lower, upper] (default the actuator
        bounds). ``rate_box``: (lo, hi) of the rate limit, only to say which
        bound blocks an unreachable sample."""
        lo = self.lower if lower is None else np.asarray(lower, float)
        hi = self.upper if upper is None else np.asarray(upper, float)
        with_rot = getattr(self, "_with_rot", False) and self.swo > 0
        target = np.ascontiguousarray(target, dtype=float)
        u = np.clip(np.asarray(u_init, dtype=float), lo, hi)
        with one_blas_thread():
            try:
                res = self._statics(u, q_init)
            except st.StaticsError:
                res = self._statics(u, None)
            q, g = res.q, res.tip_pose
            e = self._error(g, target, with_rot)
            it_total = 0
            scale = None
            hint = res.tangent          # the statics tangent at (about) the current q, carried along
            for phase_eps in ((self.EPS_REDUNDANCY, 1e-2 * self.EPS_REDUNDANCY, 0.0) if redundancy else (0.0,)):
                u, q, g, e, it, scale, hint = self._gauss_newton(u, q, g, e, target, lo, hi, phase_eps, with_rot,
                                                                 hint)
                it_total += it
        pe, we, oe = self._errors(g, target, with_rot)
        reached = self._reached(g, target, with_rot)
        status = "reached" if reached else self._blocking(u, q, g, e, lo, hi, rate_box, with_rot)
        return SampleResult(u, q, g, pe, we, oe, reached, status, it_total)

    def _gauss_newton(self, u, q, g, e, target, lo, hi, eps, with_rot, hint):
        lam = 0.0
        it = 0
        scale = None
        tol = self.options.tolerance

        def cost(u_, e_):
            c = float(e_ @ e_)
            if eps > 0:
                r = eps * scale * (u_ - lo_reg)
                c += float(r @ r)
            return c

        lo_reg = np.where(np.isfinite(lo), lo, 0.0)
        costs = []
        for it in range(1, self.options.max_iterations + 1):
            if eps == 0.0 and self._reached(g, target, with_rot):
                return u, q, g, e, it - 1, scale, hint
            # the tangent of the statics that gave q (Gauss-Newton needs no more accurate a Jacobian)
            Je = self._error_jacobian(g, e, q, u, with_rot, hint)
            if scale is None:
                scale = np.maximum(np.linalg.norm(Je, axis=0), 1e-12 * max(np.linalg.norm(Je), 1e-300))
            c0 = cost(u, e)
            improved = False
            for _ in range(10):
                du, all_fixed = bounded_gauss_newton_step(Je, e, u, lo, hi, scale, eps, lo_reg, lam)
                if all_fixed:
                    return u, q, g, e, it, scale, hint
                if np.linalg.norm(du * scale) <= 1e-14 * max(np.linalg.norm(u * scale), tol):
                    return u, q, g, e, it, scale, hint
                # the linear model promises (almost) nothing: at the (regularised) optimum
                n_task = e.size
                r_lin = Je @ du + e
                pred = float(r_lin @ r_lin)
                if eps > 0:
                    rr = eps * scale * (u + du - lo_reg)
                    pred += float(rr @ rr)
                if lam <= 1e-8 and (np.linalg.norm(scale * du) <= 0.1 * tol or c0 - pred <= 1e-3 * c0) \
                        and (eps > 0 or not n_task or np.sqrt(pred) > tol or np.linalg.norm(scale * du) <= 1e-3 * tol):
                    return u, q, g, e, it, scale, hint
                u_new = np.clip(u + du, lo, hi)
                try:
                    r = self._statics(u_new, q, hint, self._predicted(q, u, u_new))
                except st.StaticsError:
                    lam = max(4 * lam, 1e-4)
                    continue
                e_new = self._error(r.tip_pose, target, with_rot)
                if cost(u_new, e_new) < c0:
                    u, q, g, e = u_new, r.q, r.tip_pose, e_new
                    hint = r.tangent
                    lam = lam / 10 if lam > 1e-8 else 0.0
                    improved = True
                    break
                lam = max(4 * lam, 1e-4)
            if not improved:
                break
            if eps > 0 and cost(u, e) > (1 - 1e-10) * c0:
                break
            costs.append(cost(u, e))
            if len(costs) > 4 and costs[-1] > 0.25 * costs[-5]:
                break      # stagnating (error not halved in 4 steps): a near-singular direction or a bound
        return u, q, g, e, it, scale, hint

    def _blocking(self, u, q, g, e, lo, hi, rate_box, with_rot):
        """Why an unreached sample stopped: the bound the gradient of the
        error presses against, or none (out of the workspace)."""
        try:
            Je = self._error_jacobian(g, e, q, u, with_rot)
        except (np.linalg.LinAlgError, ValueError):
            return "statics_failed"
        grad = Je.T @ e                   # d(0.5 |e|^2)/du: descent is -grad
        sc = np.abs(grad).max(initial=0.0)
        atol = 1e-9 * np.maximum(1.0, np.abs(u))
        press_lo = (u <= lo + atol) & (grad > 1e-6 * sc)
        press_hi = (u >= hi - atol) & (grad < -1e-6 * sc)
        if not np.any(press_lo | press_hi):
            return "out_of_workspace"
        if rate_box is not None:
            rlo, rhi = rate_box
            by_rate = (press_lo & (rlo > self.lower + atol)) | (press_hi & (rhi < self.upper - atol))
            if np.any(by_rate):
                return "rate_limit"
        return "at_limit"


# ----------------------------------------------------------------------------
# Paths
# ----------------------------------------------------------------------------

@dataclass
class Plan:
    """An actuation sequence: times (N,) [s]; u (N, n_act) inputs (N, Pa);
    q (N, n_dof) the static shapes; tip (N, 3) predicted tip positions
    (quasi-static, world); target (N, 3) (world); position_error (N,) [m]
    (3-D distance), weighted_error (N,) [m], orientation_error (N,) [rad];
    reached (N,) bool; status (N,) str; lower/upper (n_act,) the actuator
    bounds, max_rate (n_act,) [unit/s]; actuator_names; iterations (N,)."""
    times: np.ndarray
    u: np.ndarray
    q: np.ndarray
    tip: np.ndarray
    target: np.ndarray
    position_error: np.ndarray
    weighted_error: np.ndarray
    orientation_error: np.ndarray
    reached: np.ndarray
    status: list
    lower: np.ndarray
    upper: np.ndarray
    max_rate: np.ndarray
    actuator_names: tuple
    iterations: np.ndarray
    tip_rotation: np.ndarray = None

    def summary(self):
        """Counts and error statistics (quasi-static prediction)."""
        r = self.reached
        err = self.weighted_error
        return {"samples": int(len(self.times)), "reached": int(r.sum()), "unreachable": int((~r).sum()),
                "max_error_reached_m": float(err[r].max()) if r.any() else None,
                "max_error_m": float(err.max()), "rms_error_m": float(np.sqrt(np.mean(err ** 2))),
                "max_position_distance_m": float(self.position_error.max()),
                "statuses": {s: self.status.count(s) for s in sorted(set(self.status))}}


def rate_bounds(lower, upper, rlo, rhi):
    """Bounds [lo, hi] of a sample: the actuator (or joint) bounds cut by the
    rate box [rlo, rhi]; where they do not overlap, the bound nearest the box."""
    lo, hi = np.maximum(lower, rlo), np.minimum(upper, rhi)
    return np.minimum(lo, hi), np.maximum(np.minimum(lo, hi), hi)


def warm_start(hist, default):
    """Start (inputs, shape) of the next sample: linear extrapolation from the
    two previous samples' (inputs, shape) in ``hist``, the previous one after
    the first, ``default`` before any."""
    if len(hist) >= 2:
        (u1, q1), (u2, q2) = hist[-2], hist[-1]
        return u2 + (u2 - u1), q2 + (q2 - q1)
    return hist[-1] if hist else default


def plan_path(model, path, options=None, u_start=None, q_start=None, solver=None):
    """Plan the actuation sequence of a :class:`TipPath` (base frame).

    u_start: the inputs before the path starts (rate limits then also hold
    from u_start to the first sample; default: the first sample is free).
    q_start: the shape to warm-start from (default: the equilibrium under
    u_start, or the rest shape)."""
    if not isinstance(path, TipPath):
        raise PlanError(f"path: expected a TipPath, got {type(path).__name__}")
    solver = TipSolver(model, options) if solver is None else solver
    o = solver.options
    targets = path.world_targets(model.base_pose)
    solver._with_rot = path.orientations is not None
    n_act = len(model.actuators)
    u_prev = None if u_start is None else st.actuation_vector(model, u_start)
    if q_start is not None:
        q = model.check_q(np.array(q_start, dtype=float), "q_start")
    else:
        q = st.solve_statics(model, u_prev, solver.loads).q
    u_guess = np.clip(np.zeros(n_act) if u_prev is None else u_prev, solver.lower, solver.upper)
    N = len(path)
    out = {k: [] for k in ("u", "q", "tip", "R", "pe", "we", "oe", "reached", "status", "it")}
    t_prev = path.times[0]
    hist = []
    for i in range(N):
        lo, hi, box = solver.lower, solver.upper, None
        if u_prev is not None and np.any(np.isfinite(solver.rate)):
            dt = path.times[i] - t_prev if i > 0 else 0.0
            if i == 0 and u_start is not None:
                dt = 0.0
            step = solver.rate * dt
            rlo, rhi = u_prev - step, u_prev + step
            lo, hi = rate_bounds(solver.lower, solver.upper, rlo, rhi)
            box = (rlo, rhi)
        u0, q0 = warm_start(hist, (u_guess, q))
        try:
            r = solver.solve(targets[i], np.clip(u0, lo, hi), q0, lo, hi, box)
        except st.StaticsError:
            if not hist:
                raise
            # the extrapolated start may lie beyond what the rod carries: from the sample before,
            # else that sample held and flagged
            try:
                r = solver.solve(targets[i], np.clip(hist[-1][0], lo, hi), hist[-1][1], lo, hi, box)
            except st.StaticsError:
                r = solver.held(targets[i], *hist[-1])
        u_prev, t_prev = r.u, path.times[i]
        hist.append((r.u, r.q))
        out["u"].append(r.u)
        out["q"].append(r.q)
        out["tip"].append(r.tip_pose[:3, 3])
        out["R"].append(r.tip_pose[:3, :3])
        out["pe"].append(r.position_error)
        out["we"].append(r.weighted_error)
        out["oe"].append(r.orientation_error)
        out["reached"].append(r.reached)
        out["status"].append(r.status)
        out["it"].append(r.iterations)
    return Plan(path.times.copy(), np.array(out["u"]), np.array(out["q"]), np.array(out["tip"]),
                targets[:, :3, 3].copy(), np.array(out["pe"]), np.array(out["we"]), np.array(out["oe"]),
                np.array(out["reached"], bool), out["status"], solver.lower.copy(), solver.upper.copy(),
                solver.rate.copy(), model.actuator_names, np.array(out["it"]), np.array(out["R"]))


def check_plan(plan, rtol=0.0):
    """Violations of the plan's bounds and rate limits (a list of strings,
    empty when none)."""
    bad = []
    for k, name in enumerate(plan.actuator_names):
        u = plan.u[:, k]
        if np.any(u < plan.lower[k] - rtol) or np.any(u > plan.upper[k] + rtol):
            bad.append(f"{name}: outside [{plan.lower[k]}, {plan.upper[k]}]")
        if np.isfinite(plan.max_rate[k]) and len(u) > 1:
            rate = np.abs(np.diff(u)) / np.diff(plan.times)
            if np.any(rate > plan.max_rate[k] * (1 + 1e-12) + rtol):
                bad.append(f"{name}: rate {rate.max()} > {plan.max_rate[k]}")
    return bad


# ----------------------------------------------------------------------------
# Dynamic verification and feed-forward compensation
# ----------------------------------------------------------------------------

@dataclass
class Tracking:
    """A simulated execution of a plan: time (M,) [s]; tip (M, 3) world;
    target (M, 3) the path at those times (linear between samples);
    error (M,) [m] weighted distance (position_weights), distance (M,) [m]
    3-D; converged: every step converged."""
    time: np.ndarray
    tip: np.ndarray
    target: np.ndarray
    error: np.ndarray
    distance: np.ndarray
    converged: bool

    def summary(self):
        return {"max_error_m": float(self.error.max()), "rms_error_m": float(np.sqrt(np.mean(self.error ** 2))),
                "final_error_m": float(self.error[-1]), "max_distance_m": float(self.distance.max()),
                "converged": bool(self.converged)}


def actuation_profile(times, u):
    """u(t) linear between the samples (held outside): a callable of t [s]
    returning (n_act,)."""
    times = np.asarray(times, dtype=float)
    u = np.asarray(u, dtype=float)

    def f(t):
        return np.array([np.interp(t, times, u[:, k]) for k in range(u.shape[1])])
    return f


def simulate_plan(model, plan, path_positions_world=None, dt=0.005, loads=None, weights=(1.0, 1.0, 1.0),
                  theta=0.5, hold=0.0):
    """Execute ``plan`` with the dynamics (:class:`dynamics.Simulator`) from
    rest at the static equilibrium of its first sample, the inputs linear
    between samples, for the plan's duration plus ``hold`` [s] (last inputs
    held). The error is measured against ``path_positions_world`` (N, 3) at
    the plan's times (default: the plan's targets), linear between samples."""
    from .dynamics import Simulator
    from .model import State
    loads = Loads() if loads is None else loads
    P = plan.target if path_positions_world is None else np.asarray(path_positions_world, float)
    sw = np.sqrt(np.asarray(weights, dtype=float))
    q0 = st.solve_statics(model, plan.u[0], loads, q_init=plan.q[0]).q
    t0 = float(plan.times[0])
    sim = Simulator(model, dt=dt, actuation=actuation_profile(plan.times, plan.u), loads=loads,
                    state=State(q0, np.zeros(model.n_dof), t0), theta=theta)
    n = int(round((plan.times[-1] - t0 + hold) / dt))
    ts, tips = [t0], [kin.tip_and_spatial_jacobian(model, q0)[0][:3, 3]]
    ok = True
    for _ in range(n):
        info = sim.step(1)
        if not info.converged:
            ok = False
            break
        ts.append(sim.state.t)
        tips.append(kin.tip_and_spatial_jacobian(model, sim.state.q)[0][:3, 3])
    ts, tips = np.array(ts), np.array(tips)
    tgt = np.stack([np.interp(ts, plan.times, P[:, k]) for k in range(3)], axis=-1)
    d = tgt - tips
    return Tracking(ts, tips, tgt, np.linalg.norm(d * sw, axis=1), np.linalg.norm(d, axis=1), ok)


def _smooth(times, x, sigma):
    """Zero-phase Gaussian smoothing of x (N, k) sampled at ``times`` with
    standard deviation ``sigma`` [s] (ends reflected): the Q-filter that keeps
    the learning update below the arm's resonance."""
    if sigma <= 0 or len(times) < 3:
        return x
    t = np.asarray(times, dtype=float)
    tt = np.concatenate([2 * t[0] - t[:0:-1], t, 2 * t[-1] - t[-2::-1]])
    xx = np.concatenate([x[:0:-1], x, x[-2::-1]])
    W = np.exp(-0.5 * ((t[:, None] - tt[None, :]) / sigma) ** 2)
    return (W @ xx) / W.sum(axis=1)[:, None]


def compensate_lag(model, path, options=None, iterations=4, gain=0.5, dt=0.005, u_start=None, sigma=0.25):
    """Feed-forward compensation of the dynamic lag by iterating the plan
    against the simulated response (iterative learning on the targets):
    plan, simulate, shift every sample's target by ``gain`` times the
    simulated error at its time (smoothed over ``sigma`` [s], a zero-phase
    Gaussian: the learning filter), replan; ``iterations`` times. The error
    is always measured against the original path. Returns (best plan, its
    Tracking, history: one summary dict per iteration, 0 = uncompensated)."""
    options = PlanOptions() if options is None else options
    solver = TipSolver(model, options)
    base = model.base_pose
    P_world = path.world_targets(base)[:, :3, 3]
    w = np.asarray(options.position_weights, dtype=float)
    targets = path.positions.copy()
    best, history = None, []
    for j in range(iterations + 1):
        plan = plan_path(model, path.with_positions(targets), options, u_start=u_start, solver=solver)
        tr = simulate_plan(model, plan, P_world, dt, solver.loads, w)
        s = {"iteration": j, **tr.summary(), "plan_unreachable": int((~plan.reached).sum())}
        history.append(s)
        if best is None or s["rms_error_m"] < best[2]["rms_error_m"]:
            best = (plan, tr, s)
        if j == iterations:
            break
        # the simulated error at the sample times, in the base frame (tracked axes only)
        err_w = P_world - np.stack([np.interp(plan.times, tr.time, tr.tip[:, k]) for k in range(3)], axis=-1)
        err_w = err_w * (w > 0)
        targets = targets + gain * (_smooth(plan.times, err_w, sigma) @ base[:3, :3])
    return best[0], best[1], history
