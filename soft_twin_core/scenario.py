"""Scenario files for ``soft-twin-sim``: a robot, its loads and actuation,
for a statics solve or a dynamic simulation.

Schema (YAML; SI units)::

    robot: ../robots/tendon_arm.yaml   # path (relative to this file), an example robot's
                                       # name (tendon_arm) or an inline robot mapping
    sections: 10                       # optional: sections per segment (CLI --sections wins)
    actuation: {tendon_y_pos: 2.0}     # constant inputs (N for tendons, Pa for chambers)
    actuation_profile:                 # optional, dynamics: piecewise-linear [t, value] pairs
      tendon_y_pos: [[0.0, 0.0], [0.5, 2.0]]
    gravity: true
    loads:
      - {s: tip, force: [0, 0, -0.1], moment: [0, 0, 0], frame: world}   # s: metres or "tip"
      - {s: 0.2, in_plane_force: {magnitude: 8.896, angle_deg: 30}}       # P (cos a y + sin a z), world
      - {distributed: true, force: [0, 0.1, 0], start: 0.0, end: 0.3, frame: world}   # N/m
      - {s: tip, force: [0, 1, 0], profile: [[0, 0], [1, 1]]}             # dynamics: scale vs time
    load_steps: 1                      # statics: apply the loads in this many increments
    initial_strains: null              # dynamics: optional (n_sections x 6) start, default rest
    reference:                         # optional: values to plot a --sweep-angle against
      {label: text, angle_deg: [0, 45], tip_position: [[x, y, z], [x, y, z]]}   # m, world

Numbers may be written as the robot files accept them (``1e6``, ``1.0e6``,
``2.5e-3``; :func:`model.parse_number`).
"""

import math
import os
from dataclasses import dataclass

import numpy as np

from . import kinematics as kin
from .loads import DistributedLoad, Loads, PointLoad
from .timeline import (check_output_size, check_scenario_input, count, n_steps_for, parse_profile,  # noqa: F401
                       step_times)  # (check_output_size, n_steps_for: the runner's API)
from .model import (ModelError, find_file, load_model, model_from_dict, parse_number,
                    parse_numbers, read_yaml_file)
from .errors import ScenarioError


@dataclass
class Scenario:
    model: object
    actuation: np.ndarray
    actuation_profile: dict       # actuator index -> (times, values)
    loads: list                   # list of (PointLoad | DistributedLoad, profile or None)
    gravity: bool
    load_steps: int
    initial_strains: object
    source: str
    reference: object = None      # reference values of a sweep (issue 12; see _reference)

    def loads_at(self, t=None, factor=1.0):
        """Loads at time t (profiles applied; None: profiles ignored)."""
        pts, dist = [], []
        for ld, prof in self.loads:
            k = factor
            if prof is not None and t is not None:
                k *= float(np.interp(t, prof[0], prof[1]))
            w = tuple(k * np.asarray(ld.wrench, dtype=float))
            if isinstance(ld, PointLoad):
                pts.append(PointLoad(ld.s, w, ld.frame))
            else:
                dist.append(DistributedLoad(w, ld.frame, ld.start, ld.end))
        return Loads(point=tuple(pts), distributed=tuple(dist), gravity=self.gravity)

    def actuation_at(self, t):
        u = self.actuation.copy()
        for i, (ts, vs) in self.actuation_profile.items():
            u[i] = float(np.interp(t, ts, vs))
        return u

    @property
    def time_varying(self):
        return bool(self.actuation_profile) or any(p is not None for _, p in self.loads)


def _vec3(d, key, where):
    v = d.get(key, [0.0, 0.0, 0.0])
    try:
        return parse_numbers(v, (3,), f"{where}.{key}", ScenarioError)
    except ScenarioError:
        raise ScenarioError(f"{where}.{key}: expected 3 finite numbers, got {v!r}") from None


def _number(v, where):
    return parse_number(v, where, ScenarioError)


def _s_value(v, model, where):
    if v == "tip":
        return model.total_length
    try:
        s = parse_number(v, where + ".s", ScenarioError)
    except ScenarioError:
        raise ScenarioError(f"{where}.s: expected a finite number (m) or 'tip', got {v!r}") from None
    if not 0.0 <= s <= model.total_length + 1e-12:
        raise ScenarioError(f"{where}.s: must lie in [0, {model.total_length}] m, got {v}")
    return s


_LOAD_KEYS = {"s", "force", "moment", "frame", "in_plane_force", "distributed", "start", "end", "profile"}


def _load(d, i, model, angle_override):
    where = f"loads[{i}]"
    if not isinstance(d, dict):
        raise ScenarioError(f"{where}: expected a mapping, got {d!r}")
    unknown = set(d) - _LOAD_KEYS
    if unknown:
        raise ScenarioError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(_LOAD_KEYS)}")
    frame = d.get("frame", "world")
    if frame not in ("world", "body"):
        raise ScenarioError(f"{where}.frame: expected 'world' or 'body', got {frame!r}")
    force = _vec3(d, "force", where)
    moment = _vec3(d, "moment", where)
    if "in_plane_force" in d:
        ip = d["in_plane_force"]
        if not isinstance(ip, dict) or "magnitude" not in ip:
            raise ScenarioError(f"{where}.in_plane_force: expected {{magnitude: N, angle_deg: deg}}, got {ip!r}")
        P = _number(ip["magnitude"], f"{where}.in_plane_force.magnitude")
        a = _number(ip.get("angle_deg", 0.0) if angle_override is None else angle_override,
                    f"{where}.in_plane_force.angle_deg")
        a = np.radians(a)
        force = force + P * np.array([0.0, np.cos(a), np.sin(a)])
    wrench = tuple(np.concatenate([force, moment]))
    prof = parse_profile(d["profile"], where + ".profile") if "profile" in d else None
    if d.get("distributed", False):
        start = _number(d.get("start", 0.0), where + ".start")
        end = _number(d.get("end", model.total_length), where + ".end")
        if not 0.0 <= start < end <= model.total_length + 1e-12:
            raise ScenarioError(f"{where}: need 0 <= start < end <= {model.total_length} m, got {start}, {end}")
        return DistributedLoad(wrench, frame, start, end), prof
    if "s" not in d:
        raise ScenarioError(f"{where}.s: missing (arc length in m, or 'tip')")
    return PointLoad(_s_value(d["s"], model, where), wrench, frame), prof


def load_scenario(path, sections=None, angle_deg=None):
    """Parse a scenario file; ``sections`` overrides the sections per segment,
    ``angle_deg`` the angle of every ``in_plane_force``. ``path`` may also
    name an example scenario, from any working directory
    (``load_scenario("tendon_arm_dynamics")``; see :func:`model.find_file`).
    Raises ScenarioError or ModelError naming the bad field."""
    path = find_file(path, "scenarios", ScenarioError)
    d = read_yaml_file(path, ScenarioError, "scenario")
    if isinstance(d, dict) and "robot" not in d and ("segments" in d or "bodies" in d):
        from .model import robot_not_scenario_hint
        stem = os.path.splitext(os.path.basename(str(path)))[0]
        has = "segments" if "segments" in d else "bodies"
        raise ScenarioError(f"scenario {path}: this is a robot file (it has {has}), not a scenario. "
                            f"{robot_not_scenario_hint(stem)}")
    return scenario_from_dict(d, os.path.dirname(os.path.abspath(path)), sections, angle_deg, str(path))


def _is_tree_robot(robot, base_dir):
    """True if the scenario's robot is a tree robot file (a ``bodies`` list)."""
    from .mechanism import is_tree_file
    from .model import robot_mapping
    if isinstance(robot, dict):
        return is_tree_file(robot)
    if not isinstance(robot, str):
        return False
    p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
    if not os.path.isfile(p) and os.path.basename(robot) == robot:
        try:
            p = find_file(robot, "robots")
        except ModelError:
            return False
    try:
        return is_tree_file(robot_mapping(read_yaml_file(p), p))
    except ModelError:
        return False


def scenario_from_dict(d, base_dir=".", sections=None, angle_deg=None, source="<dict>"):
    """A Scenario (or, for a tree robot file, a
    :class:`mechanism_scenario.MechanismScenario`) from a parsed mapping."""
    if not isinstance(d, dict):
        raise ScenarioError("scenario: expected a mapping at top level")
    if "robot" in d and _is_tree_robot(d["robot"], base_dir):
        from .mechanism_scenario import mechanism_scenario_from_dict
        if sections is not None:
            raise ScenarioError("sections: articulated robots take their section counts from the robot file")
        return mechanism_scenario_from_dict(d, base_dir, source)
    allowed = {"robot", "sections", "actuation", "actuation_profile", "gravity", "loads", "load_steps",
               "initial_strains", "description", "reference"}
    unknown = set(d) - allowed
    if unknown:
        raise ScenarioError(f"scenario: unknown field(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    if "robot" not in d:
        raise ScenarioError("scenario.robot: missing (a robot file path or an inline robot mapping)")
    n = sections if sections is not None else d.get("sections")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ScenarioError(f"scenario.sections: expected an integer >= 1, got {n!r}")
    robot = d["robot"]
    try:
        if isinstance(robot, str):
            p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
            if not os.path.isfile(p) and os.path.basename(robot) == robot:
                p = robot                     # not next to the scenario: an example robot's name
            model = load_model(p, n)
        elif isinstance(robot, dict):
            model = model_from_dict(robot, n)
        else:
            raise ScenarioError(f"scenario.robot: expected a path or a mapping, got {robot!r}")
    except ModelError as e:
        raise ScenarioError(f"scenario.robot: {e}") from None
    names = model.actuator_names
    u = np.zeros(len(names))
    act = d.get("actuation") or {}
    if not isinstance(act, dict):
        raise ScenarioError(f"scenario.actuation: expected a mapping name -> value, got {act!r}")
    for k, v in act.items():
        if k not in names:
            raise ScenarioError(f"scenario.actuation: unknown actuator {k!r}; the robot has {list(names)}")
        v = _number(v, f"scenario.actuation.{k}")
        check_scenario_input(model.actuators[names.index(k)], [v], f"scenario.actuation.{k}", ScenarioError)
        u[names.index(k)] = float(v)
    prof = {}
    profiles = d.get("actuation_profile") or {}
    if not isinstance(profiles, dict):
        raise ScenarioError(f"scenario.actuation_profile: expected a mapping name -> [[t, value], ...], "
                            f"got {profiles!r}")
    for k, v in profiles.items():
        if k not in names:
            raise ScenarioError(f"scenario.actuation_profile: unknown actuator {k!r}; the robot has {list(names)}")
        ts, vs = parse_profile(v, f"scenario.actuation_profile.{k}")
        check_scenario_input(model.actuators[names.index(k)], vs, f"scenario.actuation_profile.{k}",
                             ScenarioError)
        prof[names.index(k)] = (ts, vs)
    raw_loads = d.get("loads") or []
    if not isinstance(raw_loads, list):
        raise ScenarioError(f"scenario.loads: expected a list of loads, got {raw_loads!r}")
    loads = [_load(ld, i, model, angle_deg) for i, ld in enumerate(raw_loads)]
    steps = d.get("load_steps", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ScenarioError(f"scenario.load_steps: expected an integer >= 1, got {steps!r}")
    grav = d.get("gravity", True)
    if not isinstance(grav, bool):
        raise ScenarioError(f"scenario.gravity: expected true or false, got {grav!r}")
    init = d.get("initial_strains")
    if init is not None:
        init = parse_numbers(init, (model.n_sections, 6), "scenario.initial_strains", ScenarioError)
        try:
            init = model.q_from_strains(init)
        except (ModelError, ValueError) as e:
            raise ScenarioError(f"scenario.initial_strains: {e}") from None
    return Scenario(model, u, prof, loads, grav, steps, init, source, _reference(d.get("reference")))


def _reference(v):
    """``reference: {label: text, angle_deg: [a_1, ...], tip_position: [[x, y, z], ...]}``:
    tip positions [m] (world) to plot against a statics sweep over the
    in_plane_force angle [deg] (soft-twin-sim statics --sweep-angle --plot)."""
    if v is None:
        return None
    where = "scenario.reference"
    if not isinstance(v, dict) or set(v) - {"label", "angle_deg", "tip_position"} or "angle_deg" not in v \
            or "tip_position" not in v:
        raise ScenarioError(f"{where}: expected {{label: text, angle_deg: [...], tip_position: [[x, y, z], ...]}}, "
                            f"got {v!r}")
    a = parse_numbers(v["angle_deg"], (None,), where + ".angle_deg", ScenarioError)
    p = parse_numbers(v["tip_position"], (len(a), 3), where + ".tip_position", ScenarioError)
    return {"label": str(v.get("label", "reference")), "angle_deg": a.tolist(), "tip_position": p.tolist()}


# ----------------------------------------------------------------------------
# Runs
# ----------------------------------------------------------------------------

def input_profiles(sc):
    """(end time [s], names) of the scenario's time-varying inputs (either
    kind of scenario): the time at which every profile, trajectory and
    load profile has reached its final value, and what varies
    ("actuation_profile.close_0", "loads[1].profile", ...); (0.0, []) for
    constant inputs."""
    ends, names = [], []
    mech = getattr(sc, "mech", None)
    acts = (mech.actuator_names if mech is not None else sc.model.actuator_names)
    for i, (ts, _) in sc.actuation_profile.items():
        ends.append(float(ts[-1]))
        names.append(f"actuation_profile.{acts[i]}")
    if mech is not None:
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


def run_statics(sc, points_per_section=10, time=None):
    """Solve the scenario's equilibrium (loads applied in load_steps
    increments, each warm-started). Returns a JSON-ready dict, including the
    internal wrenches [N, N m] (body frame, the distal part acting on the
    proximal part) at the backbone sample points ``backbone_s`` [m].

    Time-varying inputs (profiles, trajectories) are evaluated at ``time``
    [s], by default at the end of the last profile (:func:`statics_time`);
    the result then holds ``time`` and ``time_note``."""
    t, note = statics_time(sc, time)
    from .mechanism_scenario import MechanismScenario, run_mechanism_statics
    if isinstance(sc, MechanismScenario):
        out = run_mechanism_statics(sc, t)
        if note is not None:
            out.update(time=t, time_note=note)
        return out
    from .statics import solve_statics
    q, iters, res = None, 0, None
    u = sc.actuation_at(t)
    for k in range(1, sc.load_steps + 1):
        f = k / sc.load_steps
        loads = sc.loads_at(t, f)
        res = solve_statics(sc.model, f * u, loads, q_init=q)
        q, iters = res.q, iters + res.iterations
    s_bb, P = kin.backbone(sc.model, q, points_per_section)
    from .statics import internal_wrenches
    W = internal_wrenches(sc.model, q, s_bb, u, sc.loads_at(t))
    extra = {} if note is None else {"time": t, "time_note": note}
    return {
        "tip_position": res.tip_pose[:3, 3].tolist(),
        "tip_rotation": res.tip_pose[:3, :3].ravel().tolist(),
        "backbone_positions": P[:, :3, 3].tolist(),
        "base_wrench": res.base_wrench_world.tolist(),
        "strains": res.strains.tolist(),
        "internal_wrenches": W.tolist(),
        "backbone_s": s_bb.tolist(),
        "iterations": int(iters),
        "residual": res.residual,
        "stable": res.stable,
        "n_sections": sc.model.n_sections,
        **extra,
    }


# Time-history fields of :func:`run_dynamics`: one row per recorded time
# (``time``), and one row per backbone sample (``backbone_time``).
HISTORY_FIELDS = ("time", "tip_position", "tip_velocity", "base_wrench", "strains", "strain_rates",
                  "newton_iterations")
BACKBONE_FIELDS = ("backbone_time", "backbone_s", "backbone", "backbone_velocity", "backbone_acceleration",
                   "internal_wrenches")


def run_dynamics(sc, duration, dt, backbone_every=0, theta=0.5, progress=None,
                 points_per_section=10, record_every=1, progress_every=1.0):
    """Integrate the scenario for ``duration`` s with step ``dt`` s
    (``n = ceil(duration / dt)`` steps; see :func:`n_steps_for`).

    Returns a dict of time histories, one row per recorded step (every
    ``record_every`` steps, the first and the last, and every backbone
    sample): ``time`` (N,) [s], ``k * dt`` (:func:`step_times`); ``tip_position`` (N, 3)
    [m] and ``tip_velocity`` (N, 3) [m/s], world; ``base_wrench`` (N, 6)
    [N, N m] (the support's reaction with inertia: world axes, about the
    base origin); ``strains`` and ``strain_rates`` (N, n_sections, 6) (fixed
    modes: the reference strain and 0); ``newton_iterations`` (N,). With
    ``backbone_every = K > 0`` also, at t = 0 and every K steps,
    ``backbone_time`` (B,), ``backbone_s`` (B, P) [m], ``backbone`` (B, P, 3),
    ``backbone_velocity`` and ``backbone_acceleration`` (B, P, 3) [m/s,
    m/s^2] (world), ``internal_wrenches`` (B, P, 6) (body frame; see
    :func:`dynamics.internal_wrenches_dynamic`). Accelerations are those of
    the equations of motion at the recorded (q, qdot, t). ``n_sections``,
    ``dt`` and, when a step fails, ``error`` (the reason; the histories then
    end at the last converged step) complete the dict.

    The kernels are compiled (or loaded from numba's cache) and the inputs
    checked by a warm-up before the clock starts: ``progress(fraction,
    elapsed_s)`` is called once with (0.0, 0.0) right after the warm-up,
    then at most once per ``progress_every`` wall-clock seconds (0: after
    every step); ``elapsed_s`` counts from the end of the warm-up."""
    import time as _time
    from .mechanism_scenario import MechanismScenario, run_mechanism_dynamics
    if isinstance(sc, MechanismScenario):
        return run_mechanism_dynamics(sc, duration, dt, theta, progress, record_every, backbone_every,
                                      progress_every)
    from .dynamics import Simulator, base_reaction_dynamic, internal_wrenches_dynamic
    from .model import State
    m = sc.model
    n_steps = n_steps_for(duration, dt)
    dt = float(dt)
    time_of = step_times(dt)
    backbone_every = count(backbone_every, "backbone_every", 0)
    record_every = count(record_every, "record_every", 1)
    points_per_section = count(points_per_section, "points_per_section", 1)
    check_output_size(n_steps, record_every, backbone_every, m.n_sections * points_per_section + 1)
    state = State.rest(m)
    if sc.initial_strains is not None:
        state.q = sc.initial_strains.copy()
    if sc.time_varying:
        inputs = dict(actuation=sc.actuation_at, loads=sc.loads_at)
    else:
        inputs = dict(actuation=sc.actuation, loads=sc.loads_at(None))
    sim = Simulator(m, dt, state=state, theta=theta, **inputs)
    # accelerations at recorded states come from a second simulator: its own
    # workspace, so the integrator's kept factorisation is never disturbed
    probe = Simulator(m, dt, state=state, theta=theta, **inputs)
    out = {key: [] for key in HISTORY_FIELDS + (BACKBONE_FIELDS if backbone_every else ())}
    fixed_rates = np.zeros(6 * m.n_sections)

    def record(k, q, qdot, qddot, iterations):
        t = time_of(k)
        u, loads = sim.actuation_at(t), sim.loads_at(t)
        out["time"].append(t)
        out["tip_position"].append(kin.tip_pose(m, q)[:3, 3].tolist())
        out["tip_velocity"].append((kin.tip_jacobian(m, q, frame="world")[:3] @ qdot).tolist())
        out["base_wrench"].append(base_reaction_dynamic(m, q, qdot, qddot, u, loads).tolist())
        out["strains"].append(m.strains(q).tolist())
        rates = fixed_rates.copy()
        rates[m.free_index] = qdot
        out["strain_rates"].append(rates.reshape(m.n_sections, 6).tolist())
        out["newton_iterations"].append(int(iterations))

    def sample_backbone(k, q, qdot, qddot):
        t = time_of(k)
        s_bb, P = kin.backbone(m, q, points_per_section)
        mot = kin.point_motion(m, q, qdot, qddot, s_bb)
        out["backbone_time"].append(t)
        out["backbone_s"].append(s_bb.tolist())
        out["backbone"].append(P[:, :3, 3].tolist())
        out["backbone_velocity"].append(mot["v_world"].tolist())
        out["backbone_acceleration"].append(mot["a_world"].tolist())
        out["internal_wrenches"].append(internal_wrenches_dynamic(
            m, q, qdot, qddot, s_bb, sim.actuation_at(t), sim.loads_at(t)).tolist())

    def finish(error=None):
        if error is not None:
            out["error"] = error
        out["n_sections"] = m.n_sections
        out["dt"] = dt
        return out

    # warm-up: everything the loop calls runs once (numba compiles or loads
    # its cache) before the clock starts; the t = 0 row is computed here
    try:
        qddot = probe.acceleration(state.q, state.qdot, 0.0)
        if not np.all(np.isfinite(qddot)):
            return finish("the initial acceleration is not finite (inputs too large?); nothing simulated")
        record(0, state.q, state.qdot, qddot, 0)
        if backbone_every:
            sample_backbone(0, state.q, state.qdot, qddot)
        probe.step()           # compiles the step; probe's own state, discarded
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
        for key in out:
            out[key].clear()
        return finish(f"the initial state cannot be evaluated: {type(e).__name__}: {e}; nothing simulated")
    if progress is not None:
        progress(0.0, 0.0)
    t0 = last = _time.monotonic()
    recorded = 0                # the last recorded step
    iterations = 0              # Newton iterations of the last converged step
    for k in range(1, n_steps + 1):
        sim.state.t = time_of(k - 1)
        try:
            info = sim.step()
            failure = None if info.converged else (
                f"Newton's iteration did not converge ({info.iterations} iterations, "
                f"relative update {info.update:.3g}, even with sub-steps)")
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            failure = f"{type(e).__name__}: {e}"
        if failure is None and not (np.all(np.isfinite(sim.state.q)) and np.all(np.isfinite(sim.state.qdot))):
            failure = "the state became non-finite"
        if failure is not None:
            if recorded != k - 1:       # end the history at the last converged step
                st = sim.state
                record(k - 1, st.q, st.qdot, probe.acceleration(st.q, st.qdot, time_of(k - 1)), iterations)
            return finish(f"step {k} of {n_steps} (t = {time_of(k - 1):.6g} -> {time_of(k):.6g} s) failed: "
                          f"{failure}; the history ends at t = {time_of(k - 1):.6g} s")
        st = sim.state
        st.t = time_of(k)
        iterations = info.iterations
        sample = backbone_every and k % backbone_every == 0
        if k % record_every == 0 or k == n_steps or sample:
            qddot = probe.acceleration(st.q, st.qdot, st.t)
            record(k, st.q, st.qdot, qddot, info.iterations)
            recorded = k
            if sample:
                sample_backbone(k, st.q, st.qdot, qddot)
        if progress is not None and _time.monotonic() - last >= progress_every:
            progress(k / n_steps, _time.monotonic() - t0)
            last = _time.monotonic()
    return finish()
