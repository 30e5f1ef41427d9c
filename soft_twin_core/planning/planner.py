"""Planner: a tip path (:mod:`soft_twin_core.planning.paths`) to a sequence of
commands through statics, for every robot (:class:`mechanism.Mechanism`: a
classic rod, a tree, a soft articulated arm, closed chains): the position
commands (rad or m) of the position-controlled joints and the actuator
inputs (tendon tensions [N], chamber pressures [Pa]).

Unknowns per sample: ``x = [q_cmd (position-controlled joints, in the order
of mech.joints_with("position")), u (actuators)]``. A frame of the robot
(``options.frame``, default its tip, :func:`mechanism.tip_frame`) follows
the path, given in the robot's base frame (``mech.base_pose``; a prescribed
base's where ``options.base_pose`` carries it: every sample's statics then
holds the base there).

* **Sensitivity (exact).** The equilibrium ``R(q, lam; x) = 0``,
  ``Phi(q; q_cmd) = 0`` (constraint rows and the rows ``q_j - q_cmd,j``)
  is differentiated by the implicit function theorem:
  ``[[Kt, -G^T], [G, 0]] [dq; dlam] = -[dR/dx; dPhi/dx] dx`` with Kt the
  engine's analytic tangent, ``dPhi/dq_cmd = -E`` and ``dR/du = -B(q)``,
  the actuation force per unit input (exact: ``tau_act = B(q) u`` is
  linear in u; :func:`forces.actuation_matrix`, point-moment tendons included).
  Without multipliers (no constraint, no position-controlled joint: a
  classic rod, a tree of members on passive or effort-controlled joints)
  this is ``dq/du = Kt^-1 B`` on the compiled statics (:class:`_FreeStatics`:
  the problem made once, Newton from the tangent of the last solve and from
  the first-order prediction of the new equilibrium). The frame's twist per
  unit of x is ``J(q) dq/dx``. Tested against finite differences of full
  equilibrium solves.
* **Bounds.** Joint commands within the joint ``limits`` (minus
  ``joint_limits_margin``); tendon tensions in ``[max(pretension, min),
  min(limit, max, max_tension)]``, chamber pressures in ``[max(-limit,
  min), min(limit, max, max_pressure)]`` (``limit``, ``min``, ``max`` from
  the robot file, :attr:`model.Actuator.lower`/``upper``; unbounded when
  none is declared). Every planned value lies in its box (a projected
  method: the box is never left, not even by round-off).
* **Rate limits.** A position-controlled joint's ``max_velocity`` and
  ``max_acceleration`` (robot file; the bounds with which the twin shapes
  its commands, so a plan within them is followed without lag): with
  samples dt apart, ``|dq_k| <= v_max dt`` and ``|dq_k - dq_{k-1}| <=
  a_max dt^2`` (the plan starts at rest), and a joint never moves towards
  a limit faster than it can still stop before it (:func:`braking_step`).
  Actuators: ``max_rate`` [N/s, Pa/s] between consecutive samples. Each
  becomes a per-sample box.
* **Redundancy resolution.** Among the x that reach a sample, the planner
  takes the one of least ``sum_k ((x_k - x_ref,k) / s_k)^2`` (``x_ref``:
  the previous joint commands and the inputs' lower bounds, the
  pretension; ``s_k``: the scale of x_k, the norm of its tip sensitivity):
  Gauss-Newton phases on ``|W e|^2 + eps^2 |S (x - x_ref)|^2`` (``eps =
  1e-3``, then ``1e-5``, biasing the tip by O(eps^2)) walk along the
  redundant directions, then a phase on the tip error alone polishes the
  target without moving along them. For antagonistic tendons
  (co-contraction leaves the shape unchanged) this puts the slack tendon of
  every pair exactly at the pretension and the other at the least tension
  that holds the pose: the **minimum total tension above the pretension**.
* **Continuity.** Each sample is warm-started from the previous one (x and
  shape extrapolated linearly from the two previous samples), so
  consecutive samples follow the same branch.
* **Unreachable samples** are flagged (``reached`` False, ``status`` says
  why: ``at_limit`` a bound blocks, ``rate_limit`` a rate limit blocks,
  ``out_of_workspace`` the frame cannot get closer by any small change of
  x, ``statics_failed`` no equilibrium), and the plan follows the closest
  reachable point (the minimiser of the weighted error within the bounds,
  locally).

Errors are weighted: ``position_weights`` (3, per world axis, e.g. [0, 1,
1] tracks y and z only) and ``orientation_weight`` [m/rad] when the path
has orientations. A sample is ``reached`` when the weighted position error
is at most ``tolerance`` [m] and the orientation error at most
``tolerance_rad``. :func:`simulate_plan` executes a plan with the dynamics
and :func:`compensate_lag` iterates the plan against it.
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core._blas import one_blas_thread
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import actuation_matrix, point_moment_arrays
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.bvls import box_lstsq_kernel, regularised_box_step
from soft_twin_core.engine.kernels.data import kernel_array
from soft_twin_core.engine.kernels.frames import point_pose, spatial_jacobian
from soft_twin_core.engine.kernels.tip_error import error_jacobian, tip_error
from soft_twin_core.engine.loads import Loads
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import PlanError, StaticsError
from soft_twin_core.lie import checked_rigid_transform, hat
from soft_twin_core.planning.paths import TipPath
from soft_twin_core.robot.mechanism import base_targets, tip_frame
from soft_twin_core.solve import constrained as cs, equilibrium as eq


# ----------------------------------------------------------------------------
# Bounded least squares
# ----------------------------------------------------------------------------

def box_lstsq(A, b, lo, hi, max_iterations=None):
    """min |A x - b|^2 subject to lo <= x <= hi (lo <= 0 <= hi), by the
    active-set method of Stark and Parker (BVLS) from x = 0, compiled
    (:func:`soft_twin_core.engine.kernels.bvls.box_lstsq_kernel`; for the few
    columns of an IK step a scipy call costs more than the solve).
    Returns x, always inside the box."""
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
    (:func:`kernels.bvls.regularised_box_step`). Unknowns whose box is empty
    stay put. Returns (dx, all_fixed)."""
    c = kernel_array
    dx = np.empty(x.size)
    held = regularised_box_step(c(Je, dtype=float), c(e, dtype=float), c(x, dtype=float), c(lo, dtype=float),
                                c(hi, dtype=float), c(scale, dtype=float), float(eps), c(x_ref, dtype=float),
                                float(lam), dx)
    return dx, bool(held)


# ----------------------------------------------------------------------------
# Options, bounds
# ----------------------------------------------------------------------------

def _per_actuator(mech, value, name, default, allow_inf=True):
    """A scalar, a list (one per actuator) or a dict {name: value} -> array."""
    names = tuple(mech.actuator_names)
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
    (:class:`loads.Loads`, default gravity only); frame: the frame that
    follows the path (default the robot's tip, :func:`mechanism.tip_frame`);
    joint_limits_margin [rad or m] kept inside the joint limits; efforts
    {joint: N m or N} held by the effort-controlled joints (default 0) and
    point_loads (:class:`constrained.FrameLoad` on named frames), both
    constant over the path (e.g. the node's current joint efforts and tip
    wrench); base_pose (4x4, world <- base; None: the robot file's): where
    a prescribed base is carried (the twin's base pose): the statics hold
    it there, and the path's base frame is there."""
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
    frame: str = None
    joint_limits_margin: float = 0.0
    efforts: object = None
    point_loads: tuple = ()
    base_pose: object = None

    def weights(self):
        """(sqrt of the position weights (3,), sqrt of the orientation
        weight); PlanError naming a bad option."""
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


def base_pose_of(mech, options):
    """(the base's pose 4x4, world <- base; the constraints' ``targets``
    of the statics, None for the robot file's): ``options.base_pose`` for
    a prescribed base (checked: a rigid transform), else the robot
    file's; PlanError naming ``base_pose`` on a robot whose base is not
    prescribed or on a bad pose."""
    T = None if options is None else options.base_pose
    if T is None:
        return np.asarray(mech.base_pose, dtype=float), None
    if mech.base_motion != "prescribed":
        raise PlanError(f"base_pose: only for a robot whose base is prescribed (base: {{motion: prescribed}}); "
                        f"this robot's base is {mech.base_motion}")
    try:
        T = checked_rigid_transform(T, "base_pose")
    except ValueError as e:
        raise PlanError(str(e)) from None
    return T, base_targets(mech, T)


def actuator_bounds(mech, options=None):
    """(lower, upper) input bounds (n_act,): the robot file's range of each
    actuator ([Actuator.lower, Actuator.upper]: limit, min, max) cut by the
    options: tendons [max(lower, pretension), min(upper, max_tension)],
    chambers [lower, min(upper, max_pressure)]."""
    o = PlanOptions() if options is None else options
    pre = _per_actuator(mech, o.pretension, "pretension", 0.0, allow_inf=False)
    tmax = _per_actuator(mech, o.max_tension, "max_tension", np.inf)
    pmax = _per_actuator(mech, o.max_pressure, "max_pressure", np.inf)
    lo, hi = np.empty(len(mech.actuators)), np.empty(len(mech.actuators))
    for k, a in enumerate(mech.actuators):
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


def rate_limits(mech, options):
    """Per-actuator rate limit [unit/s] (inf: none)."""
    r = _per_actuator(mech, options.max_rate, "max_rate", np.inf)
    if np.any(r <= 0):
        raise PlanError(f"max_rate: expected values > 0 (per second), got {r.tolist()}")
    return r


# ----------------------------------------------------------------------------
# The statics of a sample and its exact sensitivity
# ----------------------------------------------------------------------------

def _actuators(mech):
    """The mechanism's :func:`forces.actuator_arrays`, made once."""
    return cs._cached(mech, "_act_arrays", lambda: cs.actuator_arrays(mech.tree))


@dataclass
class _Eq:
    """An equilibrium of a sample: q, the frame's pose, the statics tangent
    it was found with (or None) and the solver's result (or None)."""
    q: np.ndarray
    pose: np.ndarray
    tangent: object = None
    result: object = None


class _Statics:
    """The equilibrium of a sample as a function of x, and its exact
    sensitivity, for one mechanism, frame and held inputs (efforts, loads):
    the general path through :func:`constrained.solve_equilibrium` and the
    KKT system."""

    def __init__(self, mech, ref, options, loads, n_j, targets=None):
        self.mech, self.ref, self.options, self.loads, self.n_j = mech, ref, options, loads, n_j
        self.targets = targets          # a carried base's clamp target (base_pose_of)
        self.ws = Workspace(mech.tree)

    def pose(self, q):
        """World pose (4x4) of the frame at q."""
        ws = self.ws
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, dtype=float), ws.zeros_v, ws.zeros_v, 0)
        g = np.empty((4, 4))
        point_pose(ws.m, ws.w, self.ref.joint, self.ref.x, g)
        return g

    def solve(self, x, q_init, hint=None, q_guess=None, stability=False):
        """The equilibrium under x from q_init (StaticsError if none)."""
        o, nj = self.options, self.n_j
        try:
            r = cs.solve_equilibrium(self.mech, actuation=x[nj:] if len(x) > nj else None, efforts=o.efforts,
                                     positions=x[:nj] if nj else None, loads=self.loads,
                                     point_loads=tuple(o.point_loads), q_init=q_init,
                                     check_stability=stability, tangent_hint=hint, targets=self.targets)
        except ValueError as e:
            raise StaticsError(str(e)) from None
        return _Eq(r.q, self.pose(r.q), getattr(r, "tangent", None), r)

    def sensitivity(self, e, x, Kt=None):
        """(frame pose, spatial Jacobian Js (6, nv), dq/dx (nv, n_x)) at the
        equilibrium ``e``: the implicit function theorem on the KKT system."""
        mech, tree, nj = self.mech, self.mech.tree, self.n_j
        pb = cs._Equilibrium(mech, e.result.inputs, self.targets)
        q, lam = e.q, e.result.lam
        Kt = pb.tangent(q, lam)
        _, phi, G = pb.residual(q, lam)
        n_x = len(x)
        dR = np.zeros((tree.nv, n_x))
        dphi = np.zeros((len(phi), n_x))
        for k in range(nj):                              # rows q_j - q_cmd,j: d/dq_cmd = -1
            dphi[len(phi) - nj + k, k] = -1.0
        if n_x > nj:
            dR[:, nj:] = -actuation_matrix(mech.tree, self.ws, _actuators(mech), q)
        fac = cs.factor_kkt(Kt, G, G)
        if pb.T is not None:            # variable-strain segments: the KKT system in their coordinates
            dR = pb.T.T @ dR
        dq = np.column_stack([cs.solve_factored(fac, dR[:, k], dphi[:, k])[0] for k in range(n_x)])
        return self._jacobian(q) + (pb.lift(dq),)

    def _jacobian(self, q):
        ws = self.ws
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, dtype=float), ws.zeros_v, ws.zeros_v, 0)
        g, Js = np.empty((4, 4)), np.empty((6, self.mech.tree.nv))
        spatial_jacobian(ws.m, ws.w, self.ref.joint, self.ref.x, g, Js)
        return g, Js


class _FreeStatics(_Statics):
    """The statics of a sample without multipliers (no constraint, no
    position-controlled joint: x = u), as the classic rod's: the compiled
    problem made once and re-used for every u (its coefficients and the
    point-moment tendons' moments set per u), Newton from a tangent hint;
    the full solver (continuation, stability) when Newton fails;
    ``dq/du = Kt^-1 B``. With variable-strain segments the Newton and the
    tangents are in their coordinates z (:class:`equilibrium.ReducedProblem`)
    and ``dq/du = T (T^T Kt T)^-1 T^T B`` (T the strain basis)."""

    def __init__(self, mech, ref, options, loads, n_j):
        super().__init__(mech, ref, options, loads, n_j)
        inp = cs.make_inputs(mech, None, options.efforts, None, None, loads, tuple(options.point_loads))
        self._base_loads, self._pm = inp.loads, point_moment_arrays
        self.point_moment = any(a.tendon_model == "point_moment" for a in mech.actuators)
        self.pb = self.full = cs.free_problem(mech, inp)
        self.ws = self.full.ws
        self.T = mech.basis
        if self.T is not None:
            self.pb = eq.ReducedProblem(self.full, self.T)
        self._u = None

    def _set(self, u):
        pb = self.full
        if self._u is not None and np.array_equal(self._u, u):
            return self.pb
        pb.coef = np.ascontiguousarray(pb.act.unit @ u) if u.size else pb.coef
        if self.point_moment:
            pb.loads = cs.concat_loads(self._base_loads, self._pm(self.mech.tree, u))
        self._u = np.array(u, dtype=float)
        return self.pb

    def newton(self, q, u, hint=None, tol=1e-12):
        """(q, converged and stable, last tangent): Newton from q under u."""
        pb = self._set(np.asarray(u, dtype=float))
        if self.T is not None:
            z1, _, _, ok, Kt = eq.newton(pb, pb.z_of(q), tol, 30, hint)
            q1 = pb.q_of(z1)
        else:
            q1, _, _, ok, Kt = eq.newton(pb, q, tol, 30, hint)
        if ok and Kt is not None and Kt is not hint:
            ok = eq.is_stable(Kt)
        elif ok:
            Kt = None
        return q1, ok, Kt

    def solve(self, x, q_init, hint=None, q_guess=None, stability=True):
        for start in ((q_guess, q_init) if q_guess is not None else (q_init,)):
            if start is not None:
                q, ok, Kt = self.newton(np.asarray(start, float), x, hint)
                if ok:
                    return _Eq(q, self.pose(q), Kt)
        r = super().solve(x, q_init, hint, stability=True)
        return _Eq(r.q, r.pose, getattr(r.result, "tangent", None))

    def sensitivity(self, e, x, Kt=None):
        pb = self._set(np.asarray(x, dtype=float))
        if Kt is None:
            Kt = pb.tangent(e.q if self.T is None else pb.z_of(e.q))
        g, Js = self._jacobian(e.q)                       # the forward pass at q, then B on it
        B = actuation_matrix(self.mech.tree, self.ws, _actuators(self.mech), e.q, posed=True)
        if self.T is not None:
            return g, Js, self.T @ np.linalg.solve(Kt, self.T.T @ B)
        return g, Js, np.linalg.solve(Kt, B)


@dataclass
class SampleResult:
    """x (n_j + n_act,): joint commands then inputs; q (equilibrium); the
    frame's pose (4x4 world); position_error [m] (3-D distance),
    weighted_error [m] (with position_weights), orientation_error [rad],
    reached, status ("reached", "at_limit", "rate_limit",
    "out_of_workspace", "statics_failed"), iterations."""
    x: np.ndarray
    q: np.ndarray
    pose: np.ndarray
    position_error: float
    weighted_error: float
    orientation_error: float
    reached: bool
    status: str
    iterations: int


class TipSolver:
    """Joint commands and actuator inputs that put a frame at a target
    through statics, for one mechanism, frame, held inputs and options;
    re-used sample after sample (warm starts, the compiled statics made
    once)."""

    EPS_REDUNDANCY = 1e-3

    def __init__(self, mech, options=None):
        self.mech = mech
        self.options = o = PlanOptions() if options is None else options
        tree = mech.tree
        self.pos = mech.joints_with("position")
        self.joint_names = tuple(tree.joints[i].name for i in self.pos)
        self.actuator_names = tuple(mech.actuator_names)
        self.n_j, self.n_u = len(self.pos), len(self.actuator_names)
        if self.n_j + self.n_u == 0:
            raise PlanError("this robot has no actuators and no position-controlled joints: nothing to plan")
        self.frame = o.frame or tip_frame(mech)
        try:
            self.ref = mech.frame(self.frame)
        except KeyError as e:
            raise PlanError(f"frame: {e.args[0]}") from None
        self.sw, self.swo = o.weights()
        margin = _number(o.joint_limits_margin, "joint_limits_margin", False)
        if margin < 0:
            raise PlanError(f"joint_limits_margin: expected a number >= 0, got {margin}")
        self.loads = Loads() if o.loads is None else o.loads
        self.base_pose, targets = base_pose_of(mech, o)
        jlo, jhi = np.full(self.n_j, -np.inf), np.full(self.n_j, np.inf)
        vmax, amax = np.full(self.n_j, np.inf), np.full(self.n_j, np.inf)
        for k, i in enumerate(self.pos):
            j = tree.joints[i]
            if j.limits is not None:
                jlo[k], jhi[k] = j.limits[0] + margin, j.limits[1] - margin
                if not jlo[k] < jhi[k]:
                    raise PlanError(f"joint_limits_margin: {margin} leaves no range of joint {j.name!r} "
                                    f"(limits {list(j.limits)})")
            vmax[k], amax[k] = mech.motion_limits.get(j.name, (np.inf, np.inf))
        ulo, uhi = actuator_bounds(mech, o)
        self.rate = rate_limits(mech, o)
        self.lower, self.upper = np.concatenate([jlo, ulo]), np.concatenate([jhi, uhi])
        self.max_velocity, self.max_acceleration = vmax, amax
        try:
            free = self.n_j == 0 and mech.n_constraint_rows == 0          # no multiplier: the compiled statics
            self.statics = _FreeStatics(mech, self.ref, o, self.loads, self.n_j) if free else \
                _Statics(mech, self.ref, o, self.loads, self.n_j, targets)
        except ValueError as e:
            raise PlanError(str(e)) from None
        self.with_rot = False          # the orientation counts (a path with orientations, a pose target)

    def split(self, x):
        return x[:self.n_j], x[self.n_j:]

    def reference(self, x_prev):
        """x_ref of the redundancy resolution: the previous joint commands,
        the inputs' lower bounds (0 where unbounded)."""
        nj = self.n_j
        return np.concatenate([np.asarray(x_prev, float)[:nj],
                               np.where(np.isfinite(self.lower[nj:]), self.lower[nj:], 0.0)])

    # -- error model ------------------------------------------------------
    def _rot(self):
        return self.with_rot and self.swo > 0

    def _error(self, g, target):
        e = np.empty(6 if self._rot() else 3)
        tip_error(np.ascontiguousarray(g, dtype=float), target, self.sw, self.swo, self._rot(), e)
        return e

    def errors(self, g, target):
        """(position distance [m], weighted position error [m], orientation error [rad] or 0)."""
        return tip_error(np.ascontiguousarray(g, dtype=float), np.ascontiguousarray(target, dtype=float), self.sw,
                         self.swo, self._rot(), np.empty(6))

    def reached(self, g, target):
        _, we, oe = self.errors(g, target)
        return we <= self.options.tolerance and (not self._rot() or oe <= self.options.tolerance_rad)

    def _error_jacobian(self, e_eq, x, err, Kt=None):
        key = getattr(self, "_jac_key", None)
        if key is not None and key[0] is e_eq.q and np.array_equal(key[1], x) and np.array_equal(key[2], err):
            return key[3]
        g, Js, dq_dx = self.statics.sensitivity(e_eq, x, Kt)
        self._dq_dx = (e_eq.q, np.array(x), dq_dx)
        Je = np.empty((err.size, dq_dx.shape[1]))
        error_jacobian(g, Js, np.ascontiguousarray(dq_dx), err, self.sw, self.swo, self._rot(), Je)
        self._jac_key = (e_eq.q, np.array(x), np.array(err), Je)
        return Je

    def _predicted(self, q, x, x_new):
        """The equilibrium under x_new to first order from the one at (q, x),
        with the sensitivity of the last Jacobian (None if not taken at q)."""
        d = getattr(self, "_dq_dx", None)
        if d is None or d[0] is not q or not np.array_equal(d[1], x) or q.shape != d[2].shape[:1]:
            return None         # (no sensitivity at q; or a carried base's quaternion: q is not additive)
        return q + d[2] @ (x_new - x)

    def held(self, target, x, q):
        """A sample whose statics failed from every start: the x and
        equilibrium (x, q) of the sample before are kept, flagged
        ``statics_failed`` (never reached)."""
        g = self.statics.pose(q)
        pe, we, oe = self.errors(g, target)
        return SampleResult(np.array(x, float), np.array(q, float), g, pe, we, oe, False, "statics_failed", 0)

    # -- the solve ---------------------------------------------------------
    def solve(self, target, x_init, q_init, lower=None, upper=None, rate_box=None, x_ref=None, redundancy=True):
        """x within [lower, upper] (default the bounds) whose equilibrium
        puts the frame at ``target`` (world: a position (3,) [m] or a pose
        4x4; the orientation counts when ``with_rot`` and the orientation
        weight > 0); ``x_ref``: the reference of the redundancy resolution
        (default: :meth:`reference` of x_init); ``rate_box``: (lo, hi) of
        the rate limits, only to say which bound blocks an unreachable
        sample. Returns a :class:`SampleResult`; StaticsError when no
        equilibrium is found from x_init."""
        target = np.asarray(target, dtype=float)
        if target.shape == (3,):                    # a position: for this solve, the orientation is free
            T = np.eye(4)
            T[:3, 3] = target
            with_rot, self.with_rot = self.with_rot, False
            try:
                return self.solve(T, x_init, q_init, lower, upper, rate_box, x_ref, redundancy)
            finally:
                self.with_rot = with_rot
        lo = self.lower if lower is None else np.asarray(lower, float)
        hi = self.upper if upper is None else np.asarray(upper, float)
        target = np.ascontiguousarray(target)
        x = np.clip(np.asarray(x_init, dtype=float), lo, hi)
        x_ref = self.reference(x) if x_ref is None else np.asarray(x_ref, float)
        with one_blas_thread():
            try:
                res = self.statics.solve(x, q_init)
            except StaticsError:
                res = self.statics.solve(x, None)
            err = self._error(res.pose, target)
            it_total, scale = 0, None
            for eps in ((self.EPS_REDUNDANCY, 1e-2 * self.EPS_REDUNDANCY, 0.0) if redundancy else (0.0,)):
                x, res, err, it, scale = self._gauss_newton(x, res, err, target, lo, hi, eps, x_ref, scale)
                it_total += it
        pe, we, oe = self.errors(res.pose, target)
        reached = self.reached(res.pose, target)
        status = "reached" if reached else self._blocking(x, res, err, lo, hi, rate_box)
        return SampleResult(x, res.q, res.pose, pe, we, oe, reached, status, it_total)

    def _gauss_newton(self, x, res, err, target, lo, hi, eps, x_ref, scale):
        lam, it = 0.0, 0
        tol = self.options.tolerance
        scale = None if eps > 0 or scale is None else scale

        def cost(x_, e_):
            c = float(e_ @ e_)
            if eps > 0:
                r = eps * scale * (x_ - x_ref)
                c += float(r @ r)
            return c

        costs = []
        for it in range(1, self.options.max_iterations + 1):
            if eps == 0.0 and self.reached(res.pose, target):
                return x, res, err, it - 1, scale
            try:
                # the tangent of the statics that gave q (Gauss-Newton needs no more accurate a Jacobian)
                Je = self._error_jacobian(res, x, err, res.tangent)
            except (np.linalg.LinAlgError, ValueError):
                return x, res, err, it, scale
            if scale is None:
                scale = np.maximum(np.linalg.norm(Je, axis=0), 1e-12 * max(np.linalg.norm(Je), 1e-300))
            c0 = cost(x, err)
            improved = False
            for _ in range(10):
                dx, all_fixed = bounded_gauss_newton_step(Je, err, x, lo, hi, scale, eps, x_ref, lam)
                if all_fixed or np.linalg.norm(dx * scale) <= 1e-14 * max(np.linalg.norm(x * scale), tol):
                    return x, res, err, it, scale
                # the linear model promises (almost) nothing: at the (regularised) optimum
                r_lin = Je @ dx + err
                pred = float(r_lin @ r_lin)
                if eps > 0:
                    rr = eps * scale * (x + dx - x_ref)
                    pred += float(rr @ rr)
                if lam <= 1e-8 and (np.linalg.norm(scale * dx) <= 0.1 * tol or c0 - pred <= 1e-3 * c0) \
                        and (eps > 0 or np.sqrt(pred) > tol or np.linalg.norm(scale * dx) <= 1e-3 * tol):
                    return x, res, err, it, scale
                x_new = np.clip(x + dx, lo, hi)
                try:
                    r = self.statics.solve(x_new, res.q, res.tangent, self._predicted(res.q, x, x_new))
                except StaticsError:
                    lam = max(4 * lam, 1e-4)
                    continue
                e_new = self._error(r.pose, target)
                if cost(x_new, e_new) < c0:
                    x, res, err = x_new, r, e_new
                    lam = lam / 10 if lam > 1e-8 else 0.0
                    improved = True
                    break
                lam = max(4 * lam, 1e-4)
            if not improved:
                break
            if eps > 0 and cost(x, err) > (1 - 1e-10) * c0:
                break
            costs.append(cost(x, err))
            if len(costs) > 4 and costs[-1] > 0.25 * costs[-5]:
                break      # stagnating (error not halved in 4 steps): a near-singular direction or a bound
        return x, res, err, it, scale

    def _blocking(self, x, res, err, lo, hi, rate_box):
        """Why an unreached sample stopped: the bound the gradient of the
        error presses against, or none (out of the workspace)."""
        try:
            Je = self._error_jacobian(res, x, err)
        except (np.linalg.LinAlgError, ValueError, StaticsError):
            return "statics_failed"
        grad = Je.T @ err                   # d(0.5 |e|^2)/dx: descent is -grad
        sc = np.abs(grad).max(initial=0.0)
        atol = 1e-9 * np.maximum(1.0, np.abs(x))
        press_lo = (x <= lo + atol) & (grad > 1e-6 * sc)
        press_hi = (x >= hi - atol) & (grad < -1e-6 * sc)
        if not np.any(press_lo | press_hi):
            return "out_of_workspace"
        if rate_box is not None:
            rlo, rhi = rate_box
            if np.any((press_lo & (rlo > self.lower + atol)) | (press_hi & (rhi < self.upper - atol))):
                return "rate_limit"
        return "at_limit"


    def frame_motion(self, e, x):
        """(frame pose, S (6, n_x)): the velocity of the frame's origin and
        its angular velocity, world axes, per unit of each x, at the
        equilibrium ``e`` under x: ``[Js_v - hat(p) Js_w; Js_w] dq/dx``
        (Js: the spatial Jacobian of the frame)."""
        g, Js, dq_dx = self.statics.sensitivity(e, np.asarray(x, float))
        J = np.vstack([Js[:3] - hat(g[:3, 3]) @ Js[3:], Js[3:]])
        return g, J @ dq_dx


def frame_sensitivity(mech, q, x, options=None):
    """d(frame position, world)/dx (3, n_j + n_act) at the equilibrium
    reached from q under x (the options' frame, default the tip)."""
    solver = TipSolver(mech, options)
    e = solver.statics.solve(np.asarray(x, float), np.asarray(q, float))
    return solver.frame_motion(e, x)[1][:3]


# ----------------------------------------------------------------------------
# Paths
# ----------------------------------------------------------------------------

@dataclass
class Plan:
    """A command sequence: times (N,) [s]; u (N, n_act) inputs (N, Pa); q
    (N, nq) the static shapes; tip (N, 3) predicted positions of the frame
    (quasi-static, world); target (N, 3) (world); position_error (N,) [m]
    (3-D distance), weighted_error (N,) [m], orientation_error (N,) [rad];
    reached (N,) bool; status (N,) str; lower/upper (n_act,) the actuator
    bounds, max_rate (n_act,) [unit/s]; actuator_names; iterations (N,);
    tip_rotation (N, 3, 3) with a path with orientations; joint_names,
    joints (N, n_joints) position commands [rad or m], joint_lower/upper,
    max_velocity [rad/s or m/s] and max_acceleration [rad/s^2 or m/s^2] of
    those joints (empty without position-controlled joints); frame: the
    frame that follows the path."""
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
    joint_names: tuple = ()
    joints: np.ndarray = None
    joint_lower: np.ndarray = None
    joint_upper: np.ndarray = None
    max_velocity: np.ndarray = None
    max_acceleration: np.ndarray = None
    frame: str = ""

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
    """Bounds [lo, hi] of a sample: the bounds cut by the rate box [rlo,
    rhi]; where they do not overlap, the bound nearest the box."""
    lo, hi = np.maximum(lower, rlo), np.minimum(upper, rhi)
    return np.minimum(lo, hi), np.maximum(np.minimum(lo, hi), hi)


def warm_start(hist, default):
    """Start (x, shape) of the next sample: linear extrapolation from the two
    previous samples' (x, shape) in ``hist``, the previous one after the
    first, ``default`` before any."""
    if len(hist) >= 2:
        (x1, q1), (x2, q2) = hist[-2], hist[-1]
        return x2 + (x2 - x1), q2 + (q2 - q1)
    return hist[-1] if hist else default


def braking_step(distance, astep):
    """The largest increment per step towards a joint limit ``distance``
    away (>= 0) from which the joint still stops before it, decelerating by
    at most ``astep`` per step (the increments d, d - astep, ... sum to at
    most d + d^2 / (2 astep) <= distance): astep (sqrt(1 + 2 distance /
    astep) - 1); inf without an acceleration limit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = astep * (np.sqrt(1.0 + 2.0 * np.maximum(distance, 0.0) / astep) - 1.0)
    return np.where(np.isfinite(astep), np.where(astep > 0, out, 0.0), np.inf)


def _rate_box(solver, x_prev, d_prev, dt):
    """(lo, hi) of x from the rate limits: joints by velocity and
    acceleration (d_prev: previous joint increment) and by what still lets
    them stop before their limits (:func:`braking_step`), inputs by
    max_rate."""
    nj = solver.n_j
    lo, hi = np.full(x_prev.size, -np.inf), np.full(x_prev.size, np.inf)
    def per_step(limit, scale):                  # limit * scale, inf where no limit (also at dt = 0)
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(limit), limit * scale, np.inf)
    vstep = per_step(solver.max_velocity, dt)
    astep = per_step(solver.max_acceleration, dt * dt)
    dlo = np.maximum(-vstep, d_prev - astep)
    dhi = np.minimum(vstep, d_prev + astep)
    # towards a limit no faster than the joint can brake in time; a joint already faster than that
    # (it cannot be, from a start at rest) brakes as hard as allowed
    dhi = np.maximum(np.minimum(dhi, braking_step(solver.upper[:nj] - x_prev[:nj], astep)), dlo)
    dlo = np.minimum(np.maximum(dlo, -braking_step(x_prev[:nj] - solver.lower[:nj], astep)), dhi)
    lo[:nj], hi[:nj] = x_prev[:nj] + dlo, x_prev[:nj] + dhi
    ustep = per_step(solver.rate, dt)
    lo[nj:], hi[nj:] = x_prev[nj:] - ustep, x_prev[nj:] + ustep
    return lo, hi


def start_vector(mech, solver, actuation=None, positions=None):
    """x of the given inputs: position commands ({joint: rad or m}, default
    each joint's reference) and actuator inputs (default their lower
    bounds), clipped to the bounds."""
    tree, nj = mech.tree, solver.n_j
    pos = dict(positions or {})
    qc = [float(pos.get(n, tree.joints[i].q_ref)) for n, i in zip(solver.joint_names, solver.pos)]
    u = cs.actuation_vector(mech, actuation) if actuation is not None else np.where(
        np.isfinite(solver.lower[nj:]), solver.lower[nj:], 0.0)
    return np.clip(np.concatenate([qc, u]), solver.lower, solver.upper)


def plan_path(mech, path, options=None, start=None, q_start=None, solver=None, from_start=False):
    """Plan the joint commands and actuator inputs of a :class:`TipPath`
    (the base frame; with orientations the frame's orientation is tracked
    too, weighted by ``orientation_weight``).

    start: x = [joint commands, inputs] before the path (default: the joint
    references, the inputs at their lower bounds); the first sample starts
    from it. ``from_start``: the rate limits also hold from ``start`` to the
    first sample (which then is ``start`` where they bind: the robot is
    there now); else the first sample is free and the plan starts at rest
    there. q_start: the shape to warm-start from (default: the equilibrium
    under ``start``)."""
    if not isinstance(path, TipPath):
        raise PlanError(f"path: expected a TipPath, got {type(path).__name__}")
    solver = TipSolver(mech, options) if solver is None else solver
    solver.with_rot = path.orientations is not None
    nj = solver.n_j
    if start is None:
        x = start_vector(mech, solver)
    else:
        x = np.asarray(start, float)
        if x.shape != solver.lower.shape:
            raise PlanError(f"start: expected {solver.lower.size} values (joints {list(solver.joint_names)}, "
                            f"actuators {list(solver.actuator_names)})")
        x = np.clip(x, solver.lower, solver.upper)
    if q_start is not None:
        q = mech.tree.check_q(np.array(q_start, dtype=float), "q_start")
    else:
        q = solver.statics.solve(x, None).q
    targets = path.world_targets(solver.base_pose)
    N = len(path)
    out = {k: [] for k in ("x", "q", "tip", "R", "pe", "we", "oe", "reached", "status", "it")}
    d_prev = np.zeros(nj)
    hist = []
    for i in range(N):
        lo, hi, box = solver.lower, solver.upper, None
        if i > 0 or from_start:
            rlo, rhi = _rate_box(solver, x, d_prev, path.times[i] - path.times[i - 1] if i > 0 else 0.0)
            lo, hi = rate_bounds(solver.lower, solver.upper, rlo, rhi)
            box = (rlo, rhi)
        x0, q0 = warm_start(hist, (x, q))
        x_ref = solver.reference(x)
        try:
            r = solver.solve(targets[i], np.clip(x0, lo, hi), q0, lo, hi, box, x_ref)
        except StaticsError:
            if not hist:
                raise
            # the extrapolated start may lie beyond what the robot carries: from the sample before,
            # else that sample held and flagged
            try:
                r = solver.solve(targets[i], np.clip(hist[-1][0], lo, hi), hist[-1][1], lo, hi, box, x_ref)
            except StaticsError:
                r = solver.held(targets[i], *hist[-1])
        if i > 0 or from_start:
            d_prev = r.x[:nj] - x[:nj]
        x = r.x
        hist.append((r.x, r.q))
        for k, v in zip(out, (r.x, r.q, r.pose[:3, 3], r.pose[:3, :3], r.position_error, r.weighted_error,
                              r.orientation_error, r.reached, r.status, r.iterations)):
            out[k].append(v)
    X = np.array(out["x"]).reshape(N, -1)
    return Plan(path.times.copy(), X[:, nj:].copy(), np.array(out["q"]), np.array(out["tip"]),
                targets[:, :3, 3].copy(), np.array(out["pe"]), np.array(out["we"]), np.array(out["oe"]),
                np.array(out["reached"], bool), out["status"], solver.lower[nj:].copy(), solver.upper[nj:].copy(),
                solver.rate.copy(), solver.actuator_names, np.array(out["it"]),
                None if path.orientations is None else np.array(out["R"]), solver.joint_names,
                X[:, :nj].copy(), solver.lower[:nj].copy(), solver.upper[:nj].copy(), solver.max_velocity.copy(),
                solver.max_acceleration.copy(), solver.frame)


def check_plan(plan, rtol=1e-12):
    """Violations of the plan's actuator bounds and rates, joint limits and
    joint velocity/acceleration limits (a list of strings, empty when none).
    The plan starts at rest at its first sample."""
    bad = []
    dt = np.diff(plan.times)
    for k, name in enumerate(plan.actuator_names):
        u = plan.u[:, k]
        if np.any(u < plan.lower[k] - rtol) or np.any(u > plan.upper[k] + rtol):
            bad.append(f"{name}: outside [{plan.lower[k]}, {plan.upper[k]}]")
        if np.isfinite(plan.max_rate[k]) and len(u) > 1:
            rate = np.abs(np.diff(u)) / dt
            if np.any(rate > plan.max_rate[k] * (1 + 1e-12) + rtol):
                bad.append(f"{name}: rate {rate.max()} > {plan.max_rate[k]}")
    for k, name in enumerate(plan.joint_names):
        qk = plan.joints[:, k]
        if np.any(qk < plan.joint_lower[k] - rtol) or np.any(qk > plan.joint_upper[k] + rtol):
            bad.append(f"joint {name}: outside [{plan.joint_lower[k]}, {plan.joint_upper[k]}]")
        if len(qk) < 2:
            continue
        d = np.diff(qk)
        vmax, amax = plan.max_velocity[k], plan.max_acceleration[k]
        if np.isfinite(vmax) and np.any(np.abs(d) > vmax * dt * (1 + 1e-9) + rtol):
            bad.append(f"joint {name}: speed {np.max(np.abs(d) / dt)} > {vmax}")
        if np.isfinite(amax):
            dd = np.diff(np.concatenate([[0.0], d]))
            lim = amax * dt ** 2
            if np.any(np.abs(dd) > lim * (1 + 1e-9) + rtol):
                bad.append(f"joint {name}: acceleration {np.max(np.abs(dd) / lim * amax)} > {amax}")
    return bad


# ----------------------------------------------------------------------------
# Dynamic verification and feed-forward compensation
# ----------------------------------------------------------------------------

@dataclass
class Tracking:
    """A simulated execution of a plan: time (M,) [s]; tip (M, 3) world
    positions of the plan's frame; target (M, 3) the path at those times
    (linear between samples); error (M,) [m] weighted distance
    (position_weights), distance (M,) [m] 3-D; converged: every step
    converged."""
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


def simulate_plan(mech, plan, options=None, path_positions=None, dt=0.005, theta=0.5, hold=0.0):
    """Execute ``plan`` with the dynamics (:class:`constrained.MechanismSimulator`:
    the compiled O(n) integrator without multipliers) from rest at the
    static equilibrium of its first sample: the position-controlled joints
    reach the commands (linear between samples) at the end of each step,
    the actuator inputs linear between samples at the step's theta point,
    the options' efforts and loads held, the last commands held ``hold``
    [s] after the end. The plan's frame is compared with ``path_positions``
    (N, 3) world (default the plan's targets), linear between samples.
    Returns :class:`Tracking`; a step that fails ends the run
    (``converged`` False)."""
    o = options or PlanOptions()
    P = plan.target if path_positions is None else np.asarray(path_positions, dtype=float)
    sw = np.sqrt(np.asarray(o.position_weights, dtype=float))
    ref = mech.frame(plan.frame or tip_frame(mech))
    times = np.asarray(plan.times, dtype=float)
    nj = len(plan.joint_names)
    joints = np.zeros((len(times), 0)) if plan.joints is None else np.asarray(plan.joints, float)
    X = np.concatenate([joints.reshape(len(times), -1), np.asarray(plan.u, float).reshape(len(times), -1)],
                       axis=1)

    def commands(t):
        x = np.array([np.interp(t, times, X[:, k]) for k in range(X.shape[1])])
        return dict(zip(plan.joint_names, x[:nj])), x[nj:]
    pos, u = commands(times[0])
    _, held = base_pose_of(mech, o)                            # a carried base held where the plan was made
    eq0 = cs.solve_equilibrium(mech, u, o.efforts, pos, o.loads, o.point_loads, q_init=plan.q[0], targets=held)
    sim = cs.MechanismSimulator(mech, dt, theta, q=eq0.q)
    ws = Workspace(mech.tree)

    def frame_position(q):
        return alg.point_poses(mech.tree, ws, q, [ref.joint], [ref.x])[0][:3, 3].copy()
    ts, tips, ok = [times[0]], [frame_position(sim.q)], True
    n = int(round((times[-1] - times[0] + hold) / dt))
    for k in range(1, n + 1):
        t1 = times[0] + k * dt
        pos, _ = commands(t1)                                  # the joints reach them at the end of the step
        _, u = commands(t1 - (1.0 - theta) * dt)               # the inputs at the step's theta point
        try:
            sim.step(u, o.efforts, pos, o.loads, o.point_loads, targets=held)
        except (cs.StepError, StaticsError, ValueError, np.linalg.LinAlgError):
            ok = False
            break
        ts.append(t1)
        tips.append(frame_position(sim.q))
    ts, tips = np.array(ts), np.array(tips)
    tgt = np.stack([np.interp(ts, times, P[:, k]) for k in range(3)], axis=-1)
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


def compensate_lag(mech, path, options=None, iterations=4, gain=0.5, dt=0.005, start=None, sigma=0.25,
                   from_start=False):
    """Feed-forward compensation of the dynamic lag by iterating the plan
    against the simulated response (iterative learning on the targets):
    plan, simulate (:func:`simulate_plan`), shift every sample's target by
    ``gain`` times the simulated error at its time (smoothed over ``sigma``
    [s], a zero-phase Gaussian: the learning filter), replan;
    ``iterations`` times. The error is always measured against the
    original path. ``start``, ``from_start``: as :func:`plan_path`. Returns
    (best plan, its Tracking, history: one summary dict per iteration, 0 =
    uncompensated)."""
    options = PlanOptions() if options is None else options
    solver = TipSolver(mech, options)
    base = solver.base_pose
    P_world = path.world_targets(base)[:, :3, 3]
    w = np.asarray(options.position_weights, dtype=float)
    targets = path.positions.copy()
    best, history = None, []
    for j in range(iterations + 1):
        plan = plan_path(mech, path.with_positions(targets), options, start=start, solver=solver,
                         from_start=from_start)
        tr = simulate_plan(mech, plan, options, P_world, dt)
        s = {"iteration": j, **tr.summary(), "plan_unreachable": int((~plan.reached).sum())}
        history.append(s)
        if best is None or s["rms_error_m"] < best[2]["rms_error_m"]:
            best = (plan, tr, s)
        if j == iterations or not tr.converged:
            break
        # the simulated error at the sample times, in the base frame (tracked axes only)
        err_w = P_world - np.stack([np.interp(plan.times, tr.time, tr.tip[:, k]) for k in range(3)], axis=-1)
        err_w = err_w * (w > 0)
        targets = targets + gain * (_smooth(plan.times, err_w, sigma) @ base[:3, :3])
    return best[0], best[1], history


__all__ = ["PlanOptions", "TipSolver", "SampleResult", "Plan", "Tracking", "plan_path", "check_plan",
           "simulate_plan", "compensate_lag", "actuator_bounds", "rate_limits",
           "frame_sensitivity", "box_lstsq", "bounded_gauss_newton_step", "braking_step", "start_vector",
           "PlanError"]
