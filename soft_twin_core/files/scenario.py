"""Scenario files for ``soft-twin-sim``: a robot, its inputs and loads, for
a statics solve or a dynamic simulation. One schema and one parser for every
robot (a classic rod's ``segments`` file, a tree robot's ``bodies`` file);
fields that name joints or frames need a robot that has them.

Schema (YAML; SI units, angles in rad unless named ``_deg``)::

    robot: ../robots/tendon_arm.yaml   # path (relative to this file), an example robot's
                                       # name (tendon_arm) or an inline robot mapping
    sections: 10                       # optional, segments robots: sections per segment (CLI --sections wins)
    actuation: {tendon_y_pos: 2.0}     # constant inputs (N for tendons, Pa for chambers)
    actuation_profile:                 # optional, dynamics: piecewise-linear [t, value] pairs
      tendon_y_pos: [[0.0, 0.0], [0.5, 2.0]]
    joint_positions: {pan: 0.5}        # position-controlled joints (default: their reference)
    joint_trajectories: {tilt: [[0, 0], [1, 0.6]]}   # [t, position]: a C2 cubic spline through the
                                       # points, at rest at both ends
    joint_efforts: {wrist: 0.1}        # effort-controlled joints [N m or N]
    joint_effort_profile: {wrist: [[0, 0], [1, 0.2]]}
    base_trajectory: [[t, x, y, z, roll, pitch, yaw], ...]   # a base with motion "prescribed"
    gravity: true
    loads:
      # on a soft member, at an arc length s [m] of it (or its "tip"); member: default the first
      - {s: tip, force: [0, 0, -0.1], moment: [0, 0, 0], frame: world}
      - {member: finger_1, s: 0.02, force: [0, 0.1, 0], frame: body}          # frame: world or body axes
      - {s: 0.2, in_plane_force: {magnitude: 8.896, angle_deg: 30}}          # P (cos a y + sin a z), world
      - {distributed: true, force: [0, 0.1, 0], start: 0.0, end: 0.3}        # N/m over [start, end] m
      # on a named frame of the robot (its links, tips, points): axes world or body
      - {frame: tool, force: [0, 0, -1], moment: [0, 0, 0], axes: world}
      - {s: tip, force: [0, 1, 0], profile: [[0, 0], [1, 1]]}               # any load: scale vs time
    load_steps: 1                      # statics: apply the loads and inputs in this many increments
    initial_strains: null              # dynamics: the start, (n_soft_sections x 6) in tree order
    obstacles:                         # more obstacles (the robot file's schema, docs/robot-files.md),
      - {name: conveyor, type: plane, point: [0, 0, -0.05], normal: [0, 0, 1], friction: 0.5,
         trajectory: [[0, 0, 0, 0], [2, 0.2, 0, 0]]}   # [t, dx, dy, dz]: a translation [m], piecewise
                                       # linear in t [s], held outside its span
    reference:                         # optional: values to plot a --sweep-angle against
      {label: text, angle_deg: [0, 45], tip_position: [[x, y, z], [x, y, z]]}   # m, world

Numbers may be written as the robot files accept them (``1e6``, ``1.0e6``,
``2.5e-3``; :func:`model.parse_number`).
"""

import math
import os
from dataclasses import dataclass

import numpy as np

from soft_twin_core.engine.contact import moved
from soft_twin_core.engine.loads import DistributedLoad, Loads, PointLoad
from soft_twin_core.errors import ModelError, ScenarioError
from soft_twin_core.files.runs import run_mechanism_dynamics, run_mechanism_statics
from soft_twin_core.files.timeline import Spline, check_scenario_input, parse_profile
from soft_twin_core.robot.mechanism import (check_joint_position, from_robot_model, is_tree_file,
                                            mechanism_from_dict)
from soft_twin_core.robot.model import (find_file, model_from_dict, parse_number, parse_numbers,
                                        pose_from_dict, read_yaml_file, robot_mapping,
                                        robot_not_scenario_hint)
from soft_twin_core.robot.obstacles import obstacles_from_list
from soft_twin_core.solve.constrained import FrameLoad
from soft_twin_core.solve.contact import mechanism_contact_points
from soft_twin_core.solve.outputs import q_from_section_strains


@dataclass
class Scenario:
    """A checked scenario (see the module): the robot as a mechanism
    (``mech``; ``model``: its :class:`model.RobotModel` for a segments
    robot, None for a tree robot), constant inputs and their profiles by
    index or joint name, the loads with their profiles (PointLoad and
    DistributedLoad on members, FrameLoad on frames; profile None or (t,
    scale)), ``initial_q`` (None: the reference)."""
    mech: object
    model: object
    actuation: np.ndarray
    actuation_profile: dict        # actuator index -> (t, values)
    positions: dict                # joint -> value
    trajectories: dict             # joint -> Spline
    efforts: dict
    effort_profile: dict           # joint -> (t, values)
    base_trajectory: object        # Spline of [x, y, z, roll, pitch, yaw] or None
    loads: list                    # (load, profile or None)
    gravity: bool
    load_steps: int
    initial_q: object
    source: str
    reference: object = None       # reference values of a sweep (issue 12; see _reference)
    obstacles: tuple = ()          # the scenario's own: (Obstacle, (times, displacements) or None)

    def obstacles_at(self, t):
        """Every obstacle (the robot file's, then the scenario's, moved along
        their trajectories) at time t [s]; None when the scenario adds none
        (the simulator keeps the robot file's)."""
        if not self.obstacles:
            return None
        out = list(self.mech.obstacles)
        for ob, traj in self.obstacles:
            if traj is not None:
                ts, xs = traj
                ob = moved(ob, [np.interp(t, ts, xs[:, k]) for k in range(3)])
            out.append(ob)
        return tuple(out)

    @property
    def initial_strains(self):
        """The start of a dynamics run as q (None: at rest), as the rod runner reads it."""
        return self.initial_q

    def actuation_at(self, t):
        u = self.actuation.copy()
        for i, (ts, vs) in self.actuation_profile.items():
            u[i] = float(np.interp(t, ts, vs))
        return u

    def _scaled(self, t, factor):
        """(load, scale) of every load at time t (None: profiles ignored)."""
        for ld, prof in self.loads:
            k = factor
            if prof is not None and t is not None:
                k *= float(np.interp(t, prof[0], prof[1]))
            yield ld, k

    def load_factors(self, t):
        """The scale of every load at time t [s] (its profile's value; 1 without one)."""
        return tuple(k for _, k in self._scaled(t, 1.0))

    def loads_at(self, t=None, factor=1.0):
        """The member loads at time t (profiles applied; None: ignored),
        times ``factor``, and the gravity switch, as :class:`loads.Loads`
        (the loads on frames: :meth:`frame_loads_at`)."""
        pts, dist = [], []
        for ld, k in self._scaled(t, factor):
            if isinstance(ld, FrameLoad):
                continue
            if isinstance(ld, PointLoad):
                pts.append(PointLoad(ld.s, tuple(k * np.asarray(ld.wrench, dtype=float)), ld.frame, ld.member))
            else:
                dist.append(DistributedLoad(tuple(k * np.asarray(ld.wrench, dtype=float)), ld.frame, ld.start,
                                            ld.end, ld.member))
        return Loads(point=tuple(pts), distributed=tuple(dist), gravity=self.gravity)

    def frame_loads_at(self, t=None, factor=1.0):
        """The loads on named frames at time t, times ``factor`` (FrameLoad list)."""
        return [FrameLoad(ld.frame, k * np.asarray(ld.wrench, dtype=float), ld.axes)
                for ld, k in self._scaled(t, factor) if isinstance(ld, FrameLoad)]

    def efforts_at(self, t):
        eff = dict(self.efforts)
        for j, (ts, vs) in self.effort_profile.items():
            eff[j] = float(np.interp(t, ts, vs))
        return eff

    def positions_at(self, t):
        pos = dict(self.positions)
        for j, sp in self.trajectories.items():
            pos[j] = float(sp(t))
        return pos

    def velocities_at(self, t):
        """Commanded velocities of the position-controlled joints at t, in the
        order of ``mech.joints_with("position")`` (trajectories: the
        spline's derivative; constant positions: 0)."""
        out = {j: 0.0 for j in self.positions}
        for j, sp in self.trajectories.items():
            out[j] = float(sp.velocity(t))
        return [out.get(self.mech.tree.joints[i].name, 0.0) for i in self.mech.joints_with("position")]

    def base_pose_at(self, t):
        if self.base_trajectory is None:
            return None
        x = self.base_trajectory(t)
        return pose_from_dict({"position": x[:3].tolist(), "rpy": x[3:].tolist()}, "base_trajectory")

    @property
    def time_varying(self):
        return bool(self.actuation_profile or self.effort_profile or self.trajectories
                    or self.base_trajectory is not None) or any(p is not None for _, p in self.loads)


def load_scenario(path, sections=None, angle_deg=None):
    """Parse a scenario file; ``sections`` overrides the sections per segment
    (segments robots), ``angle_deg`` the angle of every ``in_plane_force``.
    ``path`` may also name an example scenario, from any working directory
    (``load_scenario("tendon_arm_dynamics")``; see :func:`model.find_file`).
    Raises ScenarioError naming the bad field."""
    path = find_file(path, "scenarios", ScenarioError)
    d = read_yaml_file(path, ScenarioError, "scenario")
    if isinstance(d, dict) and "robot" not in d and ("segments" in d or "bodies" in d):
        stem = os.path.splitext(os.path.basename(str(path)))[0]
        has = "segments" if "segments" in d else "bodies"
        raise ScenarioError(f"scenario {path}: this is a robot file (it has {has}), not a scenario. "
                            f"{robot_not_scenario_hint(stem)}")
    return scenario_from_dict(d, os.path.dirname(os.path.abspath(path)), sections, angle_deg, str(path))


_FIELDS = {"robot", "sections", "actuation", "actuation_profile", "joint_positions", "joint_trajectories",
           "joint_efforts", "joint_effort_profile", "base_trajectory", "gravity", "loads", "load_steps",
           "initial_strains", "description", "reference", "obstacles"}


def _robot(robot, base_dir, sections):
    """(Mechanism, RobotModel or None) of the scenario's ``robot`` field."""
    if isinstance(robot, str):
        p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
        if not os.path.isfile(p) and os.path.basename(robot) == robot:
            p = find_file(robot, "robots")            # not next to the scenario: an example robot's name
        d = robot_mapping(read_yaml_file(p, what="robot file"), f"robot file {p}")
        robot_dir = os.path.dirname(os.path.abspath(p))
    elif isinstance(robot, dict):
        d, robot_dir = robot, base_dir
    else:
        raise ScenarioError(f"scenario.robot: expected a path or a mapping, got {robot!r}")
    if is_tree_file(d):
        if sections is not None:
            raise ScenarioError("sections: a tree robot takes its section counts from the robot file")
        return mechanism_from_dict(d, robot_dir), None
    model = model_from_dict(d, sections)
    return from_robot_model(model, d, robot_dir), model


def scenario_from_dict(d, base_dir=".", sections=None, angle_deg=None, source="<dict>"):
    """A :class:`Scenario` from a parsed mapping; ScenarioError naming the
    bad field (see the module for the schema)."""
    Err = ScenarioError
    if not isinstance(d, dict):
        raise Err("scenario: expected a mapping at top level")
    unknown = set(d) - _FIELDS
    if unknown:
        raise Err(f"scenario: unknown field(s) {sorted(unknown)}; allowed: {sorted(_FIELDS)}")
    if "robot" not in d:
        raise Err("scenario.robot: missing (a robot file path or an inline robot mapping)")
    n = sections if sections is not None else d.get("sections")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise Err(f"scenario.sections: expected an integer >= 1, got {n!r}")
    try:
        mech, model = _robot(d["robot"], base_dir, n)
    except ModelError as e:
        raise Err(f"scenario.robot: {e}") from None
    u, aprof = _actuation(d, mech)
    positions, trajectories, efforts, eprof = _joints(d, mech)
    base = None
    if d.get("base_trajectory") is not None:
        if mech.base_motion != "prescribed":
            raise Err(f"scenario.base_trajectory: the robot's base motion is {mech.base_motion!r}; "
                      f"give base: {{motion: prescribed}} in the robot file")
        base = Spline(parse_numbers(d["base_trajectory"], (None, 7), "scenario.base_trajectory", Err),
                      "scenario.base_trajectory")
    raw = d.get("loads") or []
    if not isinstance(raw, list):
        raise Err(f"scenario.loads: expected a list of loads, got {raw!r}")
    loads = [_load(ld, i, mech, angle_deg) for i, ld in enumerate(raw)]
    steps = d.get("load_steps", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise Err(f"scenario.load_steps: expected an integer >= 1, got {steps!r}")
    grav = d.get("gravity", True)
    if not isinstance(grav, bool):
        raise Err(f"scenario.gravity: expected true or false, got {grav!r}")
    init = d.get("initial_strains")
    if init is not None:
        init = parse_numbers(init, (len(mech.tree.soft_joints), 6), "scenario.initial_strains", Err)
        try:
            init = q_from_section_strains(mech, init, mech.tree.q0)
        except ModelError as e:
            raise Err(f"scenario.initial_strains: {e}") from None
    return Scenario(mech, model, u, aprof, positions, trajectories, efforts, eprof, base, loads, grav, steps,
                    init, source, _reference(d.get("reference")), _obstacles(d.get("obstacles"), mech, base_dir))


def _obstacles(items, mech, base_dir=None):
    """The scenario's obstacles with their trajectories (None: fixed); mesh
    files relative to ``base_dir``."""
    if items is None:
        return ()
    if not isinstance(items, list):
        raise ScenarioError(f"scenario.obstacles: expected a list of obstacles, got {items!r}")
    trajs, plain = [], []
    for i, it in enumerate(items):
        it = dict(it) if isinstance(it, dict) else it
        tr = it.pop("trajectory", None) if isinstance(it, dict) else None
        if tr is not None:
            a = parse_numbers(tr, (None, 4), f"scenario.obstacles[{i}].trajectory", ScenarioError)
            if len(a) < 1 or np.any(np.diff(a[:, 0]) <= 0):
                raise ScenarioError(f"scenario.obstacles[{i}].trajectory: expected [t, dx, dy, dz] rows with times "
                                    f"increasing strictly, got {tr!r}")
            tr = (a[:, 0], a[:, 1:])
        trajs.append(tr)
        plain.append(it)
    try:
        obs = obstacles_from_list(plain, "scenario.obstacles", base_dir)
    except ModelError as e:
        raise ScenarioError(str(e)) from None
    names = [o.name for o in mech.obstacles]
    clash = sorted({o.name for o in obs} & set(names))
    if clash:
        raise ScenarioError(f"scenario.obstacles: {clash} already name obstacles of the robot file")
    try:
        mech_points = mechanism_contact_points(mech)       # contact needs every member's cross-section
    except ModelError as e:
        raise ScenarioError(f"scenario.obstacles: {e}") from None
    del mech_points
    return tuple(zip(obs, trajs))


def _mapping(d, key):
    v = d.get(key) or {}
    if not isinstance(v, dict):
        raise ScenarioError(f"scenario.{key}: expected a mapping name -> value, got {v!r}")
    return v


def _actuation(d, mech):
    """(constant actuation, {index: profile}), each value within the actuator's declared range."""
    names = mech.actuator_names
    u = np.zeros(len(names))
    for k, v in _mapping(d, "actuation").items():
        if k not in names:
            raise ScenarioError(f"scenario.actuation: unknown actuator {k!r}; the robot has {list(names)}")
        u[names.index(k)] = parse_number(v, f"scenario.actuation.{k}", ScenarioError)
        # the node's rule for the actuator's declared range (tension >= 0, limit, min/max)
        check_scenario_input(mech.actuators[names.index(k)], [u[names.index(k)]], f"scenario.actuation.{k}",
                             ScenarioError)
    prof = {}
    for k, v in _mapping(d, "actuation_profile").items():
        if k not in names:
            raise ScenarioError(f"scenario.actuation_profile: unknown actuator {k!r}; the robot has {list(names)}")
        prof[names.index(k)] = parse_profile(v, f"scenario.actuation_profile.{k}")
        check_scenario_input(mech.actuators[names.index(k)], prof[names.index(k)][1],
                             f"scenario.actuation_profile.{k}", ScenarioError)
    return u, prof


def _joints(d, mech):
    """(positions, trajectories, efforts, effort profiles) of the joint commands, by joint name."""
    Err = ScenarioError
    pos_names = [mech.tree.joints[i].name for i in mech.joints_with("position")]
    eff_names = [mech.tree.joints[i].name for i in mech.joints_with("effort")]
    jointof = {j.name: j for j in mech.tree.joints}

    def joints(key, allowed, kind):
        for k in _mapping(d, key):
            if k not in allowed:
                raise Err(f"scenario.{key}: {k!r} is not a {kind}-controlled joint; those are {allowed}")
        return _mapping(d, key)

    positions = {k: parse_number(v, f"scenario.joint_positions.{k}", Err)
                 for k, v in joints("joint_positions", pos_names, "position").items()}
    for k, v in positions.items():              # the node's rule (over_limit)
        bad = check_joint_position(jointof[k], v)
        if bad is not None:
            raise Err(f"scenario.joint_positions.{k}: {bad[1]} [{bad[0]}]")
    trajectories = {}
    for k, v in joints("joint_trajectories", pos_names, "position").items():
        a = parse_numbers(v, (None, 2), f"scenario.joint_trajectories.{k}", Err)
        for t, x in a:
            bad = check_joint_position(jointof[k], float(x))
            if bad is not None:
                raise Err(f"scenario.joint_trajectories.{k}: at t = {t:g} s, {bad[1]} [{bad[0]}]")
        trajectories[k] = Spline(a, f"scenario.joint_trajectories.{k}")
    efforts = {k: parse_number(v, f"scenario.joint_efforts.{k}", Err)
               for k, v in joints("joint_efforts", eff_names, "effort").items()}
    eprof = {k: parse_profile(v, f"scenario.joint_effort_profile.{k}")
             for k, v in joints("joint_effort_profile", eff_names, "effort").items()}
    return positions, trajectories, efforts, eprof


_MEMBER_LOAD = {"s", "member", "force", "moment", "frame", "axes", "in_plane_force", "distributed", "start", "end",
                "profile"}
_FRAME_LOAD = {"frame", "force", "moment", "axes", "in_plane_force", "profile"}


def _wrench(d, where, angle_override):
    """[force; moment] of a load mapping: force and moment [N, N m], plus an
    ``in_plane_force`` {magnitude: N, angle_deg: deg}: P (cos a y + sin a z)."""
    force = parse_numbers(d.get("force", [0.0, 0.0, 0.0]), (3,), f"{where}.force", ScenarioError)
    moment = parse_numbers(d.get("moment", [0.0, 0.0, 0.0]), (3,), f"{where}.moment", ScenarioError)
    if "in_plane_force" in d:
        ip = d["in_plane_force"]
        if not isinstance(ip, dict) or "magnitude" not in ip:
            raise ScenarioError(f"{where}.in_plane_force: expected {{magnitude: N, angle_deg: deg}}, got {ip!r}")
        P = parse_number(ip["magnitude"], f"{where}.in_plane_force.magnitude", ScenarioError)
        a = parse_number(ip.get("angle_deg", 0.0) if angle_override is None else angle_override,
                         f"{where}.in_plane_force.angle_deg", ScenarioError)
        a = np.radians(a)
        force = force + P * np.array([0.0, np.cos(a), np.sin(a)])
    return tuple(np.concatenate([force, moment]))


def _load(d, i, mech, angle_override):
    """(PointLoad | DistributedLoad | FrameLoad, profile or None) of loads[i]."""
    Err = ScenarioError
    where = f"scenario.loads[{i}]"
    if not isinstance(d, dict):
        raise Err(f"{where}: expected a mapping, got {d!r}")
    on_member = "s" in d or "distributed" in d or "member" in d
    allowed = _MEMBER_LOAD if on_member else _FRAME_LOAD
    unknown = set(d) - allowed
    if unknown:
        raise Err(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(allowed)} (a load on a member "
                  f"has s or distributed, a load on a frame names the frame)")
    prof = parse_profile(d["profile"], where + ".profile") if "profile" in d else None
    wrench = _wrench(d, where, angle_override)
    if not on_member:
        if "frame" not in d:
            raise Err(f"{where}: give s (an arc length on a member), distributed: true, or frame (a frame of the "
                      f"robot: {sorted(mech.frames)})")
        if not isinstance(d["frame"], str) or d["frame"] not in mech.frames:
            raise Err(f"{where}.frame: {d['frame']!r} is not a frame of the robot; frames: {sorted(mech.frames)}")
        axes = d.get("axes", "world")
        if axes not in ("world", "body"):
            raise Err(f"{where}.axes: expected 'world' or 'body', got {axes!r}")
        return FrameLoad(d["frame"], np.asarray(wrench, dtype=float), axes), prof
    if "frame" in d and "axes" in d:
        raise Err(f"{where}: give the axes once (frame or axes: world or body)")
    axes = d.get("axes", d.get("frame", "world"))
    if axes not in ("world", "body"):
        hint = (f"; to load the frame {axes!r}, give no s, member or distributed"
                if isinstance(axes, str) and axes in mech.frames else "")
        raise Err(f"{where}.{'axes' if 'axes' in d else 'frame'}: expected 'world' or 'body' (the axes of a load "
                  f"on a member), got {axes!r}{hint}")
    names = [m.name for m in mech.members]
    if not names:
        raise Err(f"{where}: the robot has no soft member; load one of its frames: {sorted(mech.frames)}")
    member = d.get("member")
    if member is not None and (not isinstance(member, str) or member not in names):
        raise Err(f"{where}.member: {member!r} is not a soft member of the robot; members: {names}")
    length = float(mech.tree.paths[mech.member(member or names[0]).path].length)
    if d.get("distributed", False) is True:
        start = parse_number(d.get("start", 0.0), where + ".start", Err)
        end = parse_number(d.get("end", length), where + ".end", Err)
        if not 0.0 <= start < end <= length + 1e-12:
            raise Err(f"{where}: need 0 <= start < end <= {length:g} m, got {start}, {end}")
        return DistributedLoad(wrench, axes, start, end, member), prof
    if "distributed" in d and d["distributed"] is not False:
        raise Err(f"{where}.distributed: expected true or false, got {d['distributed']!r}")
    if "s" not in d:
        raise Err(f"{where}.s: missing (arc length in m, or 'tip')")
    v = d["s"]
    if v == "tip":
        s = length
    else:
        try:
            s = parse_number(v, where + ".s", Err)
        except Err:
            raise Err(f"{where}.s: expected a finite number (m) or 'tip', got {v!r}") from None
        if not 0.0 <= s <= length + 1e-12:
            raise Err(f"{where}.s: must lie in [0, {length:g}] m, got {v}")
    return PointLoad(s, wrench, axes, member), prof


def _reference(v):
    """``reference: {label: text, angle_deg: [a_1, ...], tip_position: [[x, y, z], ...]}``,
    or a list of them: tip positions [m] (world) to plot against a statics
    sweep over the in_plane_force angle [deg] (soft-twin-sim statics
    --sweep-angle --plot); a component a source does not give is ``null``.
    Returns a list of {label, angle_deg, tip_position (NaN: not given)}."""
    if v is None:
        return None
    return [_one_reference(r, f"scenario.reference[{k}]") for k, r in enumerate(v)] if isinstance(v, list) \
        else [_one_reference(v, "scenario.reference")]


def _one_reference(v, where):
    if not isinstance(v, dict) or set(v) - {"label", "angle_deg", "tip_position"} or "angle_deg" not in v \
            or "tip_position" not in v:
        raise ScenarioError(f"{where}: expected {{label: text, angle_deg: [...], tip_position: [[x, y, z], ...]}}, "
                            f"got {v!r}")
    a = parse_numbers(v["angle_deg"], (None,), where + ".angle_deg", ScenarioError)
    rows = v["tip_position"]
    given = [[c is not None for c in r] if isinstance(r, list) else [True] * 3 for r in rows] \
        if isinstance(rows, list) else None
    if given is not None:                   # null: a component the source does not give
        rows = [[0.0 if c is None else c for c in r] if isinstance(r, list) else r for r in rows]
    p = parse_numbers(rows, (len(a), 3), where + ".tip_position", ScenarioError)
    if given is not None:
        p[~np.array(given, dtype=bool).reshape(p.shape)] = np.nan
    return {"label": str(v.get("label", "reference")), "angle_deg": a.tolist(), "tip_position": p.tolist()}


# ----------------------------------------------------------------------------
# Runs
# ----------------------------------------------------------------------------

def input_profiles(sc):
    """(end time [s], names) of the scenario's time-varying inputs: the
    time at which every profile, trajectory and load profile has reached its final value, and what varies
    ("actuation_profile.close_0", "loads[1].profile", ...); (0.0, []) for
    constant inputs."""
    ends, names = [], []
    acts = sc.mech.actuator_names
    for i, (ts, _) in sc.actuation_profile.items():
        ends.append(float(ts[-1]))
        names.append(f"actuation_profile.{acts[i]}")
    for j, (ts, _) in sc.effort_profile.items():
        ends.append(float(ts[-1]))
        names.append(f"joint_effort_profile.{j}")
    for j, sp in sc.trajectories.items():
        ends.append(float(sp.t1))
        names.append(f"joint_trajectories.{j}")
    if sc.base_trajectory is not None:
        ends.append(float(sc.base_trajectory.t1))
        names.append("base_trajectory")
    for k, (_, prof) in enumerate(sc.loads):
        if prof is not None:
            ends.append(float(prof[0][-1]))
            names.append(f"loads[{k}].profile")
    for ob, traj in sc.obstacles:
        if traj is not None:
            ends.append(float(traj[0][-1]))
            names.append(f"obstacles.{ob.name}.trajectory")
    return (max(ends) if ends else 0.0), names


def statics_time(sc, time=None):
    """(t, note) of a statics solve: ``time`` if given (its profiles
    evaluated there), else, when inputs vary in time, the end of the last
    profile (every input at its final value: the state the scenario
    settles to), else 0. ``note``: a sentence saying which, or None."""
    end, names = input_profiles(sc)
    if time is not None:
        t = _positive_or_zero_time(time, "time")
        if not names:
            return t, f"solved at t = {t:g} s (the scenario's inputs are constant)"
        return t, f"solved at t = {t:g} s of the scenario's time-varying inputs ({', '.join(names)})"
    if not names:
        return 0.0, None
    return end, (f"the scenario's inputs vary in time ({', '.join(names)}): solved at t = {end:g} s, where every "
                 f"profile has reached its final value (--time T for another time)")


def _positive_or_zero_time(v, name):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ScenarioError(f"{name}: expected a finite time >= 0 in s, got {v!r}")
    return float(v)


def run_statics(sc, points_per_section=10, time=None, path_steps=0):
    """Solve the scenario's equilibrium, for any robot, through the one
    equilibrium solver (:func:`constrained.solve_equilibrium`: the compiled
    Newton without constraint rows, KKT with them; the stability judged),
    the inputs and loads applied in ``load_steps`` warm-started increments.
    Returns a JSON-ready dict (:func:`mechanism_scenario.run_mechanism_statics`):
    joints, frames, constraint and transmitted wrenches, every member's
    samples (``points_per_section`` per section: positions, orientations,
    internal wrenches, strains, stresses), ``strains`` of every soft
    section, and for every robot ``tip_position``, ``tip_rotation``,
    ``base_wrench`` [N, N m] (the support's reaction, world axes, about the
    base origin), the main member's ``backbone_s``, ``backbone_positions``
    and ``internal_wrenches`` [N, N m] (body frame, the distal part acting
    on the proximal part), ``iterations``, ``residual``, ``stable``.

    Time-varying inputs (profiles, trajectories) are evaluated at ``time``
    [s], by default at the end of the last profile (:func:`statics_time`);
    the result then holds ``time`` and ``time_note``. ``path_steps`` N > 0:
    solved at N equal times from 0 to that time instead, each from the
    one before, so that friction keeps its history (where the contacts
    stick); the result holds ``path_steps``."""
    t, note = statics_time(sc, time)
    if not (isinstance(path_steps, (int, np.integer)) and path_steps >= 0):
        raise ValueError(f"path_steps: expected an integer >= 0 (0: the inputs at one time), got {path_steps!r}")
    out = run_mechanism_statics(sc, t, points_per_section, int(path_steps))
    if path_steps:
        out.update(path_steps=int(path_steps))
    if note is not None:
        out.update(time=t, time_note=note)
    return out


def run_dynamics(sc, duration, dt, backbone_every=0, theta=0.5, progress=None,
                 points_per_section=10, record_every=1, progress_every=1.0):
    """Integrate the scenario of any robot for ``duration`` s with step
    ``dt`` s (``n = ceil(duration / dt)`` steps; see :func:`n_steps_for`):
    :func:`mechanism_scenario.run_mechanism_dynamics`, whose docstring lists
    the time histories (the tip frame, the support's reaction, joints,
    frames, constraints, section strains and rates, stresses) and, every
    ``backbone_every`` steps, every member's samples at
    ``points_per_section`` points per section. ``progress(fraction,
    elapsed_s)`` is called after the warm-up with (0, 0), then at most once
    per ``progress_every`` wall-clock seconds."""
    return run_mechanism_dynamics(sc, duration, dt, theta, progress, record_every, backbone_every,
                                  progress_every, points_per_section)
