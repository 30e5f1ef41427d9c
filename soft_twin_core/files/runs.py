"""Runs of a scenario of any robot (:mod:`scenario` parses every scenario
and its runners hand over here): statics and dynamics with actuation,
joint commands, loads on members and frames and a prescribed base, and
outputs of the tip frame, the support, joints, frames, constraints and
members.

Outputs (JSON; the CSV has the same time histories): see
:func:`run_mechanism_statics` and :func:`run_mechanism_dynamics`.
"""

import numpy as np

from soft_twin_core._blas import one_blas_thread
from soft_twin_core.errors import StaticsError
from soft_twin_core.engine.loads import Loads
from soft_twin_core.solve.constrained import (MechanismSimulator, StepError, basis_coordinates, concat_loads,
                                              make_inputs, solve_equilibrium)

_NO_LOADS = Loads(gravity=False)
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.files.timeline import check_output_size, count, n_steps_for, step_times
from soft_twin_core.robot.mechanism import base_targets, tip_frame
from soft_twin_core.solve.contact import MemberContact, contacts_dict
from soft_twin_core.solve.outputs import (frame_velocity, main_member, member_samples, section_rates,
                                          section_strains, state_outputs)


def scenario_inputs(sc, t, factor=1.0):
    """The checked :class:`constrained.Inputs` of the scenario at time t [s];
    ``factor`` scales the actuation, the efforts and the loads (gravity
    stays whole: load stepping)."""
    eff = {j: factor * v for j, v in sc.efforts_at(t).items()}
    return make_inputs(sc.mech, factor * sc.actuation_at(t), eff, sc.positions_at(t), sc.velocities_at(t),
                       sc.loads_at(t, factor), sc.frame_loads_at(t, factor))


def _targets(sc, t):
    return base_targets(sc.mech, sc.base_pose_at(t))


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


def _backbone_view(mech, out):
    """The fields every robot's statics result has beside its joints,
    frames and members: ``tip_position`` [m] and ``tip_rotation`` (3x3
    row-major) of the tip frame (:func:`mechanism.tip_frame`),
    ``base_wrench`` (:func:`outputs.base_reaction`), and the main member's
    samples (:func:`outputs.main_member`): ``backbone_s`` [m],
    ``backbone_positions`` [m] and ``internal_wrenches`` (its cross-sections'
    axes)."""
    tip = tip_frame(mech)
    g = np.asarray(out.frames[tip], dtype=float)
    d = {"tip_position": g[:3, 3].tolist(), "tip_rotation": g[:3, :3].ravel().tolist(),
         "base_wrench": out.base_wrench.tolist()}
    main = main_member(mech, tip)
    m = next((x for x in out.members if main is not None and x.name == main.name), None)
    if m is not None:
        d.update(backbone_s=m.s.tolist(), backbone_positions=m.poses[:, :3, 3].tolist(),
                 internal_wrenches=m.internal_wrench.tolist())
    return d


def _quaternions(T):
    """[x, y, z, w] (w >= 0) of the rotations of poses (N, 4, 4)."""
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(np.asarray(T, dtype=float)[:, :3, :3]).as_quat()
    return np.where(q[:, 3:] < 0, -q, q).tolist()


def _nan_none(a):
    return [None if not np.isfinite(x) else float(x) for x in a]


def run_mechanism_statics(sc, t=0.0, points_per_section=1, path_steps=0):
    """Equilibrium of the scenario's inputs at time ``t`` [s] (default 0;
    :func:`scenario.run_statics` picks the end of the profiles), reached in
    the scenario's ``load_steps`` increments of the inputs at t, or, with
    ``path_steps`` N > 0, through the inputs at N equal times from 0 to t
    (statics with a history: a gripper that closes, then lifts, holds
    what it closed on). JSON-ready dict: joint_names and
    joint_positions/efforts [rad or m, N m or N]; frame_names and
    frame_positions (world, m) and frame_poses (4x4, world); constraint_names and constraint_wrenches
    (world [f; m] on the constraint's frame, N, N m); transmitted_names and
    transmitted_wrenches (the wrench through every joint, world axes, about
    its input origin); members: per soft member at its sample points
    (``points_per_section`` per section and its end) s [m], positions, orientations (quaternions x, y, z, w), internal_wrench (body axes), strains,
    normal_stress and shear_stress [Pa] (null without geometry); iterations, residual; stable and
    min_stiffness_eigenvalue (constrained.equilibrium_stability). Friction
    (obstacles and bodies' shapes with ``friction``) acts from increment to increment:
    a contact made in one sticks where it landed from the next (one made
    at the start, where the robot file places it, from the first:
    :class:`solve.contact.StickPoints`), so a single increment has friction
    only where the robot touches at the start."""
    q, iterations = None, 0
    steps = [(t * k / path_steps, 1.0) for k in range(1, path_steps + 1)] if path_steps else \
        [(t, k / sc.load_steps) for k in range(1, sc.load_steps + 1)]       # (time, fraction of its inputs)
    contact, stick = MemberContact(sc.mech, sc.obstacles_at(0.0)), None
    if contact.has_friction:
        ws = Workspace(sc.mech.tree)
        stick = contact.stuck_at(ws, sc.mech.tree.q0)
    for k, (tk, fraction) in enumerate(steps):      # each warm-started from the one before
        obstacles = sc.obstacles_at(tk)
        if obstacles is not None:                   # the scenario's own obstacles, where they are at tk
            contact = contact.with_obstacles(obstacles)
        try:
            eq = solve_equilibrium(sc.mech, q_init=q, targets=_targets(sc, tk),
                                   inputs=scenario_inputs(sc, tk, fraction), obstacles=obstacles, stick=stick,
                                   check_stability=k == len(steps) - 1)    # the final equilibrium's is judged
        except StaticsError as e:
            if not path_steps:
                raise
            raise StaticsError(f"statics through the timeline: the solve at t = {tk:.6g} s (time {k + 1} of "
                               f"{len(steps)}) failed: {e}") from e
        q, iterations = eq.q, iterations + eq.iterations
        if stick is not None:
            stick = contact.stuck_after(ws, q, stick, eq.contacts)
    out = state_outputs(sc.mech, eq.q, eq.lam, eq.inputs, points_per_section=points_per_section,
                        contacts=eq.contacts)
    d = _outputs_dict(sc, out)
    d.update(contacts=contacts_dict(sc.mech, eq.contacts, sc.obstacles_at(t)))
    tree = sc.mech.tree
    d.update(section_names=[tree.joints[i].name for i in tree.soft_joints],
             strains=section_strains(sc.mech, eq.q).tolist(), n_sections=len(tree.soft_joints))
    if sc.mech.basis is not None:          # variable-strain segments: their coordinates too
        d.update(coordinate_names=list(sc.mech.coordinate_names),
                 coordinates=basis_coordinates(sc.mech, eq.q).tolist())
    d.update(_backbone_view(sc.mech, out))
    d.update(iterations=iterations, residual=eq.residual, constraint_error=eq.constraint_error,
             stable=eq.stable, min_stiffness_eigenvalue=eq.min_stiffness_eigenvalue)
    return d


# history fields of a dynamics run, one row per recorded step, in CSV column order
HISTORY_FIELDS = ("time", "tip_position", "tip_orientation", "tip_velocity", "base_wrench", "joint_positions",
                  "joint_velocities", "joint_accelerations", "joint_efforts", "frame_positions", "constraint_wrenches",
                  "constraint_error", "transmitted_wrenches", "strains", "strain_rates", "peak_normal_stress",
                  "peak_shear_stress", "newton_iterations", "contact_count", "contact_force")
# fields of the member samples (``backbone_every``), one row per sample, in CSV column order
SAMPLE_FIELDS = ("member_positions", "member_velocities", "member_internal_wrenches")


# the lists of a dynamics run (JSON) sampled with its member samples (``members_time``)
MEMBER_SAMPLE_KEYS = SAMPLE_FIELDS + ("members", "frame_poses", "energies")


def shifted_run(out, t0):
    """The run ``out`` (a dynamics JSON or a recording read back) from its
    time ``t0`` [s] on, with t0 taken as t = 0: the samples before it
    dropped from every series, every time shifted (to the nanosecond). A
    JSON run's series are its ``history_fields`` (with ``time``) and
    :data:`MEMBER_SAMPLE_KEYS` (with ``members_time``); a recording has one
    clock, every list as long as it (names aside) is cut with it.
    ValueError if the run ends before t0."""
    out = dict(out)
    t = np.asarray(out["time"], dtype=float)
    if not len(t) or t[-1] < t0 - 1e-9:
        raise ValueError(f"--t0 {t0:g} s: the run ends at {t[-1] if len(t) else 0:.6g} s")
    if "history_fields" in out:
        clocks = {"time": [k for k in out["history_fields"] if k != "time" and k in out],
                  "members_time": [k for k in MEMBER_SAMPLE_KEYS if k in out]}
    else:
        clocks = {"time": [k for k, v in out.items() if isinstance(v, list) and len(v) == len(t)
                           and not k.endswith("_names") and k not in ("time", "members_time")],
                  "members_time": []}           # (a recording's member samples are its states: the same clock)
    for clock, keys in clocks.items():
        if clock not in out:
            continue
        tc = np.asarray(out[clock], dtype=float)
        keep = tc >= t0 - 1e-9
        for k in keys:
            if isinstance(out[k], list) and len(out[k]) == len(tc):
                out[k] = [v for v, ok in zip(out[k], keep) if ok]
        out[clock] = [round(float(x) - t0, 9) for x in tc[keep]]
    return out


class StepInputs:
    """The checked inputs of the steps t0 -> t1 [s] of the theta method:
    the forces (actuation, efforts, loads) at the step's theta point t0 +
    theta (t1 - t0), where the method balances them (second order at theta
    = 1/2); the position commands at t1, where the joints must reach them.
    The loads are checked and laid out once for each set of their profiles'
    factors (once for a run whose loads do not vary)."""

    def __init__(self, sc, theta):
        self.sc, self.theta = sc, theta
        self._key, self._loads = None, None

    def __call__(self, t0, t1):
        from dataclasses import replace
        sc = self.sc
        tt = t0 + self.theta * (t1 - t0)
        key = sc.load_factors(tt)
        if key != self._key:
            self._loads = make_inputs(sc.mech, loads=sc.loads_at(tt), point_loads=sc.frame_loads_at(tt))
            self._key = key
        inp = make_inputs(sc.mech, sc.actuation_at(tt), sc.efforts_at(tt), sc.positions_at(t1),
                          sc.velocities_at(t1), _NO_LOADS)     # its loads: the point-moment tendons' at u
        return replace(inp, loads=concat_loads(self._loads.loads, inp.loads), gravity=self._loads.gravity)


class _Recorder:
    """The time histories of a dynamics run: :data:`HISTORY_FIELDS` at
    every recorded step, and the member samples every ``sample_every``
    steps. Outputs are evaluated in a workspace of their own (the
    integrator's keeps its state)."""

    def __init__(self, sc, sim, sample_every, points_per_section, inputs):
        mech = sc.mech
        self.sc, self.sim, self.mech, self.inputs = sc, sim, mech, inputs
        self.sample_every, self.pps = sample_every, points_per_section
        self.ws = Workspace(mech.tree)
        self.probe = MechanismSimulator(mech, sim.dt, sim.theta)      # instantaneous accelerations
        self.tip = tip_frame(mech)
        tree = mech.tree
        self.out = out = {key: [] for key in HISTORY_FIELDS}
        out.update(tip_frame=self.tip, transmitted_names=[j.name for j in tree.joints],
                   section_names=[tree.joints[i].name for i in tree.soft_joints], n_sections=len(tree.soft_joints),
                   joint_names=list(mech.joint_names), frame_names=list(mech.frames),
                   constraint_names=[c.name for c in mech.constraints], member_names=[m.name for m in mech.members],
                   history_fields=list(HISTORY_FIELDS), dt=sim.dt)
        if mech.basis is not None:         # variable-strain segments: their coordinates, a row per step (JSON)
            out.update(coordinate_names=list(mech.coordinate_names), coordinates=[])
        if sample_every:
            out.update({key: [] for key in SAMPLE_FIELDS}, members_time=[], members=[], frame_poses=[], energies=[],
                       member_point_names=[f"{m.name}_{k}" for m in mech.members
                                           for k in range(len(member_samples(mech, m, points_per_section)[0]))],
                       sample_fields=list(SAMPLE_FIELDS))

    def record(self, k, t, iterations):
        """Row k (time t [s]) from the simulator's state; a member sample too
        when k is a multiple of ``sample_every``."""
        sc, sim, mech, out = self.sc, self.sim, self.mech, self.out
        inp = self.inputs(t, t)              # the loads and efforts at the recorded instant
        sample = bool(self.sample_every) and k % self.sample_every == 0
        a = sim.a
        if sim.lam.size == 0 and k > 0 and not sim.contact:
            # no multipliers: the acceleration of the equations of motion at (q, v, t), the instant
            # recorded; with multipliers the step's own (its mean acceleration and reactions, which
            # balance each other; the instantaneous pair would need the constraints' dG/dt v)
            self.probe.q, self.probe.v = sim.q.copy(), sim.v.copy()
            a = self.probe.start_multipliers(inp).a
        contacts = sim.contacts if k > 0 else None      # the step's (its mean acceleration's) contact forces
        o = state_outputs(mech, sim.q, sim.lam, inp, sim.v, a, self.ws, self.pps if sample else 1,
                          member_motion=sample, contacts=contacts)
        g = np.asarray(o.frames[self.tip], dtype=float)
        out["time"].append(t)
        out["tip_position"].append(g[:3, 3].tolist())
        out["tip_orientation"].append(_quaternions(g[None])[0])
        out["tip_velocity"].append(frame_velocity(mech, self.ws, sim.v, self.tip)[:3].tolist())
        out["base_wrench"].append(o.base_wrench.tolist())
        out["joint_positions"].append([o.positions[n] for n in mech.joint_names])
        out["joint_velocities"].append([o.velocities[n] for n in mech.joint_names])
        out["joint_accelerations"].append([o.accelerations[n] for n in mech.joint_names])
        out["joint_efforts"].append([o.efforts[n] for n in mech.joint_names])
        out["frame_positions"].append([o.frames[n][:3, 3].tolist() for n in mech.frames])
        out["constraint_wrenches"].append([w.tolist() for w in o.constraint_wrenches.values()])
        out["constraint_error"].append(sim.constraint_error(_targets(sc, t)))
        out["transmitted_wrenches"].append([w.tolist() for w in o.joint_wrenches.values()])
        out["strains"].append(section_strains(mech, sim.q).tolist())
        if mech.basis is not None:
            out["coordinates"].append(basis_coordinates(mech, sim.q).tolist())
        out["strain_rates"].append(section_rates(mech, sim.v).tolist())
        out["peak_normal_stress"].append([float(np.nanmax(m.normal_stress, initial=0)) for m in o.members])
        out["peak_shear_stress"].append([float(np.nanmax(m.shear_stress, initial=0)) for m in o.members])
        out["newton_iterations"].append(int(iterations))
        out["contact_count"].append(len(contacts) if contacts is not None else 0)
        out["contact_force"].append((contacts.force.sum(axis=0) if contacts is not None and len(contacts)
                                     else np.zeros(3)).tolist())
        if sample:
            out["members_time"].append(t)
            out["members"].append(_outputs_dict(sc, o)["members"])
            # the same samples flat (every member's sample points in order), for the CSV
            out["member_positions"].append(np.concatenate([m.poses[:, :3, 3] for m in o.members]).tolist())
            out["member_velocities"].append(np.concatenate([m.velocities for m in o.members]).tolist())
            out["member_internal_wrenches"].append(np.concatenate([m.internal_wrench for m in o.members]).tolist())
            out["frame_poses"].append([np.asarray(o.frames[n], dtype=float).tolist() for n in mech.frames])
            out["energies"].append(_nan_none(sample_energies(sim)))

    def clear(self):
        for key in HISTORY_FIELDS + ((SAMPLE_FIELDS + ("members_time", "members", "frame_poses", "energies"))
                                     if self.sample_every else ()):
            self.out[key].clear()
        if "coordinates" in self.out:
            self.out["coordinates"].clear()


def _start(sc, sim):
    """Put the simulator at the scenario's start: its initial strains, the
    position-controlled joints where their commands are at t = 0, and the
    accelerations and multipliers of that state (t = 0's base reaction
    includes the inertia of the first motion)."""
    inp0 = scenario_inputs(sc, 0.0)
    if sc.initial_q is not None:
        sim.q[:] = sc.initial_q
    for k, i in enumerate(sc.mech.joints_with("position")):
        sim.q[sc.mech.tree.idx_q[i]] = inp0.q_cmd[k]
    sim.start_multipliers(inp0, _targets(sc, 0.0))


def run_mechanism_dynamics(sc, duration, dt, theta=0.5, progress=None, record_every=1, backbone_every=0,
                           progress_every=1.0, points_per_section=1):
    """Integrate the scenario of any robot (``n = ceil(duration / dt)``
    steps of :class:`constrained.MechanismSimulator`: the compiled O(n)
    integrator without constraint rows, the KKT step with them), the forces
    at each step's theta point (:class:`StepInputs`). Returns the time
    histories, one row per recorded step (every ``record_every`` steps, the
    first, the last and every sample):

    - ``time`` [s], ``k * dt``;
    - ``tip_position`` [m], ``tip_orientation`` (quaternion x, y, z, w),
      ``tip_velocity`` [m/s] of the tip frame (``tip_frame``,
      :func:`mechanism.tip_frame`), world;
    - ``base_wrench`` [N, N m]: the support's reaction with inertia, world
      axes, about the base origin (:func:`outputs.base_reaction`);
    - ``joint_positions``, ``_velocities``, ``_accelerations``, ``_efforts``
      (N, n_joints) in the order of ``joint_names``;
    - ``frame_positions`` (N, n_frames, 3) [m] in the order of ``frame_names``;
    - ``constraint_wrenches`` (N, n_constraints, 6), ``constraint_error`` (N,)
      [m or rad];
    - ``transmitted_wrenches`` (N, n_joints, 6): the wrench through every
      joint, world axes about its input origin (``transmitted_names``);
    - ``strains`` and ``strain_rates`` (N, n_sections, 6) of every soft
      section in tree order (``section_names``; fixed modes: the reference
      strain and 0);
    - ``peak_normal_stress``, ``peak_shear_stress`` (N, n_members) [Pa];
    - ``newton_iterations``.

    Accelerations (and the base wrench's inertia) are those of the equations
    of motion at the recorded (q, v, t); with constraint or joint-command
    multipliers, after t = 0, the step's mean acceleration ((v1 - v0) / dt)
    with the reactions it balances. With ``backbone_every = K > 0``, at t = 0 and every K steps,
    every member's outputs under ``members_time`` and ``members`` (as in
    statics: ``points_per_section`` points per section and its end), flat
    for the CSV as ``member_positions``, ``member_velocities`` (B, P, 3)
    [m, m/s] and ``member_internal_wrenches`` (B, P, 6) [N, N m]
    (``member_point_names``: ``<member>_<k>``), and for the JSON
    ``frame_poses`` (B, n_frames, 4, 4) and ``energies`` (B, 3) [J]:
    kinetic, elastic, gravitational (:func:`sample_energies`). ``error``
    when a step fails (the history then ends at the last converged step).

    The kernels are compiled (or loaded from numba's cache) and the inputs
    checked by a warm-up before the clock starts: ``progress(fraction,
    elapsed_s)`` is called once with (0.0, 0.0) right after it, then at most
    once per ``progress_every`` wall-clock seconds (0: after every step)."""
    mech = sc.mech
    n_steps = n_steps_for(duration, dt)
    dt = float(dt)
    record_every = count(record_every, "record_every", 1)
    backbone_every = count(backbone_every, "backbone_every", 0)
    points_per_section = count(points_per_section, "points_per_section", 1)
    check_output_size(n_steps, record_every, backbone_every,
                      sum(len(m.joints) for m in mech.members) * points_per_section + len(mech.members))
    time_of = step_times(dt)
    sim = MechanismSimulator(mech, dt, theta, obstacles=sc.obstacles_at(0.0))
    step_inputs = StepInputs(sc, theta)
    rec = _Recorder(sc, sim, backbone_every, points_per_section, step_inputs)
    out = rec.out
    # warm-up: everything the loop calls runs once (numba compiles or loads its cache) before the
    # clock starts, the first step on a simulator of its own; the t = 0 row is recorded here
    try:
        _start(sc, sim)
        if not (np.all(np.isfinite(sim.a)) and np.all(np.isfinite(sim.lam))):
            out["error"] = "the initial acceleration is not finite (inputs too large?); nothing simulated"
            return out
        rec.record(0, 0.0, 0)
        probe = MechanismSimulator(mech, dt, theta, q=sim.q, v=sim.v, obstacles=sc.obstacles_at(0.0))
        probe.step(inputs=step_inputs(0.0, time_of(1)), targets=_targets(sc, time_of(1)),
                   obstacles=sc.obstacles_at(time_of(1)))
    except StepError:
        pass                 # the run's own first step reports it
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
        rec.clear()
        out["error"] = f"the initial state cannot be evaluated: {type(e).__name__}: {e}; nothing simulated"
        return out
    if progress is not None:
        progress(0.0, 0.0)
    with one_blas_thread():        # once for the run, not once a step
        _integrate(rec, step_inputs, n_steps, record_every, progress, progress_every)
    return out


def _integrate(rec, step_inputs, n_steps, record_every, progress, progress_every):
    """The run's steps 1..n_steps of ``rec``'s simulator, recorded into
    ``rec`` (see :func:`run_mechanism_dynamics`); a failed step ends the
    history."""
    import time as _time
    sc, sim, out, backbone_every = rec.sc, rec.sim, rec.out, rec.sample_every
    time_of = step_times(sim.dt)
    t0 = last = _time.monotonic()
    recorded, iterations = 0, 0          # the last recorded step, the last step's Newton iterations
    for k in range(1, n_steps + 1):
        ta, tb = time_of(k - 1), time_of(k)
        good = sim.q.copy(), sim.v.copy(), sim.a.copy(), sim.lam.copy()
        try:
            sim.step(inputs=step_inputs(ta, tb), targets=_targets(sc, tb), obstacles=sc.obstacles_at(tb))
            sim.t = tb
            if not (np.all(np.isfinite(sim.q)) and np.all(np.isfinite(sim.v))):
                raise StepError("the state became non-finite")
        except (StepError, ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            sim.q, sim.v, sim.a, sim.lam = good        # the last converged state ends the history
            sim.t = ta
            if recorded != k - 1:
                rec.record(k - 1, ta, iterations)
            out["error"] = (f"step {k} of {n_steps} (t = {ta:.6g} -> {tb:.6g} s) failed: {e}; "
                            f"the history ends at t = {ta:.6g} s" + failure_context(sc, out, ta, tb))
            break
        iterations = sim.iterations
        if k % record_every == 0 or k == n_steps or (backbone_every and k % backbone_every == 0):
            rec.record(k, tb, iterations)
            recorded = k
        if progress is not None and _time.monotonic() - last >= progress_every:
            progress(k / n_steps, _time.monotonic() - t0)
            last = _time.monotonic()


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
