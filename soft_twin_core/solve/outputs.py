"""What a state of a mechanism gives the user: joint states and efforts, the
wrench through every joint, constraint reactions, and along every soft
member the internal wrench, strains and peak stresses.

Everything comes from one forward pass and one RNEA pass of the engine at the
state (q, v, a) with the applied loads and the constraint reactions
(:mod:`constrained`), so it holds in statics and in dynamics (inertia
included). Frames and signs (docs/CONVENTIONS.md):

* ``joint_wrenches[i]``: the wrench [f; m] (N, N m) the parent side exerts
  on joint i's subtree through the joint, world axes, moment about the
  joint's input-frame origin (for the root: the support's reaction).
* member ``internal_wrench`` at a cross-section: the wrench the distal part
  exerts on the proximal part (stress resultant), in the cross-section's
  axes [N, N m]: [axial, shear_y, shear_z, torsion, bending_y, bending_z];
  it includes the tendons' pull on the cut (a tendon of tension T crossing
  the cut at offset d with unit tangent t adds -T [t; d x t]).
* peak stresses from the cross-section geometry (:func:`stress.peak_stresses`).
"""

from dataclasses import dataclass
import math

import numpy as np

from soft_twin_core.engine.forces import concat_loads, point_moment_arrays, tendon_tension
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.frames import point_poses, spatial_jacobian, spatial_jacobian_dot
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import ModelError
from soft_twin_core.lie import Ad, Ad_inv, se3_inv
from soft_twin_core.robot.stress import peak_stresses, von_mises
from soft_twin_core.solve.constrained import _efforts_out, constraint_loads, constraint_wrenches
from soft_twin_core.solve.contact import contact_loads


@dataclass
class MemberOutput:
    """Along one soft member, at its sample points (base to tip: evenly
    spaced points in every section and the member's end; by default its
    n_sections + 1 section boundaries): arc length s [m], cross-section poses (world),
    internal wrench (body axes, see the module), strains of the section at
    or after each point (the last: the last section's), peak normal and shear
    stress [Pa]; ``velocities`` and ``accelerations`` (world, m/s and m/s^2)
    of the centre-line points (zero in statics)."""
    name: str
    s: np.ndarray
    poses: np.ndarray
    internal_wrench: np.ndarray
    strains: np.ndarray
    normal_stress: np.ndarray
    shear_stress: np.ndarray
    velocities: np.ndarray = None
    accelerations: np.ndarray = None


def _tendon_pull(mech, ws, member, s, strains, u):
    """Tendon contributions -T(s) [t; d x t] (body axes) at arc lengths s of
    the member (T(s) with the capstan decay of sheath friction: the tension
    the tendon carries across the cut)."""
    out = np.zeros((len(s), 6))
    if u is None or not len(u):
        return out
    for k, a in enumerate(mech.actuators):
        if u[k] == 0.0 or mech.tree.path_of_actuator(k) is not mech.tree.paths[member.path]:
            continue
        inside = (s >= a.start) & (s < a.end)
        if not np.any(inside):
            continue
        d, dd = a.offset_at(s)
        t = strains[:, :3] + np.cross(strains[:, 3:], d) + dd
        t = t / np.linalg.norm(t, axis=-1, keepdims=True)
        T = np.zeros(len(s))
        T[inside] = tendon_tension(mech.tree, ws, k, u[k], s[inside])
        w = -a.force_per_unit_input * T[:, None] * np.concatenate([t, np.cross(d, t)], axis=-1)
        out[inside] += w[inside]
    return out


def _end_loads(ws, loads, j, L):
    """Sum (body axes at the section's end) of the loads at the end x = L of soft joint j."""
    g = ws.work.g_out[j]
    R = g[:3, :3]
    out = np.zeros(6)
    if loads is None:
        return out
    for k in range(loads.joint.shape[0]):
        if loads.joint[k] == j and loads.x[k] >= L - 1e-12:
            wk = loads.wrench[k]
            out += np.concatenate([R.T @ wk[:3], R.T @ wk[3:]]) if loads.world[k] else wk
    return out


def member_samples(mech, member, points_per_section=1):
    """(joint, x, s) of a member's sample points: ``points_per_section``
    evenly spaced points per section from its start, and the member's end
    (n_sections * points_per_section + 1 points, base to tip)."""
    path = mech.tree.paths[member.path]
    J, X, S = [], [], []
    for k, j in enumerate(path.joints):
        x = path.lengths[k] * np.arange(points_per_section) / points_per_section
        J += [j] * points_per_section
        X.append(x)
        S.append(path.s_starts[k] + x)
    J.append(path.joints[-1])
    X.append([path.lengths[-1]])
    S.append([path.length])
    return np.array(J, np.int64), np.concatenate(X).astype(float), np.concatenate(S).astype(float)


def _samples(mech, points_per_section):
    """[(member, joint, x, s)] of every member's samples (kept on the mechanism)."""
    key = f"_member_samples_{int(points_per_section)}"
    out = mech.__dict__.get(key)
    if out is None:
        out = [(m,) + member_samples(mech, m, points_per_section) for m in mech.members]
        object.__setattr__(mech, key, out)
    return out


def state_shape(mech, ws, q, points_per_section=1):
    """The poses of configuration q, nothing else (one forward pass): (frames
    {name: world 4x4}, members {member: (poses (P, 4, 4), s (P,))} at
    ``points_per_section`` points per section and its end)."""
    passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), ws.zeros_v, ws.zeros_v, 0)
    members = {}
    for m, J, X, S in _samples(mech, points_per_section):
        G = np.empty((len(J), 4, 4))
        point_poses(ws.m, ws.w, J, X, G)
        members[m.name] = (G, S)
    return frame_poses(mech, ws), members


def frame_poses(mech, ws):
    """{frame name: world 4x4} of every named frame at the workspace's last
    forward pass (the frames' points kept on the mechanism)."""
    refs = mech.__dict__.get("_frame_arrays")
    if refs is None:
        names = list(mech.frames)
        refs = (names, np.array([mech.frames[n].joint for n in names], np.int64),
                np.array([mech.frames[n].x for n in names], float))
        object.__setattr__(mech, "_frame_arrays", refs)
    P = np.empty((len(refs[0]), 4, 4))
    if refs[0]:
        point_poses(ws.m, ws.w, refs[1], refs[2], P)
    return dict(zip(refs[0], P))


def cut_wrenches(ws, loads, joints, xs, poses):
    """The wrenches [f; m] the distal part exerts on the proximal part
    through the cross-sections at abscissae ``xs`` (P,) of soft joints
    ``joints`` (P,) (world poses ``poses`` (P, 4, 4)), each in its
    cross-section's axes, from the workspace's last forward and RNEA passes
    with LoadArrays ``loads`` (tendons' pull on the cut not included).

    The distal part of a cut at x is what lies beyond the section's end
    (the RNEA's wrench there) and the section's own quadrature points and
    load points at x or beyond (a load exactly at x counts as distal): the
    engine's own discretisation of the section's gravity, inertia and
    loads, so that the cut at x = 0 is the section's input wrench and the
    cut at its end the next section's."""
    w, m = ws.work, ws.arrays                 # the arrays themselves (ws.m: their structref, for the kernels)
    J = np.atleast_1d(np.asarray(joints, dtype=np.int64))
    xs = np.atleast_1d(np.asarray(xs, dtype=float))
    g_in_inv = se3_inv(w.g_in[J])
    f = np.einsum("pji,pj->pi", w.Ad_J_inv[J], w.f[J])                   # what lies past each section's end
    # each quadrature point's wrench in its section's input frame (padding points: zero weight, zero wrench)
    point = np.einsum("pkji,pkj->pki", w.Ad_p_inv[J], w.fp[J])
    beyond = (m.px[J] >= xs[:, None]) & (np.arange(m.px.shape[1])[None, :] < m.npt[J][:, None])
    f = f + np.einsum("pk,pki->pi", beyond.astype(float), point)
    if loads is not None:
        on = np.flatnonzero(np.isin(loads.joint, J) & (loads.x >= 0.0))
        if on.size:
            G = np.empty((on.size, 4, 4))
            point_poses(ws.m, ws.w, loads.joint[on], np.ascontiguousarray(loads.x[on]), G)
            W = loads.wrench[on]
            R = G[:, :3, :3]
            Wb = np.where(loads.world[on][:, None], np.concatenate(
                [np.einsum("pji,pj->pi", R, W[:, :3]), np.einsum("pji,pj->pi", R, W[:, 3:])], axis=1), W)
            for k, l in enumerate(on):                  # few loads: each into its section's input frame
                at = (J == loads.joint[l]) & (xs <= loads.x[l])
                if np.any(at):
                    lw = Ad_inv(se3_inv(w.g_in[loads.joint[l]]) @ G[k]).T @ Wb[k]   # as the RNEA adds it
                    f[at] -= lw
    # Ad(g_in^-1 g_x)^T: from the input frame into each cut's axes
    return -np.einsum("pji,pj->pi", Ad(g_in_inv @ np.asarray(poses, dtype=float)), f)


def member_outputs(mech, ws, u=None, loads=None, points_per_section=1, v=None, a=None):
    """MemberOutput of every soft member from the workspace's last forward
    and RNEA passes, at ``points_per_section`` points per section and the
    member's end (1: its section boundaries); ``u``: the actuation (for the
    tendons' pull), ``loads``: the LoadArrays of the passes; ``v``, ``a``:
    the state's velocity and acceleration (None: at rest) for the points'
    velocities and accelerations (world, from their spatial Jacobian and its
    derivative)."""
    w = ws.work
    out = []
    for mem in mech.members:
        J, X, s = member_samples(mech, mem, points_per_section)
        P = np.empty((len(J), 4, 4))
        point_poses(ws.m, ws.w, J, X, P)
        wr = cut_wrenches(ws, loads, J, X, P)
        strains = w.strain[J].copy()
        wr = wr + _tendon_pull(mech, ws, mem, s, strains, u)
        sec = [list(mech.tree.paths[mem.path].joints).index(j) for j in J]      # section index along the member
        geo = [mem.geometry[k] for k in sec]
        normal = np.empty(len(s))
        shear = np.empty(len(s))
        for g in {id(x): x for x in geo}.values():          # each cross-section once, vectorised
            idx = [k for k, x in enumerate(geo) if x is g]
            normal[idx], shear[idx] = peak_stresses(g, wr[idx])
        vel, acc = np.zeros((len(s), 3)), np.zeros((len(s), 3))
        if v is not None:
            g = np.empty((4, 4))
            Js, Jd = np.empty((6, mech.tree.nv)), np.empty((6, mech.tree.nv))
            vv = np.ascontiguousarray(v, dtype=float)
            for k, (j, x) in enumerate(zip(J, X)):
                spatial_jacobian(ws.m, ws.w, int(j), float(x), g, Js)
                spatial_jacobian_dot(ws.m, ws.w, int(j), float(x), vv, Jd)
                tw = Js @ vv                                  # spatial twist [v_s; omega]
                dtw = Js @ a + Jd @ vv if a is not None else Jd @ vv
                p = P[k, :3, 3]
                pdot = tw[:3] + np.cross(tw[3:], p)
                vel[k] = pdot
                acc[k] = dtw[:3] + np.cross(dtw[3:], p) + np.cross(tw[3:], pdot)
        out.append(MemberOutput(mem.name, s, P, wr, strains, normal, shear, vel, acc))
    return out


def main_member(mech, tip):
    """The member that is the robot's backbone (published on ``~/backbone``,
    a run's ``backbone_*`` fields): the one whose name begins the tip
    frame's (``arm`` of ``arm_tip``), else the last one; None without members."""
    return next((m for m in mech.members if tip.startswith(m.name)), None) or (
        mech.members[-1] if mech.members else None)


def base_reaction(mech, joint_wrenches, ws, u):
    """The support's reaction on the robot (6,) [f; m]: the wrench through
    every root joint (``joint_wrenches`` {joint: world [f; m] about its
    input origin}), world axes, moment about the base origin (a constraint
    to the world reacts on its own: ``constraint_wrenches``), at the
    workspace ``ws`` of those wrenches and the inputs ``u``: the follower
    moments of point-moment tendons are internal (their motor sits on the
    support, which takes the opposite couple), so the loads the root joints
    transmit, less those moments in world axes."""
    base = np.zeros(6)
    for j in mech.tree.joints:
        if j.parent == -1:
            wr = np.asarray(joint_wrenches[j.name], dtype=float)
            base += np.concatenate([wr[:3], wr[3:] + np.cross(j.placement[:3, 3], wr[:3])])
    base[3:] += tendon_couple(mech, ws, u)
    return base


def tendon_couple(mech, ws, u):
    """The sum (3,) [N m] of the point-moment tendons' follower moments at
    inputs u, in world axes, at the workspace's last forward pass (zero
    without such tendons)."""
    pm = point_moment_arrays(mech.tree, u)
    if not len(pm.joint):
        return np.zeros(3)
    G = np.empty((len(pm.joint), 4, 4))
    point_poses(ws.m, ws.w, pm.joint, np.ascontiguousarray(pm.x), G)
    return np.einsum("pij,pj->i", G[:, :3, :3], pm.wrench[:, 3:])


def max_von_mises(mech, members):
    """(largest von Mises stress [Pa], its arc length along its member [m])
    over every member's samples: ``members`` {member: {"s": (P,),
    "internal_wrench": (P, 6)}} (a statics result's), each sample's
    cross-section that of the section holding it; (NaN, NaN) if no member
    has a known fibre distance (:func:`stress.von_mises`)."""
    best, where = -np.inf, math.nan
    for mem in mech.members:
        d = members[mem.name]
        s, W = np.asarray(d["s"], dtype=float), np.asarray(d["internal_wrench"], dtype=float)
        path = mech.tree.paths[mem.path]
        sec = np.clip(np.searchsorted(path.s_starts, s, side="right") - 1, 0, len(mem.geometry) - 1)
        v = np.full(len(s), np.nan)
        for k in np.unique(sec):
            v[sec == k] = von_mises(W[sec == k], mem.geometry[k])
        # a section's start is also the end of the one before: its cross-section counts too
        for i in np.flatnonzero((sec > 0) & np.isclose(s, np.asarray(path.s_starts)[sec], rtol=0, atol=1e-12)):
            v[i] = np.fmax(v[i], von_mises(W[i:i + 1], mem.geometry[sec[i] - 1])[0])
        if np.any(np.isfinite(v)) and np.nanmax(v) > best:
            i = int(np.nanargmax(v))
            best, where = float(v[i]), float(s[i])
    return (best, where) if np.isfinite(best) else (math.nan, math.nan)


def section_strains(mech, q):
    """(n_soft_sections, 6) full strains of every soft section in tree order
    (free modes from q, the others at the reference strain f0)."""
    tree = mech.tree
    out = []
    for i in tree.soft_joints:
        sec = tree.joints[i].section
        f = sec.f0.copy()
        iq = tree.idx_q[i]
        f[sec.modes] = q[iq:iq + len(sec.modes)]
        out.append(f)
    return np.array(out, dtype=float).reshape(-1, 6)


def section_rates(mech, v):
    """(n_soft_sections, 6) strain rates [1/(m s), 1/s] of every soft section
    in tree order: the free modes' velocities from v, 0 for the others."""
    tree = mech.tree
    out = np.zeros((len(tree.soft_joints), 6))
    for k, i in enumerate(tree.soft_joints):
        sec = tree.joints[i].section
        iv = tree.idx_v[i]
        out[k, sec.modes] = v[iv:iv + len(sec.modes)]
    return out


def frame_velocity(mech, ws, v, frame):
    """World velocity [v; omega] (6,) [m/s, rad/s] of a named frame's origin
    at the workspace's last forward pass (its configuration) and velocity v:
    the frame's spatial twist ``J_s v`` moved to its origin."""
    ref = mech.frames[frame]
    g, J = np.empty((4, 4)), np.empty((6, mech.tree.nv))
    spatial_jacobian(ws.m, ws.w, int(ref.joint), float(ref.x), g, J)
    tw = J @ np.ascontiguousarray(v, dtype=float)
    return np.concatenate([tw[:3] + np.cross(tw[3:], g[:3, 3]), tw[3:]])


def q_from_section_strains(mech, strains, q):
    """``q`` with every soft section's free modes taken from ``strains``
    ((n_soft_sections, 6) or as many values row-major, the order of
    :func:`section_strains`); rigid joints as in q. ModelError naming the
    bad value: a wrong count, NaN or inf, or a mode that is not free set
    away from the reference strain (the inverse of :func:`section_strains`)."""
    tree = mech.tree
    n = len(tree.soft_joints)
    xi = np.asarray(strains, dtype=float).reshape(-1)
    if xi.size != 6 * n:
        raise ModelError(f"strains: expected {6 * n} values ({n} soft sections x 6, in tree order), got {xi.size}")
    if not np.all(np.isfinite(xi)):
        raise ModelError("strains: contain NaN or inf")
    xi = xi.reshape(n, 6)
    out = np.array(q, dtype=float)
    for k, i in enumerate(tree.soft_joints):
        sec = tree.joints[i].section
        fixed = np.setdiff1d(np.arange(6), sec.modes)
        bad = fixed[np.abs(xi[k, fixed] - sec.f0[fixed]) > 1e-12]
        if bad.size:
            raise ModelError(f"strains: section {k} ({tree.joints[i].name}) sets mode(s) {bad.tolist()}, which are "
                             f"not free in this robot, to {xi[k, bad].tolist()}; they must stay at the reference "
                             f"strain {sec.f0[bad].tolist()}")
        iq = tree.idx_q[i]
        out[iq:iq + len(sec.modes)] = xi[k, sec.modes]
    return out


def joint_wrenches(mech, ws):
    """(n_joints, 6) wrench through every joint, world axes, about its input
    frame origin (see the module), from the last RNEA pass."""
    w = ws.work
    R = w.g_in[:, :3, :3]
    return np.concatenate([np.einsum("nij,nj->ni", R, w.f_in[:, :3]), np.einsum("nij,nj->ni", R, w.f_in[:, 3:])],
                          axis=1)


def run_passes(mech, ws, q, v, a, loads, gravity):
    """Forward and RNEA passes at (q, v, a) with ``loads`` (LoadArrays incl.
    constraint reactions); v = a = None: at rest."""
    tree = mech.tree
    z = np.zeros(tree.nv)
    at_rest = v is None
    v = z if v is None else np.ascontiguousarray(v, float)
    a = z if a is None else np.ascontiguousarray(a, float)
    passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), v, a, 0 if at_rest else 2)
    passes.rnea_pass(ws.m, ws.w, loads, gravity, np.empty(tree.nv), at_rest)


@dataclass
class MechanismOutputs:
    """Every output of one state of a mechanism (see the module for frames
    and signs): joint ``positions``, ``velocities``, ``accelerations`` and
    ``efforts`` by name (1-dof rigid joints; rad, rad/s, rad/s^2, N m, or m,
    m/s, m/s^2, N), ``joint_wrenches`` {joint: world [f; m] (6,)} for every
    joint (soft sections included), ``constraint_wrenches`` {constraint:
    world [f; m] on its frame a}, ``frames`` {name: world pose 4x4},
    ``members`` (MemberOutput list), ``base_wrench`` (6,) the support's
    reaction (:func:`base_reaction`; a prescribed base's carrier's: the
    clamp 'base''s wrench, world axes, about the world origin),
    ``contacts`` (the ContactState the
    loads include, None without obstacles)."""
    positions: dict
    velocities: dict
    accelerations: dict
    efforts: dict
    joint_wrenches: dict
    constraint_wrenches: dict
    frames: dict
    members: list
    base_wrench: np.ndarray
    contacts: object = None


def state_outputs(mech, q, lam, inputs, v=None, a=None, ws=None, points_per_section=1, member_motion=True,
                  contacts=None):
    """MechanismOutputs at (q, v, a) with multipliers lam under ``inputs``
    (:class:`constrained.Inputs`); v = a = None: statics. The members are
    sampled at ``points_per_section`` points per section (1: their section
    boundaries) and their ends; ``member_motion`` False leaves their points'
    velocities and accelerations at zero (they cost two Jacobians a point).
    ``contacts``: the ContactState whose forces act too (an equilibrium's or
    a step's)."""
    tree = mech.tree
    ws = Workspace(tree) if ws is None else ws
    loads = concat_loads(inputs.loads, constraint_loads(mech, lam), contact_loads(mech, contacts))
    run_passes(mech, ws, q, v, a, loads, inputs.gravity)
    names = [tree.joints[i].name for i in mech.rigid_joints]
    iq = [tree.idx_q[i] for i in mech.rigid_joints]
    iv = [tree.idx_v[i] for i in mech.rigid_joints]
    z = np.zeros(tree.nv)
    v_ = z if v is None else v
    a_ = z if a is None else a
    frames = frame_poses(mech, ws)
    jw = joint_wrenches(mech, ws)
    by_joint = {j.name: jw[i] for i, j in enumerate(tree.joints)}
    members = member_outputs(mech, ws, inputs.u, loads, points_per_section, *((v, a) if member_motion else ()))
    cw = constraint_wrenches(mech, lam)
    base = base_reaction(mech, by_joint, ws, inputs.u)
    if mech.base_motion == "prescribed":
        # the carrier holds the robot through the clamp 'base' (its free root joint transmits nothing):
        # the clamp's wrench, from the carried base's origin to the world origin
        f, m = cw["base"][:3], cw["base"][3:]
        base += np.concatenate([f, m + np.cross(frames["base"][:3, 3], f)])
    return MechanismOutputs(
        positions={n: float(q[k]) for n, k in zip(names, iq)},
        velocities={n: float(v_[k]) for n, k in zip(names, iv)},
        accelerations={n: float(a_[k]) for n, k in zip(names, iv)},
        efforts=_efforts_out(mech, lam, inputs),
        joint_wrenches=by_joint,
        constraint_wrenches=cw,
        frames=frames,
        members=members,
        base_wrench=base, contacts=contacts)
