"""PCS equations of motion (slides part B "Dynamics"):

    M(q) qddot + C(q, qdot) qdot + D qdot + K (q - q0) = Q(q, t) + tau(q, u(t))

with, by Gauss quadrature over every section (same points everywhere, so the
semi-discrete system is exactly Lagrangian and conserves energy):

    M = int J^T Mc J ds
    C = int J^T (Mc Jdot + (Mc ad(eta) - ad(eta)^T Mc) J) ds,  eta = J qdot

(Mc: cross-section inertia density; the skew middle term makes Mdot - 2C
skew-symmetric; ``C qdot = int J^T (Mc Jdot qdot - ad(eta)^T Mc eta) ds`` is
the body-frame Newton-Euler bias). D and K are the generalised damping and
stiffness ``sum_i L_i B_i^T (D_i, K_i) B_i``; Q the external loads (gravity
included) and tau the actuation of :mod:`soft_twin_core.loads`.

These functions are the readable reference implementation of the chain;
the time integrators run on the multibody engine (recursive compiled
passes, tested against these and :mod:`soft_twin_core.reference`).
"""

import numpy as np

from . import kinematics as kin
from .integrators import StepInfo  # noqa: F401  (re-exported: Simulator.step returns it)
from . import lie
from .loads import Loads, actuation_force, gauss_points, generalized_external_force, load_points
from .statics import actuation_vector, base_reaction


def _quadrature(model):
    s, w, sec = gauss_points(model)
    Mc = np.array([model.sections[i].M for i in sec])
    return s, w, Mc


def mass_matrix(model, q):
    """Generalised mass matrix M(q) (n_dof, n_dof), symmetric positive definite."""
    s, w, Mc = _quadrature(model)
    J = kin.jacobian(model, q, s)
    return np.einsum("p,pai,pab,pbj->ij", w, J, Mc, J)


def coriolis_matrix(model, q, qdot):
    """C(q, qdot) (n_dof, n_dof) with Mdot - 2C skew-symmetric."""
    s, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    A = lie.ad(eta)
    Mid = Mc @ A - np.swapaxes(A, -1, -2) @ Mc
    return np.einsum("p,pai,paj->ij", w, J, Mc @ Jdot + Mid @ J)


def bias_force(model, q, qdot):
    """C(q, qdot) qdot = int J^T (Mc Jdot qdot - ad(eta)^T Mc eta) ds."""
    s, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    acc = np.einsum("pij,j->pi", Jdot, qdot)
    h = np.einsum("pab,pb->pa", Mc, acc) - np.einsum("pba,pb->pa", lie.ad(eta), np.einsum("pab,pb->pa", Mc, eta))
    return np.einsum("p,pai,pa->i", w, J, h)


def applied_force(model, q, qdot, u, loads):
    """Everything but inertia: Q_ext + tau_act - K (q - q0) - D qdot."""
    ch = kin.chain(model, q)
    Q, _ = generalized_external_force(model, ch, loads)
    tau = actuation_force(model, ch, u)
    return Q + tau - model.K_q @ (q - model.q0) - model.D_q @ qdot


def forward_dynamics(model, q, qdot, u=None, loads=None):
    """qddot from M qddot = applied - C qdot."""
    loads = Loads() if loads is None else loads
    u = actuation_vector(model, u)
    rhs = applied_force(model, q, qdot, u, loads) - bias_force(model, q, qdot)
    return np.linalg.solve(mass_matrix(model, q), rhs)


def energy(model, q, qdot, u=None, gravity=True):
    """(kinetic, elastic, gravitational, actuator) energies [J].

    Gravitational energy -int rho A g . p ds uses the same quadrature as the
    dynamics; the actuator potential of constant inputs is sum c_a u_a ell_a
    (tendon tension times path length)."""
    from .loads import tendon_lengths
    M = mass_matrix(model, q)
    kinetic = 0.5 * qdot @ M @ qdot
    dq = q - model.q0
    elastic = 0.5 * dq @ model.K_q @ dq
    grav = 0.0
    if gravity:
        s, w, Mc = _quadrature(model)
        p = kin.poses(model, q, s)[:, :3, 3]
        grav = -np.sum(w * Mc[:, 0, 0] * (p @ model.gravity))
    act = 0.0
    if u is not None and len(model.actuators):
        u = actuation_vector(model, u)
        c = np.array([a.force_per_unit_input for a in model.actuators])
        act = float(np.sum(c * u * tendon_lengths(model, q)))
    return float(kinetic), float(elastic), float(grav), act


def base_reaction_dynamic(model, q, qdot, qddot, u=None, loads=None):
    """Support reaction [f; m] (world axes, moment about the base origin):
    the wrench the support transmits into the root joint, by the engine's
    inverse dynamics at (q, qdot, qddot) under the loads (actuators are
    internal: their forces close through the base).
    :func:`_base_reaction_reference` is the numpy version."""
    from . import algorithms as alg
    from .forces import gravity_of, load_arrays
    from .workspace import thread_workspace
    loads = Loads() if loads is None else loads
    tree = model.tree
    ws = thread_workspace(tree)
    alg.rnea(tree, ws, q, qdot, qddot, load_arrays(tree, loads), gravity_of(tree, loads), elastic=False)
    R = ws.work.g_in[0, :3, :3]
    f = ws.work.f_in[0]
    return np.concatenate([R @ f[:3], R @ f[3:]])


def _base_reaction_reference(model, q, qdot, qddot, loads):
    s, w, Mc = _quadrature(model)
    g, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    eta_dot = J @ qddot + Jdot @ qdot
    Wb = w[:, None] * (np.einsum("pab,pb->pa", Mc, eta_dot)
                       - np.einsum("pba,pb->pa", lie.ad(eta), np.einsum("pab,pb->pa", Mc, eta)))
    F_inertia = np.einsum("pji,pj->i", lie.Ad_inv(g), Wb)
    _, F_ext = generalized_external_force(model, kin.chain(model, q), loads)
    return base_reaction(model, F_ext - F_inertia)


def dynamics_terms(model, q, qdot, u, loads):
    """(M, f) with f = Q_ext + tau - K (q - q0) - D qdot - C qdot, sharing one
    kinematic pass (reference implementation of the integrators' kernel)."""
    s, w, Mc = _quadrature(model)
    g, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, s)
    M = np.einsum("p,pai,pab,pbj->ij", w, J, Mc, J)
    acc = np.einsum("pij,j->pi", Jdot, qdot)
    h = np.einsum("pab,pb->pa", Mc, acc) - np.einsum("pba,pb->pa", lie.ad(eta),
                                                      np.einsum("pab,pb->pa", Mc, eta))
    bias = np.einsum("p,pai,pa->i", w, J, h)
    return M, applied_force(model, q, qdot, u, loads) - bias


# ----------------------------------------------------------------------------
# Time integration
# ----------------------------------------------------------------------------

def _profile(value, model, kind):
    """A constant or a callable of time t [s]; returns a function of t.
    kind "actuation": a dict/vector of inputs (validated); "loads": Loads."""
    if callable(value):
        return value
    if kind == "actuation":
        u = actuation_vector(model, value)
        f = lambda t: u  # noqa: E731
    else:
        loads = Loads() if value is None else value
        f = lambda t: loads  # noqa: E731
    f.constant = True          # the same inputs at every t: Simulator.step(n) may run n steps in one call
    return f


def held(u):
    """A constant input profile of an inputs vector checked already (at the
    node's door, :func:`soft_twin_core.commands.parse_actuation`): for
    :meth:`Simulator.set_actuation` without a second check."""
    u = np.array(u, dtype=float)
    f = lambda t: u  # noqa: E731
    f.constant = True
    return f


class Simulator:
    """Fixed-step implicit integrator (theta-method) of a robot description,
    for the node and the scenario runner: the multibody engine's
    :class:`soft_twin_core.integrators.ThetaIntegrator` on the robot's tree
    (:func:`multibody.from_robot_model`), with the inputs of the description.

    One step of size dt [s] solves, for v1 (strain rates at t + dt),
        M(qt) (v1 - v0) = dt f(qt, vt, t + theta dt),
        vt = (1 - theta) v0 + theta v1,  qt = q0 + theta dt vt,  q1 = q0 + dt vt.
    theta = 1/2 (default) is the implicit midpoint rule: second order,
    A-stable, no numerical damping (the energy error of the undamped arm stays
    O(dt^2) without drift). theta = 1 is implicit Euler: first order,
    L-stable, damps the stiff modes that the midpoint rule lets ring (use it
    for strongly damped arms or to reach equilibrium). Newton's iteration
    uses ``M + theta dt D + (theta dt)^2 K`` factorised in O(n) by the
    articulated-body algorithm, once per step; it stops when the update, or
    the remaining error estimated from the convergence rate r as r/(1 - r)
    times the update (Hairer & Wanner), is below ``tol`` relative to the
    largest strain rate. The default 1e-4 keeps Newton's error two orders
    below the time-step error: on the benchmark cantilever it moves the tip
    trajectory of the first second by 0.007 mm against 1e-10 (1e-6: 0.004
    mm), where the time-step error is 0.7 mm at dt = 2 ms (at 5 ms: 0.04 mm
    against more than 1 mm), at 2.0 instead of 2.9 iterations a step (1e-6).
    A step that fails is split into sub-steps (the state is only updated by
    converged steps).

    actuation: dict/vector, or a callable t -> vector; loads: Loads or a
    callable t -> Loads. ``full_newton``: when the O(n) iteration fails even
    in sub-steps, try a dense full Newton (robust, but 25-700 ms a step;
    real-time users turn it off). ``reuse_factorisation``: Newton's
    factorisation serves later steps while it contracts the error as a fresh
    one does (:data:`integrators.REUSE_MAX_RATIO`); False: a fresh one every
    step (the Newton tolerance's effect on the trajectory is then smaller,
    the step dearer). The model is never modified;
    ``state`` holds q, qdot and t.
    """

    def __init__(self, model, dt=1e-3, actuation=None, loads=None, state=None,
                 max_iterations=10, tol=1e-4, max_substep_levels=4, theta=0.5, full_newton=True,
                 reuse_factorisation=True):
        from .forces import actuator_arrays
        from .integrators import ThetaIntegrator
        from .model import State
        from .workspace import Workspace
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt: expected a positive time step in s, got {dt!r}")
        if not 0.5 <= theta <= 1.0:
            raise ValueError(f"theta: expected a value in [0.5, 1], got {theta!r}")
        self.theta = float(theta)
        self.model = model
        self.dt = float(dt)
        self.state = State.rest(model) if state is None else state.copy()
        self.set_actuation(actuation)
        self.set_loads(loads)
        self.tree = model.tree
        self.workspace = Workspace(self.tree)
        self._act = actuator_arrays(self.tree)
        self._effort = np.zeros(self.tree.nv)
        self._inputs_key = None
        self._integrator = ThetaIntegrator(self.tree, self.workspace, self._act, self._inputs, self.dt,
                                           self.theta, tol, max_iterations, max_substep_levels, full_newton,
                                           reuse_factorisation)

    @property
    def last_qddot(self):
        return self._integrator.last_a

    @property
    def newton_iterations(self):
        """Newton iterations so far (all steps)."""
        return self._integrator.iterations

    @property
    def jacobian_refreshes(self):
        """Factorisations of Newton's matrix so far."""
        return self._integrator.factorisations

    def set_actuation(self, actuation):
        """Constant inputs (dict or vector, validated) or a callable of t."""
        self._u = _profile(actuation, self.model, "actuation")

    def set_loads(self, loads):
        self._loads = _profile(loads, self.model, "loads")

    def actuation_at(self, t):
        return self._u(t)

    def loads_at(self, t):
        return self._loads(t)

    def _inputs(self, t):
        """Engine inputs at t, rebuilt only when the loads object or the
        actuation values change."""
        from .forces import gravity_of, load_arrays
        u = np.asarray(self._u(t), dtype=float)
        loads = self._loads(t)
        key = self._inputs_key
        if key is None or key[0] is not loads or not np.array_equal(key[1], u):
            arrays = (load_arrays(self.tree, loads, u), gravity_of(self.tree, loads),
                      np.ascontiguousarray(self._act.unit @ u) if u.size else np.zeros(len(self._act.joint)),
                      self._effort)
            self._inputs_key = key = (loads, u.copy(), arrays)
        return key[2]

    def acceleration(self, q, qdot, t):
        """qddot at (q, qdot, t) under the simulator's inputs: the solve of
        ``M qddot = -R(q, qdot, 0)`` (R: the integrator's residual) in O(n)."""
        from . import algorithms as alg
        from .integrators import residual_pass
        loads, g, coef, effort = self._inputs(t)
        q = np.ascontiguousarray(q, dtype=float)
        v = np.ascontiguousarray(qdot, dtype=float)
        R = np.empty(self.tree.nv)
        # a workspace of its own: the integrator keeps its factorisation in self.workspace
        ws = self.__dict__.get("_acc_ws")
        if ws is None:
            from .workspace import Workspace
            ws = self._acc_ws = Workspace(self.tree)
        residual_pass(ws.m, ws.w, self._act, loads, g, coef, effort, q, v, np.zeros(self.tree.nv), R, False)
        alg.factor(self.tree, ws, q)
        return alg.solve(self.tree, ws, -R)

    def step(self, n=1):
        """Advance n steps; returns the StepInfo of the last one. A step that
        cannot converge even with sub-steps leaves the state at the last good
        step and returns ``converged`` False."""
        if n > 1 and self._constant_inputs():
            return self._integrator.run(self.state, n)
        info = None
        for _ in range(n):
            info = self._integrator.step(self.state)
            if not info.converged:
                break
        return info

    def _constant_inputs(self):
        return getattr(self._u, "constant", False) and getattr(self._loads, "constant", False)


def simulate_ivp(model, t_span, state, actuation=None, loads=None, method="Radau",
                 rtol=1e-8, atol=1e-10, t_eval=None):
    """Adaptive offline integration with scipy.integrate.solve_ivp (Radau or
    BDF for stiff arms). The Jacobian of the first-order system
    [qdot; M^-1 f] is [[0, I], [M^-1 df/dq, M^-1 df/dqdot]] with df/dq ~ -K and
    df/dqdot ~ -D refined by scipy's own finite differences when
    ``jac=None``; here it is supplied by central finite differences of the
    exact right-hand side (verified in the tests)."""
    from scipy.integrate import solve_ivp
    sim = Simulator(model, dt=1.0, actuation=actuation, loads=loads)
    n = model.n_dof

    def rhs(t, y):
        return np.concatenate([y[n:], sim.acceleration(y[:n], y[n:], t)])

    def jac(t, y):
        eps = 1e-7 * np.maximum(1.0, np.abs(y))
        Jm = np.empty((2 * n, 2 * n))
        for k in range(2 * n):
            e = np.zeros(2 * n)
            e[k] = eps[k]
            Jm[:, k] = (rhs(t, y + e) - rhs(t, y - e)) / (2 * eps[k])
        return Jm

    y0 = np.concatenate([state.q, state.qdot])
    return solve_ivp(rhs, t_span, y0, method=method, rtol=rtol, atol=atol, jac=jac, t_eval=t_eval)


def internal_wrenches_dynamic(model, q, qdot, qddot, s, u=None, loads=None):
    """Internal wrench [force; moment] (P, 6), body frame at arc lengths s,
    in motion: the statics cut (:func:`statics.internal_wrenches`) with the
    d'Alembert inertial wrenches ``-(Mc eta_dot - ad(eta)^T Mc eta)`` of the
    distal quadrature points added as follower loads."""
    from .loads import PointLoad
    from .statics import internal_wrenches
    loads = Loads() if loads is None else loads
    sq, w, Mc = _quadrature(model)
    _, J, Jdot, eta = kin.jacobian_and_derivative(model, q, qdot, sq)
    eta_dot = J @ qddot + Jdot @ qdot
    h = np.einsum("pab,pb->pa", Mc, eta_dot) - np.einsum("pba,pb->pa", lie.ad(eta),
                                                         np.einsum("pab,pb->pa", Mc, eta))
    inertial = tuple(PointLoad(float(si), tuple(-wi * hi), "body") for si, wi, hi in zip(sq, w, h))
    all_loads = Loads(point=tuple(loads.point) + inertial, distributed=loads.distributed,
                      gravity=loads.gravity)
    return internal_wrenches(model, q, s, u, all_loads)
