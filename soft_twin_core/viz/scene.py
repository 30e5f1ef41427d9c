"""What a picture of the robot shows at one instant: a :class:`Snapshot` of
soft members (polylines of backbone points, world frame, m), optional rigid
link segments and frames, and a caption (the time, or the swept value); and
the snapshot of a mechanism (any robot) from its members' points and its
named frames' poses (:func:`snapshot`): every soft member's backbone, every
rigid link's visual shape (box, cylinder along its local z axis, sphere;
the ``visual`` of the robot file, placed by its ``position``/``rpy`` in the
link frame, as in URDF) as a wire outline, a bar from the parent link (or
the base) to each link without a visual, and the rigid joints as markers
with a segment along their axis. Runs (:func:`run_snapshots`: the samples
of :func:`mechanism_scenario.run_mechanism_dynamics`), statics results
(:func:`statics_snapshot`) and the node's state become snapshots.

Plots (:mod:`plots`), animations (:mod:`animate`) and the viewers draw
snapshots only. No matplotlib here; no ROS anywhere in the core.
"""

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from soft_twin_core.engine.joint_kinds import PRISMATIC, REVOLUTE
from soft_twin_core.lie import rotation_with_z
from soft_twin_core.robot.model import pose_from_dict
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.solve.outputs import member_samples, state_shape


@dataclass
class Snapshot:
    """One instant of a robot.

    members: list of (P_i, 3) arrays [m], world; each a soft member's
        backbone from its proximal to its distal end.
    links: list of (2, 3) arrays [m], world: rigid link segments (drawn as
        straight bars), e.g. the rigid offsets or links of articulated robots.
    frames: dict name -> (4, 4) world pose (drawn as axes triads).
    time: s, or None for a static snapshot.
    caption: text shown with the snapshot (default: ``t = ... s``).
    solids: list of (N, 3) arrays [m], world: the outlines of rigid bodies'
        visual shapes (boxes, cylinders, spheres) as polylines, NaN rows
        separating their edges (:mod:`scene`).
    joints: (K, 3) [m], world: the origins of the rigid joints (drawn as
        markers), with ``joint_axes``: (2, 3) segments along their axes.
    shapes: list of (visual dict, 4x4 world pose of the shape's centre,
        its placement in the link applied): the rigid bodies' shapes
        themselves, for viewers drawing solids (the live view).
    obstacles: list of (N, 3) polylines [m], world, NaN rows between
        edges: the outlines of the obstacles (:func:`obstacle_outline`),
        drawn but not framed (a table is larger than the robot).
    contacts: (K, 3) [m], world: the contact points pressed into them.
    """
    members: list
    links: list = field(default_factory=list)
    frames: dict = field(default_factory=dict)
    time: object = None
    caption: str = ""
    solids: list = field(default_factory=list)
    joints: object = None
    joint_axes: list = field(default_factory=list)
    shapes: list = field(default_factory=list)
    obstacles: list = field(default_factory=list)
    contacts: object = None

    def __post_init__(self):
        ms = []
        for i, m in enumerate(self.members):
            a = np.asarray(m, dtype=float)
            if a.ndim != 2 or a.shape[1] != 3 or len(a) < 1:
                raise ValueError(f"members[{i}]: expected points of shape (P, 3), got {a.shape}")
            ms.append(a)
        if not ms:
            raise ValueError("members: a snapshot needs at least one member")
        self.members = ms
        ls = []
        for i, seg in enumerate(self.links):
            a = np.asarray(seg, dtype=float)
            if a.shape != (2, 3):
                raise ValueError(f"links[{i}]: expected a segment of shape (2, 3), got {a.shape}")
            ls.append(a)
        self.links = ls
        self.solids = [np.asarray(a, dtype=float).reshape(-1, 3) for a in self.solids]
        self.joints = np.zeros((0, 3)) if self.joints is None else np.asarray(self.joints, float).reshape(-1, 3)
        self.joint_axes = [np.asarray(a, dtype=float).reshape(2, 3) for a in self.joint_axes]
        self.obstacles = [np.asarray(a, dtype=float).reshape(-1, 3) for a in self.obstacles]
        self.contacts = np.zeros((0, 3)) if self.contacts is None else np.asarray(self.contacts, float).reshape(-1, 3)
        if not self.caption and self.time is not None:
            self.caption = f"t = {self.time:.2f} s"

    @property
    def points(self):
        """All member, link, solid and joint points, (N, 3) [m] (no NaN)."""
        P = np.concatenate(self.members + self.links + self.solids + [self.joints] + self.joint_axes, axis=0)
        return P[np.all(np.isfinite(P), axis=1)]

    @property
    def tip(self):
        """The distal end of the last member [m]."""
        return self.members[-1][-1]


def bounds(snapshots, pad=0.05, min_extent=0.02):
    """(lo, hi): a box [m] holding every point of every snapshot, padded by
    ``pad`` of the largest extent (at least ``min_extent`` wide per axis):
    one fixed camera framing the whole motion."""
    P = np.concatenate([s.points for s in snapshots], axis=0)
    lo, hi = P.min(axis=0), P.max(axis=0)
    size = max(float(np.max(hi - lo)), min_extent)
    c = 0.5 * (lo + hi)
    half = np.maximum(0.5 * (hi - lo), 0.5 * min_extent) + pad * size
    return c - half, c + half


def sample_times(times, fps):
    """Indices into increasing ``times`` [s] of the frames of an animation
    playing in real time at ``fps`` frames/s: for each frame time k / fps the
    latest sample at or before it (a sample held while the run is sampled
    more coarsely than the frame rate)."""
    times = np.asarray(times, dtype=float)
    if len(times) == 0:
        return np.zeros(0, dtype=int)
    if fps <= 0:
        raise ValueError(f"fps: must be > 0, got {fps}")
    n = int(np.floor((times[-1] - times[0]) * fps + 1e-9)) + 1
    frame_t = times[0] + np.arange(n) / fps
    return np.clip(np.searchsorted(times, frame_t + 1e-9, side="right") - 1, 0, len(times) - 1)


CIRCLE_POINTS = 24
JOINT_AXIS_LENGTH = 0.03     # m, the drawn segment along a joint axis (centred on the joint)


def visual_placement(visual):
    """The visual's pose in its link frame (4x4; identity if not given)."""
    v = {k: visual[k] for k in ("position", "rpy") if k in visual}
    return pose_from_dict(v or None, "visual")


@lru_cache(maxsize=32)
def _mesh_outline(ob):
    """A mesh obstacle's triangles as closed loops (T, 3, 3) -> (5 T - 1, 3),
    NaN rows between, in the world; kept for the obstacle (immutable: a
    view drawing every frame builds it once)."""
    W = ob.triangles @ ob.rotation.T + ob.a
    loops = np.concatenate([W, W[:, :1], np.full((len(W), 1, 3), np.nan)], axis=1)
    out = loops.reshape(-1, 3)[:-1]
    out.setflags(write=False)
    return out


def obstacle_outline(ob, centre, extent):
    """(N, 3) [m] world polyline of an obstacle (engine.contact.Obstacle):
    a tube's centre line and a ring at each of its vertices; a mesh's
    triangles; a sphere's great circles; a capsule's cylinder and end circles; a
    plane's square of side 1.2 ``extent`` around the point of the plane
    nearest ``centre`` (the robot's), with a short stroke along its normal."""
    nan = np.full((1, 3), np.nan)
    if ob.kind == "tube":                    # its wall's two outlines beside the centre line, rings at its vertices
        W = ob.path @ ob.rotation.T + ob.a
        parts = [W]
        for k, p in enumerate(W):
            t = W[min(k + 1, len(W) - 1)] - W[max(k - 1, 0)]
            R = _translation(p)
            R[:3, :3] = rotation_with_z(t / np.linalg.norm(t))
            parts.append(solid_outline({"shape": "sphere", "radius": ob.radius}, R)[:CIRCLE_POINTS + 1])
        return np.concatenate([np.vstack([q, nan]) for q in parts])[:-1]
    if ob.kind == "mesh":                    # every triangle's edges
        return _mesh_outline(ob)
    if ob.kind == "sphere":
        return solid_outline({"shape": "sphere", "radius": ob.radius}, _translation(ob.a))
    if ob.kind == "box":
        T = _translation(ob.a)
        T[:3, :3] = ob.rotation
        return solid_outline({"shape": "box", "size": (2 * ob.half_size).tolist()}, T)
    z = ob.b - ob.a if ob.kind == "capsule" else ob.b
    T = _translation(ob.a if ob.kind == "plane" else 0.5 * (ob.a + ob.b))
    T[:3, :3] = rotation_with_z(z / np.linalg.norm(z))
    if ob.kind == "capsule":
        parts = [solid_outline({"shape": "cylinder", "radius": ob.radius, "length": float(np.linalg.norm(z))}, T)]
        for end in (ob.a, ob.b):
            E = T.copy()
            E[:3, 3] = end
            parts.append(solid_outline({"shape": "sphere", "radius": ob.radius}, E)[:CIRCLE_POINTS + 1])
        return np.concatenate([np.vstack([p, nan]) for p in parts])[:-1]
    n = ob.b
    c = np.asarray(centre, float) - ((np.asarray(centre, float) - ob.a) @ n) * n
    T[:3, 3] = c
    half = 0.6 * max(float(extent), 1e-3)
    sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [-1, -1, 0]], float) * [half, half, 0]
    stroke = np.array([[0, 0, 0], [0, 0, 0.15 * half]])
    P = np.vstack([sq, nan, stroke])
    return np.where(np.isnan(P), np.nan, P @ T[:3, :3].T + T[:3, 3])


def _translation(p):
    T = np.eye(4)
    T[:3, 3] = p
    return T


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


def snapshot(mech, members, frame_poses, time=None, caption="", contacts=None):
    """A :class:`scene.Snapshot` of a mechanism: ``members`` {member name:
    (P, 3) backbone points [m]} (or a list in the order of ``mech.members``),
    ``frame_poses`` {frame name: 4x4 world pose}; the robot file's obstacles
    outlined around it; ``contacts``: (K, 3) contact points [m]."""
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
    obstacles = []
    if mech.obstacles:
        P = np.concatenate(members)
        extent = float(np.max(P.max(axis=0) - P.min(axis=0)))
        obstacles = [obstacle_outline(ob, P.mean(axis=0), extent) for ob in mech.obstacles]
    return Snapshot(members, links, time=time, caption=caption, solids=solids,
                    joints=np.array(joints).reshape(-1, 3), joint_axes=axes, shapes=shapes, obstacles=obstacles,
                    contacts=contacts)


def skeleton(mech, q, points_per_section=4):
    """Polylines (each (N, 3) [m]; NaN rows separate pieces) of the robot at
    configuration ``q``, drawn as :func:`snapshot` draws it: its members'
    backbones, its links (a line from the parent link's frame) and the
    outlines of their shapes. A "ghost" of a shape the robot is not in:
    an IK answer before it is applied."""
    frames, members = state_shape(mech, Workspace(mech.tree), q, points_per_section)
    snap = snapshot(mech, {m: G[:, :3, 3] for m, (G, _) in members.items()}, frames)
    return list(snap.members) + list(snap.links) + list(snap.solids)


def member_radii(mech, n_points=None, default=0.005):
    """[radii (P,) [m] along each member]: the outer extent max(cy, cz) of
    the cross-section of the section holding each point (``default``
    without geometry), at the member's section boundaries (the last
    section's at the tip), or at the points of a run sampled with
    {member: P} points (P = n_sections * points_per_section + 1:
    :func:`outputs.member_samples`)."""
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
    read back by :func:`recording.read_node_recording`): one per
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
    contacts = [c["position"] for c in result.get("contacts", ())]
    return snapshot(mech, {n: m["positions"] for n, m in result["members"].items()}, fp, caption=caption,
                    contacts=contacts)
