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

from soft_twin_core.engine.kernels import contact as kc

PLANE, SPHERE, CAPSULE, BOX, MESH, TUBE = 0, 1, 2, 3, 4, 5
OBSTACLE_KINDS = {"plane": PLANE, "sphere": SPHERE, "capsule": CAPSULE, "box": BOX, "mesh": MESH, "tube": TUBE}


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A rigid obstacle. ``kind``: "plane", "sphere", "capsule", "box",
    "mesh" (closed, convex or not) or "tube" (the free space inside ``radius`` of the
    centre line ``path``, open at both ends: a lumen); ``a``: a point of the plane, the sphere's centre, the
    capsule's first end, the box's centre or the mesh's reference point
    (its vertices' mean) [m, world]; ``b``: the plane's outward normal
    (unit) or the capsule's second end; ``radius`` [m] (sphere, capsule);
    ``rotation`` (3x3, world <- box or mesh axes), ``half_size`` (3,) [m]
    of a box, ``triangles`` (T, 3, 3) [m] of a mesh (in its axes about a,
    counter-clockwise seen from outside); ``stiffness``
    [N/m^2] per unit length of member and metre of penetration (None: the
    member's Young's modulus); ``smoothing`` [m] the depth eps over which
    the force law turns on (None: a tenth of the member's radius);
    ``damping``: Hunt-Crossley alpha [s/m] (dynamics); ``friction``:
    Coulomb coefficient mu (dynamics, and statics from stick points:
    :func:`stick_friction`), regularised below ``stiction_velocity``
    [m/s] (:func:`friction_force`); ``torsional_friction`` mu_t [m]: the
    spin friction of a contact patch, a moment about the normal of at most
    mu_t F_n against the spin of the touching frame relative to the
    obstacle (dynamics; :func:`kernels.contact.spin_friction`; zero: none,
    the default). Checked at the door
    (:func:`soft_twin_core.robot.obstacles.obstacles_from_list`). ``body``: the
    joint whose output frame carries it (-1: the world); ``touches``: the
    names of the members (or links) whose contact points it touches (None:
    all), for the capsules along a member that other members touch;
    ``skips`` (member, s_lo, s_hi): a capsule on that member touched by the
    member's own points outside that arc window (self-contact)
    (:func:`soft_twin_core.robot.obstacles.member_capsules`)."""
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
    torsional_friction: float = 0.0
    rotation: np.ndarray = None
    half_size: np.ndarray = None
    triangles: np.ndarray = None     # a closed mesh: (T, 3, 3) [m] in its axes (rotation) about a, outward
    path: np.ndarray = None          # a tube's centre line: (N, 3) [m] in its axes (rotation) about a
    body: int = -1                   # a link's collision shape: its joint (a, b, rotation in its output frame)
    touches: tuple = None            # the members whose points it touches (None: every point)
    skips: tuple = None              # (member, s_lo, s_hi): its own member's points it touches outside [s_lo, s_hi]


@dataclass(frozen=True, eq=False)
class ContactPoints:
    """Contact points of the soft members and of the links' round
    collision shapes: on joint ``joint`` at abscissa ``x`` [m] (a tree's
    point; x < 0: the joint's output frame), ``offset`` (3,) [m] in that
    point's frame (zero on a member's backbone; a link's: the point of its
    shape's axis), standing for a length ``weight`` [m] of member or shape,
    circle (sphere) radius ``radius`` [m], the member's Young's modulus or
    the shape's stiffness ``modulus`` [Pa] (the default contact stiffness),
    its member's or link's name and arc length ``s`` [m] (0 on links)."""
    joint: np.ndarray
    x: np.ndarray
    weight: np.ndarray
    radius: np.ndarray
    modulus: np.ndarray
    member: tuple
    s: np.ndarray
    offset: np.ndarray = None

    def __post_init__(self):
        if self.offset is None:
            object.__setattr__(self, "offset", np.zeros((len(self.joint), 3)))

    def __len__(self):
        return len(self.joint)


def moved(ob, delta):
    """The obstacle translated by delta (3,) [m] (a scenario's trajectory)."""
    delta = np.asarray(delta, dtype=float)
    return replace(ob, a=ob.a + delta, b=ob.b + delta if ob.kind == "capsule" else ob.b)


def sample_path(path, spacing):
    """(joint, x, s, weight) of contact points along a tree path: the
    midpoints of ceil(L / spacing) equal intervals, each standing for its
    interval (the midpoint rule: a tip pressed head-on is felt from half an
    interval behind it)."""
    n = max(1, int(np.ceil(path.length / spacing - 1e-9)))
    w = path.length / n
    s = (np.arange(n) + 0.5) * w
    j, x = path.locate(s)
    return np.asarray(j, np.int64), np.asarray(x, float), s, np.full(n, w)


def _flat(*xs):
    """Broadcast, contiguous 1-D float copies of the arguments, and their shape."""
    arrs = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in xs))
    return [np.ascontiguousarray(x).ravel() for x in arrs], arrs[0].shape


def normal_force_density(delta, k, eps):
    """(f, df/ddelta) of the penalty law (module docstring) [N/m, N/m^2],
    element-wise (:func:`kernels.contact.penalty`)."""
    (d, k, e), shape = _flat(delta, k, eps)
    f, df, phi = np.empty(d.size), np.empty(d.size), np.empty(d.size)
    kc.penalty_arrays(d, k, e, f, df, phi)
    return f.reshape(shape), df.reshape(shape)


def normal_potential_density(delta, k, eps):
    """Phi(delta) = integral of f from 0 to delta [N]: the penalty's
    stored energy per unit length of member."""
    (d, k, e), shape = _flat(delta, k, eps)
    f, df, phi = np.empty(d.size), np.empty(d.size), np.empty(d.size)
    kc.penalty_arrays(d, k, e, f, df, phi)
    return phi.reshape(shape)


def discrete_gradient(delta0, delta1, k, eps):
    """(fbar, d fbar / d delta1): the mean force over a step from
    penetration delta0 to delta1, ``(Phi(delta1) - Phi(delta0)) / (delta1 -
    delta0)``. A step with this force does on the member the work its
    stored energy changes by, so an implicit midpoint step does not pump
    energy into a contact (with f at the midpoint it does: the penalty is
    stiff and nonlinear). Both ends in one branch of the law: the quotient
    in closed form (no cancellation as delta1 -> delta0): k (d0^2 + d0 d1
    + d1^2) / (6 eps) on the quadratic branch, k ((d0 + d1) - eps) / 2 on
    the linear one, 0 outside (:func:`kernels.contact.mean_force`)."""
    (d0, d1, k, e), shape = _flat(delta0, delta1, k, eps)
    fbar, dfbar = np.empty(d0.size), np.empty(d0.size)
    kc.mean_force_arrays(d0, d1, k, e, fbar, dfbar)
    return fbar.reshape(shape), dfbar.reshape(shape)


def signed_distance(ob, p):
    """(d (P,), n (P, 3), H (P, 3, 3)): signed distance of points p (P, 3)
    from the obstacle's surface (> 0 outside), its gradient (the outward
    normal) and its Hessian (:func:`kernels.contact.distance`: a plane; a
    sphere or capsule, ``(I - n n^T - t t^T) / |p - c|`` with c the nearest
    point of the centre or axis and t the axis inside the capsule's span; a
    box, in its axes with e = |p| - h per axis: outside ``|max(e, 0)|`` (to
    a face, an edge or a corner: Hessian ``(A - n n^T) / d`` with A the
    projector on the axes where e > 0), inside ``max(e)`` (to the nearest
    face: Hessian 0))."""
    p = np.ascontiguousarray(p, dtype=float)
    P = p.shape[0]
    d, n, H = np.empty(P), np.empty((P, 3)), np.empty((P, 3, 3))
    kc.distance_arrays(kc.obstacle_arrays((ob,)), 0, p, d, n, H)
    return d, n, H


@dataclass
class ContactState:
    """The contacts at a configuration: for every (point, obstacle) pair in
    contact, the point index, obstacle index, world position p [m] of the
    backbone point, outward normal n, gap = d - r [m] (< 0: pressed in),
    force F (3,) [N] on the member (world), its derivative dF/dp (3, 3)
    [N/m] (the damping factor held) and dF/dv (3, 3) [N s/m] (zero
    without damping): the normal force's, through the backbone point; the
    friction's, which acts at the contact surface (``-r n`` from the
    point), in dFf_dp and dFf_dv (:func:`kernels.contact.step_contacts`)."""
    point: np.ndarray
    obstacle: np.ndarray
    p: np.ndarray
    normal: np.ndarray
    gap: np.ndarray
    force: np.ndarray
    dF_dp: np.ndarray
    dF_dv: np.ndarray = None
    moment: np.ndarray = None        # (n, 3) [N m] about the contact point: the spin friction's (along the
    #                                  normal) and the moment of the friction at the surface, (-r n) x F_t
    slip: np.ndarray = None          # (n, 3) [m/s] tangential velocity of the contact surface's point
    body: np.ndarray = None          # (n,) the joint of the touched obstacle's body (-1: the world's)
    arm: np.ndarray = None           # (n, 3) [m] from the point's frame origin to the point (a link's offset)
    body_arm: np.ndarray = None      # (n, 3) [m] from the touched body's frame origin to the point
    spin: np.ndarray = None          # (n,) [rad/s] the point's frame's spin about the normal, relative
    dM_dw: np.ndarray = None         # (n,) [N m s] d(spin moment)/d(spin) / theta (zero without spin friction)
    dFf_dp: np.ndarray = None        # (n, 3, 3) [N/m] the friction's growth with the normal force, through p
    dFf_dv: np.ndarray = None        # (n, 3, 3) [N s/m] d(friction)/d(surface point's velocity) / theta
    dFf_dd: np.ndarray = None        # (n, 3, 3) [N/m] statics: d(friction)/d(surface point's displacement)
    radius: np.ndarray = None        # (n,) [m] the backbone point's distance from the surface, r

    def __len__(self):
        return len(self.point)


def contact_forces(points, obstacles, p, allowed=None, obs=None):
    """:class:`ContactState` of the contact points (:class:`ContactPoints`)
    at rest at world positions p (P, 3) against ``obstacles`` (statics; a
    time step's: :func:`step_contact_forces`): every ``allowed`` (P, O)
    pair (None: all) with a positive force (penetration) is listed
    (:func:`kernels.contact.rest_contacts`). ``obs``: the obstacles'
    arrays as posed (bodies' shapes; default: ``obstacles`` as given)."""
    p = np.ascontiguousarray(p, dtype=float)
    m = p.shape[0] * len(obstacles)
    out = _outputs(m)
    allowed = np.ones((p.shape[0], len(obstacles)), np.bool_) if allowed is None else allowed
    c = kc.rest_contacts(points.radius, points.modulus, points.weight, allowed,
                         kc.obstacle_arrays(obstacles) if obs is None else obs, p,
                         out["idx"], out["ob"], out["n"], out["gap"], out["F"], out["dF"])
    i = out["idx"][:c]
    return ContactState(i.copy(), out["ob"][:c].copy(), p[i], out["n"][:c].copy(), out["gap"][:c].copy(),
                        out["F"][:c].copy(), out["dF"][:c].copy(), np.zeros((c, 3, 3)),
                        radius=points.radius[i].copy())


def _outputs(m):
    return dict(idx=np.empty(m, np.int64), ob=np.empty(m, np.int64), n=np.empty((m, 3)), gap=np.empty(m),
                F=np.empty((m, 3)), dF=np.empty((m, 3, 3)), dV=np.empty((m, 3, 3)), dFf=np.empty((m, 3, 3)),
                dVf=np.empty((m, 3, 3)), M=np.empty((m, 3)),
                slip=np.empty((m, 3)), spin=np.empty(m), dW=np.empty(m))


def step_contact_forces(points, obstacles, p0, p1, pt, h, theta, v0=None, obstacles0=None, allowed=None,
                        posed=None, ovel0=None, spin=None):
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
    translation and rotation over the step; None: they do not move).
    ``allowed`` (P, O): the pairs that may touch (None: all); ``posed``:
    (obs0, obs1, obst), the obstacles' arrays at the step's start, end and
    theta point, for obstacles carried by the robot's bodies (they move
    with it), and ``ovel0`` (O, 6) their velocities at the step's start
    ([at a0; angular], NaN rows for the others). ``spin``: (R0, R1, w0),
    the points' frames' rotations (P, 3, 3) at the step's ends and angular
    velocities (P, 3) at its start, for torsional friction and for the
    friction at the contact surface (None: the points' frames do not
    turn; refused with torsional friction, or friction on an obstacle
    that moves). The pass: :func:`kernels.contact.step_contacts`."""
    p0, p1, pt = (np.ascontiguousarray(x, dtype=float) for x in (p0, p1, pt))
    if posed is not None:
        obs0, obs, obst = posed
        moving = np.array([ob.body >= 0 for ob in obstacles], np.bool_)
        if obstacles0 is not None:
            moving |= np.array([a is not b for a, b in zip(obstacles0, obstacles)], np.bool_)
    else:
        obs = obst = kc.obstacle_arrays(obstacles)
        moving = np.zeros(len(obstacles), np.bool_) if obstacles0 is None else np.array(
            [a is not b for a, b in zip(obstacles0, obstacles)], np.bool_)
        obs0 = obs if obstacles0 is None else kc.obstacle_arrays(obstacles0)
    m = p0.shape[0] * len(obstacles)
    out = _outputs(m)
    v = np.zeros_like(p0) if v0 is None else np.ascontiguousarray(v0, dtype=float)
    allowed = np.ones((p0.shape[0], len(obstacles)), np.bool_) if allowed is None else allowed
    if ovel0 is None:
        ovel0 = np.full((len(obstacles), 6), np.nan)
    if spin is None:
        if np.any(obs.torsion > 0) or np.any((obs.friction > 0) & moving):
            raise ValueError("spin: an obstacle has torsional friction, or moves with friction; give the "
                             "points' frames' rotations")
        eye = np.broadcast_to(np.eye(3), (p0.shape[0], 3, 3))
        spin = (eye, eye, np.zeros_like(p0))
    R0, R1, w0 = (np.ascontiguousarray(x, dtype=float) for x in spin)
    c = kc.step_contacts(points.radius, points.modulus, points.weight, allowed, obs, obs0, obst, moving,
                         np.ascontiguousarray(ovel0, float), p0, p1, pt, float(h),
                         float(theta), v, v0 is not None, R0, R1, w0, out["idx"], out["ob"], out["n"], out["gap"],
                         out["F"], out["dF"], out["dV"], out["dFf"], out["dVf"], out["M"], out["slip"], out["spin"],
                         out["dW"])
    i = out["idx"][:c]
    return ContactState(i.copy(), out["ob"][:c].copy(), pt[i], *(out[k][:c].copy() for k in
                                                                    ("n", "gap", "F", "dF", "dV", "M", "slip")),
                        spin=out["spin"][:c].copy(), dM_dw=out["dW"][:c].copy(), dFf_dp=out["dFf"][:c].copy(),
                        dFf_dv=out["dVf"][:c].copy(), radius=points.radius[i].copy())


def friction_force(fn, vt, mu, v_s):
    """(F (P, 3), dF/dvt (P, 3, 3)): regularised Coulomb friction on points
    slipping at tangential velocities vt (P, 3) under normal forces fn (P,)
    [N]: ``F = -mu fn vt / sqrt(|vt|^2 + v_s^2)``. Below the stiction
    velocity v_s it acts as a steep viscous law: a tangential load T <
    mu fn is held with a creep ``v = v_s t / sqrt(1 - t^2)``, t = T / (mu
    fn) (at t = 1/2, 0.58 v_s) (:func:`kernels.contact.friction`)."""
    fn = np.ascontiguousarray(fn, dtype=float)
    vt = np.ascontiguousarray(vt, dtype=float)
    F, dF = np.empty((len(fn), 3)), np.empty((len(fn), 3, 3))
    kc.friction_arrays(fn, vt, float(mu), float(v_s), F, dF)
    return F, dF


STICK_TIME = 1.0      # [s] statics' stick length: the stiction velocity times this time


def stick_friction(fn, d, mu, v_s):
    """(F (P, 3), dF/dd (P, 3, 3)): statics' friction on points displaced
    tangentially by d (P, 3) [m] from where they stick, under normal forces
    fn (P,) [N]: ``F = -mu fn tanh(|d| / l_s) d / |d|``, Coulomb's law
    smoothed over the stick length ``l_s = v_s STICK_TIME`` (0.1 mm at the
    default stiction velocity v_s): a tangential load T < mu fn is held
    with the points displaced ``l_s atanh(T / (mu fn))``; beyond mu fn they
    slide, the friction at mu fn (99.5 % of it at 3 l_s: so a stick point
    is dragged along 3 l_s behind a sliding point, and a load turned back
    takes up at most 6 l_s before the point slides back). A tanh, not the
    dynamics' ``|v| / sqrt(|v|^2 + v_s^2)`` (:func:`friction_force`),
    which needs 10 stick lengths for the same 99.5 %: statics has no
    time to creep over, only this take-up."""
    fn = np.asarray(fn, dtype=float)
    d = np.asarray(d, dtype=float).reshape(-1, 3)
    ls = v_s * STICK_TIME
    size = np.sqrt(np.einsum("ck,ck->c", d, d))
    x = size / ls
    small = x < 1e-4
    g = np.where(small, (1.0 - x * x / 3.0) / ls, np.tanh(x) / np.where(small, 1.0, size))   # tanh(x) / |d|
    u = d / np.where(small, 1.0, size)[:, None]
    radial = np.where(small, 0.0, 1.0 / np.cosh(np.minimum(x, 350.0)) ** 2 / ls - g)    # d(g |d|)/d|d| - g
    F = -(mu * fn * g)[:, None] * d
    uu = u[:, :, None] * u[:, None, :]
    dF = -(mu * fn)[:, None, None] * (g[:, None, None] * np.eye(3) + radial[:, None, None] * uu)
    return F, dF


def transition_step(slip, dslip, v_s):
    """The fraction alpha in (0, 1] of a Newton update to take so that no
    contact's friction jumps across its stiction zone: Castro et al.'s
    transition-aware line search (TAMSI: "A Transition-Aware Method for the
    Simulation of Compliant Contact with Regularized Friction", IEEE RA-L
    5(2), 2020), on slips ``slip`` (c, 3) [m/s] changing by ``dslip`` (c, 3)
    under the full update, stiction velocities ``v_s`` (c,). A contact
    sticking (``|slip| < v_s``) that the update would set sliding faster
    than 2 v_s stops there (past the regularised law's knee); one sliding
    that the update would turn past
    the origin (its slip reversed) stops where its path passes closest to
    it; any other change is taken whole. Without it a full Newton step
    flips a regularised friction, whose derivative along a fast slip is
    nearly zero, between fast slips of opposite signs."""
    slip, dslip = (np.ascontiguousarray(x, dtype=float).reshape(-1, 3) for x in (slip, dslip))
    return kc.transition_fractions(slip, dslip, np.ascontiguousarray(v_s, dtype=float).ravel())
