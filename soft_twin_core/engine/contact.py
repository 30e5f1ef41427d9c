"""Contact of soft members with rigid obstacles: a smooth penalty on the
gap, with its analytic tangent.

A soft member touches the world through **contact points**: points on its
backbone at a spacing of its own (independent of the PCS sections), each
the centre of a circle of radius r (the cross-section) standing for a
length w of the member. Against an obstacle whose surface is at signed
distance d(p) from the point p (d > 0 outside), the penetration is
``delta = r - d(p)`` and the member receives the force per unit length

    f(delta) = 0                            delta <= 0
             = k delta^2 / (2 eps)          0 < delta < eps
             = k (delta - eps / 2)          delta >= eps

(:func:`normal_force_density`: continuous with its first derivative, so
Newton keeps its quadratic convergence through touch-down), along the
outward normal n = grad d: ``F = w f(delta) n``, applied at the backbone
point (a normal force through the cross-section's centre has no moment
about it). k [N/m^2 = Pa] is the stiffness per unit length of member and
metre of penetration, eps [m] the smoothing depth. In dynamics the force
is Hunt and Crossley's, ``F = w f(delta) (1 + alpha d delta/dt) n``
(``alpha`` [s/m], the obstacle's ``damping``; ``d delta/dt = -n . v`` with
v the point's velocity): the damping grows with the force from zero at
touch-down, and a contact never pulls (the factor is held at 0 or more).

The force's derivative with respect to the point (:func:`contact_forces`):

    dF/dp = w (-f'(delta) n n^T + f(delta) Hess d)

with ``Hess d = (I - n n^T) / |p - c|`` about a centre c (sphere; for a
capsule's side ``(I - n n^T - a a^T) / |p - c|``, a its axis) and 0 for a
plane. Mapped to the joints, ``dtau/dq = J^T dF/dp J`` (J: the point's
world velocity Jacobian) plus the geometric term of a world force at a
moving point, which the engine's static tangent already has for every
dead load (:func:`kernels.tangent.static_tangent_pass`).

Obstacles (world poses, or poses in the robot file's base frame made
world at load): plane (a point and its outward normal), sphere (centre,
radius), capsule (segment end points, radius).
"""

from dataclasses import dataclass, replace

import numpy as np

PLANE, SPHERE, CAPSULE, BOX = 0, 1, 2, 3
OBSTACLE_KINDS = {"plane": PLANE, "sphere": SPHERE, "capsule": CAPSULE, "box": BOX}


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A rigid obstacle. ``kind``: "plane", "sphere", "capsule" or "box";
    ``a``: a point of the plane, the sphere's centre, the capsule's first
    end or the box's centre [m, world]; ``b``: the plane's outward normal
    (unit) or the capsule's second end; ``radius`` [m] (sphere, capsule);
    ``rotation`` (3x3, world <- box axes) and ``half_size`` (3,) [m] of a
    box; ``stiffness``
    [N/m^2] per unit length of member and metre of penetration (None: the
    member's Young's modulus); ``smoothing`` [m] the depth eps over which
    the force law turns on (None: a tenth of the member's radius);
    ``damping``: Hunt-Crossley alpha [s/m] (dynamics); ``friction``:
    Coulomb coefficient mu (dynamics), regularised below ``stiction_velocity``
    [m/s] (:func:`friction_force`). Checked at the door
    (:func:`soft_twin_core.robot.obstacles.obstacles_from_list`)."""
    name: str
    kind: str
    a: np.ndarray
    b: np.ndarray = None
    radius: float = 0.0
    stiffness: float = None
    smoothing: float = None
    damping: float = 0.0
    friction: float = 0.0
    stiction_velocity: float = 1e-4
    rotation: np.ndarray = None
    half_size: np.ndarray = None


@dataclass(frozen=True, eq=False)
class ContactPoints:
    """Contact points of the soft members: on soft joint ``joint`` at
    abscissa ``x`` [m] (a tree's point), standing for a length ``weight``
    [m] of member, circle radius ``radius`` [m], the member's Young's
    modulus ``modulus`` [Pa] (the default contact stiffness), its member's
    name and arc length ``s`` [m]."""
    joint: np.ndarray
    x: np.ndarray
    weight: np.ndarray
    radius: np.ndarray
    modulus: np.ndarray
    member: tuple
    s: np.ndarray

    def __len__(self):
        return len(self.joint)


def moved(ob, delta):
    """The obstacle translated by delta (3,) [m] (a scenario's trajectory)."""
    delta = np.asarray(delta, dtype=float)
    return replace(ob, a=ob.a + delta, b=ob.b + delta if ob.kind == "capsule" else ob.b)


def sample_path(path, spacing):
    """(joint, x, s, weight) of contact points along a tree path: the
    midpoints of ceil(L / spacing) equal intervals, each standing for its
    interval (the midpoint rule)."""
    n = max(1, int(np.ceil(path.length / spacing - 1e-9)))
    w = path.length / n
    s = (np.arange(n) + 0.5) * w
    j, x = path.locate(s)
    return np.asarray(j, np.int64), np.asarray(x, float), s, np.full(n, w)


def normal_force_density(delta, k, eps):
    """(f, df/ddelta) of the penalty law (module docstring) [N/m, N/m^2]."""
    delta = np.asarray(delta, dtype=float)
    f = np.where(delta <= 0, 0.0, np.where(delta < eps, 0.5 * k * delta ** 2 / eps, k * (delta - 0.5 * eps)))
    df = np.where(delta <= 0, 0.0, np.where(delta < eps, k * delta / eps, k))
    return f, df


def normal_potential_density(delta, k, eps):
    """Phi(delta) = integral of f from 0 to delta [N]: the penalty's
    stored energy per unit length of member."""
    delta = np.asarray(delta, dtype=float)
    return np.where(delta <= 0, 0.0, np.where(delta < eps, k * delta ** 3 / (6 * eps),
                                               k * (delta ** 2 / 2 - eps * delta / 2 + eps ** 2 / 6)))


def discrete_gradient(delta0, delta1, k, eps):
    """(fbar, d fbar / d delta1): the mean force over a step from
    penetration delta0 to delta1, ``(Phi(delta1) - Phi(delta0)) / (delta1 -
    delta0)``. A step with this force does on the member the work its
    stored energy changes by, so an implicit midpoint step does not pump
    energy into a contact (with f at the midpoint it does: the penalty is
    stiff and nonlinear). Both ends in one branch of the law: the quotient
    in closed form (no cancellation as delta1 -> delta0): k (d0^2 + d0 d1
    + d1^2) / (6 eps) on the quadratic branch, k ((d0 + d1) - eps) / 2 on
    the linear one, 0 outside."""
    d0, d1 = np.broadcast_arrays(np.asarray(delta0, float), np.asarray(delta1, float))
    k, eps = np.broadcast_to(k, d0.shape), np.broadcast_to(eps, d0.shape)
    dd = d1 - d0
    safe = np.where(dd == 0.0, 1.0, dd)
    f1, _ = normal_force_density(d1, k, eps)
    quotient = (normal_potential_density(d1, k, eps) - normal_potential_density(d0, k, eps)) / safe
    quad = (d0 > 0) & (d1 > 0) & (d0 < eps) & (d1 < eps)
    lin = (d0 >= eps) & (d1 >= eps)
    out = (d0 <= 0) & (d1 <= 0)
    fbar = np.where(quad, k * (d0 * d0 + d0 * d1 + d1 * d1) / (6 * eps),
                    np.where(lin, 0.5 * k * (d0 + d1 - eps), np.where(out, 0.0, quotient)))
    dfbar = np.where(quad, k * (d0 + 2 * d1) / (6 * eps),
                     np.where(lin, 0.5 * k, np.where(out, 0.0, (f1 - quotient) / safe)))
    return fbar, dfbar


def signed_distance(ob, p):
    """(d (P,), n (P, 3), H (P, 3, 3)): signed distance of points p (P, 3)
    from the obstacle's surface (> 0 outside), its gradient (the outward
    normal) and its Hessian."""
    P = p.shape[0]
    if ob.kind == "plane":
        n = np.broadcast_to(ob.b, (P, 3)).copy()
        return (p - ob.a) @ ob.b, n, np.zeros((P, 3, 3))
    if ob.kind == "box":
        return _box_distance(ob, p)
    if ob.kind == "sphere":
        c = np.broadcast_to(ob.a, (P, 3))
        axis = None
    elif ob.kind == "capsule":
        ab = ob.b - ob.a
        L2 = float(ab @ ab)
        t = np.clip((p - ob.a) @ ab / L2, 0.0, 1.0)
        c = ob.a + t[:, None] * ab
        axis = np.where(((t > 0) & (t < 1))[:, None], ab / np.sqrt(L2), 0.0)
    else:
        raise ValueError(f"obstacle {ob.name!r}: unknown kind {ob.kind!r}")
    r = p - c
    dist = np.linalg.norm(r, axis=1)
    dist_safe = np.maximum(dist, 1e-300)
    n = r / dist_safe[:, None]
    proj = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    if axis is not None:
        proj = proj - axis[:, :, None] * axis[:, None, :]
    return dist - ob.radius, n, proj / dist_safe[:, None, None]


def _box_distance(ob, p):
    """Signed distance of points from a box, its gradient and Hessian: in
    the box's axes, with e = |p| - h per axis, outside ``|max(e, 0)|`` (to
    a face, an edge or a corner: Hessian ``(A - n n^T) / d`` with A the
    projector on the axes where e > 0), inside ``max(e)`` (to the nearest
    face: Hessian 0)."""
    R, h = ob.rotation, ob.half_size
    loc = (p - ob.a) @ R
    e = np.abs(loc) - h
    sgn = np.where(loc < 0, -1.0, 1.0)
    out_e = np.maximum(e, 0.0)
    d_out = np.linalg.norm(out_e, axis=1)
    outside = d_out > 0
    k = np.argmax(e, axis=1)
    P = p.shape[0]
    n_loc = np.zeros((P, 3))
    n_loc[np.arange(P), k] = sgn[np.arange(P), k]                 # inside: the nearest face's normal
    safe = np.where(outside, d_out, 1.0)
    n_loc = np.where(outside[:, None], sgn * out_e / safe[:, None], n_loc)
    d = np.where(outside, d_out, e[np.arange(P), k])
    active = (e > 0).astype(float)
    H_loc = (active[:, :, None] * np.eye(3)[None] - n_loc[:, :, None] * n_loc[:, None, :]) / safe[:, None, None]
    H_loc = np.where(outside[:, None, None], H_loc, 0.0)
    return d, n_loc @ R.T, R[None] @ H_loc @ R.T[None]


@dataclass
class ContactState:
    """The contacts at a configuration: for every (point, obstacle) pair in
    contact, the point index, obstacle index, world position p [m] of the
    backbone point, outward normal n, gap = d - r [m] (< 0: pressed in),
    force F (3,) [N] on the member (world), its derivative dF/dp (3, 3)
    [N/m] (the damping factor held) and dF/dv (3, 3) [N s/m] (zero
    without damping)."""
    point: np.ndarray
    obstacle: np.ndarray
    p: np.ndarray
    normal: np.ndarray
    gap: np.ndarray
    force: np.ndarray
    dF_dp: np.ndarray
    dF_dv: np.ndarray = None
    moment: np.ndarray = None        # (n, 3) [N m] about the backbone point (friction at the surface)
    slip: np.ndarray = None          # (n, 3) [m/s] tangential velocity of the backbone point

    def __len__(self):
        return len(self.point)


def contact_forces(points, obstacles, p):
    """:class:`ContactState` of the contact points (:class:`ContactPoints`)
    at rest at world positions p (P, 3) against ``obstacles`` (statics; a
    time step's: :func:`step_contact_forces`): every pair with a positive
    force (penetration) is listed."""
    idx, obs, ps, ns, gaps, Fs, dFs, dVs = [], [], [], [], [], [], [], []
    for o, ob in enumerate(obstacles):
        d, n, H = signed_distance(ob, p)
        delta = points.radius - d
        hit = np.flatnonzero(delta > 0)
        if not len(hit):
            continue
        k = points.modulus[hit] if ob.stiffness is None else np.full(len(hit), ob.stiffness)
        eps = 0.1 * points.radius[hit] if ob.smoothing is None else np.full(len(hit), ob.smoothing)
        f, df = normal_force_density(delta[hit], k, eps)
        w = points.weight[hit]
        nh = n[hit]
        dVs.append(np.zeros((len(hit), 3, 3)))
        idx.append(hit)
        obs.append(np.full(len(hit), o))
        ps.append(p[hit])
        ns.append(nh)
        gaps.append(-delta[hit])
        Fs.append((w * f)[:, None] * nh)
        dFs.append(w[:, None, None] * (-df[:, None, None] * nh[:, :, None] * nh[:, None, :]
                                      + f[:, None, None] * H[hit]))
    return _stacked(idx, obs, ps, ns, gaps, Fs, dFs, dVs)


def step_contact_forces(points, obstacles, p0, p1, pt, h, theta, v0=None, obstacles0=None):
    """:class:`ContactState` of a time step from positions p0 to p1 (P, 3),
    the forces acting at pt (the step's theta point): the normal force is
    the :func:`discrete_gradient` of the penetrations at the two ends, along
    the normal at pt, with the Hunt-Crossley factor of the step's mean
    penetration rate ``(delta1 - delta0) / h``. dF/dp and dF/dv are taken
    through the end point (``dq1 = dq_t / theta`` in Newton's update).
    Friction acts against the slip at the end of the step, ``((p1 - p0) / h
    - (1 - theta) v0) / theta`` (v0: the points' velocities at the step's
    start; None: at rest), as implicit Euler would: regularised friction is
    a very stiff damper (mu F_n / v_s), which the midpoint rule would let
    ring from step to step instead of damping it. ``obstacles0``: where
    the obstacles were at the step's start (moving obstacles: the
    penetration at the start is against them, the slip relative to their
    translation over the step; None: they do not move)."""
    idx, obs, ps, ns, gaps, Fs, dFs, dVs, Ms, Vs = [], [], [], [], [], [], [], [], [], []
    r = points.radius
    for o, ob in enumerate(obstacles):
        ob0 = ob if obstacles0 is None else obstacles0[o]
        d0, _, _ = signed_distance(ob0, p0)
        d1, _, _ = signed_distance(ob, p1)
        hit = np.flatnonzero((r - d0 > 0) | (r - d1 > 0))
        if not len(hit):
            continue
        dt_, n, H = signed_distance(ob, pt[hit])
        k = points.modulus[hit] if ob.stiffness is None else np.full(len(hit), ob.stiffness)
        eps = 0.1 * r[hit] if ob.smoothing is None else np.full(len(hit), ob.smoothing)
        delta0, delta1 = r[hit] - d0[hit], r[hit] - d1[hit]
        fbar, dfbar = discrete_gradient(delta0, delta1, k, eps)
        rate = (delta1 - delta0) / h
        fac = np.maximum(1.0 + ob.damping * rate, 0.0)
        w = points.weight[hit]
        idx.append(hit)
        obs.append(np.full(len(hit), o))
        ps.append(pt[hit])
        ns.append(n)
        gaps.append(dt_ - r[hit])
        fn = w * fac * fbar
        nn = n[:, :, None] * n[:, None, :]
        dF = (w * fac)[:, None, None] * (-(dfbar / theta)[:, None, None] * nn + fbar[:, None, None] * H)
        dv = np.where(fac > 0, ob.damping, 0.0)
        dV = -(w * fbar * dv)[:, None, None] * nn
        vel = (p1[hit] - p0[hit]) / h
        if v0 is not None:
            vel = (vel - (1.0 - theta) * v0[hit]) / theta          # the end of the step's
        if ob0 is not ob:
            vel = vel - (ob.a - ob0.a) / h                        # relative to the obstacle's surface
        slip = vel - np.sum(vel * n, axis=1)[:, None] * n
        F = fn[:, None] * n
        M = np.zeros((len(hit), 3))
        if ob.friction > 0:
            Ft, dFt = friction_force(fn, slip, ob.friction, ob.stiction_velocity)
            F = F + Ft
            M = np.cross(-r[hit][:, None] * n, Ft)            # applied at the surface, not the backbone
            dV = dV + dFt @ (np.eye(3)[None] - nn) / theta   # slip = (I - n n^T) v1; Newton's matrix has theta Dt
            # friction grows with the normal force: dFt/dp = -mu (slip/s) dfn/dp^T, dfn/dp = -w fac fbar'/theta n
            unit = Ft / np.maximum(fn, 1e-300)[:, None]       # -mu slip / s
            dF = dF - unit[:, :, None] * ((w * fac * dfbar / theta)[:, None] * n)[:, None, :]
        dFs.append(dF)
        Fs.append(F)
        dVs.append(dV)
        Ms.append(M)
        Vs.append(slip)
    return _stacked(idx, obs, ps, ns, gaps, Fs, dFs, dVs, Ms, Vs)


def friction_force(fn, vt, mu, v_s):
    """(F (P, 3), dF/dvt (P, 3, 3)): regularised Coulomb friction on points
    slipping at tangential velocities vt (P, 3) under normal forces fn (P,)
    [N]: ``F = -mu fn vt / sqrt(|vt|^2 + v_s^2)``. Below the stiction
    velocity v_s it acts as a steep viscous law: a tangential load T <
    mu fn is held with a creep ``v = v_s t / sqrt(1 - t^2)``, t = T / (mu
    fn) (at t = 1/2, 0.58 v_s)."""
    s = np.sqrt(np.sum(vt * vt, axis=1) + v_s * v_s)
    c = mu * fn / s
    F = -c[:, None] * vt
    dF = -c[:, None, None] * (np.eye(3)[None] - vt[:, :, None] * vt[:, None, :] / (s * s)[:, None, None])
    return F, dF


def _stacked(idx, obs, ps, ns, gaps, Fs, dFs, dVs, Ms=None, Vs=None):
    if not idx:
        z = np.zeros(0)
        return ContactState(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), z,
                            np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
    return ContactState(np.concatenate(idx), np.concatenate(obs), np.concatenate(ps), np.concatenate(ns),
                        np.concatenate(gaps), np.concatenate(Fs), np.concatenate(dFs), np.concatenate(dVs),
                        np.concatenate(Ms) if Ms else None, np.concatenate(Vs) if Vs else None)
