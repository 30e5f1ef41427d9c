"""Contact of a mechanism's soft members with its obstacles, on a
workspace: the contact forces at q as dead point loads for the engine's
passes, and their stiffness ``-J^T dF/dp J`` for Newton's matrix (the law:
:mod:`soft_twin_core.engine.contact`)."""

import numpy as np

from soft_twin_core.engine.contact import (contact_forces, normal_potential_density, signed_distance,
                                           step_contact_forces)
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.frames import point_poses, world_point_jacobians
from soft_twin_core.robot.obstacles import contact_points


def mechanism_contact_points(mech):
    """The mechanism's :class:`ContactPoints` (made once, kept with it)."""
    pts = mech.__dict__.get("_contact_points")
    if pts is None:
        pts = contact_points(mech, mech.contact_spacing)
        object.__setattr__(mech, "_contact_points", pts)
    return pts


def contact_loads(mech, st):
    """The contact forces of a ContactState of ``mech`` (None: none) as dead
    point loads: world axes, at the backbone points, with the friction's
    moment about them."""
    if st is None or not len(st):
        return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))
    return _point_loads(mechanism_contact_points(mech), st)


def _point_loads(points, st):
    n = len(st)
    wr = np.zeros((n, 6))
    wr[:, :3] = st.force
    if st.moment is not None:
        wr[:, 3:] = st.moment
    return LoadArrays(np.ascontiguousarray(points.joint[st.point]), np.ascontiguousarray(points.x[st.point]), wr,
                      np.ones(n, np.bool_))


def contacts_dict(mech, st, obstacles=None):
    """JSON-ready contacts of a ContactState (None: none): per contact its
    member, arc length s [m], obstacle, position [m], normal, gap [m] (< 0:
    pressed in), force [N] on the member (world), slip velocity [m/s]
    (``obstacles``: those the contacts index, default the robot file's)."""
    if st is None or not len(st):
        return []
    pts = mechanism_contact_points(mech)
    names = [ob.name for ob in (mech.obstacles if obstacles is None else obstacles)]
    return [dict(member=pts.member[i], s=float(pts.s[i]), obstacle=names[o],
                 position=st.p[c].tolist(), normal=st.normal[c].tolist(), gap=float(st.gap[c]),
                 force=st.force[c].tolist(), slip=(st.slip[c].tolist() if st.slip is not None else [0.0] * 3))
            for c, (i, o) in enumerate(zip(st.point, st.obstacle))]


class MemberContact:
    """The contact points of ``mech`` against ``obstacles`` (default the
    robot file's)."""

    def __init__(self, mech, obstacles=None):
        self.mech = mech
        self.obstacles = tuple(mech.obstacles if obstacles is None else obstacles)
        self.points = mechanism_contact_points(mech) if self.obstacles else None

    def __bool__(self):
        return bool(self.obstacles) and len(self.points) > 0

    def positions(self, ws, q):
        """World positions (P, 3) of the contact points at q (a forward pass of ``ws``)."""
        z = ws.zeros_v
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), z, z, 0)
        g = np.empty((len(self.points), 4, 4))
        point_poses(ws.m, ws.w, self.points.joint, self.points.x, g)
        return g[:, :3, 3]

    def motion(self, ws, q, v):
        """(positions, velocities) (P, 3) of the contact points at (q, v)."""
        P = len(self.points)
        g = np.empty((P, 4, 4))
        J = np.empty((P, 6, len(v)))
        z = ws.zeros_v
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), z, z, 0)
        world_point_jacobians(ws.m, ws.w, self.points.joint, self.points.x, g, J)
        return g[:, :3, 3].copy(), J[:, :3, :] @ v

    def state(self, ws, q):
        """:class:`ContactState` at rest at q (statics)."""
        return contact_forces(self.points, self.obstacles, self.positions(ws, q))

    def with_obstacles(self, obstacles):
        """This contact with ``obstacles`` instead (the same points)."""
        return MemberContact(self.mech, tuple(obstacles))

    def step_state(self, ws, start, q1, qt, h, theta, obstacles0=None):
        """:class:`ContactState` of a time step h from the points' ``start``
        (:meth:`motion` at the step's start) to configuration q1, acting at the theta point
        qt (:func:`engine.contact.step_contact_forces`)."""
        p0, v0 = start
        p1 = self.positions(ws, q1)
        return step_contact_forces(self.points, self.obstacles, p0, p1, self.positions(ws, qt), h, theta, v0,
                                   obstacles0)

    def loads(self, st):
        """The contact forces of ``st`` as dead point loads (:func:`contact_loads`)."""
        return _point_loads(self.points, st)

    def add_stiffness(self, ws, st, Kt, scale=1.0, Dt=None):
        """Kt -= scale J^T dF/dp J over the contacts of ``st`` (the
        workspace posed at their q); J: each point's world velocity
        Jacobian. ``Dt``: also Dt -= J^T dF/dv J (the contacts' damping)."""
        n = len(st)
        if not n:
            return Kt
        g = np.empty((n, 4, 4))
        J = np.empty((n, 6, Kt.shape[0]))
        world_point_jacobians(ws.m, ws.w, np.ascontiguousarray(self.points.joint[st.point]),
                              np.ascontiguousarray(self.points.x[st.point]), g, J)
        Jl = np.ascontiguousarray(J[:, :3, :])
        Jf = Jl.reshape(3 * n, -1)                     # the stacked point Jacobians: one GEMM each
        Kt -= scale * (Jf.T @ np.matmul(st.dF_dp, Jl).reshape(3 * n, -1))
        if Dt is not None:
            Dt -= Jf.T @ np.matmul(st.dF_dv, Jl).reshape(3 * n, -1)
        return Kt

    def potential(self, ws, q):
        """The energy [J] the contacts store at q: the sum over points and
        obstacles of ``w Phi(delta)`` (:func:`engine.contact.normal_potential_density`)."""
        p = self.positions(ws, q)
        r = self.points.radius
        out = 0.0
        for ob in self.obstacles:
            d, _, _ = signed_distance(ob, p)
            k = self.points.modulus if ob.stiffness is None else ob.stiffness
            eps = 0.1 * r if ob.smoothing is None else ob.smoothing
            out += float(np.sum(self.points.weight * normal_potential_density(r - d, k, eps)))
        return out
