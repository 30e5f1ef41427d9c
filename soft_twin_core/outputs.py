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

import numpy as np

from .errors import ModelError
from .kernels import passes
from .stress import peak_stresses


@dataclass
class MemberOutput:
    """Along one soft member, at its section boundaries (n_sections + 1
    points, base to tip): arc length s [m], cross-section poses (world),
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


def _tendon_pull(mech, member, s, strains, u):
    """Tendon contributions -T [t; d x t] (body axes) at arc lengths s of the member."""
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
        w = -a.force_per_unit_input * u[k] * np.concatenate([t, np.cross(d, t)], axis=-1)
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


def member_outputs(mech, ws, u=None, loads=None):
    """MemberOutput of every soft member from the workspace's last forward
    and RNEA passes; ``u``: the actuation (for the tendons' pull), ``loads``:
    the LoadArrays of the passes (a load at a member's very end counts as
    distal to its last cut, as at any other cut)."""
    w = ws.work
    out = []
    for mem in mech.members:
        path = mech.tree.paths[mem.path]
        js = list(path.joints)
        s = np.concatenate([path.s_starts, [path.length]])
        poses = np.concatenate([w.g_in[js], w.g_out[js[-1:]]])
        # the cut at a section's start: -f_in (the parent side acts on the distal part with f_in)
        wr = np.concatenate([-w.f_in[js], -w.f[js[-1:]]])
        wr[-1] += _end_loads(ws, loads, js[-1], path.lengths[-1])
        strains = np.concatenate([w.strain[js], w.strain[js[-1:]]])
        wr = wr + _tendon_pull(mech, mem, s, strains, u)
        geo = list(mem.geometry) + [mem.geometry[-1]]
        normal = np.empty(len(s))
        shear = np.empty(len(s))
        for g in {id(x): x for x in geo}.values():          # each cross-section once, vectorised
            idx = [k for k, x in enumerate(geo) if x is g]
            normal[idx], shear[idx] = peak_stresses(g, wr[idx])
        # body twists and accelerations of the cross-sections -> world point velocity and acceleration
        V = np.concatenate([w.Vin[js], w.V[js[-1:]]])
        A = np.concatenate([w.Ain[js], w.A[js[-1:]]])
        R = poses[:, :3, :3]
        vel = np.einsum("nij,nj->ni", R, V[:, :3])
        wv = V[:, 3:]
        vv = V[:, :3]
        wxv = np.stack([wv[:, 1] * vv[:, 2] - wv[:, 2] * vv[:, 1], wv[:, 2] * vv[:, 0] - wv[:, 0] * vv[:, 2],
                        wv[:, 0] * vv[:, 1] - wv[:, 1] * vv[:, 0]], axis=1)
        acc = np.einsum("nij,nj->ni", R, A[:, :3] + wxv)
        out.append(MemberOutput(mem.name, s, poses.copy(), wr, strains.copy(), normal, shear, vel, acc))
    return out


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
    ``members`` (MemberOutput list)."""
    positions: dict
    velocities: dict
    accelerations: dict
    efforts: dict
    joint_wrenches: dict
    constraint_wrenches: dict
    frames: dict
    members: list


def state_outputs(mech, q, lam, inputs, v=None, a=None, ws=None):
    """MechanismOutputs at (q, v, a) with multipliers lam under ``inputs``
    (:class:`constrained.Inputs`); v = a = None: statics."""
    from .constrained import _concat_loads, _efforts_out, constraint_loads, constraint_wrenches
    from .kernels.frames import point_poses
    from .workspace import Workspace
    tree = mech.tree
    ws = Workspace(tree) if ws is None else ws
    loads = _concat_loads(inputs.loads, constraint_loads(mech, lam))
    run_passes(mech, ws, q, v, a, loads, inputs.gravity)
    names = [tree.joints[i].name for i in mech.rigid_joints]
    iq = [tree.idx_q[i] for i in mech.rigid_joints]
    iv = [tree.idx_v[i] for i in mech.rigid_joints]
    z = np.zeros(tree.nv)
    v_ = z if v is None else v
    a_ = z if a is None else a
    fnames = list(mech.frames)
    refs = [mech.frames[n] for n in fnames]
    P = np.empty((len(refs), 4, 4))
    if refs:
        point_poses(ws.m, ws.w, np.array([r.joint for r in refs], np.int64), np.array([r.x for r in refs]), P)
    jw = joint_wrenches(mech, ws)
    members = member_outputs(mech, ws, inputs.u, loads)
    if v is None:                    # statics: the pass computed no motion (its arrays may hold old values)
        for mo in members:
            mo.velocities[:] = 0.0
            mo.accelerations[:] = 0.0
    return MechanismOutputs(
        positions={n: float(q[k]) for n, k in zip(names, iq)},
        velocities={n: float(v_[k]) for n, k in zip(names, iv)},
        accelerations={n: float(a_[k]) for n, k in zip(names, iv)},
        efforts=_efforts_out(mech, lam, inputs),
        joint_wrenches={j.name: jw[i] for i, j in enumerate(tree.joints)},
        constraint_wrenches=constraint_wrenches(mech, lam),
        frames=dict(zip(fnames, P)),
        members=members)
