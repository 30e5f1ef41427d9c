"""Scenario files for soft articulated robots (tree robot files): statics and
dynamics runs with joint commands, frame loads and a prescribed base, for
``soft-twin-sim`` (:mod:`scenario` hands a scenario over here when its robot
file has ``bodies``).

Schema (YAML; SI units, angles in rad)::

    robot: ../robots/pan_tilt_arm.yaml
    actuation: {tendon_z_pos: 2.0}               # N (tendons), Pa (chambers)
    actuation_profile: {tendon_z_pos: [[0, 0], [1, 4]]}     # piecewise linear [t, value]
    joint_positions: {pan: 0.5}                  # position-controlled joints (default: reference)
    joint_trajectories: {tilt: [[0, 0], [1, 0.6]]}   # [t, position]: a C2 cubic spline through the
                                                 # points, at rest at both ends
    joint_efforts: {wrist: 0.1}                  # effort-controlled joints [N m or N]
    joint_effort_profile: {wrist: [[0, 0], [1, 0.2]]}
    base_trajectory: [[t, x, y, z, roll, pitch, yaw], ...]   # base motion "prescribed": the base
                                                 # pose (cubic spline per coordinate, at rest at both ends)
    gravity: true
    loads:
      - {frame: tool, force: [0, 0, -1], moment: [0, 0, 0], axes: world, profile: [[0, 0], [1, 1]]}

Outputs (JSON; the CSV has the same time histories): see
:func:`run_mechanism_statics` and :func:`run_mechanism_dynamics`.
"""

import os
from dataclasses import dataclass

import numpy as np

from .constrained import FrameLoad, MechanismSimulator, StepError, make_inputs, solve_equilibrium
from .mechanism import check_joint_position, load_mechanism, mechanism_from_dict
from .errors import ScenarioError
from .model import ModelError, parse_number, parse_numbers
from .timeline import check_output_size, check_scenario_input, count, n_steps_for, parse_profile, step_times




@dataclass
class MechanismScenario:
    """A checked scenario of a mechanism (see the module)."""
    mech: object
    actuation: np.ndarray
    actuation_profile: dict        # actuator index -> (t, values)
    positions: dict                # joint -> value
    trajectories: dict             # joint -> CubicSpline
    efforts: dict
    effort_profile: dict           # joint -> (t, values)
    base_trajectory: object        # CubicSpline of [x, y, z, roll, pitch, yaw] or None
    loads: list                    # (FrameLoad, profile or None)
    gravity: bool
    source: str

    def velocities_at(self, t):
        """{joint: commanded velocity} of the position-controlled joints at t
        (trajectories: the spline's derivative; constant positions: 0)."""
        out = {j: 0.0 for j in self.positions}
        for j, sp in self.trajectories.items():
            out[j] = float(sp.velocity(t))
        pos_names = [self.mech.tree.joints[i].name for i in self.mech.joints_with("position")]
        return [out.get(j, 0.0) for j in pos_names]

    def inputs_at(self, t, sim=None):
        """(actuation, efforts, positions, point loads) at time t [s]."""
        u = self.actuation.copy()
        for i, (ts, vs) in self.actuation_profile.items():
            u[i] = float(np.interp(t, ts, vs))
        eff = dict(self.efforts)
        for j, (ts, vs) in self.effort_profile.items():
            eff[j] = float(np.interp(t, ts, vs))
        pos = dict(self.positions)
        for j, sp in self.trajectories.items():
            pos[j] = float(sp(t))
        pls = []
        for fl, prof in self.loads:
            k = 1.0 if prof is None else float(np.interp(t, prof[0], prof[1]))
            pls.append(FrameLoad(fl.frame, k * np.asarray(fl.wrench), fl.axes))
        return u, eff, pos, pls

    def base_pose_at(self, t):
        if self.base_trajectory is None:
            return None
        from .model import pose_from_dict
        x = self.base_trajectory(t)
        return pose_from_dict({"position": x[:3].tolist(), "rpy": x[3:].tolist()}, "base_trajectory")


class _Spline:
    """A clamped cubic spline through [t, values...] rows (at rest at both
    ends), held constant outside its time span; ``velocity(t)`` its derivative."""

    def __init__(self, a, where):
        from scipy.interpolate import CubicSpline
        self.t0, self.t1 = a[0, 0], a[-1, 0]
        y = a[:, 1:] if a.shape[1] > 2 else a[:, 1]
        if len(a) == 1:
            self.sp = None
            self.value = y[0]
            return
        if np.any(np.diff(a[:, 0]) <= 0):
            raise ScenarioError(f"{where}: times must increase strictly, got {a[:, 0].tolist()}")
        self.sp = CubicSpline(a[:, 0], y, bc_type="clamped")
        self.dsp = self.sp.derivative()

    def __call__(self, t):
        if self.sp is None:
            return np.copy(self.value)
        return self.sp(min(max(t, self.t0), self.t1))

    def velocity(self, t):
        if self.sp is None or not self.t0 <= t <= self.t1:
            return 0.0 * np.asarray(self(t))
        return self.dsp(t)


def _spline(a, where):
    return _Spline(a, where)


def mechanism_scenario_from_dict(d, base_dir, source):
    """A MechanismScenario from a parsed scenario mapping whose robot is a
    tree robot file; ScenarioError naming the field."""
    Err = ScenarioError
    allowed = {"robot", "actuation", "actuation_profile", "joint_positions", "joint_trajectories",
               "joint_efforts", "joint_effort_profile", "base_trajectory", "gravity", "loads", "description"}
    unknown = set(d) - allowed
    if unknown:
        raise Err(f"scenario: unknown field(s) {sorted(unknown)} for an articulated robot; allowed: "
                  f"{sorted(allowed)}")
    robot = d["robot"]
    try:
        if isinstance(robot, str):
            p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
            if not os.path.isfile(p) and os.path.basename(robot) == robot:
                from .model import find_file
                p = find_file(robot, "robots")
            mech = load_mechanism(p)
        else:
            mech = mechanism_from_dict(robot)
    except ModelError as e:
        raise Err(f"scenario.robot: {e}") from None
    names = mech.actuator_names
    u = np.zeros(len(names))

    def mapping(key):
        v = d.get(key) or {}
        if not isinstance(v, dict):
            raise Err(f"scenario.{key}: expected a mapping name -> value, got {v!r}")
        return v

    for k, v in mapping("actuation").items():
        if k not in names:
            raise Err(f"scenario.actuation: unknown actuator {k!r}; the robot has {list(names)}")
        u[names.index(k)] = parse_number(v, f"scenario.actuation.{k}", Err)
        # the node's rule for the actuator's declared range (tension >= 0, limit, min/max)
        check_scenario_input(mech.actuators[names.index(k)], [u[names.index(k)]], f"scenario.actuation.{k}", Err)
    aprof = {}
    for k, v in mapping("actuation_profile").items():
        if k not in names:
            raise Err(f"scenario.actuation_profile: unknown actuator {k!r}; the robot has {list(names)}")
        aprof[names.index(k)] = parse_profile(v, f"scenario.actuation_profile.{k}")
        check_scenario_input(mech.actuators[names.index(k)], aprof[names.index(k)][1],
                             f"scenario.actuation_profile.{k}", Err)
    pos_names = [mech.tree.joints[i].name for i in mech.joints_with("position")]
    eff_names = [mech.tree.joints[i].name for i in mech.joints_with("effort")]

    def joints(key, allowed_names, kind):
        out = {}
        for k, v in mapping(key).items():
            if k not in allowed_names:
                raise Err(f"scenario.{key}: {k!r} is not a {kind}-controlled joint; those are {allowed_names}")
            out[k] = v
        return out

    positions = {k: parse_number(v, f"scenario.joint_positions.{k}", Err)
                 for k, v in joints("joint_positions", pos_names, "position").items()}
    jointof = {j.name: j for j in mech.tree.joints}
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
        trajectories[k] = _spline(a, f"scenario.joint_trajectories.{k}")
    efforts = {k: parse_number(v, f"scenario.joint_efforts.{k}", Err)
               for k, v in joints("joint_efforts", eff_names, "effort").items()}
    eprof = {k: parse_profile(v, f"scenario.joint_effort_profile.{k}")
             for k, v in joints("joint_effort_profile", eff_names, "effort").items()}
    base = None
    if d.get("base_trajectory") is not None:
        if mech.base_motion != "prescribed":
            raise Err(f"scenario.base_trajectory: the robot's base motion is {mech.base_motion!r}; "
                      f"give base: {{motion: prescribed}} in the robot file")
        a = parse_numbers(d["base_trajectory"], (None, 7), "scenario.base_trajectory", Err)
        base = _spline(a, "scenario.base_trajectory")
    loads = []
    raw = d.get("loads") or []
    if not isinstance(raw, list):
        raise Err(f"scenario.loads: expected a list, got {raw!r}")
    for i, ld in enumerate(raw):
        where = f"scenario.loads[{i}]"
        if not isinstance(ld, dict):
            raise Err(f"{where}: expected a mapping, got {ld!r}")
        extra = set(ld) - {"frame", "force", "moment", "axes", "profile"}
        if extra:
            raise Err(f"{where}: unknown field(s) {sorted(extra)}; allowed: axes, force, frame, moment, profile")
        if ld.get("frame") not in mech.frames:
            raise Err(f"{where}.frame: {ld.get('frame')!r} is not a frame of the robot; frames: {sorted(mech.frames)}")
        axes = ld.get("axes", "world")
        if axes not in ("world", "body"):
            raise Err(f"{where}.axes: expected 'world' or 'body', got {axes!r}")
        w = np.concatenate([parse_numbers(ld.get("force", [0, 0, 0]), (3,), where + ".force", Err),
                            parse_numbers(ld.get("moment", [0, 0, 0]), (3,), where + ".moment", Err)])
        prof = parse_profile(ld["profile"], where + ".profile") if "profile" in ld else None
        loads.append((FrameLoad(ld["frame"], w, axes), prof))
    grav = d.get("gravity", True)
    if not isinstance(grav, bool):
        raise Err(f"scenario.gravity: expected true or false, got {grav!r}")
    sc = MechanismScenario(mech, u, aprof, positions, trajectories, efforts, eprof, base, loads, grav, source)
    try:                                   # every input checked once, at t = 0
        _inputs(sc, 0.0)
    except ValueError as e:
        raise Err(f"scenario: {e}") from None
    return sc


def _inputs(sc, t):
    from .loads import Loads
    u, eff, pos, pls = sc.inputs_at(t)
    return make_inputs(sc.mech, u, eff, pos, sc.velocities_at(t), Loads(gravity=sc.gravity), pls)


def _targets(sc, t):
    g = sc.base_pose_at(t)
    if g is None:
        return None
    return [g if c.name == "base" else None for c in sc.mech.constraints]


def _outputs_dict(sc, out, prefix=""):
    """JSON-ready dict of MechanismOutputs."""
    mech = sc.mech
    d = {
        "joint_names": list(mech.joint_names),
        "joint_positions": [out.positions[n] for n in mech.joint_names],
        "joint_velocities": [out.velocities[n] for n in mech.joint_names],
        "joint_accelerations": [out.accelerations[n] for n in mech.joint_names],
        "joint_efforts": [out.efforts[n] for n in mech.joint_names],
        "frame_names": list(out.frames),
        "frame_positions": [out.frames[n][:3, 3].tolist() for n in out.frames],
        "frame_poses": [np.asarray(out.frames[n], dtype=float).tolist() for n in out.frames],
        "constraint_names": list(out.constraint_wrenches),
        "constraint_wrenches": [w.tolist() for w in out.constraint_wrenches.values()],
        "transmitted_names": list(out.joint_wrenches),
        "transmitted_wrenches": [w.tolist() for w in out.joint_wrenches.values()],
        "members": {m.name: {"s": m.s.tolist(), "positions": m.poses[:, :3, 3].tolist(),
                             "orientations": _quaternions(m.poses),
                             "velocities": m.velocities.tolist(), "accelerations": m.accelerations.tolist(),
                             "internal_wrench": m.internal_wrench.tolist(), "strains": m.strains.tolist(),
                             "normal_stress": _nan_none(m.normal_stress), "shear_stress": _nan_none(m.shear_stress)}
                    for m in out.members},
    }
    return d


def _quaternions(T):
    """[x, y, z, w] (w >= 0) of the rotations of poses (N, 4, 4)."""
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(np.asarray(T, dtype=float)[:, :3, :3]).as_quat()
    return np.where(q[:, 3:] < 0, -q, q).tolist()


def _nan_none(a):
    return [None if not np.isfinite(x) else float(x) for x in a]


def run_mechanism_statics(sc, t=0.0):
    """Equilibrium of the scenario's inputs at time ``t`` [s] (default 0;
    :func:`scenario.run_statics` picks the end of the profiles). JSON-ready dict: joint_names and
    joint_positions/efforts [rad or m, N m or N]; frame_names and
    frame_positions (world, m) and frame_poses (4x4, world); constraint_names and constraint_wrenches
    (world [f; m] on the constraint's frame, N, N m); transmitted_names and
    transmitted_wrenches (the wrench through every joint, world axes, about
    its input origin); members: per soft member at its section boundaries
    s [m], positions, orientations (quaternions x, y, z, w), internal_wrench (body axes), strains,
    normal_stress and shear_stress [Pa] (null without geometry); iterations, residual; stable and
    min_stiffness_eigenvalue (constrained.equilibrium_stability)."""
    from .outputs import state_outputs
    from .loads import Loads
    u, eff, pos, pls = sc.inputs_at(t)
    eq = solve_equilibrium(sc.mech, u, eff, pos, loads=Loads(gravity=sc.gravity), point_loads=pls,
                           targets=_targets(sc, t))
    out = state_outputs(sc.mech, eq.q, eq.lam, eq.inputs)
    d = _outputs_dict(sc, out)
    d.update(iterations=eq.iterations, residual=eq.residual, constraint_error=eq.constraint_error,
             stable=eq.stable, min_stiffness_eigenvalue=eq.min_stiffness_eigenvalue)
    return d


# history fields of a dynamics run, in CSV column order
HISTORY_FIELDS = ("time", "joint_positions", "joint_velocities", "joint_accelerations", "joint_efforts",
                  "frame_positions", "constraint_wrenches", "constraint_error", "transmitted_wrenches", "strains",
                  "peak_normal_stress", "peak_shear_stress", "newton_iterations")


def run_mechanism_dynamics(sc, duration, dt, theta=0.5, progress=None, record_every=1, backbone_every=0,
                           progress_every=1.0):
    """Integrate the scenario (``n = ceil(duration / dt)`` steps). Returns the
    time histories, one row per recorded step: time [s]; joint_positions,
    velocities, accelerations, efforts (N, n_joints) in the order of
    ``joint_names``; frame_positions (N, n_frames, 3) world [m] in the order
    of ``frame_names``; constraint_wrenches (N, n_constraints, 6);
    constraint_error (N,) [m or rad]; transmitted_wrenches (N, n_joints, 6)
    (the wrench through every joint, world axes about its input origin, in
    the order of ``transmitted_names``); strains (N, n_soft_sections, 6) of
    every soft section in tree order (``section_names``); peak_normal_stress and
    peak_shear_stress (N, n_members) [Pa], the largest over each member's
    section boundaries; newton_iterations. With ``backbone_every = K``,
    every K steps the full member outputs under ``members_time`` and
    ``members`` (as in statics), and the same samples flat for the CSV:
    ``member_positions`` (B, P, 3) [m] and ``member_internal_wrenches``
    (B, P, 6) [N, N m] at every member's section boundaries
    (``member_point_names``: ``<member>_<k>``); JSON only, at the same samples:
    ``frame_poses`` (B, n_frames, 4, 4) world poses of the frames of
    ``frame_names`` and ``energies`` (B, 3) [J]: kinetic, elastic (members and
    joint springs), gravitational (:func:`sample_energies`). ``error`` when a
    step fails (the history ends at the last converged step)."""
    import time as _time
    from .outputs import section_strains, state_outputs
    mech = sc.mech
    n_steps = n_steps_for(duration, dt)
    check_output_size(n_steps, count(record_every, "record_every", 1), count(backbone_every, "backbone_every", 0),
                      mech.tree.n_joints + len(mech.frames) + 1)
    time_of = step_times(dt)
    sim = MechanismSimulator(mech, float(dt), theta)
    inp0 = _inputs(sc, 0.0)
    # start where the commanded joints are at t = 0
    for k, i in enumerate(mech.joints_with("position")):
        sim.q[mech.tree.idx_q[i]] = inp0.q_cmd[k]
    out = {key: [] for key in HISTORY_FIELDS}
    soft = mech.tree.soft_joints
    out.update(transmitted_names=[j.name for j in mech.tree.joints],
               section_names=[mech.tree.joints[i].name for i in soft])
    out.update(joint_names=list(mech.joint_names), frame_names=list(mech.frames),
               constraint_names=[c.name for c in mech.constraints], member_names=[m.name for m in mech.members],
               history_fields=list(HISTORY_FIELDS))
    if backbone_every:
        out.update(members_time=[], members=[], member_positions=[], member_internal_wrenches=[],
                   member_point_names=[f"{m.name}_{k}" for m in mech.members
                                       for k in range(len(mech.tree.paths[m.path].joints) + 1)],
                   sample_fields=["member_positions", "member_internal_wrenches"], frame_poses=[], energies=[])

    def record(k, inp, iterations):
        o = state_outputs(mech, sim.q, sim.lam, inp, sim.v, sim.a, sim.ws)
        out["time"].append(time_of(k))
        out["joint_positions"].append([o.positions[n] for n in mech.joint_names])
        out["joint_velocities"].append([o.velocities[n] for n in mech.joint_names])
        out["joint_accelerations"].append([o.accelerations[n] for n in mech.joint_names])
        out["joint_efforts"].append([o.efforts[n] for n in mech.joint_names])
        out["frame_positions"].append([o.frames[n][:3, 3].tolist() for n in mech.frames])
        out["constraint_wrenches"].append([w.tolist() for w in o.constraint_wrenches.values()])
        out["constraint_error"].append(sim.constraint_error(_targets(sc, time_of(k))))
        out["transmitted_wrenches"].append([w.tolist() for w in o.joint_wrenches.values()])
        out["strains"].append(section_strains(mech, sim.q).tolist())
        out["peak_normal_stress"].append([float(np.nanmax(m.normal_stress, initial=0)) for m in o.members])
        out["peak_shear_stress"].append([float(np.nanmax(m.shear_stress, initial=0)) for m in o.members])
        out["newton_iterations"].append(int(iterations))
        if backbone_every and k % backbone_every == 0:
            out["members_time"].append(time_of(k))
            out["members"].append(_outputs_dict(sc, o)["members"])
            # the same samples flat (every member's section boundaries in order), for the CSV
            out["member_positions"].append(np.concatenate([m.poses[:, :3, 3] for m in o.members]).tolist())
            out["member_internal_wrenches"].append(np.concatenate([m.internal_wrench for m in o.members]).tolist())
            # issue 12 (figures): every frame's pose and the energies at the samples
            out["frame_poses"].append([np.asarray(o.frames[n], dtype=float).tolist() for n in mech.frames])
            out["energies"].append(_nan_none(sample_energies(sim)))

    sim.start_multipliers(inp0, _targets(sc, 0.0))
    record(0, inp0, 0)
    if progress is not None:
        progress(0.0, 0.0)
    t0 = last = _time.monotonic()
    for k in range(1, n_steps + 1):
        t1 = time_of(k)
        inp = _inputs(sc, t1)
        try:
            sim.step(inputs=inp, targets=_targets(sc, t1))
        except (StepError, ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            out["error"] = (f"step {k} of {n_steps} (t = {time_of(k - 1):.6g} -> {t1:.6g} s) failed: {e}; "
                            f"the history ends at t = {time_of(k - 1):.6g} s" + failure_context(sc, out, time_of(k - 1), t1))
            break
        if k % record_every == 0 or k == n_steps or (backbone_every and k % backbone_every == 0):
            record(k, inp, sim.iterations)
        if progress is not None and _time.monotonic() - last >= progress_every:
            progress(k / n_steps, _time.monotonic() - t0)
            last = _time.monotonic()
    out["dt"] = float(dt)
    return out


def failure_context(sc, out, t0, t1):
    """A failed dynamics step (t0 -> t1) in physical terms: how far a
    prescribed base was asked to go (from its start, and within the step),
    and at the last recorded state the members' largest peak normal stress
    (with the multiple of the Young's modulus it is) and the constraint
    error. '' when there is nothing to say."""
    mech, asked, state = sc.mech, [], []
    g0, ga, gb = sc.base_pose_at(0.0), sc.base_pose_at(t0), sc.base_pose_at(t1)
    if g0 is not None:
        asked.append(f"the step asked the prescribed base to be {np.linalg.norm(gb[:3, 3] - g0[:3, 3]):.3g} m from "
                     f"its start, {np.linalg.norm(gb[:3, 3] - ga[:3, 3]):.3g} m in one step")
    stress = np.asarray(out["peak_normal_stress"][-1], dtype=float) if out.get("peak_normal_stress") else []
    if len(stress) and np.nanmax(stress) > 0:
        k = int(np.nanargmax(stress))
        E = member_youngs_modulus(mech, k)
        ratio = f" ({stress[k] / E:.3g} times its Young's modulus {E:.3g} Pa)" if E else ""
        state.append(f"member {mech.members[k].name!r} was at a peak normal stress of {stress[k]:.3g} Pa{ratio}")
    if out.get("constraint_error"):
        state.append(f"the constraints were off by up to {np.nanmax(out['constraint_error'][-1]):.3g} m or rad")
    if not (asked or state):
        return ""
    text = "; " + "; ".join(asked)
    if state:
        text += f"; at the last good state (t = {out['time'][-1]:.6g} s) " + " and ".join(state)
    return text + (": the motion asked for is larger or faster than the structure can follow by deforming "
                   "(a smaller dt or a slower motion may pass; a real structure would break, or its clamps "
                   "and joints slip)")


def member_youngs_modulus(mech, k):
    """Young's modulus [Pa] of soft member k's first section: its axial
    stiffness EA (the section's stiffness, strain order [nu; kappa]) over
    its area (None without geometry)."""
    m = mech.members[k]
    g = m.geometry[0] if m.geometry else None
    if g is None or not g.A:
        return None
    return float(mech.tree.joints[m.joints[0]].section.K[0, 0] / g.A)


def sample_energies(sim):
    """(kinetic, elastic, gravitational) [J] of a MechanismSimulator's state:
    its :meth:`~constrained.MechanismSimulator.energy` with the potential
    split into the strain (and joint spring) energy 1/2 dq^T K dq and the
    rest, the gravity potential (zero at the world origin). The elastic part
    is NaN when the tree has quaternion joints (nq != nv: ``energy`` then
    gives the gravity potential only)."""
    kin, pot = sim.energy()
    tree = sim.tree
    if tree.nq != tree.nv:
        return float(kin), float("nan"), float(pot)
    dq = sim.q - tree.q0
    ela = 0.5 * float(dq @ sim.K @ dq)
    return float(kin), ela, float(pot) - ela
