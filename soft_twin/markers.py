"""RViz markers of a published state (``~/markers``): a tube of cylinders
along every soft member (one per sample interval, the diameter of its
section), the rigid links' visual shapes (a small sphere for a link without
one), a sphere at the tip, the robot file's obstacles (translucent grey: a
plane as a thin square around the robot, spheres, capsules, meshes: these
sent when they change and once a second) and an arrow per contact, along its
force on the member (the longest 5 cm, the others to scale).

:class:`Markers` remembers how many tube cylinders and contact arrows it drew
last, so that a state with fewer deletes the extra ones.
"""

import numpy as np
from geometry_msgs.msg import Point, Vector3
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from soft_twin import conversions as cv
from soft_twin_core.lie import rotation_with_z

TUBE = ColorRGBA(r=0.85, g=0.45, b=0.2, a=0.9)
LINK = ColorRGBA(r=0.6, g=0.6, b=0.65, a=1.0)
TIP = ColorRGBA(r=0.2, g=0.4, b=0.9, a=1.0)
OBSTACLE = ColorRGBA(r=0.5, g=0.5, b=0.5, a=0.35)
CONTACT = ColorRGBA(r=0.9, g=0.1, b=0.1, a=1.0)
DEFAULT_RADIUS = 0.005      # m, a member section without geometry
ARROW_LENGTH = 0.05         # m, the arrow of the largest contact force


def tube(T, radii, header, first_id):
    """Cylinder markers between consecutive poses T (P, 4, 4) of a member's
    backbone, radii (P - 1,) [m], ids from ``first_id``."""
    p = T[:, :3, 3]
    mid = 0.5 * (p[1:] + p[:-1])
    length = np.linalg.norm(p[1:] - p[:-1], axis=1)
    quat = cv.cylinder_orientation(T[:-1]).tolist()
    out = []
    for i, (c, L, q, r) in enumerate(zip(mid.tolist(), length.tolist(), quat, np.asarray(radii).tolist())):
        m = Marker(header=header, ns="tube", id=first_id + i, type=Marker.CYLINDER, action=Marker.ADD, color=TUBE)
        m.pose.position = cv.point(c)
        m.pose.orientation = cv.quaternion(q)
        m.scale = Vector3(x=2 * r, y=2 * r, z=max(L * 1.05, 1e-6))
        out.append(m)
    return out


def link_marker(visual, pose, header, k):
    """The marker of a rigid link's visual shape (box, cylinder, sphere) at its frame's pose."""
    vis = visual or {"shape": "sphere", "radius": 0.01}
    kind = {"box": Marker.CUBE, "cylinder": Marker.CYLINDER, "sphere": Marker.SPHERE}[vis["shape"]]
    m = Marker(header=header, ns="links", id=k, type=kind, action=Marker.ADD, color=LINK)
    m.pose = cv.pose_msg(pose)
    if vis["shape"] == "box":
        m.scale = Vector3(x=float(vis["size"][0]), y=float(vis["size"][1]), z=float(vis["size"][2]))
    elif vis["shape"] == "cylinder":
        d = 2 * float(vis["radius"])
        m.scale = Vector3(x=d, y=d, z=float(vis["length"]))
    else:
        d = 2 * float(vis["radius"])
        m.scale = Vector3(x=d, y=d, z=d)
    return m


def tip_marker(pose, diameter, header):
    m = Marker(header=header, ns="tip", id=0, type=Marker.SPHERE, action=Marker.ADD, color=TIP)
    m.pose = cv.pose_msg(pose)
    m.scale = Vector3(x=diameter, y=diameter, z=diameter)
    return m


def obstacle_markers(obstacles, centre, extent, header):
    """Markers of the obstacles (engine.contact.Obstacle) but meshes
    (:func:`mesh_marker`): a plane as a 1 mm thick square of side 1.2
    ``extent`` [m] around the point of it nearest ``centre``, a sphere, a
    capsule as a cylinder and two spheres, a tube as its centre line as wide
    as its lumen."""
    out = []

    def add(kind, T, sx, sy, sz):
        m = Marker(header=header, ns="obstacles", id=len(out), type=kind, action=Marker.ADD, color=OBSTACLE)
        m.pose = cv.pose_msg(T)
        m.scale = Vector3(x=float(sx), y=float(sy), z=float(sz))
        out.append(m)
    for ob in obstacles:
        T = np.eye(4)
        if ob.kind == "mesh":               # (mesh_marker, in their own namespace)
            continue
        if ob.kind == "box":
            T[:3, :3], T[:3, 3] = ob.rotation, ob.a
            add(Marker.CUBE, T, *(2 * ob.half_size))
            continue
        if ob.kind == "tube":               # its centre line, as wide as the lumen
            T[:3, :3], T[:3, 3] = ob.rotation, ob.a
            add(Marker.LINE_STRIP, T, 2 * ob.radius, 0.0, 0.0)
            out[-1].points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in ob.path]
            continue
        if ob.kind == "plane":
            T[:3, :3] = rotation_with_z(ob.b)
            c = np.asarray(centre, float)
            T[:3, 3] = c - ((c - ob.a) @ ob.b) * ob.b - 0.0005 * ob.b
            add(Marker.CUBE, T, 1.2 * extent, 1.2 * extent, 0.001)
            continue
        ends = [ob.a] if ob.kind == "sphere" else [ob.a, ob.b]
        for p in ends:
            T[:3, 3] = p
            add(Marker.SPHERE, T, *(3 * [2 * ob.radius]))
        if ob.kind == "capsule":
            axis = ob.b - ob.a
            T[:3, :3] = rotation_with_z(axis / np.linalg.norm(axis))
            T[:3, 3] = 0.5 * (ob.a + ob.b)
            add(Marker.CYLINDER, T, 2 * ob.radius, 2 * ob.radius, np.linalg.norm(axis))
    return out


def mesh_marker(ob, k, header):
    """A mesh obstacle's TRIANGLE_LIST marker (``obstacle_meshes``, id k),
    its points in its own frame."""
    m = Marker(header=header, ns="obstacle_meshes", id=k, type=Marker.TRIANGLE_LIST, action=Marker.ADD,
               color=OBSTACLE)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = ob.rotation, ob.a
    m.pose = cv.pose_msg(T)
    m.scale = Vector3(x=1.0, y=1.0, z=1.0)
    m.points = [Point(x=x, y=y, z=z) for x, y, z in ob.triangles.reshape(-1, 3).tolist()]
    return m


MESH_REFRESH_S = 1.0        # mesh markers are sent again at most this often unless the meshes change


def contact_arrows(contacts, header):
    """An arrow per contact (engine.contact.ContactState) from its backbone
    point along its force, the largest ARROW_LENGTH long."""
    F = np.asarray(contacts.force, dtype=float)
    scale = ARROW_LENGTH / max(float(np.max(np.linalg.norm(F, axis=1), initial=0.0)), 1e-300)
    out = []
    for k, (p, f) in enumerate(zip(np.asarray(contacts.p, float), F)):
        m = Marker(header=header, ns="contacts", id=k, type=Marker.ARROW, action=Marker.ADD, color=CONTACT)
        m.points = [cv.point(p.tolist()), cv.point((p + scale * f).tolist())]
        m.scale = Vector3(x=0.002, y=0.004, z=0.006)        # shaft and head diameters, head length [m]
        out.append(m)
    return out


class Markers:
    """The MarkerArray of a state: a tube per soft member (its sections'
    radii), the links' shapes, a sphere at the tip."""

    def __init__(self):
        self.n_tube = 0
        self.n_contacts = 0
        self.n_obstacles = 0          # obstacle markers drawn (removed obstacles: deleted)
        # meshes: built once each and sent when they change, else every MESH_REFRESH_S (RViz keeps a marker
        # until it is replaced; a mesh of 2048 triangles costs 60 ms a message to build and serialise)
        self._meshes, self._mesh_markers, self._mesh_sent = (), [], -np.inf

    def __call__(self, snap, robot, header):
        out = MarkerArray()
        mech = robot.mech
        pps = snap.points_per_section
        for mem in mech.members:
            T = snap.backbones[mem.name][0]
            radii = [self._radius(mem.geometry[min(i // pps, len(mem.geometry) - 1)]) for i in range(len(T) - 1)]
            out.markers += tube(T, radii, header, len(out.markers))
        n = len(out.markers)
        out.markers += [link_marker(lk.visual, snap.frames[lk.name], header, k) for k, lk in enumerate(mech.links)]
        main = next((m for m in mech.members if m.name == snap.main_member), None)
        diameter = 2.4 * self._radius(main.geometry[-1]) if main is not None and main.geometry else 0.015
        tip = tip_marker(snap.tip_pose, diameter, header)
        out.markers.append(tip)
        # fewer samples than before: delete the extra cylinders
        out.markers += [Marker(header=header, ns="tube", id=i, action=Marker.DELETE) for i in range(n, self.n_tube)]
        self.n_tube = n
        if snap.obstacles or self.n_obstacles:
            P = np.concatenate([snap.backbones[m.name][0][:, :3, 3] for m in mech.members] + [snap.tip_pose[None, :3, 3]])
            extent = max(float(np.max(P.max(axis=0) - P.min(axis=0))), 0.05)
            shapes = obstacle_markers(snap.obstacles, P.mean(axis=0), extent, header)
            out.markers += shapes
            out.markers += [Marker(header=header, ns="obstacles", id=i, action=Marker.DELETE)
                            for i in range(len(shapes), self.n_obstacles)]
            self.n_obstacles = len(shapes)
        out.markers += self._mesh_update(snap.obstacles or (), header)
        arrows = contact_arrows(snap.contacts, header) if snap.contacts is not None and len(snap.contacts) else []
        out.markers += arrows
        out.markers += [Marker(header=header, ns="contacts", id=i, action=Marker.DELETE)
                        for i in range(len(arrows), self.n_contacts)]
        self.n_contacts = len(arrows)
        return out

    def _mesh_update(self, obstacles, header):
        """The mesh obstacles' markers when they changed (those removed
        deleted) or were last sent MESH_REFRESH_S ago, else none."""
        import time
        meshes = tuple(ob for ob in obstacles if ob.kind == "mesh")
        now = time.monotonic()
        changed = len(meshes) != len(self._meshes) or any(a is not b for a, b in zip(meshes, self._meshes))
        if not changed and now - self._mesh_sent < MESH_REFRESH_S:
            return []
        old = len(self._meshes)
        if changed:
            self._mesh_markers = [mesh_marker(ob, k, header) for k, ob in enumerate(meshes)]
            self._meshes = meshes
        for m in self._mesh_markers:
            m.header = header
        self._mesh_sent = now
        return list(self._mesh_markers) + [Marker(header=header, ns="obstacle_meshes", id=k, action=Marker.DELETE)
                                           for k in range(len(meshes), old)]

    @staticmethod
    def _radius(g):
        return max(g.cy, g.cz) if g is not None else DEFAULT_RADIUS
