"""Planner for soft articulated robots (tree robot files,
:mod:`soft_twin_core.mechanism`): a tip path to a sequence of joint position
commands (rad or m) of the position-controlled joints and tendon tensions
[N] / chamber pressures [Pa], through the articulated statics
(:func:`soft_twin_core.constrained.solve_equilibrium`).

Unknowns per sample: ``x = [q_cmd (position-controlled joints, in the order
of mech.joints_with("position")), u (actuators)]``.

* **Sensitivity (exact).** The equilibrium ``R(q, lam; u) = 0``,
  ``Phi(q; q_cmd) = 0`` (constraints and the rows ``q_j - q_cmd,j = 0``)
  is differentiated by the implicit function theorem:
  ``[[Kt, -G^T], [G, 0]] [dq; dlam] = -[dR/dx; dPhi/dx] dx`` with Kt the
  engine's analytic tangent, ``dPhi/dq_cmd = -E`` and ``dR/du`` the
  actuation force per unit input (exact: it is linear in u at fixed q).
  The frame's world velocity Jacobian turns dq into d(frame position).
  Tested against finite differences of full equilibrium solves.
* **Bounds.** Joint commands within the joint ``limits``; tendons in
  ``[pretension, min(limit, max_tension)]``, chambers
  ``[-limit, min(limit, max_pressure)]``.
* **Rate limits.** A position-controlled joint's ``max_velocity`` and
  ``max_acceleration`` (robot file; the same bounds with which the twin
  shapes its commands, so a plan within them is followed without lag):
  with samples dt apart, ``|dq_k| <= v_max dt`` and
  ``|dq_k - dq_{k-1}| <= a_max dt^2`` (``dq_k = q_cmd,k - q_cmd,k-1``);
  the plan starts at rest at its first sample (``dq_0 = 0``), the first
  sample itself is free (moving there is not part of the plan). Actuators:
  ``max_rate`` [N/s, Pa/s] as in :mod:`planner`. Each becomes a per-sample
  box; every planned value lies in its box.
* **Redundancy resolution** (a 3-D tip target, more inputs): among the
  inputs that reach the sample, the least change of the joint commands from
  the previous sample plus the least input above its lower bound
  (pretension), each scaled by its tip sensitivity: a Gauss-Newton phase on
  ``|W e|^2 + eps^2 |S (x - x_ref)|^2`` (eps = 1e-3), then a phase on the
  tip error alone polishes the target.
* **Unreachable samples** are flagged (``reached`` False; ``status``
  ``at_limit``, ``rate_limit``, ``out_of_workspace`` or ``statics_failed``)
  and the plan follows the closest reachable point (locally).

The result is a :class:`ArticulatedPlan` (a :class:`planner.Plan` with joint
columns); :func:`check_articulated_plan` lists violated bounds.
"""

from dataclasses import dataclass

import numpy as np

from . import algorithms as alg
from . import constrained as cs
from . import lie
from .mechanism import tip_frame
from .planner import (Plan, PlanError, PlanOptions, _number, actuator_bounds, bounded_gauss_newton_step,
                      rate_bounds, rate_limits, warm_start)
from .statics import StaticsError
from .workspace import Workspace


@dataclass
class ArticulatedPlanOptions(PlanOptions):
    """The classic planner's options (:class:`planner.PlanOptions`:
    position_weights, orientation_weight [m/rad], tolerance [m],
    tolerance_rad, pretension, max_tension, max_pressure, max_rate,
    max_iterations, loads), plus: frame, the frame that follows the path
    (default the robot's tip, :func:`mechanism.tip_frame`);
    joint_limits_margin [rad or m] kept inside the joint limits; efforts
    {joint: N m or N} held by the effort-controlled joints (default 0) and
    point_loads (:class:`constrained.FrameLoad` on named frames), both
    constant over the path (e.g. the node's current joint efforts and tip
    wrench)."""
    frame: str = None
    joint_limits_margin: float = 0.0
    efforts: object = None
    point_loads: tuple = ()


class ArticulatedTipSolver:
    """Joint commands and actuator inputs reaching a frame position, through
    the articulated statics; re-used sample after sample (warm starts)."""

    EPS_REDUNDANCY = 1e-3

    def __init__(self, mech, options=None):
        self.mech = mech
        self.options = o = ArticulatedPlanOptions() if options is None else options
        tree = mech.tree
        self.pos = mech.joints_with("position")
        self.joint_names = tuple(tree.joints[i].name for i in self.pos)
        self.actuator_names = tuple(mech.actuator_names)
        self.n_j, self.n_u = len(self.pos), len(self.actuator_names)
        if self.n_j + self.n_u == 0:
            raise PlanError("this robot has no position-controlled joints and no actuators: nothing to plan")
        self.frame = o.frame or tip_frame(mech)
        try:
            self.ref = mech.frame(self.frame)
        except KeyError as e:
            raise PlanError(f"frame: {e.args[0]}") from None
        self.sw, self.swo = o.weights()           # the classic planner's checks (PlanError naming the option)
        margin = _number(o.joint_limits_margin, "joint_limits_margin", False)
        if margin < 0:
            raise PlanError(f"joint_limits_margin: expected a number >= 0, got {margin}")
        from .loads import Loads
        self.loads = Loads() if o.loads is None else o.loads
        # bounds: joints, then actuators
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
        # the actuators' ranges and rates: the classic planner's rules, on the mechanism's actuators
        ulo, uhi = actuator_bounds(mech, o)
        self.rate = rate_limits(mech, o)
        self.lower, self.upper = np.concatenate([jlo, ulo]), np.concatenate([jhi, uhi])
        self.max_velocity, self.max_acceleration = vmax, amax
        self.ws = Workspace(tree)
        self._pidx = np.array([tree.idx_v[i] for i in self.pos], np.int64)

    # -- equilibrium and its sensitivity ---------------------------------------
    def split(self, x):
        return x[:self.n_j], x[self.n_j:]

    def equilibrium(self, x, q_init):
        qc, u = self.split(x)
        o = self.options
        return cs.solve_equilibrium(self.mech, actuation=u if self.n_u else None, efforts=o.efforts,
                                    positions=qc if self.n_j else None, loads=self.loads,
                                    point_loads=tuple(o.point_loads), q_init=q_init,
                                    check_stability=False)   # per iteration: 0.2-0.9 ms saved

    def frame_pose(self, q):
        return alg.point_poses(self.mech.tree, self.ws, q, [self.ref.joint], [self.ref.x])[0]

    def sensitivity(self, eq):
        """(frame pose 4x4, d(frame motion)/dx (6, n_j + n_u): the velocity of
        its origin and its angular velocity, world axes, per unit of each
        input) at an equilibrium."""
        mech, tree = self.mech, self.mech.tree
        pb = cs._Equilibrium(mech, eq.inputs)
        q, lam = eq.q, eq.lam
        Kt = pb.tangent(q, lam)
        R, phi, G = pb.residual(q, lam)
        n_x = self.n_j + self.n_u
        dR = np.zeros((tree.nv, n_x))
        dphi = np.zeros((len(phi), n_x))
        npos = self.n_j
        for k in range(npos):                       # rows q_j - q_cmd,j: d/dq_cmd = -1
            dphi[len(phi) - npos + k, k] = -1.0
        if self.n_u:
            coef = pb.coef
            pb.coef = np.zeros_like(coef)
            r0 = pb.residual(q, lam)[0]
            for k in range(self.n_u):
                pb.coef = np.ascontiguousarray(pb.act.unit[:, k], dtype=float)
                dR[:, npos + k] = pb.residual(q, lam)[0] - r0     # linear in u at fixed q
            pb.coef = coef
        fac = cs.factor_kkt(Kt, G, G)
        dq = np.empty((tree.nv, n_x))
        for k in range(n_x):
            dq[:, k] = cs.solve_factored(fac, dR[:, k], dphi[:, k])[0]
        g, J = alg.point_jacobian(tree, self.ws, q, self.ref.joint, self.ref.x, frame="world")
        return g, J @ dq

    # -- one sample ----------------------------------------------------------
    @staticmethod
    def _with_rot(target):
        return np.shape(target) == (4, 4)

    def _error(self, g, target):
        """Weighted error: position sw (p_target - p); with a pose target also
        the rotation swo log(R_target R^T) (world axes, rad)."""
        if not self._with_rot(target):
            return self.sw * (target - g[:3, 3])
        return np.concatenate([self.sw * (target[:3, 3] - g[:3, 3]),
                               self.swo * lie.log_so3(target[:3, :3] @ g[:3, :3].T)])

    def _error_jacobian(self, S, target):
        """d(error)/dx: to first order the error falls by the frame's motion
        (for the rotation, exactly so as the error vanishes)."""
        if not self._with_rot(target):
            return -(self.sw[:, None] * S[:3])
        return -np.vstack([self.sw[:, None] * S[:3], self.swo * S[3:]])

    def errors(self, g, target):
        """(position distance [m], weighted position error [m], orientation error [rad] or 0)."""
        p = target[:3, 3] if self._with_rot(target) else target
        d = p - g[:3, 3]
        oe = float(np.linalg.norm(lie.log_so3(g[:3, :3].T @ target[:3, :3]))) if self._with_rot(target) else 0.0
        return float(np.linalg.norm(d)), float(np.linalg.norm(self.sw * d)), oe

    def reached(self, g, target):
        _, we, oe = self.errors(g, target)
        o = self.options
        return we <= o.tolerance and (not self._with_rot(target) or self.swo == 0 or oe <= o.tolerance_rad)

    def solve(self, target, x_init, q_init, lo, hi, x_ref, rate_box=None):
        """x within [lo, hi] whose equilibrium puts the frame at ``target``
        (world position (3,) [m], or world pose 4x4: then its orientation
        too); ``x_ref``: the reference of the redundancy resolution (previous
        joint commands, lower input bounds). Returns (x, equilibrium, frame
        pose, position distance, weighted position error, orientation error,
        reached, status, iterations)."""
        x = np.clip(np.asarray(x_init, float), lo, hi)
        try:
            eq = self.equilibrium(x, q_init)
        except (StaticsError, ValueError):
            eq = self.equilibrium(x, None)
        g = self.frame_pose(eq.q)
        e = self._error(g, target)
        it_total = 0
        scale = None
        for eps in (self.EPS_REDUNDANCY, 0.0):
            x, eq, g, e, it, scale = self._gauss_newton(x, eq, g, e, target, lo, hi, eps, x_ref, scale)
            it_total += it
        pe, we, oe = self.errors(g, target)
        reached = self.reached(g, target)
        status = "reached" if reached else self._blocking(x, eq, e, target, lo, hi, rate_box)
        return x, eq, g, pe, we, oe, reached, status, it_total

    def _gauss_newton(self, x, eq, g, e, target, lo, hi, eps, x_ref, scale):
        tol = self.options.tolerance
        lam = 0.0
        it = 0

        def cost(x_, e_):
            c = float(e_ @ e_)
            if eps > 0:
                r = eps * scale * (x_ - x_ref)
                c += float(r @ r)
            return c

        for it in range(1, self.options.max_iterations + 1):
            if eps == 0.0 and self.reached(g, target):
                return x, eq, g, e, it - 1, scale
            try:
                _, S = self.sensitivity(eq)
            except (np.linalg.LinAlgError, ValueError):
                return x, eq, g, e, it, scale
            Je = self._error_jacobian(S, target)
            if scale is None:
                scale = np.maximum(np.linalg.norm(Je, axis=0), 1e-12 * max(np.linalg.norm(Je), 1e-300))
            c0 = cost(x, e)
            improved = False
            for _ in range(10):
                dx, _ = bounded_gauss_newton_step(Je, e, x, lo, hi, scale, eps, x_ref, lam)
                if np.linalg.norm(dx * scale) <= 1e-3 * tol:
                    return x, eq, g, e, it, scale
                x_new = np.clip(x + dx, lo, hi)
                try:
                    eq_new = self.equilibrium(x_new, eq.q)
                except (StaticsError, ValueError):
                    lam = max(4 * lam, 1e-4)
                    continue
                g_new = self.frame_pose(eq_new.q)
                e_new = self._error(g_new, target)
                if cost(x_new, e_new) < c0:
                    x, eq, g, e = x_new, eq_new, g_new, e_new
                    lam = lam / 10 if lam > 1e-8 else 0.0
                    improved = True
                    break
                lam = max(4 * lam, 1e-4)
            if not improved:
                break
            if eps > 0 and cost(x, e) > (1 - 1e-8) * c0:
                break
        return x, eq, g, e, it, scale

    def _blocking(self, x, eq, e, target, lo, hi, rate_box):
        try:
            _, S = self.sensitivity(eq)
        except (np.linalg.LinAlgError, ValueError):
            return "statics_failed"
        grad = self._error_jacobian(S, target).T @ e
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


@dataclass
class ArticulatedPlan(Plan):
    """A :class:`planner.Plan` (``u``: actuator inputs) plus joint_names,
    joints (N, n_joints) position commands [rad or m], joint_lower/upper,
    max_velocity [rad/s or m/s] and max_acceleration [rad/s^2 or m/s^2] of
    those joints, and the frame that follows the path."""
    joint_names: tuple = ()
    joints: np.ndarray = None
    joint_lower: np.ndarray = None
    joint_upper: np.ndarray = None
    max_velocity: np.ndarray = None
    max_acceleration: np.ndarray = None
    frame: str = ""


def braking_step(distance, astep):
    """The largest increment per step towards a joint limit ``distance``
    away (>= 0) from which the joint still stops before it, decelerating by
    at most ``astep`` per step (the increments d, d - astep, ... sum to at
    most d + d^2 / (2 astep) <= distance): astep (sqrt(1 + 2 distance /
    astep) - 1); inf without an acceleration limit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = astep * (np.sqrt(1.0 + 2.0 * np.maximum(distance, 0.0) / astep) - 1.0)
    return np.where(np.isfinite(astep), out, np.inf)


def _rate_box(solver, x_prev, d_prev, dt):
    """(lo, hi) of x from the rate limits: joints by velocity and
    acceleration (d_prev: previous joint increment) and by what still lets
    them stop before their limits (:func:`braking_step`), inputs by
    max_rate."""
    nj = solver.n_j
    lo, hi = np.full(x_prev.size, -np.inf), np.full(x_prev.size, np.inf)
    vstep = solver.max_velocity * dt
    astep = solver.max_acceleration * dt * dt
    dlo = np.maximum(-vstep, d_prev - astep)
    dhi = np.minimum(vstep, d_prev + astep)
    # towards a limit no faster than the joint can brake in time; a joint already faster than that
    # (it cannot be, from a start at rest) brakes as hard as allowed
    dhi = np.maximum(np.minimum(dhi, braking_step(solver.upper[:nj] - x_prev[:nj], astep)), dlo)
    dlo = np.minimum(np.maximum(dlo, -braking_step(x_prev[:nj] - solver.lower[:nj], astep)), dhi)
    lo[:nj], hi[:nj] = x_prev[:nj] + dlo, x_prev[:nj] + dhi
    ustep = solver.rate * dt
    lo[nj:], hi[nj:] = x_prev[nj:] - ustep, x_prev[nj:] + ustep
    return lo, hi


def plan_articulated_path(mech, path, options=None, start=None):
    """Plan joint commands and actuator inputs for a :class:`paths.TipPath`
    (the world frame of the mechanism; with orientations, the frame's
    orientation is tracked too, weighted by ``orientation_weight``). ``start``: x = [joint commands, inputs] to warm-start the
    first sample from (default: the joint references, inputs at their lower
    bounds)."""
    from .paths import TipPath
    if not isinstance(path, TipPath):
        raise PlanError(f"path: expected a TipPath, got {type(path).__name__}")
    solver = ArticulatedTipSolver(mech, options)
    tree = mech.tree
    nj = solver.n_j
    if start is None:
        x = np.concatenate([[tree.joints[i].q_ref for i in solver.pos], np.where(
            np.isfinite(solver.lower[nj:]), solver.lower[nj:], 0.0)])
    else:
        x = np.asarray(start, float)
        if x.shape != solver.lower.shape:
            raise PlanError(f"start: expected {solver.lower.size} values (joints {list(solver.joint_names)}, "
                            f"actuators {list(solver.actuator_names)})")
    x = np.clip(x, solver.lower, solver.upper)
    q = solver.equilibrium(x, None).q
    N = len(path)
    targets = path.positions if path.orientations is None else path.world_targets(np.eye(4))
    out = {k: [] for k in ("x", "q", "tip", "R", "pe", "we", "oe", "reached", "status", "it")}
    x_ref_lo = np.where(np.isfinite(solver.lower[nj:]), solver.lower[nj:], 0.0)
    d_prev = np.zeros(nj)
    hist = []
    for i in range(N):
        lo, hi, box = solver.lower, solver.upper, None
        if i > 0:
            rlo, rhi = _rate_box(solver, x, d_prev, path.times[i] - path.times[i - 1])
            lo, hi = rate_bounds(solver.lower, solver.upper, rlo, rhi)
            box = (rlo, rhi)
        x0, q0 = warm_start(hist, (x, q))
        x_ref = np.concatenate([x[:nj], x_ref_lo])
        x_new, eq, g, pe, we, oe, reached, status, it = solver.solve(targets[i], np.clip(x0, lo, hi), q0, lo, hi,
                                                                     x_ref, box)
        if i > 0:
            d_prev = x_new[:nj] - x[:nj]
        x = x_new
        hist.append((x, eq.q))
        out["x"].append(x)
        out["q"].append(eq.q)
        out["tip"].append(g[:3, 3])
        out["R"].append(g[:3, :3])
        out["pe"].append(pe)
        out["we"].append(we)
        out["oe"].append(oe)
        out["reached"].append(reached)
        out["status"].append(status)
        out["it"].append(it)
    X = np.array(out["x"]).reshape(N, -1)
    return ArticulatedPlan(
        path.times.copy(), X[:, nj:].copy(), np.array(out["q"]), np.array(out["tip"]), path.positions.copy(),
        np.array(out["pe"]), np.array(out["we"]), np.array(out["oe"]), np.array(out["reached"], bool), out["status"],
        solver.lower[nj:].copy(), solver.upper[nj:].copy(), solver.rate.copy(), solver.actuator_names,
        np.array(out["it"]), None if path.orientations is None else np.array(out["R"]), solver.joint_names, X[:, :nj].copy(), solver.lower[:nj].copy(),
        solver.upper[:nj].copy(), solver.max_velocity.copy(), solver.max_acceleration.copy(), solver.frame)


def check_articulated_plan(plan, rtol=1e-12):
    """Violations of the plan's joint limits, joint velocity/acceleration
    limits and actuator bounds and rates (a list of strings, empty when
    none). The plan starts at rest at its first sample."""
    from .planner import check_plan
    bad = check_plan(plan, rtol)
    dt = np.diff(plan.times)
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


__all__ = ["ArticulatedPlanOptions", "ArticulatedTipSolver", "ArticulatedPlan", "plan_articulated_path",
           "check_articulated_plan"]


def simulate_articulated_plan(mech, plan, options=None, path_positions=None, dt=0.005, theta=0.5, hold=0.0):
    """Execute an articulated ``plan`` with the dynamics
    (:class:`constrained.MechanismSimulator`) from the static equilibrium of
    its first sample: the position-controlled joints reach the commands
    linear between samples at the end of each step, the actuator inputs
    linear between samples, the options' efforts and loads held, the last
    commands held ``hold`` [s] after the end. The frame the plan follows is
    compared with ``path_positions`` (N, 3) (default the plan's targets),
    linear between samples. Returns :class:`planner.Tracking`; a step that
    fails ends the run (``converged`` False)."""
    from .planner import Tracking
    o = options or ArticulatedPlanOptions()
    P = plan.target if path_positions is None else np.asarray(path_positions, dtype=float)
    sw = np.sqrt(np.asarray(o.position_weights, dtype=float))
    ref = mech.frame(plan.frame)
    times = np.asarray(plan.times, dtype=float)
    X = np.concatenate([np.asarray(plan.joints, float).reshape(len(times), -1), np.asarray(plan.u, float)], axis=1)
    nj = len(plan.joint_names)

    def commands(t):
        x = np.array([np.interp(t, times, X[:, k]) for k in range(X.shape[1])])
        return dict(zip(plan.joint_names, x[:nj])), x[nj:]
    pos, u = commands(times[0])
    eq0 = cs.solve_equilibrium(mech, u, o.efforts, pos, o.loads, o.point_loads)
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
            sim.step(u, o.efforts, pos, o.loads, o.point_loads)
        except (cs.StepError, StaticsError, ValueError, np.linalg.LinAlgError):
            ok = False
            break
        ts.append(t1)
        tips.append(frame_position(sim.q))
    ts, tips = np.array(ts), np.array(tips)
    tgt = np.stack([np.interp(ts, times, P[:, k]) for k in range(3)], axis=-1)
    d = tgt - tips
    return Tracking(ts, tips, tgt, np.linalg.norm(d * sw, axis=1), np.linalg.norm(d, axis=1), ok)
