"""Contact of a mechanism's soft members with its obstacles, on a
workspace: the contact forces at q as dead point loads for the engine's
passes, and their stiffness ``-J^T dF/dp J`` for Newton's matrix (the law:
:mod:`soft_twin_core.engine.contact`). Statics' friction acts against the
displacement of each contact's surface point from where it sticks
(:class:`StickPoints`: the points' positions and frames at an earlier
equilibrium), by :func:`engine.contact.stick_friction`."""

from dataclasses import dataclass

import numpy as np

from soft_twin_core.engine.contact import (STICK_TIME, ContactState, contact_forces, normal_potential_density,
                                           step_contact_forces, stick_friction, transition_step)
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.contact import distance_arrays, obstacle_arrays, posable, pose_obstacles
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.frames import (body_point_twists, frame_spins, offset_point_positions,
                                                  relative_point_jacobians)
from soft_twin_core.lie import log_so3
from soft_twin_core.robot.obstacles import contact_points


STICK_CAP = 3.0      # a sliding point's stick point is dragged along to this many stick lengths behind it


@dataclass(frozen=True)
class StickPoints:
    """Where the contact points stick, for statics' friction: their
    positions p (P, 3) [m] and frames' rotations R (P, 3, 3) at the
    equilibrium they last rested in, and which of them touched an obstacle
    with friction there (``touching`` (P,) bool): only those have a stick
    point; one that touches down in a solve lands where it meets the
    obstacle, which a statics solve cannot know (the path is not solved),
    so it is frictionless in that solve and sticks where it landed from the
    next (:meth:`MemberContact.stick_points`,
    :meth:`MemberContact.stuck_after`). ``body`` (P,) int: the joint whose
    output frame p and R are given in, the body carrying the touched shape
    (a loose object held by the fingers: the stick point moves with it);
    -1 (or None for all): the world's axes."""
    p: np.ndarray
    R: np.ndarray
    touching: np.ndarray
    body: np.ndarray = None

    def __post_init__(self):
        if self.body is None:
            object.__setattr__(self, "body", np.full(len(self.p), -1, np.int64))

    @classmethod
    def from_world(cls, ws, p, R, touching, body):
        """Stick points given in world axes (p (P, 3), R (P, 3, 3)), kept
        in the output frames of the joints ``body`` (P,) (-1: the world's),
        the bodies posed as the workspace is: :meth:`in_world`'s inverse."""
        p, R = p.copy(), R.copy()
        on = np.flatnonzero(body >= 0)
        g = ws.work.g_out[body[on]]
        p[on] = np.einsum("cji,cj->ci", g[:, :3, :3], p[on] - g[:, :3, 3])
        R[on] = np.matmul(np.transpose(g[:, :3, :3], (0, 2, 1)), R[on])
        return cls(p, R, touching, body)

    def in_world(self, ws):
        """(p, R): these stick points' positions and rotations in world
        axes, the bodies posed as the workspace is (after its forward
        pass)."""
        on = np.flatnonzero(self.body >= 0)
        if not len(on):
            return self.p, self.R
        p, R = self.p.copy(), self.R.copy()
        g = ws.work.g_out[self.body[on]]
        p[on] = np.einsum("cij,cj->ci", g[:, :3, :3], self.p[on]) + g[:, :3, 3]
        R[on] = np.matmul(g[:, :3, :3], self.R[on])
        return p, R


def mechanism_contact_points(mech):
    """The mechanism's :class:`ContactPoints` (made once, kept with it)."""
    pts = mech.__dict__.get("_contact_points")
    if pts is None:
        pts = contact_points(mech, mech.contact_spacing)
        object.__setattr__(mech, "_contact_points", pts)
    return pts


def contact_loads(mech, st):
    """The contact forces of a ContactState of ``mech`` (None: none) as dead
    point loads: world axes, at the contact points, with the spin
    friction's moment about them, and their reactions on the bodies whose shapes are
    touched."""
    if st is None or not len(st):
        return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))
    return _point_loads(mechanism_contact_points(mech), st)


def _point_loads(points, st):
    """Each contact's force F and moment M on its point's frame (about its
    origin: ``M + arm x F``) and, when a body carries the obstacle, -F and
    -M on that body (``-M - body_arm x F``)."""
    n = len(st)
    M = st.moment if st.moment is not None else np.zeros((n, 3))
    wr = np.zeros((n, 6))
    wr[:, :3] = st.force
    wr[:, 3:] = M if st.arm is None else M + np.cross(st.arm, st.force)
    joint, x = points.joint[st.point], points.x[st.point]
    if st.body is not None and np.any(st.body >= 0):
        b = st.body >= 0
        rw = np.zeros((int(b.sum()), 6))
        rw[:, :3] = -st.force[b]
        rw[:, 3:] = -M[b] - np.cross(st.body_arm[b], st.force[b])
        wr = np.concatenate([wr, rw])
        joint = np.concatenate([joint, st.body[b]])
        x = np.concatenate([x, np.full(int(b.sum()), -1.0)])
    return LoadArrays(np.ascontiguousarray(joint, np.int64), np.ascontiguousarray(x, float),
                      np.ascontiguousarray(wr), np.ones(len(joint), np.bool_))


def contact_mask(tree, points, obstacles):
    """(P, O) bool: the (point, obstacle) pairs that may touch. A world
    obstacle touches every point; a body's shape no point of its own body,
    of the bodies it carries, or of those carrying it (a finger does not
    touch the palm it is mounted on, nor a link its own shape); an
    obstacle that ``touches`` named members only their points, and one
    that ``skips`` an arc window of its own member that member's points
    outside the window (self-contact)."""
    allowed = np.ones((len(points), len(obstacles)), np.bool_)
    for o, ob in enumerate(obstacles):
        if ob.touches is not None:           # a member's capsule: the points of the members it touches
            allowed[:, o] = [m in ob.touches for m in points.member]
        if ob.body < 0:
            continue
        below = set(tree.subtree(ob.body))
        above = set(tree.support(ob.body))
        apart = [int(j) not in below and int(j) not in above for j in points.joint]
        if ob.skips is not None:             # a member's capsule on itself: its points away along the arc
            mem, lo, hi = ob.skips
            apart = [a or (m == mem and not lo <= s <= hi) for a, m, s in zip(apart, points.member, points.s)]
        allowed[:, o] &= apart
    return allowed


def contacts_dict(mech, st, obstacles=None):
    """JSON-ready contacts of a ContactState (None: none): per contact its
    member, arc length s [m], obstacle, position [m], normal, gap [m] (< 0:
    pressed in), force [N] on the member (world), slip velocity [m/s],
    moment [N m] (the spin friction's, about the normal) and spin [rad/s]
    (``obstacles``: those the contacts index, default the robot file's)."""
    if st is None or not len(st):
        return []
    pts = mechanism_contact_points(mech)
    names = [ob.name for ob in (mech.obstacles if obstacles is None else obstacles)] + [
        ob.name for ob in mech.shapes]
    return [dict(member=pts.member[i], s=float(pts.s[i]), obstacle=names[o],
                 position=st.p[c].tolist(), normal=st.normal[c].tolist(), gap=float(st.gap[c]),
                 force=st.force[c].tolist(), slip=(st.slip[c].tolist() if st.slip is not None else [0.0] * 3),
                 moment=(st.moment[c].tolist() if st.moment is not None else [0.0] * 3),
                 spin=float(st.spin[c]) if st.spin is not None else 0.0)
            for c, (i, o) in enumerate(zip(st.point, st.obstacle))]


def _subset(st, rows):
    """The contacts ``rows`` of a ContactState (the fields slip_jacobians reads)."""
    return ContactState(st.point[rows], st.obstacle[rows], st.p[rows], st.normal[rows], st.gap[rows],
                        st.force[rows], st.dF_dp[rows], body=None if st.body is None else st.body[rows],
                        radius=None if st.radius is None else st.radius[rows])


class MemberContact:
    """The contact points of ``mech`` against ``obstacles`` (default the
    robot file's) and the collision shapes its links carry
    (``mech.shapes``, after the obstacles in ``all``: a ContactState's
    obstacle indices count in it)."""

    def __init__(self, mech, obstacles=None):
        self.mech = mech
        self.obstacles = tuple(mech.obstacles if obstacles is None else obstacles)
        self.all = self.obstacles + tuple(mech.shapes)
        self.points = mechanism_contact_points(mech) if self.all else None
        self.allowed = contact_mask(mech.tree, self.points, self.all) if self.all else None
        self._local = obstacle_arrays(self.all) if self.all else None
        # the points' frames' rotations are needed: torsional friction, or friction (at the surface: rolling)
        self.turns = bool(self.all) and bool(np.any((self._local.torsion > 0) | (self._local.friction > 0)))
        self._some = bool(self.all) and len(self.points) > 0 and bool(self.allowed.any())

    def __bool__(self):              # (a simulator asks at every step)
        return self._some

    def _positions(self, ws):
        """World positions (P, 3) of the points and their frames' poses, on the workspace as posed."""
        P = len(self.points)
        G, p = np.empty((P, 4, 4)), np.empty((P, 3))
        offset_point_positions(ws.m, ws.w, self.points.joint, self.points.x, self.points.offset, G, p)
        return p, G

    def _posed(self, ws, local=None):
        """The obstacles' arrays with the bodies' shapes posed as the workspace is."""
        local = self._local if local is None else local
        if not self.mech.shapes:
            return local
        out = posable(local)
        pose_obstacles(ws.w, local, out)
        return out

    def positions(self, ws, q, frames=False):
        """World positions (P, 3) of the contact points at q (a forward pass
        of ``ws``; ``frames``: and their frames' poses (P, 4, 4))."""
        z = ws.zeros_v
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), z, z, 0)
        p, G = self._positions(ws)
        return (p, G) if frames else p

    def spin_state(self, ws, v):
        """(R, W, Jw): the points' frames' rotations (P, 3, 3), angular
        velocities at v (P, 3) and their Jacobians (P, 3, nv), the workspace
        posed."""
        P = len(self.points)
        R, W, Jw = np.empty((P, 3, 3)), np.empty((P, 3)), np.empty((P, 3, len(v)))
        frame_spins(ws.m, ws.w, self.points.joint, self.points.x, np.ascontiguousarray(v, float), R, W, Jw)
        return R, W, Jw

    def motion(self, ws, q, v, obstacles=None):
        """(positions, velocities) (P, 3) of the contact points at (q, v),
        the obstacles' arrays posed at q (``obstacles``: the world's where
        they are then, default this contact's), the bodies' twists and,
        with friction, the points' frames' (rotations, angular velocities)
        (else None)."""
        p = self.positions(ws, q)
        P = len(self.points)
        J = np.empty((P, 3, len(v)))
        relative_point_jacobians(ws.m, ws.w, self.points.joint, self.points.x, np.full(P, -1, np.int64), p, J,
                                 np.empty_like(J))
        local = self._local if obstacles is None else obstacle_arrays(tuple(obstacles) + tuple(self.mech.shapes))
        posed = self._posed(ws, local)
        tw = np.empty((len(self.all), 6))
        body_point_twists(ws.m, ws.w, local.body, posed.a, np.ascontiguousarray(v, float), tw)
        tw[local.body < 0] = np.nan
        spin0 = self.spin_state(ws, v)[:2] if self.turns else None
        return p, J @ v, posed, tw, spin0

    def _with_arms(self, ws, st, G):
        """``st`` with each contact's touched body and lever arms (the
        workspace posed at the contacts' configuration, G: the points'
        frames there)."""
        body = self._local.body[st.obstacle]
        st.body = body
        if not self.mech.shapes:            # members only: the points are their frames' origins
            return st
        st.arm = st.p - G[st.point, :3, 3]
        st.body_arm = np.where(body[:, None] >= 0, st.p - ws.work.g_out[np.maximum(body, 0), :3, 3], 0.0)
        return st

    def state(self, ws, q, stick=None):
        """:class:`ContactState` at rest at q (statics); with ``stick``
        (:class:`StickPoints`), the world obstacles' friction against the
        contacts' displacements from there (:meth:`_stick_friction`)."""
        p, G = self.positions(ws, q, frames=True)
        st = self._with_arms(ws, contact_forces(self.points, self.all, p, self.allowed, self._posed(ws)), G)
        return st if stick is None else self._stick_friction(ws, st, G, stick)

    def stick_points(self, ws, q):
        """:class:`StickPoints` of the points where they are at q."""
        p, G = self.positions(ws, q, frames=True)
        return StickPoints(p, G[:, :3, :3].copy(), np.zeros(len(p), np.bool_))

    def _surface_displacement(self, st, G, stick_pose):
        """(c, 3): each contact's surface point's tangential displacement
        from where it sticks, ``(I - n n^T) (dp + r n x phi)`` (dp: the
        backbone point's, phi: its frame's rotation vector from the stick
        frame, world axes: the surface point -r n turns by phi x (-r n))."""
        i = st.point
        sp, sR = stick_pose
        phi = log_so3(np.einsum("cij,ckj->cik", G[i, :3, :3], sR[i]))
        r = st.radius if st.radius is not None else np.zeros(len(st))
        u = st.p - sp[i] + r[:, None] * np.cross(st.normal, phi)
        return u - st.normal * np.einsum("ck,ck->c", st.normal, u)[:, None]

    def _stick_friction(self, ws, st, G, stick):
        """``st`` with statics' friction (:func:`engine.contact.stick_friction`)
        at the contacts with world obstacles that have friction: the force
        at the surface point (on the backbone point: the force and its
        moment ``(-r n) x F_t``), ``dFf_dd`` its derivative along the
        surface point's displacement (Newton's ``J_s^T dFf_dd J_s``) and
        ``dFf_dp`` its growth with the normal force (``J_s^T dFf_dp J_p``).
        A body's shape (a loose object, a link) carries its stick points
        along (:meth:`StickPoints.in_world`): the displacement is relative
        to it, and the friction's reaction acts
        on it (:func:`_point_loads`). ``stick.body``: the body each point
        stuck to; a contact with another one is frictionless in this
        solve."""
        n = len(st)
        mu = np.array([ob.friction for ob in self.all])[st.obstacle] if n else np.zeros(0)
        rows = np.flatnonzero((mu > 0) & stick.touching[st.point] & (stick.body[st.point] == self._body(st)))
        if not len(rows):
            return st
        d = self._surface_displacement(st, G, stick.in_world(ws))
        N = st.normal
        fn = np.einsum("ck,ck->c", N, st.force)
        dfn = np.einsum("ck,ckj->cj", N, st.dF_dp)           # d fn / dp (n^T Hess d n = 0)
        r = st.radius if st.radius is not None else np.zeros(n)
        force, moment = st.force.copy(), np.zeros((n, 3)) if st.moment is None else st.moment.copy()
        dFf_dd, dFf_dp = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
        proj = np.eye(3) - N[:, :, None] * N[:, None, :]
        for o in np.unique(st.obstacle[rows]):
            ob = self.all[o]
            c = rows[st.obstacle[rows] == o]
            Ft, dFt = stick_friction(fn[c], d[c], ob.friction, ob.stiction_velocity)
            force[c] += Ft
            moment[c] -= r[c, None] * np.cross(N[c], Ft)
            dFf_dd[c] = np.matmul(dFt, proj[c])
            dFf_dp[c] = (Ft / np.maximum(fn[c], 1e-300)[:, None])[:, :, None] * dfn[c][:, None, :]
        st.force, st.moment, st.dFf_dd, st.dFf_dp = force, moment, dFf_dd, dFf_dp
        st.dFf_dv = np.zeros((n, 3, 3))
        return st

    @staticmethod
    def _body(st):
        """(c,) the joint of each contact's touched body (-1: the world)."""
        return st.body if st.body is not None else np.full(len(st), -1, np.int64)

    @property
    def has_friction(self):
        """Whether an obstacle or a body's shape has friction (statics then
        keeps :class:`StickPoints` from solve to solve)."""
        return self._some and any(ob.friction > 0 for ob in self.all)

    def stuck_at(self, ws, q):
        """:class:`StickPoints` of a robot placed at q: the points touching
        an obstacle or a body's shape with friction there stick where they
        are (a loose object set on a table, in the fingers), from the first
        solve."""
        return self.stuck_after(ws, q, self.stick_points(ws, q), self.state(ws, q))

    def stuck_after(self, ws, q, stick, st=None):
        """The stick points after an equilibrium at q (its ContactState
        ``st``, made with ``stick``): a point touching an obstacle or a
        body's shape with friction that had a stick point there keeps it,
        unless it slid more than ``STICK_CAP`` stick lengths: then it is
        dragged along to that distance behind its surface point (its
        friction stays at 0.995 mu fn, and a load turned back first takes
        up the stick, at most twice that distance, before it slides back);
        one that touched down in the solve sticks where it is now; the
        others have none (they stick where they are now, untouching). A
        stick point on a body is kept in the body's frame."""
        p, G = self.positions(ws, q, frames=True)
        out_p, out_R = p.copy(), G[:, :3, :3].copy()
        touching = np.zeros(len(p), np.bool_)
        body = np.full(len(p), -1, np.int64)
        if st is None or not len(st):
            return StickPoints(out_p, out_R, touching, body)
        mu = np.array([ob.friction for ob in self.all])[st.obstacle]
        fr = np.flatnonzero(mu > 0)
        touching[st.point[fr]] = True
        body[st.point[fr]] = self._body(st)[fr]
        if st.dFf_dd is not None:
            held = np.flatnonzero(np.any(st.dFf_dd != 0, axis=(1, 2)) | np.any(st.dFf_dp != 0, axis=(1, 2)))
            wp, wR = stick.in_world(ws)
            d = self._surface_displacement(st, G, (wp, wR))
            cap = STICK_CAP * np.array([ob.stiction_velocity for ob in self.all])[st.obstacle] * STICK_TIME
            for c in held:
                i = st.point[c]
                size = np.linalg.norm(d[c])
                out_p[i], out_R[i] = wp[i], wR[i]
                if size > cap[c]:
                    out_p[i] = wp[i] + (1.0 - cap[c] / size) * d[c]
        return StickPoints.from_world(ws, out_p, out_R, touching, body)

    def with_obstacles(self, obstacles):
        """This contact with ``obstacles`` instead (the same points)."""
        return MemberContact(self.mech, tuple(obstacles))

    def step_state(self, ws, start, q1, qt, h, theta, obstacles0=None):
        """:class:`ContactState` of a time step h from the points' ``start``
        (:meth:`motion` at the step's start, with ``obstacles0``: the
        world's obstacles then, if they move) to configuration q1, acting
        at the theta point qt (:func:`engine.contact.step_contact_forces`)."""
        p0, v0, P0, tw0, spin0 = start
        p1, G1 = self.positions(ws, q1, frames=True)
        P1 = self._posed(ws)
        pt, G = self.positions(ws, qt, frames=True)
        Pt = self._posed(ws)
        all0 = None if obstacles0 is None else tuple(obstacles0) + tuple(self.mech.shapes)
        spin = None if spin0 is None else (spin0[0], G1[:, :3, :3], spin0[1])
        st = step_contact_forces(self.points, self.all, p0, p1, pt, h, theta, v0, all0, self.allowed,
                                 (P0, P1, Pt), tw0, spin)
        return self._with_arms(ws, st, G)

    def loads(self, st):
        """The contact forces of ``st`` as dead point loads (:func:`contact_loads`)."""
        return _point_loads(self.points, st)

    def add_stiffness(self, ws, st, Kt, scale=1.0, Dt=None):
        """Kt -= scale J^T dF/dq over the contacts of ``st`` (the
        workspace posed at their q); J: the Jacobian of each point's
        velocity relative to the body carrying the obstacle (the world's:
        at rest), ``dF/dq = dF/dp J - [F x] J_w`` (the force turns with
        that body, J_w its angular velocity's Jacobian), and the reaction's
        lever arm grows with the relative motion: ``Kt -= J_w^T [F x] J``
        (checked against finite differences of the residual in the tests).
        The friction acts at the contact surface: its growth with the
        normal force as ``Kt -= J_s^T dFf/dp J`` (J_s: the surface point's
        Jacobian, :meth:`surface_jacobians`). ``Dt``: also Dt -= J^T dF/dv
        J (the normal damping), ``J_s^T dFf/dv J_s`` (the friction's) and,
        for spin friction, ``J_n^T dm/dspin J_n`` with J_n = n^T (J_frame -
        J_w) the spin's Jacobian."""
        n = len(st)
        if not n:
            return Kt
        body = self._body(st)
        J = np.empty((n, 3, Kt.shape[0]))
        Jw = np.empty_like(J)
        relative_point_jacobians(ws.m, ws.w, np.ascontiguousarray(self.points.joint[st.point]),
                                 np.ascontiguousarray(self.points.x[st.point]), np.ascontiguousarray(body),
                                 np.ascontiguousarray(st.p), J, Jw)
        Jf = J.reshape(3 * n, -1)                     # the stacked point Jacobians: one GEMM each
        dFq = np.matmul(st.dF_dp, J)
        if np.any(body >= 0):
            F = st.force
            X = np.zeros((n, 3, 3))
            X[:, 0, 1], X[:, 0, 2], X[:, 1, 2] = -F[:, 2], F[:, 1], -F[:, 0]
            X[:, 1, 0], X[:, 2, 0], X[:, 2, 1] = F[:, 2], -F[:, 1], F[:, 0]
            dFq -= np.matmul(X, Jw)
            # the reaction's point of application moves over the body: d(-J_b(p)^T F)/dp J_rel = J_w^T [F x] J_rel
            Kt -= scale * (Jw.reshape(3 * n, -1).T @ np.matmul(X, J).reshape(3 * n, -1))
        Kt -= scale * (Jf.T @ dFq.reshape(3 * n, -1))
        stuck = st.dFf_dd is not None and np.any(st.dFf_dd != 0)
        fr = st.dFf_dp is not None and (np.any(st.dFf_dp != 0) or np.any(st.dFf_dv != 0) or stuck)
        Jm = self._angular_jacobians(ws, st, Jw) if fr or (st.dM_dw is not None and np.any(st.dM_dw != 0)) \
            else None
        if fr:
            Js = self._surface(st, J, Jm).reshape(3 * n, -1)
            Kt -= scale * (Js.T @ np.matmul(st.dFf_dp, J).reshape(3 * n, -1))
            if stuck:        # statics' friction: along the surface point's displacement
                Kt -= scale * (Js.T @ np.matmul(st.dFf_dd, Js.reshape(n, 3, -1)).reshape(3 * n, -1))
        if Dt is not None:
            Dt -= Jf.T @ np.matmul(st.dF_dv, J).reshape(3 * n, -1)
            if fr:
                Dt -= Js.T @ np.matmul(st.dFf_dv, Js.reshape(n, 3, -1)).reshape(3 * n, -1)
            if st.dM_dw is not None and np.any(st.dM_dw != 0):
                Jn = np.einsum("ck,ckv->cv", st.normal, Jm)
                Dt -= Jn.T @ (st.dM_dw[:, None] * Jn)
        return Kt

    def _angular_jacobians(self, ws, st, Jw):
        """(c, 3, nv): the Jacobians of each contact's frame's angular
        velocity relative to the touched body's, ``J_frame - J_w`` (Jw:
        the bodies'; the workspace posed at the contacts' configuration)."""
        n, nv = len(st), Jw.shape[2]
        Jm = np.empty((n, 3, nv))
        frame_spins(ws.m, ws.w, np.ascontiguousarray(self.points.joint[st.point]),
                    np.ascontiguousarray(self.points.x[st.point]), np.zeros(nv), np.empty((n, 3, 3)),
                    np.empty((n, 3)), Jm)
        return Jm - Jw

    @staticmethod
    def _surface(st, J, Jm):
        """(c, 3, nv): the surface points' velocities' Jacobians, ``J + r
        [n x] J_omega`` (the point -r n from the backbone point's; J, Jm
        its velocity's and its frame's angular velocity's, relative)."""
        r = st.radius if st.radius is not None else np.zeros(len(st))
        return J + r[:, None, None] * np.cross(st.normal[:, :, None], Jm, axisa=1, axisb=1, axisc=1)

    def surface_jacobians(self, ws, st):
        """(c, 3, nv): each contact's surface point's velocity Jacobian
        relative to the touched body, ``J_s = J_p + r [n x] J_omega`` (the
        workspace posed where ``st`` was made)."""
        n = len(st)
        body = self._body(st)
        J = np.empty((n, 3, len(ws.zeros_v)))
        Jw = np.empty_like(J)
        relative_point_jacobians(ws.m, ws.w, np.ascontiguousarray(self.points.joint[st.point]),
                                 np.ascontiguousarray(self.points.x[st.point]), np.ascontiguousarray(body),
                                 np.ascontiguousarray(st.p), J, Jw)
        return self._surface(st, J, self._angular_jacobians(ws, st, Jw))

    def slip_jacobians(self, ws, st):
        """(c, 3, nv): each contact's slip velocity's Jacobian, ``(I - n
        n^T) J_s`` (the surface point's: :meth:`surface_jacobians`)."""
        J = self.surface_jacobians(ws, st)
        N = st.normal
        return J - N[:, :, None] * np.einsum("ck,ckv->cv", N, J)[:, None, :]

    def update_fraction(self, ws, st, dv):
        """The fraction of a Newton update dv to take
        (:func:`engine.contact.transition_step`) for the frictional contacts
        of ``st`` (1 without any)."""
        if st is None or not len(st):
            return 1.0
        mu = np.array([ob.friction for ob in self.all])[st.obstacle]
        vs_all = np.array([ob.stiction_velocity for ob in self.all])
        alpha = 1.0
        fr = mu > 0
        if fr.any():
            sub = np.flatnonzero(fr)
            Jt = self.slip_jacobians(ws, _subset(st, sub))
            alpha = transition_step(st.slip[sub], Jt @ dv, vs_all[st.obstacle[sub]])
        mu_t = np.array([ob.torsional_friction for ob in self.all])[st.obstacle]
        if np.any(mu_t > 0):           # the spins, as slips of the patch's rim (mu_t spin)
            sub = np.flatnonzero(mu_t > 0)
            body = self._body(st)[sub]
            J, Jw = np.empty((len(sub), 3, len(dv))), np.empty((len(sub), 3, len(dv)))
            relative_point_jacobians(ws.m, ws.w, np.ascontiguousarray(self.points.joint[st.point[sub]]),
                                     np.ascontiguousarray(self.points.x[st.point[sub]]), np.ascontiguousarray(body),
                                     np.ascontiguousarray(st.p[sub]), J, Jw)
            ds = np.einsum("ck,ckv->cv", st.normal[sub], self._angular_jacobians(ws, _subset(st, sub), Jw)) @ dv
            rim = np.zeros((len(sub), 3))
            drim = np.zeros((len(sub), 3))
            rim[:, 0], drim[:, 0] = mu_t[sub] * st.spin[sub], mu_t[sub] * ds
            alpha = min(alpha, transition_step(rim, drim, vs_all[st.obstacle[sub]]))
        return alpha

    def potential(self, ws, q):
        """The energy [J] the contacts store at q: the sum over the allowed
        (point, obstacle) pairs of ``w Phi(delta)``
        (:func:`engine.contact.normal_potential_density`)."""
        p = self.positions(ws, q)
        posed = self._posed(ws)
        r = self.points.radius
        out = 0.0
        for o, ob in enumerate(self.all):
            d = np.empty(len(p))
            distance_arrays(posed, o, np.ascontiguousarray(p), d, np.empty((len(p), 3)), np.empty((len(p), 3, 3)))
            k = self.points.modulus if ob.stiffness is None else ob.stiffness
            eps = 0.1 * r if ob.smoothing is None else ob.smoothing
            out += float(np.sum(np.where(self.allowed[:, o], self.points.weight * normal_potential_density(
                r - d, k, eps), 0.0)))
        return out
