"""Plan files for ``soft-twin-sim plan PATH.yaml``: a robot, a tip path
and the planner's options; the result as a JSON-ready dict and CSV text.

    robot: tendon_arm               # example name, file (relative to this file) or inline mapping
    path: {type: circle, center: [0.30, 0.0, -0.22], radius: 0.05,
           normal: [1, 0, 0], duration: 4.0, sample_period: 0.02}   # base frame, m, s
    tracking:                       # optional
      position_weights: [0, 1, 1]   # per world axis (here: y and z tracked, x free)
      orientation_weight: 0.1       # m/rad, when the path has orientations
      tolerance: 1.0e-6             # m: a sample is reached within it
    actuation:                      # optional
      pretension: 0.0               # N (scalar or {actuator: value})
      max_tension: null             # N, on top of each actuator's `limit`
      max_pressure: null            # Pa
      max_rate: null                # N/s (Pa/s)
      initial: null                 # inputs before the path (rate limits hold from them)
    gravity: true
    dynamics:                       # optional: verify the plan in the dynamics
      dt: 0.005                     # s
      compensation_iterations: 3    # 0: verification only

See :mod:`soft_twin_core.planning.planner` for the method. One schema for every
robot file (a classic rod, a tree robot, e.g. ``robot: pan_tilt_arm``): the
plan gives the position-controlled joints' commands and the actuators'
inputs; ``tracking.frame`` names the frame that follows the path (default
the robot's tip, :func:`mechanism.tip_frame`), ``joints.limits_margin``
[rad or m] keeps the commands inside the joint limits and
``joints.initial`` ({joint: position}) gives the joints' commands before
the path (with ``actuation.initial``: the rate limits hold from them); the
joints' ``max_velocity``/``max_acceleration`` from the robot file are their
rate limits. ``dynamics`` executes the plan in the dynamics
(:func:`planner.simulate_plan`: the simulated frame positions and their
error per sample, in the JSON, the CSV and the figures) and compensates
the lag (``compensation_iterations``, ``gain``, ``filter_s`` [s]:
:func:`planner.compensate_lag`). A path with orientations has the frame's
orientation tracked too (``tracking.orientation_weight`` [m/rad],
``tracking.tolerance_rad``). The CSV has one ``q_<joint>`` column per
position-controlled joint.
"""

import csv
import io
import math
import os

import numpy as np

from soft_twin_core.engine.joint_kinds import PRISMATIC
from soft_twin_core.engine.loads import Loads
from soft_twin_core.errors import PlanFileError
from soft_twin_core.limits import MAX_PATH_SAMPLES, MAX_TIME_STEPS, check_limit
from soft_twin_core.planning import paths as pth, planner as pl
from soft_twin_core.robot.mechanism import from_robot_model, is_tree_file, load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import (ModelError, config_dirs, model_from_dict, parse_number,
                                        read_yaml_file, robot_mapping)


_TOP = {"robot", "path", "tracking", "actuation", "gravity", "dynamics", "description", "joints"}
_TRACK = {"position_weights", "orientation_weight", "tolerance", "tolerance_rad", "max_iterations", "frame"}
_JOINTS = {"limits_margin", "initial"}
_ACT = {"pretension", "max_tension", "max_pressure", "max_rate", "initial"}
_DYN = {"dt", "compensation_iterations", "gain", "filter_s"}


def find_plan_file(name):
    """A path as given, else the example plan of that name (config/paths/)."""
    p = os.path.expanduser(os.fspath(name))
    if os.path.isfile(p) or os.sep in p:
        return p
    stem = p[:-5] if p.endswith(".yaml") else p
    for c in config_dirs():
        f = c / "paths" / f"{stem}.yaml"
        if f.is_file():
            return str(f)
    return p


def _keys(d, allowed, where):
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise PlanFileError(f"{where}: expected a mapping, got {d!r}")
    bad = sorted(set(d) - allowed)
    if bad:
        raise PlanFileError(f"{where}.{bad[0]}: unknown field; allowed: {sorted(allowed)}")
    return d


def load_plan_file(path):
    """(Mechanism, TipPath, PlanOptions, start x or None, dynamics dict or None) of a plan file."""
    path = find_plan_file(path)
    d = read_yaml_file(path, PlanFileError, "plan file")
    return plan_from_dict(d, os.path.dirname(os.path.abspath(path)))


def _real(v):
    """v as a finite float (numbers and numeric strings such as YAML's 1.0e9), else None."""
    try:
        x = parse_number(v, "")
    except (ModelError, TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def check_plan_size(d):
    """Resource bounds of a plan (soft_twin_core.limits), before the path
    is sampled: samples = duration / sample_period (each an IK solve) and,
    with ``dynamics``, time steps = duration / dynamics.dt. Values that are
    not numbers are left to the field checks."""
    path = d.get("path")
    if not isinstance(path, dict):
        return
    kind = path.get("type")
    sp = _real(path.get("sample_period", 0.02 if kind != "waypoints" else None))
    if kind == "waypoints":
        pts = path.get("points")
        ts = [_real(p.get("t")) for p in pts if isinstance(p, dict)] if isinstance(pts, list) else []
        ts = [t for t in ts if t is not None]
        duration = max(ts) - min(ts) if ts else None
    else:
        duration = _real(path.get("duration"))
    if duration is None or duration <= 0:
        return
    if sp is not None and sp > 0:
        check_limit("path.duration / path.sample_period: samples", duration / sp, MAX_PATH_SAMPLES, PlanFileError)
    dyn = d.get("dynamics")
    if isinstance(dyn, dict):
        dt = _real(dyn.get("dt", 0.005))
        if dt is not None and dt > 0:
            check_limit("path.duration / dynamics.dt: time steps", duration / dt, MAX_TIME_STEPS, PlanFileError)


def _robot(robot, base_dir):
    """The mechanism of ``plan.robot``: an example name, a robot file
    (relative to the plan file) or an inline mapping, of either schema."""
    if isinstance(robot, dict):
        d = robot_mapping(robot, "plan.robot")
        return mechanism_from_dict(d, base_dir) if is_tree_file(d) else from_robot_model(model_from_dict(d), d,
                                                                                          base_dir)
    if isinstance(robot, str):
        p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
        return load_mechanism(p if os.path.isfile(p) else robot)
    raise PlanFileError(f"plan.robot: expected a name, a file or a mapping, got {robot!r}")


def plan_from_dict(d, base_dir="."):
    """(Mechanism, TipPath, PlanOptions, start x or None, dynamics dict or
    None) of a plan file's mapping; PlanFileError or PlanError naming the
    bad field."""
    d = _keys(d, _TOP, "plan")
    check_plan_size(d)
    if "robot" not in d:
        raise PlanFileError("plan.robot: missing (an example name, a robot file or a mapping)")
    if "path" not in d:
        raise PlanFileError("plan.path: missing (a path mapping with a type)")
    mech = _robot(d["robot"], base_dir)
    path = pth.path_from_dict(d["path"], "path")
    tr = _keys(d.get("tracking"), _TRACK, "tracking")
    ac = _keys(d.get("actuation"), _ACT, "actuation")
    jn = _keys(d.get("joints"), _JOINTS, "joints")
    grav = d.get("gravity", True)
    if not isinstance(grav, bool):
        raise PlanFileError(f"plan.gravity: expected true or false, got {grav!r}")
    opts = pl.PlanOptions(loads=Loads(gravity=grav), joint_limits_margin=jn.get("limits_margin", 0.0),
                          **{k: (tuple(v) if k == "position_weights" and isinstance(v, list) else v)
                             for k, v in tr.items()},
                          **{k: v for k, v in ac.items() if k != "initial"})
    solver = pl.TipSolver(mech, opts)        # checks every option (PlanError naming it)
    start = None
    if ac.get("initial") is not None or jn.get("initial") is not None:
        ini = jn.get("initial") or {}
        if not isinstance(ini, dict):
            raise PlanFileError(f"joints.initial: expected a mapping {{joint: position}}, got {ini!r}")
        for k, v in ini.items():
            if k not in solver.joint_names:
                raise PlanFileError(f"joints.initial.{k}: not a position-controlled joint; those are "
                                    f"{list(solver.joint_names)}")
            pl._number(v, f"joints.initial.{k}", False)
        try:
            start = pl.start_vector(mech, solver, ac.get("initial"), ini)
        except ValueError as e:
            raise PlanFileError(f"actuation.initial: {e}") from None
    dyn = _keys(d.get("dynamics"), _DYN, "dynamics") if d.get("dynamics") is not None else None
    if dyn is not None:
        dt = dyn.get("dt", 0.005)
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not 0 < dt <= 0.1:
            raise PlanFileError(f"dynamics.dt: expected a time step in (0, 0.1] s, got {dt!r}")
        it = dyn.get("compensation_iterations", 3)
        if isinstance(it, bool) or not isinstance(it, int) or not 0 <= it <= 20:
            raise PlanFileError(f"dynamics.compensation_iterations: expected an integer in 0..20, got {it!r}")
    return mech, path, opts, start, dyn


def run_plan(mech, path, options, start=None, dynamics=None):
    """Plan the joint commands and inputs of a path -> result dict; with
    ``dynamics`` ({dt, compensation_iterations, gain, filter_s}) the plan is
    executed in the dynamics (:func:`planner.simulate_plan`) and, with
    compensation iterations, compensated for the lag
    (:func:`planner.compensate_lag`). ``start``: x before the path (the
    rate limits hold from it)."""
    plan = pl.plan_path(mech, path, options, start=start, from_start=start is not None)
    junits = {mech.tree.joints[i].name: ("m" if mech.tree.joints[i].kind == PRISMATIC else "rad")
              for i in mech.joints_with("position")}
    out = {"robot": mech.name, "frame_followed": plan.frame,
           "actuator_names": list(plan.actuator_names), "joint_names": list(plan.joint_names),
           "frame": "world (the robot file's base pose applied to the path)",
           "units": {"time": "s", "inputs": {a.name: ("N" if a.kind == "tendon" else "Pa") for a in mech.actuators},
                     "joints": junits, "positions": "m"},
           "position_weights": list(options.position_weights),
           "lower": plan.lower.tolist(), "upper": _finite(plan.upper), "max_rate": _finite(plan.max_rate),
           "joint_lower": _finite(plan.joint_lower), "joint_upper": _finite(plan.joint_upper),
           "max_velocity": _finite(plan.max_velocity), "max_acceleration": _finite(plan.max_acceleration),
           "summary": plan.summary(), "violations": pl.check_plan(plan),
           "time": plan.times.tolist(), "joints": plan.joints.tolist(), "actuation": plan.u.tolist(),
           "target": plan.target.tolist(), "predicted_tip": plan.tip.tolist(),
           "error_m": plan.weighted_error.tolist(), "distance_m": plan.position_error.tolist(),
           "orientation_error_rad": plan.orientation_error.tolist(),
           "reached": plan.reached.tolist(), "status": list(plan.status)}
    if dynamics is None:
        return out
    dt = dynamics.get("dt", 0.005)
    w = np.sqrt(np.asarray(options.position_weights, float))

    def at(tr_):
        return np.stack([np.interp(plan.times, tr_.time, tr_.tip[:, k]) for k in range(3)], -1)
    tr0 = pl.simulate_plan(mech, plan, options, plan.target, dt)
    out["dynamics"] = {"dt": dt, "uncompensated": tr0.summary(), "simulated_tip": at(tr0).tolist(),
                       "simulated_error_m": np.linalg.norm((plan.target - at(tr0)) * w, axis=1).tolist()}
    iterations = dynamics.get("compensation_iterations", 3)
    if iterations:
        best, tr, hist = pl.compensate_lag(mech, path, options, iterations, dynamics.get("gain", 0.5), dt, start,
                                           dynamics.get("filter_s", 0.25), from_start=start is not None)
        out["dynamics"].update({
            "compensated": tr.summary(), "iterations": hist, "compensated_actuation": best.u.tolist(),
            "compensated_joints": best.joints.tolist(), "compensated_tip": at(tr).tolist(),
            "compensated_error_m": np.linalg.norm((plan.target - at(tr)) * w, axis=1).tolist()})
    return out


def _finite(a):
    return [float(x) if np.isfinite(x) else None for x in a]


def plan_csv(out):
    """One row per sample: time, inputs, target, predicted tip, errors,
    reached, status (and the dynamics columns when present)."""
    names = out["actuator_names"]
    joints = out.get("joint_names", [])
    cols = ["time_s"] + [f"q_{n}_{out['units']['joints'][n]}" for n in joints] + [f"u_{n}" for n in names] \
        + [f"target_{c}_m" for c in "xyz"] \
        + [f"tip_{c}_m" for c in "xyz"] + ["error_m", "distance_m", "orientation_error_rad", "reached", "status"]
    dyn = out.get("dynamics")
    if dyn:
        cols += [f"sim_tip_{c}_m" for c in "xyz"] + ["sim_error_m"]
        if "compensated_tip" in dyn:
            cols += [f"u_ff_{n}" for n in names] + [f"ff_tip_{c}_m" for c in "xyz"] + ["ff_error_m"]
    buf = io.StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(cols)
    for i, t in enumerate(out["time"]):
        row = [repr(t)] + [repr(v) for v in (out["joints"][i] if joints else [])] \
            + [repr(v) for v in out["actuation"][i]] + [repr(v) for v in out["target"][i]] \
            + [repr(v) for v in out["predicted_tip"][i]] \
            + [repr(out["error_m"][i]), repr(out["distance_m"][i]), repr(out["orientation_error_rad"][i]),
               int(out["reached"][i]), out["status"][i]]
        if dyn:
            row += [repr(v) for v in dyn["simulated_tip"][i]] + [repr(dyn["simulated_error_m"][i])]
            if "compensated_tip" in dyn:
                row += [repr(v) for v in dyn["compensated_actuation"][i]] \
                    + [repr(v) for v in dyn["compensated_tip"][i]] + [repr(dyn["compensated_error_m"][i])]
        wr.writerow(row)
    return buf.getvalue()


__all__ = ["PlanFileError", "load_plan_file", "plan_from_dict", "run_plan", "plan_csv"]
