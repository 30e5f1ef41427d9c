"""What the twin takes and how it behaves, free of ROS (the node wraps it):
the checks at the door, the settings, the drop policy, and the classic
rod's closed-form-capable IK query. The twin itself, for every robot, is
:class:`soft_twin_core.articulated_twin.ArticulatedTwin`.

Inputs are validated here (:func:`parse_actuation`, :func:`parse_tip_wrench`;
joint commands: :func:`soft_twin_core.articulated_twin.parse_joint_command`):
a bad input raises :class:`InputError` carrying a short reason key used for
the node's rejection counters, and is never applied. Inputs beyond declared
limits (an actuator's ``limit`` in the robot file, the node's tip force and
torque bounds) are rejected there too ("over_limit").

A dynamic step that fails (no convergence, or the core raising on absurd
numbers) keeps the last good state and drops the input that broke it
(:class:`DropPolicy`; :attr:`UpdateInfo.dropped` says which), so the next
step runs with inputs that worked. The twin's simulator is configured so
that a failing step costs about a millisecond (:class:`TwinSettings`:
bounded sub-stepping, no dense-Newton fallback).

Frames: "world" of the core model = the node's base frame. Wrenches are
[force (N); moment (N m)].
"""

from dataclasses import dataclass, field
import math

import numpy as np

from . import ik as core_ik
from . import kinematics as kin
from . import loads as ld
from . import statics as st
from .model import ModelError, check_actuator_input

from .errors import InputError  # noqa: F401  (the twin's API: tw.InputError)
from .text import clip, short_list

MODES = ("dynamic", "quasi_static")

# reason keys of rejected inputs (diagnostics counters): the first ones at the
# door (validation), "solver_failed" for an input dropped because the step or
# solve it caused failed
REJECT_REASONS = ("non_finite", "wrong_length", "unknown_name", "duplicate_name",
                  "negative_tension", "over_limit", "under_limit", "bad_frame", "wrong_mode",
                  "solver_failed")

# what a failing step may raise on absurd (finite) numbers: a failure, not a bug
STEP_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError, st.StaticsError)


# ----------------------------------------------------------------------------
# Input validation
# ----------------------------------------------------------------------------

def parse_actuation(model, names, values, current, order=None):
    """Inputs vector (n_actuators,) after applying a command to ``current``.

    names/values: the command. With names, each named actuator takes its
    value and the others keep theirs (from ``current``). With names empty,
    values must hold one value per actuator in ``order`` (actuator names;
    default the robot's order). Tendon tensions in N (>= 0), chamber
    pressures in Pa; each at most the actuator's declared ``limit`` (tension,
    or |pressure|; none declared: ``math.inf``). Raises :class:`InputError`
    (never partially applies); its message is bounded in length.
    """
    names = list(names)
    values = np.asarray(list(values), dtype=float)
    robot_names = list(model.actuator_names)
    order = robot_names if not order else list(order)
    if not names:
        if values.size != len(order):
            raise InputError("wrong_length", f"actuation without names needs {len(order)} values "
                             f"(one per actuator {short_list(order)}), got {values.size}")
        names = order
    elif len(names) != values.size:
        raise InputError("wrong_length", f"actuation has {len(names)} names but {values.size} values")
    if len(set(names)) != len(names):
        seen, dup = set(), {}
        for n in names:
            if n in seen:
                dup[n] = None
            seen.add(n)
        raise InputError("duplicate_name", f"actuation names repeated: {short_list(dup)}")
    known = set(robot_names)
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError("unknown_name", f"unknown actuator(s) {short_list(unknown)}; this robot has "
                                         f"{short_list(robot_names)}")
    bad = [n for n, v in zip(names, values) if not math.isfinite(v)]
    if bad:
        raise InputError("non_finite", f"actuation values not finite for {short_list(bad)}")
    u = np.array(current, dtype=float, copy=True)
    index = {n: k for k, n in enumerate(robot_names)}
    for n, v in zip(names, values):
        k = index[n]
        act = model.actuators[k]
        bad = check_actuator_input(act, v)      # the core's rule (robot file's limit/min/max)
        if bad is not None:
            raise InputError(*bad)
        u[k] = v
    # the core's own check (same rules): the single source of truth
    try:
        return st.actuation_vector(model, u)
    except ValueError as e:
        raise InputError("non_finite", str(e)) from None


def parse_tip_wrench(force, moment, frame_id, base_frame, tip_frame, max_force=math.inf,
                     max_torque=math.inf):
    """External tip wrench from a WrenchStamped's parts.

    frame_id == base_frame: a dead load, components along the base axes;
    frame_id == tip_frame: a follower load, components along the tip axes.
    Either way the force acts at the tip point and the moment is about it.
    |force| <= max_force [N] and |moment| <= max_torque [N m] (else
    "over_limit"). Returns (wrench (6,), core frame "world" | "body").
    """
    w = np.array(list(force) + list(moment), dtype=float)
    if frame_id == base_frame:
        frame = "world"
    elif frame_id == tip_frame:
        frame = "body"
    else:
        raise InputError("bad_frame", f"tip wrench frame_id {clip(repr(frame_id))}: expected the base "
                         f"frame {base_frame!r} or the tip frame {tip_frame!r}")
    if not np.all(np.isfinite(w)):
        raise InputError("non_finite", f"tip wrench not finite: {w.tolist()}")
    f, m = math.hypot(*w[:3]), math.hypot(*w[3:])        # no overflow on 1e300
    if f > max_force:
        raise InputError("over_limit", f"tip force |f| = {f:g} N exceeds max_tip_force_n = {max_force:g} N")
    if m > max_torque:
        raise InputError("over_limit", f"tip torque |m| = {m:g} N m exceeds max_tip_torque_nm = "
                                       f"{max_torque:g} N m")
    return w, frame


class SequenceGaps:
    """Counts the inputs lost before the node took them (a full subscription
    queue, a publisher's own queue overflowing, a lossy link) from the
    publication sequence number the middleware gives each sample: one count
    per publisher, up by one per message it publishes, so a jump of k + 1
    between two samples of a publisher means k samples lost.

    rclpy does not say which publisher a sample came from, so samples are
    sorted into streams: a sample continues the stream whose last number is
    the closest below its own. While fewer streams are known than
    publishers are matched, a sample that does not continue a stream
    exactly (last + 1) starts a new one (a publisher that just joined); a
    sample no stream can continue (a restarted publisher) starts one too.
    A new stream counts nothing lost before its first sample. Streams
    beyond the matched publisher count are forgotten, least recently used
    first. Exact for one publisher; with several an estimate (their numbers
    may interleave). ``supported`` turns False if the middleware gives no
    numbers (then nothing can be counted)."""

    UNSUPPORTED = 2 ** 64 - 1          # RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED

    def __init__(self, max_streams=16):
        self.max_streams = max_streams
        self.lost = 0
        self.supported = True
        self._streams = []             # [last number, last use] per stream
        self._uses = 0

    def add(self, seq, publishers=None):
        """One received sample's publication sequence number (None or
        ``UNSUPPORTED`` if the middleware has none) and the number of
        publishers matched now (None: unknown). Returns how many samples
        were lost just before it (0 for the first sample of a stream)."""
        if seq is None or seq <= 0 or seq >= self.UNSUPPORTED:
            self.supported = False
            return 0
        self._uses += 1
        limit = self.max_streams if not publishers else max(1, min(publishers, self.max_streams))
        while len(self._streams) > limit:
            self._streams.remove(min(self._streams, key=lambda s: s[1]))
        best = None
        for s in self._streams:
            if s[0] < seq and (best is None or s[0] > best[0]):
                best = s
        if best is not None and best[0] + 1 != seq and len(self._streams) < limit and publishers:
            best = None                # a publisher that joined, not a gap in a known one
        if best is None:
            if len(self._streams) >= limit:
                self._streams.remove(min(self._streams, key=lambda s: s[1]))
            self._streams.append([seq, self._uses])
            return 0
        gap = seq - best[0] - 1
        best[0], best[1] = seq, self._uses
        self.lost += gap
        return gap


def make_loads(model, tip_wrench=None, frame="world"):
    """Gravity plus an optional tip point load (6,) in the given core frame."""
    if tip_wrench is None or not np.any(tip_wrench):
        return ld.Loads()
    return ld.Loads(point=(ld.PointLoad(model.total_length, tuple(float(x) for x in tip_wrench), frame),))


# ----------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------

@dataclass
class UpdateInfo:
    """Outcome of one :meth:`Twin.step`: steps taken, Newton iterations,
    converged (False: the state was kept), message, compute time [s];
    dropped: the inputs dropped because the step or solve failed with them,
    a tuple of "actuation" and/or "wrench" (they went back to those of the
    last good state)."""
    steps: int = 0
    iterations: int = 0
    converged: bool = True
    message: str = ""
    compute_time: float = 0.0
    stable: bool = True
    dropped: tuple = ()
    residual: float = None      # quasi-static: the equilibrium's force residual


@dataclass
class TwinSettings:
    """mode: "dynamic" | "quasi_static"; dt: dynamic step [s];
    theta: integrator theta in [0.5, 1]; tolerance: integrator Newton
    tolerance; points_per_section: backbone samples per section.

    The work a failing dynamic step may do (real time: it must fit in a step
    period): Newton iterations per attempt (``max_iterations``), sub-step
    halvings (``max_substep_levels``: a step may split into 2**levels
    pieces) and the core's dense full-Newton fallback (``full_newton``,
    off: it costs 25-700 ms a step on the 18-dof default arm). With these
    defaults a failing step costs about a millisecond (0.7-0.9 ms for the
    default arm, 1.4-1.6 ms for the 36-dof pneumatic arm; it was 25-200 ms
    with the core's defaults, 4 levels and the fallback), and a jump from
    rest to a 100 N tendon tension (default arm, theta 0.5) still
    integrates."""
    mode: str = "dynamic"
    dt: float = 0.005
    theta: float = 0.5
    tolerance: float = 1e-4
    points_per_section: int = 10
    max_iterations: int = 10
    max_substep_levels: int = 3
    full_newton: bool = False


class DropPolicy:
    """What a twin falls back to after a failed step or solve, for every
    robot: back to the inputs of the last good state if they changed since
    (those failed); else, once, to the inputs before the state's own (a
    late failure: the state's inputs stepped well for a while); with
    nothing left to drop, new inputs are not blamed: they are kept and tried
    at every step until one converges (or a reset). ``same(a, b)``: two
    input records alike."""

    def __init__(self, same, inputs):
        self.same = same
        self.reset(inputs)

    def reset(self, inputs):
        self.good, self.fallback, self.stuck = inputs, None, False

    def succeeded(self, inputs):
        """A step or solve succeeded with ``inputs``: they are the good ones."""
        if not self.same(inputs, self.good):
            self.fallback = self.good
        self.good, self.stuck = inputs, False

    def target(self, now):
        """The inputs to go back to after a failure with ``now`` (None: keep them)."""
        if self.stuck:
            return None
        if not self.same(now, self.good):
            return self.good
        if self.fallback is not None and not self.same(now, self.fallback):
            self.good, self.fallback = self.fallback, None
            return self.good
        self.stuck = True
        return None


# ----------------------------------------------------------------------------
# Queries (pure: never touch a twin's state)
# ----------------------------------------------------------------------------

@dataclass
class QueryResult:
    """success, message; q; backbone poses (N, 4, 4); tip_pose (4, 4);
    strains (n, 6); base_wrench (6,) or None; iterations; residual."""
    success: bool
    message: str
    q: np.ndarray = None
    s: np.ndarray = None
    backbone: np.ndarray = None
    tip_pose: np.ndarray = None
    strains: np.ndarray = None
    base_wrench: np.ndarray = None
    iterations: int = 0
    residual: float = 0.0
    extra: dict = field(default_factory=dict)


def _shape(model, q, points_per_section, **kw):
    s, poses = kin.backbone(model, q, points_per_section)
    return QueryResult(True, kw.pop("message", "ok"), q=q, s=s, backbone=poses, tip_pose=poses[-1],
                       strains=model.strains(q), **kw)


def inverse_kinematics(model, q_current, points_per_section, target, position_only=False,
                       tolerance=1e-6, loads=None, u_current=None):
    """Tip IK (target 4x4 in the base frame), warm-started from the twin's
    state (inputs ``u_current``, shape ``q_current``).

    A robot with actuators: over the actuator inputs through statics
    (:class:`soft_twin_core.planner.TipSolver`: exact sensitivities
    J Kt^-1 B, tensions >= 0 and each actuator's ``limit``, least tension
    among redundant inputs). ``success`` only when the equilibrium reaches
    the target within ``tolerance`` (m and rad); otherwise ``success`` False
    and the closest pose the actuators can actually hold (the returned
    inputs hold the returned shape: ``actuation_found`` True), the message
    saying why (an actuator bound, out of the workspace). Full poses weigh
    the orientation error at 0.1 m/rad. A robot without actuators: over the
    strains (the shape reaching the target), ``actuation_found`` False.
    ``extra``: u, actuation_residual, actuation_found, position_error,
    orientation_error, achieved_pose."""
    try:
        tgt = np.asarray(target, dtype=float)
        if not np.all(np.isfinite(tgt)):
            return QueryResult(False, "target: contains NaN or inf")
        if model.actuators:
            return _actuated_ik(model, q_current, points_per_section, tgt, position_only, tolerance, loads,
                                u_current)
        r = core_ik.solve_ik(model, tgt[:3, 3] if position_only else tgt, q_init=q_current,
                             position_only=position_only, tol_position=tolerance,
                             tol_orientation=tolerance)
        out = _shape(model, r.q, points_per_section, iterations=r.iterations,
                     message=("converged: shape reaching the target (this robot has no actuators)" if r.success
                              else f"IK did not reach the target: {r.message}"))
        out.success = bool(r.success)
        out.residual = r.position_error
        out.extra = dict(u=np.zeros(0), actuation_residual=0.0, actuation_found=False,
                         position_error=r.position_error, orientation_error=r.orientation_error,
                         achieved_pose=r.achieved_pose)
        return out
    except (ModelError, ValueError, st.StaticsError, np.linalg.LinAlgError) as e:
        return QueryResult(False, f"IK failed: {e}")


_IK_STATUS = {"at_limit": "an actuator is at its bound (tension 0 or its limit)",
              "rate_limit": "a rate limit", "out_of_workspace": "outside the actuated workspace",
              "statics_failed": "no equilibrium found"}


def _actuated_ik(model, q_current, points_per_section, tgt, position_only, tolerance, loads, u_current):
    from soft_twin_core import lie, planner as pl
    opts = pl.PlanOptions(tolerance=tolerance, tolerance_rad=tolerance, loads=loads,
                          orientation_weight=0.0 if position_only else 0.1, max_iterations=30)
    solver = pl.TipSolver(model, opts)
    solver._with_rot = not position_only
    u0 = np.zeros(len(model.actuators)) if u_current is None else np.asarray(u_current, dtype=float)
    q0 = None if q_current is None else np.asarray(q_current, dtype=float)
    target = tgt.copy()
    if position_only:
        target[:3, :3] = np.eye(3)
    r = solver.solve(target, u0, q0)
    oe = r.orientation_error if not position_only else float(
        np.linalg.norm(lie.log_so3(r.tip_pose[:3, :3].T @ tgt[:3, :3])))
    if r.reached:
        msg = "converged: reached by actuation (static equilibrium)"
    else:
        msg = (f"target not reached by actuation ({_IK_STATUS.get(r.status, r.status)}): the closest pose "
               f"the actuators can hold, position error {r.position_error:.3g} m"
               + ("" if position_only else f", orientation error {oe:.3g} rad"))
    out = _shape(model, r.q, points_per_section, iterations=r.iterations, message=msg)
    out.success, out.residual = bool(r.reached), r.position_error
    out.extra = dict(u=r.u, actuation_residual=0.0, actuation_found=True, position_error=r.position_error,
                     orientation_error=oe, achieved_pose=r.tip_pose, status=r.status)
    return out
