"""A live 3D view of the twin in the browser (viser: a local web server and
its bundled three.js client; works offline). Shows the backbone as a tube
with the members' radii, rigid links as bars or, for articulated robots,
their visual shapes (boxes, cylinders, spheres) with the rigid joints as
dots and axis segments, the frames of the base and
the tip, the tip wrench as an arrow, and a panel with the time and the
actuation values.

    view = LiveView(port=8080)            # http://127.0.0.1:8080
    view.show(snapshot, radii=..., actuation={"tendon_y_pos": 2.0}, tip_force=[0, 0, -0.1])

Used by ``soft-twin-sim view`` (a recorded or simulated run played back in
a loop) and by the twin node (parameter ``live_view_port``). ``show`` is
cheap and thread-safe (viser sends the updates from its own thread).
"""

import threading

import numpy as np

TUBE_SIDES = 16
TUBE_COLOR = (217, 115, 51)
LINK_COLOR = (70, 70, 70)
SHAPE_COLOR = (64, 96, 170)    # rigid links' visual shapes (articulated robots)
JOINT_COLOR = (20, 20, 20)
FORCE_COLOR = (204, 41, 204)


def tube_mesh(points, radii, sides=TUBE_SIDES):
    """(vertices (P*sides + 2, 3), faces (F, 3)) of a closed tube of
    radius ``radii`` (P,) [m] around the polyline ``points`` (P, 3) [m]; the
    rings are normal to the local tangent (parallel transport of one normal,
    so the tube does not twist), the ends capped."""
    P = np.asarray(points, dtype=float)
    r = np.broadcast_to(np.asarray(radii, dtype=float), (len(P),))
    if len(P) < 2:
        raise ValueError(f"points: a tube needs at least 2 points, got {len(P)}")
    d = np.gradient(P, axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    T = d / np.where(n > 0, n, 1.0)
    a = np.eye(3)[np.argmin(np.abs(T[0]))]
    N = np.empty_like(P)
    N[0] = np.cross(T[0], a)
    N[0] /= np.linalg.norm(N[0])
    for k in range(1, len(P)):
        v = N[k - 1] - (N[k - 1] @ T[k]) * T[k]
        nv = np.linalg.norm(v)
        N[k] = v / nv if nv > 1e-12 else N[k - 1]
    B = np.cross(T, N)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(ang)[None, :, None] * N[:, None, :] + np.sin(ang)[None, :, None] * B[:, None, :]
    V = (P[:, None, :] + r[:, None, None] * ring).reshape(-1, 3)
    V = np.vstack([V, P[0], P[-1]])
    i = np.arange(len(P) - 1)[:, None] * sides
    j = np.arange(sides)[None, :]
    a0, a1 = i + j, i + (j + 1) % sides
    b0, b1 = a0 + sides, a1 + sides
    F = np.concatenate([np.stack([a0, b0, a1], -1).reshape(-1, 3), np.stack([a1, b0, b1], -1).reshape(-1, 3)])
    c0, c1 = len(P) * sides, len(P) * sides + 1
    last = (len(P) - 1) * sides
    caps0 = np.stack([np.full(sides, c0), (np.arange(sides) + 1) % sides, np.arange(sides)], -1)
    caps1 = np.stack([np.full(sides, c1), last + np.arange(sides), last + (np.arange(sides) + 1) % sides], -1)
    return V.astype(np.float32), np.concatenate([F, caps0, caps1]).astype(np.uint32)


def box_mesh(size, pose):
    """(vertices (8, 3), faces (12, 3)) of a box of ``size`` [m] (edge
    lengths along its local x, y, z) centred at ``pose`` (4x4, world),
    faces wound outwards."""
    h = 0.5 * np.asarray(size, dtype=float)
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * h
    T = np.asarray(pose, dtype=float)
    V = c @ T[:3, :3].T + T[:3, 3]
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return V.astype(np.float32), F.astype(np.uint32)


def shape_mesh(visual, pose, sides=TUBE_SIDES):
    """(vertices, faces) of a rigid link's visual shape at ``pose`` (4x4
    world pose of the shape's centre): box (``size``), cylinder (``radius``,
    ``length`` along its local z axis, capped), sphere (``radius``)."""
    T = np.asarray(pose, dtype=float)
    shape = visual.get("shape", "box")
    if shape == "box":
        return box_mesh(visual["size"], T)
    if shape == "cylinder":
        h = 0.5 * float(visual["length"]) * T[:3, 2]
        return tube_mesh(np.array([T[:3, 3] - h, T[:3, 3] + h]), float(visual["radius"]), sides)
    if shape == "sphere":
        r = float(visual["radius"])
        t = np.linspace(-1.0, 1.0, sides)[1:-1]          # a UV sphere: rings along z, capped at the poles
        P = T[:3, 3] + np.outer(t * r, T[:3, 2])
        return tube_mesh(np.vstack([T[:3, 3] - r * T[:3, 2], P, T[:3, 3] + r * T[:3, 2]]),
                         np.r_[0.0, r * np.sqrt(1 - t ** 2), 0.0], sides)
    raise ValueError(f"visual.shape: expected box, cylinder or sphere, got {shape!r}")


def wxyz(R):
    """Quaternion [w, x, y, z] of a rotation matrix (viser's convention)."""
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.array([w, x, y, z])


class LiveView:
    """The browser view: a viser server on ``host:port`` (port 0: a free one)."""

    def __init__(self, port=8080, host="127.0.0.1", title="soft_twin", look_at=(0.2, 0.0, -0.1), distance=0.9):
        import viser
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = self.server.get_port()
        self.host = host
        self._lock = threading.Lock()
        self._text = self.server.gui.add_markdown("**soft_twin**: waiting for the twin ...")
        self._grid = self.server.scene.add_grid("/grid", width=1.0, height=1.0, cell_size=0.05,
                                                position=(0.2, 0.0, -0.5))
        self.server.scene.set_up_direction("+z")
        # the camera of every new page: from the front-left, a little above, on the arm
        c = np.asarray(look_at, dtype=float)
        self.server.initial_camera.look_at = tuple(c)
        self.server.initial_camera.position = tuple(c + distance * np.array([0.35, -0.85, 0.4]))
        self._n_links = self._n_shapes = self._n_joints = 0
        self._sent = {}                  # scene node -> the data last sent
        self.updates = 0

    def frame(self, lo, hi):
        """Aim the camera of every new page at the box (lo, hi) [m] (a robot's
        extent, e.g. :func:`scene.bounds`) from the front-left, a little
        above, and put the grid just under it."""
        lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        c, size = 0.5 * (lo + hi), max(float(np.max(hi - lo)), 0.05)
        self.server.initial_camera.look_at = tuple(c)
        self.server.initial_camera.position = tuple(c + (1.6 * size + 0.1) * np.array([0.35, -0.85, 0.4]))
        self._grid.position = (float(c[0]), float(c[1]), float(lo[2]) - 0.02)

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"

    def show(self, snap, radii=0.01, base_pose=None, tip_pose=None, tip_force=None, actuation=None,
             force_scale=0.5, text="", joints=None):
        """Draw one :class:`scene.Snapshot`: a tube per member (radii [m]: one
        value or one per point of each member, a list per member), links as
        bars, the base and tip frames (4x4 poses, world), the tip force [N]
        as an arrow of ``force_scale`` m per N, the actuation values and the
        joint positions (``joints``: {name: rad or m})."""
        sc = self.server.scene
        with self._lock:
            for k, P in enumerate(snap.members):
                r = radii[k] if isinstance(radii, (list, tuple)) else radii
                if len(P) >= 2:
                    V, F = tube_mesh(P, r)
                    if self._changed(f"/twin/member_{k}", V, F):
                        sc.add_mesh_simple(f"/twin/member_{k}", V, F, color=TUBE_COLOR, flat_shading=False)
            for k, seg in enumerate(snap.links):
                if self._changed(f"/twin/link_{k}", seg):
                    sc.add_line_segments(f"/twin/link_{k}", np.asarray(seg, np.float32)[None], colors=LINK_COLOR,
                                         line_width=6.0)
            for k in range(len(snap.links), self._n_links):
                self._remove(f"/twin/link_{k}")
            self._n_links = len(snap.links)
            # articulated robots: the links' visual shapes, the rigid joints and their axes
            for k, (vis, T) in enumerate(snap.shapes):
                V, F = shape_mesh(vis, T)
                if self._changed(f"/twin/shape_{k}", V, F):
                    sc.add_mesh_simple(f"/twin/shape_{k}", V, F, color=SHAPE_COLOR, flat_shading=True)
            for k in range(len(snap.shapes), self._n_shapes):
                self._remove(f"/twin/shape_{k}")
            self._n_shapes = len(snap.shapes)
            for k, p in enumerate(snap.joints):
                if self._changed(f"/twin/joint_{k}", p):
                    sc.add_icosphere(f"/twin/joint_{k}", radius=0.006, color=JOINT_COLOR, position=tuple(p))
            for k in range(len(snap.joints), self._n_joints):
                self._remove(f"/twin/joint_{k}")
            self._n_joints = len(snap.joints)
            if snap.joint_axes and self._changed("/twin/joint_axes", *snap.joint_axes):
                sc.add_line_segments("/twin/joint_axes", np.asarray(snap.joint_axes, np.float32),
                                     colors=JOINT_COLOR, line_width=3.0)
            for name, T in (("base", base_pose), ("tip", tip_pose)):
                if T is not None and self._changed(f"/twin/{name}_frame", T):
                    T = np.asarray(T, dtype=float)
                    sc.add_frame(f"/twin/{name}_frame", wxyz=wxyz(T[:3, :3]), position=T[:3, 3],
                                 axes_length=0.05, axes_radius=0.002)
            if tip_force is not None and tip_pose is not None:
                p0 = np.asarray(tip_pose, dtype=float)[:3, 3]
                seg = np.array([[p0, p0 + force_scale * np.asarray(tip_force, dtype=float)]], np.float32)
                if self._changed("/twin/tip_force", seg):
                    sc.add_line_segments("/twin/tip_force", seg, colors=FORCE_COLOR, line_width=5.0)
            lines = [f"**soft_twin** {snap.caption}  {text}".rstrip()]
            if actuation:
                lines += [f"- `{k}`: {v:.3g}" for k, v in actuation.items()]
            if joints:
                lines += [f"- joint `{k}`: {v:.3g}" for k, v in joints.items()]
            if tip_force is not None:
                f = np.asarray(tip_force, dtype=float)
                lines.append(f"- tip force: [{f[0]:.3g}, {f[1]:.3g}, {f[2]:.3g}] N")
            content = "\n".join(lines)
            if content != self._text.content:
                self._text.content = content
            self.updates += 1

    def _changed(self, name, *arrays):
        """True (and remembered) when the data of scene node ``name`` differ
        from what was last sent: an unchanged state (a quasi-static twin
        republishing) sends nothing, so a slow browser never falls behind."""
        key = b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in arrays)
        if self._sent.get(name) == key:
            return False
        self._sent[name] = key
        return True

    def _remove(self, name):
        self.server.scene.remove_by_name(name)
        self._sent.pop(name, None)

    def close(self):
        self.server.stop()
