"""State estimation of a soft arm from its sensors: an extended Kalman
filter over the strains q and strain rates v of the classic robot, with the
twin's dynamics as process model, optionally augmented with an unknown
constant external wrench at the tip (payload, contact).

State ``x = [q (n); v (n); w (k)]``: n free strain modes, w the tip wrench
[N; N m] in world axes (a dead load at the tip, ``S w`` with a selection
S): ``k = 1`` (``wrench="payload"``: w is a mass [kg] at the tip, force
``w g``), 3 (force only, ``"force"``), 6 (``"wrench"``) or 0 (``None``).

**Prediction** (one step of dt [s]). The mean goes through one step of the
twin's integrator (:class:`dynamics.Simulator`, theta-method, with gravity,
the measured inputs u and the estimated wrench as a tip load; w is a random
walk). The covariance goes through the linearisation of that step: the
equations of motion ``ID(q, v, a) + K (q - q0) + D v - tau_act(q, u) -
J_world(q)^T w = 0`` linearised at the current state,

    M da = -(dtau/dq) dq - (dtau/dv) dv + J_world^T S dw + B du

(dtau/dq, dtau/dv: the analytic derivatives of inverse dynamics,
:func:`algorithms.rnea_derivatives`, plus the geometric stiffness of the
tip load and the tendons from the statics tangent; B: :func:`sensors.
actuation_matrix`), i.e. ``xdot = A x + G_u du`` with
``A = [[0, I, 0], [-M^-1 dtau/dq, -M^-1 dtau/dv, M^-1 J^T S], [0, 0, 0]]``,
discretised by the same theta-method as the integrator:

    Phi = (I - theta dt A)^-1 (I + (1 - theta) dt A),
    Gamma_u = (I - theta dt A)^-1 dt G_u.

(At rest this is the exact Jacobian of the integrator's step; elsewhere it
neglects the change of the linearisation over one step, O(dt).)
``P <- Phi P Phi^T + Q dt + Gamma_u Sigma_u Gamma_u^T`` with white process
noise on q, v and w (spectral densities ``process_noise_q``, ``_v``,
``wrench_walk``) and the input noise Sigma_u of the tension sensors.

**Update** with the sensors' residuals and analytic Jacobians
(:mod:`soft_twin_core.sensors`): each available measurement is checked
(shape, finite: else *rejected*), absent ones are *dropped*, and each is
gated by its normalised innovation squared ``NIS = e^T S^-1 e`` against the
chi-square quantile ``gate_probability`` of its dimension (else *gated*);
the accepted ones make one joint update in Joseph form.

Outputs: :attr:`q`, :attr:`v`, :meth:`wrench`, :meth:`tip_position` and
:meth:`tip_position_cov`, :meth:`payload_mass_kg`, the innovation
statistics of the last update (:class:`UpdateReport`) and the counters
(:attr:`health`).
"""

from dataclasses import dataclass, field

import numpy as np

from .sensors import TensionSensor, actuation_matrix, check_sensors, measurement_vector, residual_and_jacobian

_WRENCH_DIMS = {None: 0, "payload": 1, "force": 3, "wrench": 6}


@dataclass
class UpdateReport:
    """One measurement update: per sensor its innovation (``-e``) and NIS;
    which were accepted, gated (outliers), dropped (absent) or rejected
    (malformed: wrong shape, NaN; with the reason)."""
    innovations: dict = field(default_factory=dict)
    nis: dict = field(default_factory=dict)
    accepted: list = field(default_factory=list)
    gated: list = field(default_factory=list)
    dropped: list = field(default_factory=list)
    rejected: dict = field(default_factory=dict)

    @property
    def total_nis(self):
        """NIS of the accepted measurements (sum) and its degrees of freedom."""
        dof = sum(len(self.innovations[k]) for k in self.accepted)
        return float(sum(self.nis[k] for k in self.accepted)), dof


@dataclass
class FilterHealth:
    """Counters since the last reset."""
    predictions: int = 0
    updates: int = 0
    accepted: int = 0
    gated: int = 0
    dropped: int = 0
    rejected: int = 0
    integrator_failures: int = 0
    nis_sum: float = 0.0
    nis_dof: int = 0

    @property
    def mean_nis_per_dof(self):
        """Average NIS per measured degree of freedom (about 1 when the
        filter is consistent)."""
        return self.nis_sum / self.nis_dof if self.nis_dof else float("nan")


class StrainEKF:
    """Extended Kalman filter of a classic robot (:class:`model.RobotModel`)
    from pose sensors, position markers and tension sensors (module
    docstring).

    dt [s]: the filter step; theta: the integrator's theta (1: implicit
    Euler, L-stable: the corrections do not excite stiff modes);
    actuation: nominal inputs (vector or dict) used when a step gets none;
    q_init: the initial strains (default: static equilibrium at the nominal
    inputs); sigma_q0, sigma_v0: initial standard deviations of q and v
    (strain units, per s); sigma_wrench0 (N, N m); process_noise_q,
    process_noise_v: white-noise spectral densities on q and v (per
    sqrt(s)); wrench_walk (N, N m per sqrt(s)); input_sigma: noise of
    inputs without a tension sensor (default 0); max_gated_run: consecutive
    gated readings of a sensor after which the next is taken (the filter
    has drifted, not the sensor: :func:`gate_reading`).
    """

    def __init__(self, model, sensors, dt=0.01, *, theta=1.0, wrench="force", actuation=None, q_init=None,
                 sigma_q0=0.5, sigma_v0=1.0, sigma_wrench0=(1.0, 0.1), process_noise_q=0.2,
                 process_noise_v=10.0, wrench_walk=(0.05, 0.005), gate_probability=0.999, input_sigma=0.0,
                 max_gated_run=10):
        from scipy.stats import chi2
        from .statics import actuation_vector, solve_statics
        from .workspace import Workspace
        if wrench not in _WRENCH_DIMS:
            raise ValueError(f"wrench: expected None, 'payload', 'force' or 'wrench', got {wrench!r}")
        if not (isinstance(dt, (int, float)) and np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: expected a positive step in s, got {dt!r}")
        if not 0.0 < gate_probability < 1.0:
            raise ValueError(f"gate_probability: expected a value in (0, 1), got {gate_probability!r}")
        if model.kinematic_map != "exponential":
            raise ValueError("StrainEKF: only exponential-map robots are supported (the process Jacobian uses "
                             "algorithms.rnea_derivatives)")
        if any(a.tendon_model == "point_moment" for a in model.actuators):
            raise ValueError("StrainEKF: point-moment tendons are not supported (use the distributed model)")
        self.model = model
        self.sensors = check_sensors(model, sensors)
        self.by_name = {s.name: s for s in self.sensors}
        self.dt = float(dt)
        self.theta = float(theta)
        self.wrench_mode = wrench
        self.n = model.n_dof
        self.k = _WRENCH_DIMS[wrench]
        g = np.asarray(model.gravity, dtype=float)
        if wrench == "payload":
            if not np.linalg.norm(g) > 0:
                raise ValueError("wrench: 'payload' needs gravity (the model's gravity is zero)")
            self.S = np.concatenate([g, np.zeros(3)])[:, None]    # w = mass [kg]: tip force m g
        else:
            self.S = np.eye(6)[:, :self.k]                 # wrench selection: w_full = S w
        self.u_nominal = actuation_vector(model, actuation)
        sig_u = np.full(len(model.actuators), float(input_sigma))
        self._tension_index = {}
        for s in self.sensors:
            if isinstance(s, TensionSensor):
                a = model.actuator_names.index(s.actuator)
                sig_u[a] = s.sigma
                self._tension_index[s.name] = a
        self.sigma_u = sig_u
        self.gate = {m: float(chi2.ppf(gate_probability, m)) for m in (3, 6)}
        self.max_gated_run = int(max_gated_run)
        self._gated_run = {s.name: 0 for s in self.sensors}
        self.tree = model.tree
        self.ws = Workspace(self.tree)
        from .forces import actuator_arrays
        from .integrators import ThetaIntegrator
        self._act = actuator_arrays(self.tree)
        self._g = np.asarray(model.gravity, dtype=float)
        self._zero_g = np.zeros(3)
        self._effort = np.zeros(self.tree.nv)
        self._step_inputs = None
        # the twin's integrator (as dynamics.Simulator runs it), with the filter's inputs
        self._integrator = ThetaIntegrator(self.tree, Workspace(self.tree), self._act, self._inputs, self.dt,
                                           self.theta, 1e-9, 10, 4, False)
        n, k = self.n, self.k
        fs, ms = sigma_wrench0
        walk = np.array([wrench_walk[0]] * 3 + [wrench_walk[1]] * 3)[:k]
        w0 = np.array([fs] * 3 + [ms] * 3)[:k]
        if wrench == "payload":                            # in kg: the force levels over |g|
            walk, w0 = walk / np.linalg.norm(g), w0 / np.linalg.norm(g)
        self.Q = np.diag(np.concatenate([np.full(n, process_noise_q ** 2), np.full(n, process_noise_v ** 2),
                                         walk ** 2]))
        self._P0 = np.diag(np.concatenate([np.full(n, sigma_q0 ** 2), np.full(n, sigma_v0 ** 2), w0 ** 2]))
        if q_init is None:
            q_init = solve_statics(model, self.u_nominal).q
        self._q_init = model.check_q(np.array(q_init, dtype=float)).copy()
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, q=None):
        """Back to the initial estimate (or to strains q), zero rates and
        wrench, the initial covariance, counters cleared."""
        n, k = self.n, self.k
        self.x = np.zeros(2 * n + k)
        self.x[:n] = self._q_init if q is None else self.model.check_q(np.asarray(q, dtype=float))
        self.P = self._P0.copy()
        self.t = 0.0
        self.a = np.zeros(n)
        self.u = self.u_nominal.copy()
        self.health = FilterHealth()
        self.last_report = UpdateReport()

    @property
    def q(self):
        return self.x[:self.n]

    @property
    def v(self):
        return self.x[self.n:2 * self.n]

    def wrench(self):
        """Estimated tip wrench [f; m] (6,), world axes (zeros where not estimated)."""
        return self.S @ self.x[2 * self.n:]

    def wrench_std(self):
        """Standard deviations (6,) of :meth:`wrench` (zeros where not estimated)."""
        return self.S @ np.sqrt(np.diag(self.P)[2 * self.n:])

    def payload_mass_kg(self):
        """Mass [kg] whose weight explains the estimated tip force, and its std."""
        g = np.asarray(self.model.gravity, dtype=float)
        gn = np.linalg.norm(g)
        if self.k == 0 or gn == 0:
            return 0.0, float("inf")
        if self.wrench_mode == "payload":
            i = 2 * self.n
            return float(self.x[i]), float(np.sqrt(self.P[i, i]))
        d = g / gn
        f = self.wrench()[:3]
        Pf = self.P[2 * self.n:2 * self.n + 3, 2 * self.n:2 * self.n + 3]
        return float(f @ d / gn), float(np.sqrt(d @ Pf @ d) / gn)

    def tip_pose(self):
        from .kinematics import tip_and_spatial_jacobian
        return tip_and_spatial_jacobian(self.model, self.q)[0]

    def tip_position(self):
        return self.tip_pose()[:3, 3].copy()

    def tip_position_cov(self):
        """Covariance (3, 3) [m^2] of the tip position, ``Jp P_qq Jp^T``
        (Jp: world velocity rows of the tip Jacobian)."""
        from .kinematics import tip_jacobian
        Jp = tip_jacobian(self.model, self.q, "world")[:3]
        n = self.n
        return Jp @ self.P[:n, :n] @ Jp.T

    def tip_position_std(self):
        """Per-axis standard deviations (3,) [m] of the tip position."""
        return np.sqrt(np.diag(self.tip_position_cov()))

    def backbone(self, points_per_section=10):
        """(arc lengths, world poses) of the estimated backbone."""
        from .kinematics import backbone
        return backbone(self.model, self.q, points_per_section)

    # ------------------------------------------------------------- prediction
    def _engine_loads(self, w=None):
        """LoadArrays of the estimated tip wrench (a dead load at the tip frame)."""
        from . import algorithms as alg
        w = self.wrench() if w is None else w
        return alg.make_loads(self.tree, [self.tree.n_joints - 1], [-1.0], [w], [True])

    def _inputs(self, t):
        return self._step_inputs

    def linearisation(self, u=None):
        """(Phi, Gamma_u) of one step from the current state (module
        docstring), analytic."""
        from . import algorithms as alg
        from .forces import actuation_tangent_pass
        from .kernels import passes
        from .kernels.tangent import static_tangent_pass
        model, tree, ws = self.model, self.tree, self.ws
        n, k = self.n, self.k
        u = self.u if u is None else np.asarray(u, dtype=float)
        q, v = np.ascontiguousarray(self.q), np.ascontiguousarray(self.v)
        dq, dv = alg.rnea_derivatives(tree, ws, q, v, self.a)       # inertia, gravity, K, D
        # geometric stiffness of the tip load and the tendons (gravity is in dq already)
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
        passes.rnea_pass(ws.m, ws.w, self._engine_loads(), self._zero_g, np.empty(tree.nv), True)
        static_tangent_pass(ws.m, ws.w, self._engine_loads(), self._zero_g, dq)
        if len(model.actuators):
            actuation_tangent_pass(ws.m, ws.w, self._act, np.ascontiguousarray(self._act.unit @ u), dq)
        M = alg.crba(tree, ws, q).copy()
        cols = [dq, dv]
        if k:
            g_tip, Js = alg.point_jacobian(tree, ws, q, tree.n_joints - 1, -1.0, "world")
            cols.append(Js.T @ self.S)                    # (n, k): generalised force per unit w
        B = actuation_matrix(model, q, ws) if len(model.actuators) else np.zeros((n, 0))
        cols.append(B)
        X = np.linalg.solve(M, np.hstack(cols))
        N = 2 * n + k
        A = np.zeros((N, N))
        A[:n, n:2 * n] = np.eye(n)
        A[n:2 * n, :n] = -X[:, :n]
        A[n:2 * n, n:2 * n] = -X[:, n:2 * n]
        if k:
            A[n:2 * n, 2 * n:] = X[:, 2 * n:2 * n + k]
        Gu = np.zeros((N, B.shape[1]))
        Gu[n:2 * n] = X[:, 2 * n + k:]
        h, th = self.dt, self.theta
        L = np.eye(N) - th * h * A
        Phi = np.linalg.solve(L, np.eye(N) + (1.0 - th) * h * A)
        Gamma = np.linalg.solve(L, h * Gu)
        return Phi, Gamma

    def predict(self, u=None):
        """Advance the estimate by dt with inputs u (vector/dict; default:
        the last ones). Returns True when the integrator step converged (else
        the mean stays where it was and the failure is counted)."""
        from .model import State
        from .statics import actuation_vector
        if u is not None:
            self.u = actuation_vector(self.model, u)
        Phi, Gamma = self.linearisation()
        n = self.n
        coef = np.ascontiguousarray(self._act.unit @ self.u) if self.u.size else np.zeros(len(self._act.joint))
        self._step_inputs = (self._engine_loads(), self._g, coef, self._effort)
        state = State(self.q.copy(), self.v.copy(), self.t)
        info = self._integrator.step(state)
        ok = bool(info.converged)
        if ok:
            self.a = (state.qdot - self.v) / self.dt
            self.x[:n] = state.q
            self.x[n:2 * n] = state.qdot
        else:
            self.health.integrator_failures += 1          # the mean stays; the covariance grows
        self.P = Phi @ self.P @ Phi.T + self.Q * self.dt + (Gamma * self.sigma_u ** 2) @ Gamma.T
        self.P = 0.5 * (self.P + self.P.T)
        self.t += self.dt
        self.health.predictions += 1
        return ok

    # ----------------------------------------------------------------- update
    def update(self, measurements):
        """Measurement update with ``{sensor name: reading}`` (a 4x4 pose or
        7 numbers for pose sensors, 3 for markers; None or absent: dropped;
        tension sensors' readings become the inputs of the next prediction).
        Unknown names raise ValueError. Returns the :class:`UpdateReport`."""
        rep = UpdateReport()
        for name in measurements:
            if name not in self.by_name:
                raise ValueError(f"measurements: unknown sensor {name!r}; configured: {list(self.by_name)}")
        from .kernels import passes
        n, N = self.n, len(self.x)
        es, Hs, Rs = [], [], []
        fk = False
        for sen in self.sensors:
            z = measurements.get(sen.name)
            if z is None:
                if not isinstance(sen, TensionSensor):
                    rep.dropped.append(sen.name)
                continue
            try:
                z = measurement_vector(sen, z)
            except ValueError as err:
                rep.rejected[sen.name] = str(err)
                continue
            if isinstance(sen, TensionSensor):
                self.u[self._tension_index[sen.name]] = max(float(z), 0.0) if \
                    self.model.actuators[self._tension_index[sen.name]].kind == "tendon" else float(z)
                continue
            if not fk:
                passes.forward_pass(self.ws.m, self.ws.w, np.ascontiguousarray(self.q), self.ws.zeros_v,
                                    self.ws.zeros_v, 0)
                fk = True
            e, Hq = residual_and_jacobian(self.model, self.q, sen, z, self.ws, kinematics_done=True)
            H = np.zeros((len(e), N))
            H[:, :n] = Hq
            Rm = sen.noise_covariance()
            if not gate_reading(rep, sen.name, e, H, Rm, self.P, self.gate[len(e)], self._gated_run,
                                self.max_gated_run):
                continue
            es.append(e)
            Hs.append(H)
            Rs.append(Rm)
        if es:
            self.x, self.P = kalman_update(self.x, self.P, es, Hs, Rs)
        tally_update(self.health, rep)
        self.last_report = rep
        return rep

    def step(self, measurements, u=None):
        """predict(u) then update(measurements); returns the UpdateReport."""
        self.predict(u)
        return self.update(measurements)


def gate_reading(rep, name, e, H, Rm, P, gate, runs, max_run):
    """The gate of one reading, shared by the filters: its normalised
    innovation squared ``NIS = e^T (H P H^T + R)^-1 e`` (e = h(x) - z) against
    the chi-square quantile ``gate`` of its dimension -- unless the same
    sensor was gated ``max_run`` times in a row (``runs``: {name: count}):
    then the filter, not the sensor, has drifted and the reading is taken
    (lock-out protection). A non-finite NIS is always gated. Records the
    innovation, the NIS and the verdict in ``rep``; True: use the reading."""
    Sm = H @ P @ H.T + Rm
    nis = float(e @ np.linalg.solve(Sm, e))
    rep.innovations[name] = -e
    rep.nis[name] = nis
    if not np.isfinite(nis) or (nis > gate and runs[name] < max_run):
        rep.gated.append(name)
        runs[name] += 1
        return False
    runs[name] = 0
    rep.accepted.append(name)
    return True


def kalman_update(x, P, es, Hs, Rs):
    """The EKF measurement update with the accepted sensors' residuals es
    (e = h(x) - z), Jacobians Hs and noise covariances Rs stacked: gain
    K = P H^T (H P H^T + R)^-1, x - K e, and the covariance in Joseph form
    (I - K H) P (I - K H)^T + K R K^T, symmetrised. Returns (x, P)."""
    e, H, Rm = np.concatenate(es), np.vstack(Hs), _block_diag(Rs)
    PHt = P @ H.T
    K = np.linalg.solve(H @ PHt + Rm, PHt.T).T
    IKH = np.eye(len(x)) - K @ H
    P = IKH @ P @ IKH.T + K @ Rm @ K.T
    return x - K @ e, 0.5 * (P + P.T)


def tally_update(health, rep):
    """Add an update's report (NIS of the accepted sensors, counts of
    accepted, gated, dropped and rejected readings) to the filter's health."""
    if rep.accepted:
        nis_sum, dof = rep.total_nis
        health.nis_sum += nis_sum
        health.nis_dof += dof
    health.updates += 1
    health.accepted += len(rep.accepted)
    health.gated += len(rep.gated)
    health.dropped += len(rep.dropped)
    health.rejected += len(rep.rejected)


def _block_diag(blocks):
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        m = b.shape[0]
        out[i:i + m, i:i + m] = b
        i += m
    return out


def nees(error, cov):
    """Normalised estimation error squared ``e^T P^-1 e``."""
    error = np.asarray(error, dtype=float)
    return float(error @ np.linalg.solve(cov, error))
