"""The checks at the twin's door, free of ROS: every command the node (or
a script) gives the twin is parsed here once into values the twin applies
without checking them again.

:func:`parse_actuation` (tendon tensions [N], chamber pressures [Pa] by
name), :func:`parse_tip_wrench` (a wrench on the tip, base or tip axes),
:func:`parse_point_wrench` (on any point) and
:func:`parse_joint_command` (joint positions [rad, m] or efforts [N m, N])
raise :class:`InputError` carrying a short reason key (:data:`REJECT_REASONS`,
the node's rejection counters) and never apply part of a bad command.
Inputs beyond declared limits (an actuator's ``limit`` in the robot file,
a joint's limits, the node's tip force and torque bounds) are rejected
("over_limit"). :class:`SequenceGaps` counts the commands lost upstream.
"""

import math

import numpy as np

from soft_twin_core.engine import loads as ld
from soft_twin_core.errors import InputError
from soft_twin_core.lie import checked_rigid_transform
from soft_twin_core.robot.mechanism import check_joint_position
from soft_twin_core.robot.model import check_actuator_input
from soft_twin_core.solve.constrained import actuation_vector
from soft_twin_core.text import clip, short_list

# reason keys of rejected inputs (diagnostics counters): the first ones at the
# door (validation), "solver_failed" for an input dropped because the step or
# solve it caused failed
REJECT_REASONS = ("non_finite", "wrong_length", "unknown_name", "duplicate_name",
                  "negative_tension", "over_limit", "under_limit", "bad_frame", "wrong_mode",
                  "solver_failed", "bad_obstacle", "bad_point", "bad_pose")


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
        return actuation_vector(model, u)
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
    frame = _axes(frame_id, base_frame, tip_frame, "tip wrench", f"the tip frame {tip_frame!r}")
    return _checked_wrench(force, moment, "tip", max_force, max_torque), frame


def parse_base_pose(mech, pose, frame_id, base_frame):
    """A prescribed base's pose, where it is carried (a manipulator's
    flange, a stage): ``pose`` a 4x4 in the base frame (the robot file's
    world, ``frame_id == base_frame``). InputError "wrong_mode" if the
    robot's base is not prescribed, "bad_frame", "non_finite", "bad_pose"
    (not a rigid transform). Returns the 4x4."""
    if mech.base_motion != "prescribed":
        raise InputError("wrong_mode", f"base pose: only for a robot whose base is prescribed (base: {{motion: "
                                       f"prescribed}}); this robot's is {mech.base_motion}")
    if frame_id != base_frame:
        raise InputError("bad_frame", f"base pose frame_id {clip(repr(frame_id))}: expected the base frame "
                                      f"{base_frame!r}")
    try:
        return checked_rigid_transform(pose, "base pose")
    except ValueError as e:
        raise InputError("non_finite" if "non-finite" in str(e) else "bad_pose", str(e)) from None


def _axes(frame_id, base_frame, own_frame, what, own):
    """"world" for the base frame (a dead load), "body" for the loaded
    point's own frame (a follower load); InputError "bad_frame" else."""
    if frame_id == base_frame:
        return "world"
    if frame_id == own_frame:
        return "body"
    raise InputError("bad_frame", f"{what} frame_id {clip(repr(frame_id))}: expected the base frame "
                                  f"{base_frame!r} or {own}")


def _checked_wrench(force, moment, what, max_force, max_torque):
    """The wrench (6,) [N, N m], finite and within the limits (InputError)."""
    w = np.array(list(force) + list(moment), dtype=float)
    if not np.all(np.isfinite(w)):
        raise InputError("non_finite", f"{what} wrench not finite: {w.tolist()}")
    f, m = math.hypot(*w[:3]), math.hypot(*w[3:])        # no overflow on 1e300
    if f > max_force:
        raise InputError("over_limit", f"{what} force |f| = {f:g} N exceeds max_tip_force_n = {max_force:g} N")
    if m > max_torque:
        raise InputError("over_limit", f"{what} torque |m| = {m:g} N m exceeds max_tip_torque_nm = "
                                       f"{max_torque:g} N m")
    return w


def parse_point_wrench(mech, point, force, moment, frame_id, base_frame, max_force=math.inf,
                       max_torque=math.inf):
    """External wrench on any point of the robot, from a soft_twin/PointWrench's
    parts: ``point`` a frame of the robot or ``"<member>@<s>"`` (s [m]
    from the member's base; "bad_point" otherwise); frame_id == base_frame:
    a dead load along the base axes; frame_id == point: a follower load
    along the point's axes. The limits are the tip wrench's. Returns
    (point, wrench (6,), core axes "world" | "body")."""
    point = str(point)
    try:
        mech.frame(point)
    except KeyError as e:
        raise InputError("bad_point", f"point {clip(repr(point))}: {clip(e.args[0], 300)}") from None
    axes = _axes(frame_id, base_frame, point, "point wrench", f"the point {point!r} itself")
    return point, _checked_wrench(force, moment, f"point {point!r}", max_force, max_torque), axes


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


def parse_joint_command(mech, names, positions, velocities, efforts, current_pos, current_eff):
    """Apply a JointState command to (positions, efforts) dicts.

    Every name must be a rigid 1-dof joint of the robot. A position-
    controlled joint takes ``position[k]`` (rad or m, within its limits); an
    effort-controlled joint takes ``effort[k]`` (N m or N). ``positions`` and
    ``efforts`` are empty or as long as ``names``; velocities are ignored
    (the twin differentiates the commanded positions). Raises InputError
    (reasons: wrong_length, duplicate_name, unknown_name, wrong_mode,
    non_finite, over_limit); nothing is applied then."""
    names = list(names)
    pos = np.asarray(list(positions), dtype=float)
    eff = np.asarray(list(efforts), dtype=float)
    if not names:
        raise InputError("wrong_length", "joint command without joint names")
    for what, arr in (("position", pos), ("effort", eff)):
        if arr.size not in (0, len(names)):
            raise InputError("wrong_length", f"joint command has {len(names)} names but {arr.size} {what} values")
    if len(set(names)) != len(names):
        raise InputError("duplicate_name", f"joint names repeated in {short_list(names)}")
    tree = mech.tree
    known = {tree.joints[i].name: i for i in mech.rigid_joints}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError("unknown_name", f"unknown joint(s) {short_list(unknown)}; this robot has "
                                         f"{short_list(list(known))}")
    new_pos, new_eff = dict(current_pos), dict(current_eff)
    for k, n in enumerate(names):
        i = known[n]
        mode = mech.control[i]
        j = tree.joints[i]
        if mode == "position":
            v = _joint_value(pos, k, n, "position")
            bad = check_joint_position(j, v)        # the core's rule (robot file's limits)
            if bad is not None:
                raise InputError(*bad)
            new_pos[n] = v
        elif mode == "effort":
            new_eff[n] = _joint_value(eff, k, n, "effort")
        else:
            raise InputError("wrong_mode", f"joint {clip(n)} is passive: it takes no command")
    return new_pos, new_eff


def _joint_value(values, k, name, what):
    """values[k], the ``what`` (position or effort) a joint's control mode
    takes: present and finite, else InputError."""
    if values.size == 0:
        raise InputError("wrong_mode", f"joint {clip(name)} is {what}-controlled: give its {what}")
    v = float(values[k])
    if not math.isfinite(v):
        raise InputError("non_finite", f"joint {clip(name)} {what} is not finite")
    return v
