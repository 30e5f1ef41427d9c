"""Runs of a tree robot's scenario (:mod:`scenario` parses every scenario;
its runners hand a tree robot's over here): statics and dynamics with joint
commands, loads on members and frames and a prescribed base, and outputs of
joints, frames, constraints and members.

Outputs (JSON; the CSV has the same time histories): see
:func:`run_mechanism_statics` and :func:`run_mechanism_dynamics`.
"""

import numpy as np

from .constrained import MechanismSimulator, StepError, make_inputs, solve_equilibrium
from .timeline import check_output_size, count, n_steps_for, step_times


def _inputs(sc, t, factor=1.0):
    """The checked :class:`constrained.Inputs` of the scenario at time t [s];
    ``factor`` scales the actuation, the efforts and the loads (gravity
    stays whole: load stepping)."""
    eff = {j: factor * v for j, v in sc.efforts_at(t).items()}
    return make_inputs(sc.mech, factor * sc.actuation_at(t), eff, sc.positions_at(t), sc.velocities_at(t),
                       sc.loads_at(t, factor), sc.frame_loads_at(t, factor))


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


def _backbone_view(mech, out):
    """The fields every robot's statics result has beside its joints,
    frames and members: ``tip_position`` [m] and ``tip_rotation`` (3x3
    row-major) of the tip frame (:func:`mechanism.tip_frame`),
    ``base_wrench`` (:func:`outputs.base_reaction`), and the main member's
    samples (:func:`outputs.main_member`): ``backbone_s`` [m],
    ``backbone_positions`` [m] and ``internal_wrenches`` (its cross-sections'
    axes)."""
    from .mechanism import tip_frame
    from .outputs import base_reaction, main_member
    tip = tip_frame(mech)
    g = np.asarray(out.frames[tip], dtype=float)
    d = {"tip_position": g[:3, 3].tolist(), "tip_rotation": g[:3, :3].ravel().tolist(),
         "base_wrench": base_reaction(mech, out.joint_wrenches).tolist()}
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


def run_mechanism_statics(sc, t=0.0, points_per_section=1):
    """Equilibrium of the scenario's inputs at time ``t`` [s] (default 0;
    :func:`scenario.run_statics` picks the end of the profiles). JSON-ready dict: joint_names and
    joint_positions/efforts [rad or m, N m or N]; frame_names and
    frame_positions (world, m) and frame_poses (4x4, world); constraint_names and constraint_wrenches
    (world [f; m] on the constraint's frame, N, N m); transmitted_names and
    transmitted_wrenches (the wrench through every joint, world axes, about
    its input origin); members: per soft member at its sample points
    (``points_per_section`` per section and its end) s [m], positions, orientations (quaternions x, y, z, w), internal_wrench (body axes), strains,
    normal_stress and shear_stress [Pa] (null without geometry); iterations, residual; stable and
    min_stiffness_eigenvalue (constrained.equilibrium_stability)."""
    from .outputs import section_strains, state_outputs
    q, iterations = None, 0
    for k in range(1, sc.load_steps + 1):     # load_steps increments, each warm-started
        eq = solve_equilibrium(sc.mech, q_init=q, targets=_targets(sc, t), inputs=_inputs(sc, t, k / sc.load_steps),
                               check_stability=k == sc.load_steps)      # the final equilibrium's is the one to judge
        q, iterations = eq.q, iterations + eq.iterations
    out = state_outputs(sc.mech, eq.q, eq.lam, eq.inputs, points_per_section=points_per_section)
    d = _outputs_dict(sc, out)
    tree = sc.mech.tree
    d.update(section_names=[tree.joints[i].name for i in tree.soft_joints],
             strains=section_strains(sc.mech, eq.q).tolist(), n_sections=len(tree.soft_joints))
    d.update(_backbone_view(sc.mech, out))
    d.update(iterations=iterations, residual=eq.residual, constraint_error=eq.constraint_error,
             stable=eq.stable, min_stiffness_eigenvalue=eq.min_stiffness_eigenvalue)
    return d


# history fields of a dynamics run, in CSV column order
HISTORY_FIELDS = ("time", "joint_positions", "joint_velocities", "joint_accelerations", "joint_efforts",
                  "frame_positions", "constraint_wrenches", "constraint_error", "transmitted_wrenches", "strains",
                  "peak_normal_stress", "peak_shear_stress", "newton_iterations")


def run_mechanism_dynamics(sc, duration, dt, theta=0.5, progress=None, record_every=1, backbone_every=0,
                           progress_every=1.0, points_per_section=1):
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
    (B, P, 6) [N, N m] at every member's sample points
    (``points_per_section`` per section and its end;
    ``member_point_names``: ``<member>_<k>``); JSON only, at the same samples:
    ``frame_poses`` (B, n_frames, 4, 4) world poses of the frames of
    ``frame_names`` and ``energies`` (B, 3) [J]: kinetic, elastic (members and
    joint springs), gravitational (:func:`sample_energies`). ``error`` when a
    step fails (the history ends at the last converged step)."""
    import time as _time
    from .outputs import member_samples, section_strains, state_outputs
    mech = sc.mech
    n_steps = n_steps_for(duration, dt)
    check_output_size(n_steps, count(record_every, "record_every", 1), count(backbone_every, "backbone_every", 0),
                      mech.tree.n_joints + len(mech.frames) + 1)
    time_of = step_times(dt)
    sim = MechanismSimulator(mech, float(dt), theta)
    inp0 = _inputs(sc, 0.0)
    if sc.initial_q is not None:
        sim.q[:] = sc.initial_q
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
                                       for k in range(len(member_samples(mech, m, points_per_section)[0]))],
                   sample_fields=["member_positions", "member_internal_wrenches"], frame_poses=[], energies=[])

    def record(k, inp, iterations):
        o = state_outputs(mech, sim.q, sim.lam, inp, sim.v, sim.a, sim.ws, member_motion=False)
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
            o = state_outputs(mech, sim.q, sim.lam, inp, sim.v, sim.a, sim.ws, points_per_section)
            out["members_time"].append(time_of(k))
            out["members"].append(_outputs_dict(sc, o)["members"])
            # the same samples flat (every member's sample points in order), for the CSV
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
