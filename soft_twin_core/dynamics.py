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

These functions are the readable reference implementation; the time
integrators use the compiled kernels of :mod:`soft_twin_core._fast` where
available (same formulas, tested against these).
"""

from dataclasses import dataclass

import numpy as np

from . import kinematics as kin
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
    total inertial wrench minus the total applied wrench (actuators are
    internal: their forces close through the base). Compiled when numba is
    available; :func:`_base_reaction_reference` is the numpy version."""
    loads = Loads() if loads is None else loads
    if _select_kernel(model) is not dynamics_terms:
        from . import _fast
        return base_reaction(model, _fast.total_wrench(model, q, qdot, qddot,
                                                       actuation_vector(model, u), loads))
    return _base_reaction_reference(model, q, qdot, qddot, loads)


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

@dataclass
class StepInfo:
    """Newton iterations used by the last step (all sub-steps) and whether
    it converged."""
    iterations: int
    converged: bool
    update: float


def _profile(value, model, kind):
    """A constant or a callable of time t [s]; returns a function of t.
    kind "actuation": a dict/vector of inputs (validated); "loads": Loads."""
    if callable(value):
        return value
    if kind == "actuation":
        u = actuation_vector(model, value)
        return lambda t: u
    loads = Loads() if value is None else value
    return lambda t: loads


class Simulator:
    """Fixed-step implicit integrator (theta-method) for the node and scenarios.

    One step of size dt [s] solves, for v1 (strain rates at t + dt),
        M(qt) (v1 - v0) = dt f(qt, vt, t + theta dt),
        vt = (1 - theta) v0 + theta v1,  qt = q0 + theta dt vt,  q1 = q0 + dt vt.
    theta = 1/2 (default) is the implicit midpoint rule: second order,
    A-stable, no numerical damping (the energy error of the undamped arm stays
    O(dt^2) without drift). theta = 1 is implicit Euler: first order,
    L-stable, damps the stiff modes that the midpoint rule lets ring (use it
    for strongly damped arms or to reach equilibrium). Solved by a modified
    Newton iteration with ``A = M - theta dt df/dv - (theta dt)^2 df/dq``,
    stopped when the update, or the remaining error estimated from the
    convergence rate r as r/(1 - r) times the update (Hairer & Wanner), is
    below ``tol`` relative to the strain rates. A is built from a
    finite-difference Jacobian of f and reused across steps while the
    iteration converges fast; it is refreshed when convergence slows, and a
    step that still fails is split into sub-steps (the state is only updated
    by converged steps).

    actuation: dict/vector, or a callable t -> vector; loads: Loads or a
    callable t -> Loads. The model is never modified; ``state`` holds q,
    qdot and t.
    """

    def __init__(self, model, dt=1e-3, actuation=None, loads=None, state=None,
                 max_iterations=10, tol=1e-9, max_substep_levels=4, theta=0.5):
        from .model import State
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt: expected a positive time step in s, got {dt!r}")
        if not 0.5 <= theta <= 1.0:
            raise ValueError(f"theta: expected a value in [0.5, 1], got {theta!r}")
        self.theta = float(theta)
        self.model = model
        self.dt = float(dt)
        self.max_iterations = int(max_iterations)
        self.tol = float(tol)
        self.max_substep_levels = int(max_substep_levels)
        self.state = State.rest(model) if state is None else state.copy()
        self.set_actuation(actuation)
        self.set_loads(loads)
        self.last_qddot = np.zeros(model.n_dof)
        self._prev_qddot = None       # for the predictor's linear extrapolation
        self._terms = _select_kernel(model)
        self._newton_fast = None
        if self._terms is not dynamics_terms:
            from . import _fast
            self._newton_fast = _fast.newton_step
        self._jac = None          # (M, df/dq, df/dv) at the last refresh
        self._lu = {}             # stale parts of the iteration matrix by step size
        self.jacobian_refreshes = 0

    def set_actuation(self, actuation):
        """Constant inputs (dict or vector, validated) or a callable of t."""
        self._u = _profile(actuation, self.model, "actuation")

    def set_loads(self, loads):
        self._loads = _profile(loads, self.model, "loads")

    def actuation_at(self, t):
        return self._u(t)

    def loads_at(self, t):
        return self._loads(t)

    def step(self, n=1):
        """Advance n steps; returns the StepInfo of the last one. A step that
        cannot converge even with sub-steps leaves the state at the last good
        step and returns ``converged`` False."""
        info = None
        for _ in range(n):
            info = self._step()
            if not info.converged:
                break
        return info

    # --- internals ---------------------------------------------------------
    def _refresh(self, q, v, u, loads, dv=None):
        """Finite-difference Jacobians of f at (q, v) for the iteration matrix,
        and of the inertia term: column k of G is (dM/dq_k) dv, with dv the
        expected velocity change of a step (large when the arm accelerates
        hard; M is ill-conditioned, so this term matters)."""
        m = self.model
        M, f = self._terms(m, q, v, u, loads)
        n = m.n_dof
        dv = np.zeros(n) if dv is None else dv
        fq, fv, G = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
        for k in range(n):
            e = np.zeros(n)
            hq = 1e-7 * max(1.0, abs(q[k]))
            e[k] = hq
            Mk, fk = self._terms(m, q + e, v, u, loads)
            fq[:, k] = (fk - f) / hq
            G[:, k] = (Mk - M) @ dv / hq
            e[k] = 0.0
            hv = 1e-7 * max(1.0, abs(v[k]))
            e[k] = hv
            fv[:, k] = (self._terms(m, q, v + e, u, loads)[1] - f) / hv
        self._jac = (M, fq, fv, G)
        self._lu = {}
        self.jacobian_refreshes += 1

    def _correction(self, h):
        """Stale part of the iteration matrix: -theta h df/dv - (theta h)^2 df/dq
        + theta^2 h (dM/dq) dv; the mass matrix itself is taken fresh at
        every iteration (it is ill-conditioned: torsion has little inertia)."""
        C = self._lu.get(h)
        if C is None:
            _, fq, fv, G = self._jac
            th = self.theta * h
            C = -th * fv - th * th * fq + self.theta * th * (h / self.dt) * G
            self._lu[h] = C
        return C

    def _newton(self, q0, v0, t, h):
        m = self.model
        th = self.theta
        tm = t + th * h
        u, loads = self._u(tm), self._loads(tm)
        C = self._correction(h)
        a_pred = self.last_qddot
        if self._prev_qddot is not None and h == self.dt:
            a_pred = 2.0 * self.last_qddot - self._prev_qddot   # linear extrapolation
        v1 = v0 + h * (a_pred if np.all(np.isfinite(a_pred)) else 0.0)
        prev, rate = None, 0.0
        # relative to the rates, with a floor at round-off of the positions
        floor = 1e-14 * max(1.0, np.abs(q0).max()) / h
        if self._newton_fast is not None:
            v1, it, status, rate = self._newton_fast(m, q0, v0, v1, h, th, C, u, loads, self.tol, floor,
                                                     self.max_iterations)
            return (v1 if status == 0 else None), it, (np.inf if status == 3 else rate)
        for it in range(1, self.max_iterations + 1):
            vt = (1.0 - th) * v0 + th * v1
            M, f = self._terms(m, q0 + th * h * vt, vt, u, loads)
            try:
                dv = np.linalg.solve(M + C, -(M @ (v1 - v0) - h * f))
            except np.linalg.LinAlgError:
                return None, it, np.inf
            v1 = v1 + dv
            upd = float(np.abs(dv).max())
            if not np.isfinite(upd):
                return None, it, np.inf
            goal = max(self.tol * max(np.abs(v1).max(), np.abs(v0).max()), floor)
            if upd <= goal:
                return v1, it, rate
            if prev is not None:
                r_k = upd / prev
                # Hairer-Wanner stopping rule (remaining error ~ r/(1-r) * update)
                if r_k < 0.5 and r_k / (1.0 - r_k) * upd <= goal:
                    return v1, it, rate
                if upd > 100 * goal:                     # rate only above the noise floor
                    rate = max(rate, r_k)
                    if rate > 0.9:
                        return None, it, rate
            prev = upd
        return None, self.max_iterations, rate

    def _advance(self, q0, v0, t, h, level):
        """Returns (q1, v1, iterations) or None, sub-stepping on failure."""
        v1, it, rate = self._newton(q0, v0, t, h)
        if v1 is None or rate > 0.5 or it > 6:
            # refresh the iteration matrix at the predicted mid-step point and retry once
            th = self.theta
            tm = t + th * h
            v1p = v0 + h * self.last_qddot if v1 is None else v1
            vt = (1.0 - th) * v0 + th * v1p
            self._refresh(q0 + th * h * vt, vt, self._u(tm), self._loads(tm),
                          (v1p - v0) * (self.dt / h))
            if v1 is None:
                v1, it2, rate = self._newton(q0, v0, t, h)
                it += it2
        if v1 is not None:
            return q0 + h * ((1.0 - self.theta) * v0 + self.theta * v1), v1, it
        if level >= self.max_substep_levels:
            return None
        half = self._advance(q0, v0, t, 0.5 * h, level + 1)
        if half is None:
            return None
        q_m, v_m, it_a = half
        rest = self._advance(q_m, v_m, t + 0.5 * h, 0.5 * h, level + 1)
        if rest is None:
            return None
        return rest[0], rest[1], it_a + rest[2]

    def _step(self):
        st = self.state
        h = self.dt
        if self._jac is None:
            u, loads = self._u(st.t), self._loads(st.t)
            self._refresh(st.q, st.qdot, u, loads)
        out = self._advance(st.q, st.qdot, st.t, h, 0)
        if out is None:
            return StepInfo(self.max_iterations, False, np.inf)
        q1, v1, it = out
        self._prev_qddot = self.last_qddot
        self.last_qddot = (v1 - st.qdot) / h
        st.q, st.qdot, st.t = q1, v1, st.t + h
        return StepInfo(it, True, 0.0)


def _select_kernel(model):
    try:
        from . import _fast
        if _fast.supports(model):
            return _fast.dynamics_terms
    except ImportError:  # numba missing: the numpy reference is used
        pass
    return dynamics_terms


def simulate_ivp(model, t_span, state, actuation=None, loads=None, method="Radau",
                 rtol=1e-8, atol=1e-10, t_eval=None):
    """Adaptive offline integration with scipy.integrate.solve_ivp (Radau or
    BDF for stiff arms). The Jacobian of the first-order system
    [qdot; M^-1 f] is [[0, I], [M^-1 df/dq, M^-1 df/dqdot]] with df/dq ~ -K and
    df/dqdot ~ -D refined by scipy's own finite differences when
    ``jac=None``; here it is supplied by central finite differences of the
    exact right-hand side (verified in the tests)."""
    from scipy.integrate import solve_ivp
    u_of_t = _profile(actuation, model, "actuation")
    loads_of_t = _profile(loads, model, "loads")
    kernel = _select_kernel(model)
    n = model.n_dof

    def rhs(t, y):
        M, f = kernel(model, y[:n], y[n:], u_of_t(t), loads_of_t(t))
        return np.concatenate([y[n:], np.linalg.solve(M, f)])

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
