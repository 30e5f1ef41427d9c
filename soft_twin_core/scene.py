"""What a picture of the robot shows at one instant: a :class:`Snapshot` of
soft members (polylines of backbone points, world frame, m), optional rigid
link segments and frames, and a caption (the time, or the swept value).

Plots (:mod:`plots`), animations (:mod:`animate`) and the viewers draw
snapshots only, so a robot of any shape (one rod, several members joined by
rigid offsets, articulated trees with rigid links) is drawn by the same code
once it is turned into snapshots. No matplotlib here; no ROS anywhere in the
core.
"""

from dataclasses import dataclass, field

import numpy as np


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
        separating their edges (:mod:`mechanism_scene`).
    joints: (K, 3) [m], world: the origins of the rigid joints (drawn as
        markers), with ``joint_axes``: (2, 3) segments along their axes.
    shapes: list of (visual dict, 4x4 world pose of the shape's centre,
        its placement in the link applied): the rigid bodies' shapes
        themselves, for viewers drawing solids (the live view).
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


def split_members(points, s, member_ends):
    """Split one backbone polyline sampled at arc lengths ``s`` [m] into the
    members ending at ``member_ends`` [m] (rigid offsets between members;
    the last end is the tip). Returns (members, links): the polylines, and
    the straight segments joining the last sample of one member to the first
    of the next (the rigid offset, drawn as a link)."""
    points = np.asarray(points, dtype=float)
    s = np.asarray(s, dtype=float)
    if len(points) != len(s):
        raise ValueError(f"points and s: lengths differ ({len(points)} vs {len(s)})")
    members, links, start = [], [], 0
    for end in list(member_ends)[:-1]:
        k = int(np.searchsorted(s, end - 1e-12))        # first sample at or past the joint
        if start < k < len(s):
            members.append(points[start:k])
            links.append(points[k - 1:k + 1])
            start = k
    members.append(points[start:])
    return members, links


def segment_ends(model):
    """Arc lengths [m] where a model's members end: after each section
    followed by a rigid offset (``offset_to_next``), and at the tip."""
    ends = [float(model.s_starts[i] + model.lengths[i]) for i in range(model.n_sections - 1)
            if np.abs(model.offsets[i] - np.eye(4)).max() > 0]
    return ends + [float(model.total_length)]


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
