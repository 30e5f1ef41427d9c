"""Fourth-order Magnus kinematics of a variable-strain rod, in statics and
dynamics: the study's path (issue 28) and the reference of the robot
file's steps (:mod:`soft_twin_core.robot.strain_bases`: the midpoint step;
``magnus: 4``, :mod:`soft_twin_core.robot.soft_chain`: the commutator-free
fourth-order step, equal to :func:`commutator_free_field` to round-off).

A rod's strain field ``xi(X) = f0 + Phi(X) z`` (every strain mode a
Legendre series of order p, the coefficients z the coordinates) is sampled
at the rod's Gauss points, two in each of its n sections,
``X_g = X_k + h_k (1/2 -+ sqrt(3)/6)`` with weights ``h_k / 2``:

- **Kinematics.** From a point to the next (the base, the Gauss points,
  the tip: 2n + 1 intervals), the pose advances by the fourth-order Magnus
  step of the field (Zanna collocation at the interval's own two Gauss
  points Y_1 < Y_2),

      Omega = d/2 (xi(Y_1) + xi(Y_2)) + sqrt(3) d^2 / 12 [xi(Y_1), xi(Y_2)],

  for the body-frame ODE g' = g xi^ ([a, b] = ad(a) b; the left ODE,
  Y' = A Y, has the opposite sign). In the engine each interval is a
  massless soft section of constant strain ``Omega / d``: the
  configuration q(z) is quadratic in z (:meth:`Magnus4Field.q`), with
  Jacobian J(z) and convective term ``Jdot zdot`` in closed form.
- **Inertia and gravity.** The rod's mass sits at its Gauss points (a
  fixed joint carrying ``h_k / 2`` of the section's inertia density after
  each interval but the last): 2-point Gauss quadrature of the kinetic
  energy, the gravity potential and the loads along the rod, at points
  whose poses are fourth order. (On the sections' constant-strain arcs,
  as the engine's own sections carry it, gravity falls back to second
  order: the points inside an arc are only second order.)
- **Elasticity.** The field's own energy, ``K_z = int Phi^T K Phi dX``
  (and ``D_z``), integrated exactly (Gauss-Legendre with order + 1 points
  a section), not the sections'. (With the Gauss points' own 2-point rule,
  a basis with nearly as many functions as Gauss points has directions of
  too little stiffness for the kinematics at the intervals' points: order
  6 on 4 sections was 900x less accurate under a tip force.)

Every generalised force then follows by the chain rule through the engine's
passes on this tree: inverse dynamics ``J^T ID(q(z), J zdot, J zddot + Jdot
zdot) + K_z z + D_z zdot``, mass matrix ``J^T M(q(z)) J``. The error falls
at fourth order in the sections, in statics under gravity, in the natural
frequencies and in a transient (``test_magnus4.py``;
``benchmarks/magnus4_dynamics.py`` against the second-order step).

:func:`commutator_free_field` is the same step with each
interval two sections whose strains are linear in the field (the
commutator-free fourth-order method): then q = q0 + B z with a constant B,
the form every solver of the robot takes.

:class:`LinearField` is the second-order step in the same form (``q = q0 +
B z`` on the engine's own sections, :func:`strain_basis.legendre_basis`),
so the two share :func:`simulate` and :func:`modal_frequencies`.
"""

import numpy as np
from scipy.linalg import eigh

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.joint_kinds import SOFT
from soft_twin_core.engine.multibody import ModelBuilder, SoftSection
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError
from soft_twin_core.lie import ad
from soft_twin_core.robot.mechanism import Mechanism, Member, PointRef
from soft_twin_core.robot.soft_chain import field_energy
from soft_twin_core.robot.strain_bases import CF_WEIGHTS, GAUSS2, MAX_ORDER, StrainBasis, global_values
from soft_twin_core.solve.constrained import dense_stiffness_damping, free_problem, make_inputs

C4 = np.sqrt(3.0) / 12.0         # the commutator's coefficient in Omega / d


def _rod(mech):
    """(its soft sections, their lengths [m]) of a rod: one soft member, the
    tree nothing but its consecutive sections without offsets between them,
    every strain mode free, one reference strain, the exponential map;
    ValueError naming what is not so. (The study takes rods only: not a
    physical limit, but the engine tree of one member rebuilt here; trees
    and closed chains get the fourth order when the robot's construction
    does this per segment, the open item of issue 28.)"""
    tree = mech.tree
    js = tree.soft_joints
    if len(js) != tree.n_joints or len(tree.paths) != 1 or list(tree.paths[0].joints) != list(js):
        raise ValueError("Magnus4Field: expected a rod (one soft member, no rigid joints or branches)")
    secs = [tree.joints[j].section for j in js]
    for k, j in enumerate(js[1:], 1):
        if not np.allclose(tree.joints[j].placement, np.eye(4)) or tree.joints[j].parent != js[k - 1]:
            raise ValueError(f"Magnus4Field: section {k} has a rigid offset after section {k - 1}; the field "
                             f"is continuous along a rod without offsets")
    for s in secs:
        if list(s.modes) != list(range(6)):
            raise ValueError("Magnus4Field: the rod must have every strain mode free (free_modes: all): the "
                             "commutator reaches them all")
        if s.kinematic_map != "exponential":
            raise ValueError(f"Magnus4Field: kinematic_map must be 'exponential' (the Magnus step is the "
                             f"exponential's), got {s.kinematic_map!r}")
        if not np.allclose(s.f0, secs[0].f0):
            raise ValueError("Magnus4Field: the sections must share their reference strain f0")
    return secs, np.array([s.length for s in secs])


class _Field:
    """What every field shares: an engine rod ``mech`` / ``tree`` (its last
    joint the tip) with a workspace ``ws``, the map ``q(z)`` with its
    ``jacobian``, the field's stiffness ``K_z`` (nz, nz), and the statics
    in z by the principle of virtual work."""

    def tip(self, z):
        """The tip's world pose (4, 4) at z."""
        return alg.forward_kinematics(self.tree, self.ws, self.q(z))[1][-1].copy()

    def curvature(self, r):
        """``sum_k r_k d^2 q_k / dz^2`` (nz, nz): zero for a linear map."""
        return np.zeros((self.nz, self.nz))

    def problem(self, loads=None):
        """The engine's equilibrium problem of :attr:`mech` under ``loads``
        (:class:`engine.loads.Loads`; default gravity)."""
        return free_problem(self.mech, make_inputs(self.mech, loads=loads))

    def _forces(self, pb, q):
        """R(q) without the sections' own elasticity (the field's is K_z)."""
        return pb.residual(q) - pb.K @ (q - self.q0)

    def residual(self, pb, z):
        """The principle of virtual work in z, ``J^T (R(q(z)) - K (q -
        q0)) + K_z z``: the sections' elastic forces replaced by the
        field's (``pb``: :meth:`problem`'s)."""
        q = self.q(z)
        return self.jacobian(z).T @ self._forces(pb, q) + self.K_z @ z

    def tangent(self, pb, z):
        """d(residual)/dz, analytic: ``J^T (K_t - K) J + K_z`` plus
        :meth:`curvature` against the forces."""
        q = self.q(z)
        J = self.jacobian(z)
        return J.T @ (pb.tangent(q) - pb.K) @ J + self.K_z + self.curvature(self._forces(pb, q))


class _GaussRod(_Field):
    """A rod's Legendre strain field of order ``order`` (every mode) sampled
    at its Gauss points, on the engine's rod of the field (module
    docstring): ``parts`` massless, stiffless sections an interval between
    the points, the mass at them, the field's own energy. ``mech``: the rod
    on n sections (the quadrature's; at least (order + 2) // 2 of them).
    Attributes: ``mech`` that engine rod (its frame ``tip``), ``nz`` the
    coordinates, ``K_z``, ``D_z`` the field's stiffness and damping (nz,
    nz), per interval its length ``d`` and the basis at its two Gauss
    points ``P1``, ``P2`` (I, 6, nz), ``rows`` its sections' coordinates in q."""

    def __init__(self, mech, order, parts):
        if not (isinstance(order, (int, np.integer)) and 0 <= order <= MAX_ORDER):
            raise ValueError(f"order: expected an integer in [0, {MAX_ORDER}], got {order!r}")
        secs, h = _rod(mech)
        n, L = len(secs), float(h.sum())
        if order + 1 > 2 * n:
            raise ValueError(f"Magnus4Field: member {mech.tree.paths[0].name!r} has {2 * n} Gauss points for "
                             f"the basis's {order + 1} functions a mode, which they cannot tell apart (a singular "
                             f"Newton matrix); give it at least {(order + 2) // 2} sections")
        self.order, self.nz, self.length = order, 6 * (order + 1), L
        self.f0 = np.asarray(secs[0].f0, float)
        start = np.concatenate([[0.0], np.cumsum(h)[:-1]])
        xg = np.ravel(np.column_stack([start + (0.5 - GAUSS2) * h, start + (0.5 + GAUSS2) * h]))
        wg = np.repeat(0.5 * h, 2)
        owner = np.repeat(np.arange(n), 2)
        knots = np.concatenate([[0.0], xg, [L]])
        self.mech = self._lumped(mech, secs, knots, wg, owner, parts)
        self.tree = self.mech.tree
        self.q0 = self.tree.q0.copy()
        iv = [self.tree.idx_v[j] for j in self.tree.soft_joints]
        d = np.diff(knots)
        self.d = d
        self.rows = np.ravel(np.array(iv)[:, None] + np.arange(6))        # each section's 6 coordinates in q
        self.P1 = np.array([self.basis(a + (0.5 - GAUSS2) * w) for a, w in zip(knots[:-1], d)])   # (I, 6, nz)
        self.P2 = np.array([self.basis(a + (0.5 + GAUSS2) * w) for a, w in zip(knots[:-1], d)])
        self.K_z, self.D_z = field_energy(StrainBasis("legendre", (order,) * 6), h,      # exact, the field's own
                                          [np.asarray(s.K, float) for s in secs],
                                          [np.asarray(s.D, float) for s in secs], np.arange(6))
        self.ws = Workspace(self.tree)

    def basis(self, X):
        """Phi(X) (6, nz): the field's basis at arc length X [m] (column
        a (order + 1) + j: mode a, Legendre P_j(2 X / L - 1))."""
        vals = global_values("legendre", self.order, np.array([X / self.length]))[:, 0]
        P = np.zeros((6, self.nz))
        for a in range(6):
            P[a, a * (self.order + 1):(a + 1) * (self.order + 1)] = vals
        return P

    @staticmethod
    def _lumped(mech, secs, knots, wg, owner, parts):
        """The engine's rod of the field: ``parts`` massless, stiffless soft
        sections of equal length per interval between ``knots``, a fixed
        joint after each interval but the last carrying ``wg[g]`` times its
        section's inertia density."""
        tree = mech.tree
        b = ModelBuilder(tree.name + "_magnus4", tree.gravity)
        zero = np.zeros((6, 6))
        parent, js = -1, []
        for k, d in enumerate(np.diff(knots)):
            sec = SoftSection(float(d) / parts, zero, zero, zero, secs[0].f0, np.ones(6, bool), "exponential", 1)
            for part in range(parts):
                parent = b.add_joint(f"interval_{k}_{part}", "soft", parent,
                                     tree.joints[0].placement if parent < 0 else None, section=sec)
                js.append(parent)
            if k < len(wg):
                mc = np.asarray(secs[owner[k]].Mc, float)
                mc = np.diag(mc) if mc.ndim == 1 else mc
                parent = b.add_joint(f"gauss_{k}", "fixed", parent, inertia=wg[k] * mc)
        b.add_path("backbone", js)
        t = b.build()
        return Mechanism(t.name, t, ("",) * t.n_joints, (), (Member("backbone", 0, tuple(js), (None,) * len(js)),),
                         (), {"tip": PointRef(js[-1], t.joints[js[-1]].section.length)}, "fixed",
                         base_pose=np.array(mech.base_pose, float))

class Magnus4Field(_GaussRod):
    """The rod's field with fourth-order Magnus kinematics (module
    docstring): each interval one section of strain ``Omega / d``, so
    ``q(z)`` is quadratic in z. ``mech``, ``order``: as :class:`_GaussRod`.
    For the constant-B form see :func:`commutator_free_field`."""

    def __init__(self, mech, order):
        super().__init__(mech, order, 1)

    def _ends(self, z):
        """The field at every interval's two Gauss points, (I, 6) each."""
        return self.f0 + self.P1 @ z, self.f0 + self.P2 @ z

    def q(self, z):
        """The engine's coordinates at z: each interval's strain Omega / d
       ."""
        x1, x2 = self._ends(z)
        q = self.q0.copy()
        q[self.rows] = (0.5 * (x1 + x2) + C4 * self.d[:, None] * np.einsum("iab,ib->ia", ad(x1), x2)).ravel()
        return q

    def jacobian(self, z):
        """dq/dz (nv, nz) at z."""
        x1, x2 = self._ends(z)
        J = np.zeros((len(self.q0), self.nz))
        J[self.rows] = (0.5 * (self.P1 + self.P2) + C4 * self.d[:, None, None]
                        * (ad(x1) @ self.P2 - ad(x2) @ self.P1)).reshape(-1, self.nz)
        return J

    def convective(self, z, zd):
        """``Jdot zdot`` (nv): q's acceleration at zddot = 0, ``2 c d [Phi_1
        zdot, Phi_2 zdot]`` per interval (q is quadratic in z)."""
        out = np.zeros(len(self.q0))
        out[self.rows] = (2 * C4 * self.d[:, None] * np.einsum("iab,ib->ia", ad(self.P1 @ zd),
                                                               self.P2 @ zd)).ravel()
        return out

    def curvature(self, r):
        """``sum_k r_k d^2 q_k / dz^2`` (nz, nz): the commutator's second
        derivative against the generalised forces r (nv) on the intervals,
        ``-c d (X + X^T)``, ``X_jk = r^T ad(Phi2_j) Phi1_k`` (Phi2_j: column
        j of Phi_2; from ``ad(a) b = -ad(b) a``)."""
        ri = r[self.rows].reshape(-1, 6) * (C4 * self.d)[:, None]
        X = np.einsum("ia,iajb,ibk->jk", ri, self._ad_columns(self.P2), self.P1)
        return -(X + X.T)

    @staticmethod
    def _ad_columns(P):
        """(I, 6, nz, 6): ``ad`` of each column of each interval's P."""
        return np.moveaxis(ad(np.swapaxes(P, 1, 2)), 1, 2)


class LinearField(_Field):
    """A field whose map is linear, ``q = q0 + B z``: the robot file's
    second-order step on the engine's own sections (each the field at its
    midpoint, the mass on its arc; B e.g. :func:`strain_basis.legendre_basis`,
    ``K_z = B^T K B`` by default), or :func:`commutator_free_field`'s
    (``K_z``, ``D_z`` the field's own, its sections stiffless)."""

    def __init__(self, mech, B, K_z=None, D_z=None):
        self.mech, self.tree = mech, mech.tree
        self.B = np.asarray(B, float)
        self.q0, self.nz = self.tree.q0.copy(), self.B.shape[1]
        K, D = dense_stiffness_damping(self.tree)
        self.K_z = self.B.T @ K @ self.B if K_z is None else np.asarray(K_z, float)
        self.D_z = self.B.T @ D @ self.B if D_z is None else np.asarray(D_z, float)
        self.ws = Workspace(self.tree)

    def q(self, z):
        return self.q0 + self.B @ z

    def jacobian(self, z):
        return self.B

    def convective(self, z, zd):
        return np.zeros(len(self.q0))


def commutator_free_field(mech, order):
    """The rod's field in the constant-B form (the form the robot's solvers
    take): each interval between the Gauss points two massless sections of
    length d/2 whose strains are linear in the field, ``2 (a1 xi(Y_1) + a2
    xi(Y_2))`` then ``2 (a2 xi(Y_1) + a1 xi(Y_2))``, a1, a2 = 1/4 +-
    sqrt(3)/6 (:data:`CF_WEIGHTS`): the commutator-free fourth-order Magnus
    method of two exponentials (Blanes and Moan, Applied Numerical
    Mathematics 56, 2006), whose product agrees with Omega's exponential to
    O(d^5) (the other order of the two factors only to O(d^3)). The mass
    at the Gauss points and the field's energy as :class:`Magnus4Field`'s.
    A :class:`LinearField`."""
    rod = _GaussRod(mech, order, 2)
    a1, a2 = CF_WEIGHTS
    halves = np.stack([2 * (a1 * rod.P1 + a2 * rod.P2), 2 * (a2 * rod.P1 + a1 * rod.P2)], axis=1)
    B = np.zeros((len(rod.q0), rod.nz))
    B[rod.rows] = halves.reshape(-1, rod.nz)                  # (interval, half, 6, nz) in the tree's order
    return LinearField(rod.mech, B, rod.K_z, rod.D_z)



def inverse_dynamics(field, z, zd, zdd, gravity=None):
    """The generalised forces in z, ``J^T ID(q, J zdot, J zddot + Jdot
    zdot) + K_z z + D_z zdot`` (ID: the engine's RNEA with gravity,
    without the sections' own elasticity)."""
    J = field.jacobian(z)
    tau = alg.rnea(field.tree, field.ws, field.q(z), J @ zd, J @ zdd + field.convective(z, zd),
                   gravity=gravity, elastic=False)
    return J.T @ tau + field.K_z @ z + field.D_z @ zd


def mass_matrix(field, z):
    """``J^T M(q(z)) J`` (nz, nz), M by the engine's CRBA."""
    J = field.jacobian(z)
    return J.T @ alg.crba(field.tree, field.ws, field.q(z)) @ J


def energy(field, z, zd):
    """Kinetic + elastic + gravity energy [J] of a state: ``zd^T M_z zd / 2
    + z^T K_z z / 2 - sum m g . p`` over the tree's mass points (the rigid
    bodies' centres of mass, the sections' quadrature points)."""
    tree, w = field.tree, field.ws.work
    g_in, g_out = alg.forward_kinematics(tree, field.ws, field.q(z))
    a = tree.arrays
    V = 0.0
    for i in range(tree.n_joints):
        if a.rigid_mass[i]:
            m, I = a.inertia[i, 0, 0], a.inertia[i]
            c = np.array([I[5, 1], I[3, 2], I[4, 0]]) / m              # the m hat(c) block: the centre of mass
            V -= m * tree.gravity @ (g_out[i][:3, :3] @ c + g_out[i][:3, 3])
        for p in range(a.npt[i] if tree.kinds[i] == SOFT else 0):
            V -= a.mc[i, 0] * a.pw[i, p] * tree.gravity @ (g_in[i] @ w.gp[i, p])[:3, 3]
    return 0.5 * zd @ mass_matrix(field, z) @ zd + 0.5 * z @ field.K_z @ z + V


def modal_frequencies(field, count=None):
    """The natural frequencies [Hz] of small vibrations about the straight
    rod (z = 0, no loads: an equilibrium): ``K_z x = w^2 M_z(0) x``."""
    w2 = eigh(field.K_z, mass_matrix(field, np.zeros(field.nz)), eigvals_only=True)
    f = np.sqrt(np.maximum(w2, 0.0)) / (2 * np.pi)
    return f if count is None else f[:count]


def simulate(field, duration, h, z0=None, zd0=None, *, theta=0.5, tol=1e-10, max_iterations=50, gravity=None,
             observe=None):
    """The field's motion from (z0, zd0) (default rest, straight) for
    ``duration`` [s] in steps h [s], by the engine's theta-method in z
    (:mod:`engine.integrators`: ``zd_t = (1 - theta) zd0 + theta zd1``,
    ``z_t = z0 + theta h zd_t``, ``z1 = z0 + h zd_t``, the inverse dynamics
    at (z_t, zd_t, (zd1 - zd0) / h) zero), Newton with the matrix ``M_z +
    theta h D_z + (theta h)^2 K_z`` at each step's start (with the loads'
    statics tangent in place of K_z: 7.22 iterations a step instead of
    7.24 over a 0.5 s swing at 10 ms, so not kept). Returns (z, zd, Newton
    iterations a step) at the end, and ``observe(z, zd)`` after each step
    (a list; empty without it); StaticsError when a step does not
    converge."""
    if not 0.5 <= theta <= 1.0:
        raise ValueError(f"theta: expected a value in [0.5, 1] (1/2 the midpoint rule, 1 implicit Euler), got {theta}")
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"h: expected a positive time step [s], got {h}")
    z, zd = (np.zeros(field.nz) if x is None else np.array(x, float) for x in (z0, zd0))
    for name, x in (("z0", z), ("zd0", zd)):
        if x.shape != (field.nz,) or not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: expected {field.nz} finite values (the field's coordinates), got shape "
                             f"{x.shape}")
    steps = int(round(duration / h))
    if steps < 1 or abs(steps * h - duration) > 1e-9 * duration:
        raise ValueError(f"duration: expected a whole number of steps h = {h} s, got {duration} s")
    total, seen = 0, []
    for _ in range(steps):
        A = mass_matrix(field, z + theta * h * zd) / h + theta * field.D_z + theta ** 2 * h * field.K_z
        v1 = zd.copy()
        scale = None
        for it in range(max_iterations):
            vt = (1 - theta) * zd + theta * v1
            r = inverse_dynamics(field, z + theta * h * vt, vt, (v1 - zd) / h, gravity)
            scale = scale or 1.0 + np.abs(r).max()
            if np.abs(r).max() <= tol * scale:
                break
            v1 = v1 - np.linalg.solve(A, r)
            total += 1
        else:
            raise StaticsError(f"Magnus-4 dynamics: no convergence in {max_iterations} iterations "
                               f"(|r| = {np.abs(r).max():.3g})")
        vt = (1 - theta) * zd + theta * v1
        z, zd = z + h * vt, v1
        if observe is not None:
            seen.append(observe(z, zd))
    return z, zd, total / steps, seen


def solve_magnus4(field, loads=None, z0=None, *, tol=1e-10, max_iterations=60, load_steps=1):
    """Equilibrium of a field (:class:`Magnus4Field`,
    :func:`commutator_free_field`'s) under ``loads``
    (:class:`engine.loads.Loads`; default gravity): Newton on its residual
    with its analytic tangent, the loads in ``load_steps`` steps. Returns
    (q on the field's ``mech``, z, iterations)."""
    pb = field.problem(loads)
    z = np.zeros(field.nz) if z0 is None else np.array(z0, dtype=float)
    total = 0
    for step in range(1, load_steps + 1):
        p = pb.scaled(step / load_steps) if load_steps > 1 else pb
        scale = 1.0 + np.abs(field.residual(p, np.zeros(field.nz))).max()
        for _ in range(max_iterations):
            r = field.residual(p, z)
            if np.abs(r).max() <= tol * scale:
                break
            dz = np.linalg.solve(field.tangent(p, z), -r)
            t, n0 = 1.0, np.linalg.norm(r)
            while t > 1e-4 and np.linalg.norm(field.residual(p, z + t * dz)) > (1 - 1e-4 * t) * n0:
                t *= 0.5
            z = z + t * dz
            total += 1
        else:
            raise StaticsError(f"Magnus-4 statics: no convergence in {max_iterations} iterations at load step "
                               f"{step}/{load_steps} (|r| = {np.abs(r).max():.3g})")
    return field.q(z), z, total
