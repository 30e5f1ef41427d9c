"""Scenario files for ``soft-twin-sim``: a robot, its loads and actuation,
for a statics solve or a dynamic simulation.

Schema (YAML; SI units)::

    robot: robots/tendon_arm.yaml      # path (relative to this file) or an inline robot mapping
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
"""

import os
from dataclasses import dataclass

import numpy as np

from . import kinematics as kin
from .loads import DistributedLoad, Loads, PointLoad
from .model import ModelError, load_model, model_from_dict, read_yaml_file


class ScenarioError(ValueError):
    """A scenario file is invalid; the message names the field."""


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
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where}.{key}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ScenarioError(f"{where}.{key}: expected 3 finite numbers, got {v!r}")
    return a


def _profile(v, where):
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where}: expected a list of [t, value] pairs, got {v!r}") from None
    if a.ndim != 2 or a.shape[1] != 2 or len(a) < 1 or not np.all(np.isfinite(a)):
        raise ScenarioError(f"{where}: expected a list of [t, value] pairs, got {v!r}")
    if np.any(np.diff(a[:, 0]) <= 0):
        raise ScenarioError(f"{where}: times must increase strictly, got {a[:, 0].tolist()}")
    return a[:, 0], a[:, 1]


def _number(v, where):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ScenarioError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _s_value(v, model, where):
    if v == "tip":
        return model.total_length
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ScenarioError(f"{where}.s: expected a number (m) or 'tip', got {v!r}")
    if not 0.0 <= v <= model.total_length + 1e-12:
        raise ScenarioError(f"{where}.s: must lie in [0, {model.total_length}] m, got {v}")
    return float(v)


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
        try:
            P = float(ip["magnitude"])
            a = float(ip.get("angle_deg", 0.0) if angle_override is None else angle_override)
        except (TypeError, ValueError):
            raise ScenarioError(f"{where}.in_plane_force: magnitude and angle_deg must be numbers") from None
        a = np.radians(a)
        force = force + P * np.array([0.0, np.cos(a), np.sin(a)])
    wrench = tuple(np.concatenate([force, moment]))
    prof = _profile(d["profile"], where + ".profile") if "profile" in d else None
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
    ``angle_deg`` the angle of every ``in_plane_force``. Raises ScenarioError
    or ModelError naming the bad field."""
    d = read_yaml_file(path, ScenarioError, "scenario")
    return scenario_from_dict(d, os.path.dirname(os.path.abspath(path)), sections, angle_deg, str(path))


def scenario_from_dict(d, base_dir=".", sections=None, angle_deg=None, source="<dict>"):
    if not isinstance(d, dict):
        raise ScenarioError("scenario: expected a mapping at top level")
    allowed = {"robot", "sections", "actuation", "actuation_profile", "gravity", "loads", "load_steps",
               "initial_strains", "description"}
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
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ScenarioError(f"scenario.actuation.{k}: expected a finite number, got {v!r}")
        if model.actuators[names.index(k)].kind == "tendon" and v < 0:
            raise ScenarioError(f"scenario.actuation.{k}: tendon tension must be >= 0 N, got {v}")
        u[names.index(k)] = float(v)
    prof = {}
    profiles = d.get("actuation_profile") or {}
    if not isinstance(profiles, dict):
        raise ScenarioError(f"scenario.actuation_profile: expected a mapping name -> [[t, value], ...], "
                            f"got {profiles!r}")
    for k, v in profiles.items():
        if k not in names:
            raise ScenarioError(f"scenario.actuation_profile: unknown actuator {k!r}; the robot has {list(names)}")
        ts, vs = _profile(v, f"scenario.actuation_profile.{k}")
        if model.actuators[names.index(k)].kind == "tendon" and np.any(vs < 0):
            raise ScenarioError(f"scenario.actuation_profile.{k}: tendon tension must be >= 0 N")
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
        try:
            init = model.q_from_strains(np.array(init, dtype=float))
        except (ModelError, ValueError) as e:
            raise ScenarioError(f"scenario.initial_strains: {e}") from None
    return Scenario(model, u, prof, loads, grav, steps, init, source)


# ----------------------------------------------------------------------------
# Runs
# ----------------------------------------------------------------------------

def run_statics(sc, points_per_section=10):
    """Solve the scenario's equilibrium (loads applied in load_steps
    increments, each warm-started). Returns a JSON-ready dict, including the
    internal wrenches [N, N m] (body frame, the distal part acting on the
    proximal part) at the backbone sample points ``backbone_s`` [m]."""
    from .statics import solve_statics
    q, iters, res = None, 0, None
    for k in range(1, sc.load_steps + 1):
        f = k / sc.load_steps
        loads = sc.loads_at(None, f)
        res = solve_statics(sc.model, f * sc.actuation, loads, q_init=q)
        q, iters = res.q, iters + res.iterations
    s_bb, P = kin.backbone(sc.model, q, points_per_section)
    from .statics import internal_wrenches
    W = internal_wrenches(sc.model, q, s_bb, sc.actuation, sc.loads_at(None))
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
    }


def run_dynamics(sc, duration, dt, backbone_every=0, theta=0.5, progress=None,
                 points_per_section=10, record_every=1):
    """Integrate the scenario for ``duration`` s with step ``dt`` s.

    Returns a dict of time histories: time, tip_position (N x 3, m),
    tip_velocity (N x 3, m/s, world), base_wrench (N x 6, world, about the
    base origin), strains (N x n x 6), strain_rates (N x n_dof, free modes),
    and every ``backbone_every`` steps a backbone sample. ``progress`` is
    called as progress(fraction) about once per wall-clock second."""
    import time as _time
    from .dynamics import Simulator, base_reaction_dynamic, internal_wrenches_dynamic
    from .model import State
    m = sc.model
    if not (np.isfinite(duration) and duration > 0):
        raise ScenarioError(f"duration: expected a positive time in s, got {duration}")
    state = State.rest(m)
    if sc.initial_strains is not None:
        state.q = sc.initial_strains.copy()
    if sc.time_varying:
        sim = Simulator(m, dt, actuation=sc.actuation_at, loads=sc.loads_at, state=state, theta=theta)
    else:
        loads = sc.loads_at(None)
        sim = Simulator(m, dt, actuation=sc.actuation, loads=loads, state=state, theta=theta)
    n_steps = int(round(duration / dt))
    out = {"time": [], "tip_position": [], "tip_velocity": [], "base_wrench": [], "strains": [],
           "strain_rates": [], "backbone": [], "backbone_time": [], "backbone_velocity": [],
           "backbone_acceleration": [], "internal_wrenches": [], "newton_iterations": []}

    def record(it):
        st = sim.state
        t = st.t
        out["time"].append(t)
        out["tip_position"].append(kin.tip_pose(m, st.q)[:3, 3].tolist())
        out["base_wrench"].append(base_reaction_dynamic(m, st.q, st.qdot, sim.last_qddot,
                                                        sim.actuation_at(t), sim.loads_at(t)).tolist())
        out["strains"].append(m.strains(st.q).tolist())
        out["strain_rates"].append(st.qdot.tolist())
        out["tip_velocity"].append((kin.tip_jacobian(m, st.q, frame="world")[:3] @ st.qdot).tolist())
        out["newton_iterations"].append(it)

    record(0)
    last = _time.monotonic()
    for k in range(1, n_steps + 1):
        info = sim.step()
        if not info.converged:
            out["error"] = f"step at t = {sim.state.t:.6g} s did not converge; history ends there"
            break
        if k % record_every == 0 or k == n_steps:
            record(info.iterations)
        if backbone_every and k % backbone_every == 0:
            st = sim.state
            s_bb, P = kin.backbone(m, st.q, points_per_section)
            mot = kin.point_motion(m, st.q, st.qdot, sim.last_qddot, s_bb)
            out["backbone_time"].append(st.t)
            out["backbone"].append(P[:, :3, 3].tolist())
            out["backbone_velocity"].append(mot["v_world"].tolist())
            out["backbone_acceleration"].append(mot["a_world"].tolist())
            out["internal_wrenches"].append(internal_wrenches_dynamic(
                m, st.q, st.qdot, sim.last_qddot, s_bb, sim.actuation_at(st.t), sim.loads_at(st.t)).tolist())
        if progress is not None and _time.monotonic() - last > 1.0:
            progress(k / n_steps)
            last = _time.monotonic()
    out["n_sections"] = m.n_sections
    out["dt"] = dt
    return out
