"""Pictures of soft articulated robots (tree robot files): an instant of a
mechanism as a :class:`scene.Snapshot`, so the plots, animations and the
live view draw it like a rod: every soft member's backbone, every rigid
link's visual shape (box, cylinder along its local z axis, sphere; the
``visual`` of the robot file, placed by its ``position``/``rpy`` in the
link frame, as in URDF) as a wire outline, a bar from the parent link (or
the base) to each link without a visual, and the rigid joints as markers
with a segment along their axis.

Inputs are world poses (4x4) of the mechanism's named frames (every link
has a frame of its own name), from a run (:func:`run_snapshots`: the
``frame_poses`` samples of :func:`mechanism_scenario.run_mechanism_dynamics`)
or from the node's state. No ROS, no matplotlib.
"""

import numpy as np

from .multibody import PRISMATIC, REVOLUTE

CIRCLE_POINTS = 24
JOINT_AXIS_LENGTH = 0.03     # m, the drawn segment along a joint axis (centred on the joint)


def visual_placement(visual):
    """The visual's pose in its link frame (4x4; identity if not given)."""
    from .model import pose_from_dict
    v = {k: visual[k] for k in ("position", "rpy") if k in visual}
    return pose_from_dict(v or None, "visual")


def solid_outline(visual, pose):
    """(N, 3) [m] world polyline of a visual shape's edges at ``pose`` (4x4,
    the link frame), NaN rows between separate edges: a box's 12 edges; a
    cylinder's two end circles (normal to its local z axis, centred) and 4
    generators; a sphere's three great circles."""
    T = np.asarray(pose, dtype=float) @ visual_placement(visual)
    shape = visual.get("shape", "box")
    nan = np.full((1, 3), np.nan)
    a = np.linspace(0.0, 2 * np.pi, CIRCLE_POINTS + 1)
    c, s = np.cos(a), np.sin(a)
    parts = []
    if shape == "box":
        h = 0.5 * np.asarray(visual["size"], dtype=float)
        sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=float)
        for z in (-1.0, 1.0):                                   # bottom and top faces
            parts.append(np.c_[sq * h[:2], np.full(5, z * h[2])])
        for x, y in sq[:4]:                                     # the 4 vertical edges
            parts.append(np.array([[x * h[0], y * h[1], -h[2]], [x * h[0], y * h[1], h[2]]]))
    elif shape == "cylinder":
        r, hl = float(visual["radius"]), 0.5 * float(visual["length"])
        for z in (-hl, hl):
            parts.append(np.c_[r * c, r * s, np.full_like(c, z)])
        for k in range(0, CIRCLE_POINTS, CIRCLE_POINTS // 4):
            parts.append(np.array([[r * c[k], r * s[k], -hl], [r * c[k], r * s[k], hl]]))
    elif shape == "sphere":
        r = float(visual["radius"])
        z = np.zeros_like(c)
        parts += [np.c_[r * c, r * s, z], np.c_[r * c, z, r * s], np.c_[z, r * c, r * s]]
    else:
        raise ValueError(f"visual.shape: expected box, cylinder or sphere, got {shape!r}")
    P = np.concatenate([np.vstack([p, nan]) for p in parts])[:-1]
    out = np.full_like(P, np.nan)
    ok = np.all(np.isfinite(P), axis=1)
    out[ok] = P[ok] @ T[:3, :3].T + T[:3, 3]
    return out


def rigid_joints(mech):
    """[(joint index, the name of the link it moves)] of the 1-dof rigid joints with a link."""
    links = {lk.joint: lk.name for lk in mech.links}
    return [(i, links[i]) for i in mech.rigid_joints if i in links]


def snapshot(mech, members, frame_poses, time=None, caption=""):
    """A :class:`scene.Snapshot` of a mechanism: ``members`` {member name:
    (P, 3) backbone points [m]} (or a list in the order of ``mech.members``),
    ``frame_poses`` {frame name: 4x4 world pose}."""
    from .scene import Snapshot
    if isinstance(members, dict):
        members = [members[m.name] for m in mech.members]
    members = [np.asarray(P, dtype=float) for P in members]
    tree = mech.tree
    names = {lk.joint: lk.name for lk in mech.links}
    links, solids, shapes = [], [], []
    for lk in mech.links:
        T = np.asarray(frame_poses[lk.name], dtype=float)
        if lk.visual:
            solids.append(solid_outline(lk.visual, T))
            shapes.append((dict(lk.visual), T @ visual_placement(lk.visual)))
            continue
        par = tree.joints[lk.joint].parent
        start = np.zeros(3) if par < 0 else (np.asarray(frame_poses[names[par]])[:3, 3] if par in names else None)
        if start is not None:
            links.append(np.array([start, T[:3, 3]]))
    joints, axes = [], []
    for i, name in rigid_joints(mech):
        T = np.asarray(frame_poses[name], dtype=float)
        j = tree.joints[i]
        p, d = T[:3, 3], T[:3, :3] @ np.asarray(j.axis, dtype=float)
        joints.append(p)
        if j.kind in (REVOLUTE, PRISMATIC):
            axes.append(np.array([p - 0.5 * JOINT_AXIS_LENGTH * d, p + 0.5 * JOINT_AXIS_LENGTH * d]))
    if not members:                     # a robot of rigid links only: its last frame stands for the tip
        members = [np.asarray(list(frame_poses.values())[-1], dtype=float)[None, :3, 3]]
    return Snapshot(members, links, time=time, caption=caption, solids=solids,
                    joints=np.array(joints).reshape(-1, 3), joint_axes=axes, shapes=shapes)


def member_radii(mech, n_points=None, default=0.005):
    """[radii (P,) [m] along each member]: the outer extent max(cy, cz) of
    the cross-section of the section holding each point (``default``
    without geometry), at the member's section boundaries (the last
    section's at the tip), or at the points of a run sampled with
    {member: P} points (P = n_sections * points_per_section + 1:
    :func:`outputs.member_samples`)."""
    from .outputs import member_samples
    out = []
    for mem in mech.members:
        r = np.array([max(g.cy, g.cz) if g is not None else default for g in mem.geometry] or [default], float)
        n_sec = len(mech.tree.paths[mem.path].joints)
        n = n_sec + 1 if n_points is None else int(n_points[mem.name])
        if (n - 1) % n_sec:
            raise ValueError(f"member {mem.name}: {n} points are not {n_sec} sections sampled evenly")
        J, _, _ = member_samples(mech, mem, (n - 1) // n_sec)
        out.append(r[[list(mech.tree.paths[mem.path].joints).index(j) for j in J]])
    return out or [default]


def run_snapshots(out, mech):
    """Snapshots of an articulated robot's dynamics run (the JSON of
    ``soft-twin-sim dynamics`` with ``--backbone-every K``, or a recording
    read back by :func:`mechanism_recording.read_node_recording`): one per
    member sample, with the frame poses of the same sample."""
    if not out.get("members_time"):
        raise ValueError("the run has no member samples: run dynamics with --backbone-every K (K >= 1)")
    if "frame_poses" not in out:
        raise ValueError("the run has no frame poses at its samples (written by soft-twin-sim since issue 12)")
    fnames = out["frame_names"]
    snaps = []
    for t, members, poses in zip(out["members_time"], out["members"], out["frame_poses"]):
        fp = dict(zip(fnames, poses))
        snaps.append(snapshot(mech, {n: m["positions"] for n, m in members.items()}, fp, time=float(t)))
    return snaps


def statics_snapshot(result, mech, caption="equilibrium"):
    """The snapshot of an articulated statics result (``soft-twin-sim statics``)
    with ``frame_poses``."""
    fp = dict(zip(result["frame_names"], result["frame_poses"]))
    return snapshot(mech, {n: m["positions"] for n, m in result["members"].items()}, fp, caption=caption)
