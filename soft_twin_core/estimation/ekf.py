"""State estimation of a robot from its sensors: an extended Kalman filter
over the positions and velocities of every joint of the robot (the strains
of the soft sections and the rigid joints alike), with the twin's dynamics
as process model, for every :class:`mechanism.Mechanism`: a classic rod,
a tree of members, a soft articulated arm, ball joints, closed chains, a
free-flying robot, a robot on a prescribed (moving) base whose pose is an
input (``predict(base_pose=...)``: an arm carried by a manipulator).

State ``x = [q (nq); v (nv); b (n_pos); w (k)]``, its covariance P over the
errors ``[dq (nv); dv; db; dw]`` (error-state: a spherical or free joint's
quaternion moves on its group, ``q (+) dq = q exp(dq)`` as
:func:`integrators.integrate_pass` steps it, its error a rotation vector or
twist in its body frame; the other coordinates add):

- b: the tracking offsets of the position-controlled joints (a real servo
  stands off its command: gravity, friction, calibration), random walks of
  density ``offset_walk``;
- w: an unknown external wrench [N; N m] at the robot's tip frame
  (:func:`mechanism.tip_frame`) in world axes, a dead load ``S w`` with a
  selection S, random walk ``wrench_walk``: ``k = 1`` (``wrench="payload"``:
  w is a mass [kg] at the tip, force ``w g``), 3 (force only,
  ``"force"``), 6 (``"wrench"``) or 0 (None, the default). A force may be
  confined to known world directions (``force_directions``, k = 1 or 2: a
  contact's normal, the plane across the arm): a force the readings cannot
  see (along a straight arm, the tip force barely changes the shape) is
  then not estimated at all, instead of soaking up the model's own error.

**Process model.** The twin's dynamics ``M a + tau(q, v) = effort +
tau_act(q, u) + J_tip^T S w`` (``tau``: inertia, gravity, stiffness and
damping of the soft sections and the joints) stepped by its theta
integrator (:class:`integrators.ThetaIntegrator`, implicit Euler by
default) with the inputs u (tension sensors' readings replace the commands
of their actuators). A *position-controlled* joint is a servo towards
``q_cmd + b``: its effort, evaluated at the start of each step, is the bias
that holds the joint (its row of ``tau(q, v, 0)``: gravity, coupling,
damping) plus ``m_j (w^2 (q_cmd + b_j - q_j) - 2 zeta w v_j)`` with
``m_j = 1 / (M^-1)_jj``. With ``servo_hz`` given, ``w = 2 pi servo_hz``
and ``zeta = servo_damping`` (a servo with lag); by default the twin's own
position control: ``w = 1/dt``, ``zeta = 1/2`` (one implicit Euler step
brings a lone joint onto its target), then the efforts are corrected (at
most 3 times, by ``m_j dq / (theta dt^2)``) until the joints land on their
targets at the end of the step despite the members' reaction. The joints'
process noise stands for the servo's transient tracking error. An
*effort-controlled* joint gets its commanded effort, a passive one none.

The covariance goes through the linearisation of that model,

    M da = -dF/dq dq - dF/dv dv + F_b db + J_tip^T S dw + B du

with ``dF/dq = dtau/dq - d effort/dq`` plus the geometric stiffness of the
tip load and the tendons (analytic: :func:`algorithms.rnea_derivatives`,
:func:`kernels.tangent.static_tangent_pass`,
:func:`forces.actuation_tangent_pass`), ``d effort_j/dq = dtau_j(q, v,
0)/dq - m_j w^2 e_j`` (m_j held), ``F_b = d effort/db = m_j w^2`` on the
joint's row, likewise in v, and ``B = d tau_act/du``
(:func:`forces.actuation_matrix`); i.e. ``xdot = A x + G_u du``,
discretised by the same theta method as the integrator:

    Phi = (I - theta dt A)^-1 (I + (1 - theta) dt A),
    Gamma_u = (I - theta dt A)^-1 dt G_u,
    P <- Phi P Phi^T + Q dt + Gamma_u Sigma_u Gamma_u^T

(:func:`theta_step_jacobian`; at rest this is the exact Jacobian of the
integrator's step; elsewhere it
neglects the change of the linearisation over one step, O(dt)), with white
process noise Q (separate densities for the rigid joints and the strains)
and the input noise Sigma_u of the tension sensors.

**Closed chains.** The loops' reactions are multipliers of the step
(:class:`constrained.MechanismSimulator`, the position-controlled joints
driven by the servo's efforts), and the linearised step is the KKT system
of the linearised dynamics with ``G dq = 0`` at its end, the reactions'
geometric stiffness in ``dF/dq`` (:func:`theta_step_jacobian`). After each
prediction the covariance is conditioned on the loops holding (a perfect
measurement of ``G dq = 0``, ``G dv = 0``: :func:`constrained_covariance`),
and after each update the mean is put back onto them (the update moves
along their tangent, with a second-order gap).

**Update** with the sensors' residuals and analytic Jacobians
(:mod:`soft_twin_core.estimation.sensors`: poses and positions of frames and points of
members, joint encoders, a base force/torque sensor): each reading is
checked (shape, finite: else *rejected*), absent ones are *dropped*, each
is gated by its normalised innovation squared ``NIS = e^T S^-1 e`` against
the chi-square quantile ``gate_probability`` of its dimension (else
*gated*) -- unless the same sensor was gated ``max_gated_run`` times in a
row: then the filter, not the sensor, has drifted and the reading is taken
(lock-out protection); the accepted ones make one joint update in Joseph
form.

Outputs: :attr:`q`, :attr:`v`, :meth:`joint_positions`, :meth:`frame_pose`
and :meth:`frame_position_cov` (the tip: :meth:`tip_pose`,
:meth:`tip_position_cov`), :meth:`member_backbone`, :meth:`wrench`,
:meth:`payload_mass_kg`, :meth:`joint_offsets`, the innovation statistics
of the last update (:class:`UpdateReport`) and the counters
(:attr:`health`).
"""

from dataclasses import dataclass, field, replace

import numpy as np

from soft_twin_core._blas import block_diag
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import (actuation_matrix, actuation_tangent_pass, actuator_arrays, concat_loads,
                                          point_moment_arrays)
from soft_twin_core.engine.integrators import integrate_jacobians, integrate_pass
from soft_twin_core.engine.joint_kinds import SOFT
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import kernel_array
from soft_twin_core.engine.kernels.tangent import static_tangent_pass
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StepError
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.lie import checked_rigid_transform, log_so3
from soft_twin_core.robot.mechanism import tip_frame
from soft_twin_core.solve.constrained import (Inputs, MechanismSimulator, actuation_vector, constraint_loads,
                                              constraint_rows, factor_kkt, joint_vector, make_inputs,
                                              basis_offset, on_basis, solve_equilibrium, solve_factored)

WRENCH_DIMS = {None: 0, "payload": 1, "force": 3, "wrench": 6}


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



class EKF:
    """Extended Kalman filter of a robot (module docstring).

    dt [s]: filter step; theta: integrator theta (1: implicit Euler,
    L-stable: the corrections do not excite stiff modes); wrench: the
    estimated tip load (None, "payload", "force", "wrench");
    force_directions: with "force", the (k, 3) world directions the force
    lies along (k = 1..3; normalised; None: all three axes); actuation
    (tendon tensions N / pressures Pa, vector or dict), positions ({joint:
    rad or m} of the position-controlled joints), efforts ({joint: N m or
    N}): the nominal inputs; q_init: initial q (default: the static
    equilibrium at the nominal inputs); sigma_joint0 [rad or m], sigma_q0
    (strain units), sigma_v0 (per s), sigma_wrench0 ((N, N m)): initial
    standard deviations; process_noise_joint ((rad, rad/s) per sqrt(s)):
    white-noise densities on the rigid joints' positions (the servo's
    tracking error) and velocities; process_noise_q, process_noise_v: on
    the strains and their rates (process_noise_q: default 1.0 on a robot
    with position-controlled joints, whose tracking errors drive the
    members, else 0.2); wrench_walk ((N, N m) per sqrt(s)); servo_hz,
    servo_damping: the position servo model (None: the twin's tracking);
    sigma_offset0 [rad or m], offset_walk (per sqrt(s)): the joints'
    tracking offsets; input_sigma: noise of the inputs without a tension
    sensor (default 0); max_gated_run: consecutive gated readings of a
    sensor after which the next is taken.
    """

    def __init__(self, mech, sensors, dt=0.01, *, theta=1.0, wrench=None, actuation=None, positions=None,
                 efforts=None, q_init=None, sigma_joint0=0.05, sigma_q0=0.5, sigma_v0=1.0,
                 sigma_wrench0=(1.0, 0.1), process_noise_joint=(0.05, 2.0), process_noise_q=None,
                 process_noise_v=10.0, wrench_walk=(0.05, 0.005), servo_hz=None, servo_damping=1.0,
                 sigma_offset0=0.05, offset_walk=0.01, input_sigma=0.0, gate_probability=0.999,
                 max_gated_run=10, force_directions=None):
        from scipy.stats import chi2            # here: scipy.stats takes 0.3 s to import
        tree = mech.tree
        if not (isinstance(dt, (int, float)) and np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: expected a positive step in s, got {dt!r}")
        if not 0.0 < gate_probability < 1.0:
            raise ValueError(f"gate_probability: expected a value in (0, 1), got {gate_probability!r}")
        if wrench not in WRENCH_DIMS:
            raise ValueError(f"wrench: expected None, 'payload', 'force' or 'wrench', got {wrench!r}")
        if force_directions is not None:
            if wrench != "force":
                raise ValueError(f"force_directions: only with wrench='force', not {wrench!r}")
            force_directions = unit_directions(force_directions, "force_directions")
        _check_supported(mech)
        if servo_hz is not None and not (servo_hz > 0 and servo_damping > 0):
            raise ValueError("servo_hz and servo_damping must be > 0 (or servo_hz None: the twin's tracking)")
        self.mech, self.tree = mech, tree
        self.sensors, self._where = sn.check_sensors(mech, sensors)
        self.by_name = {s.name: s for s in self.sensors}
        self.dt, self.theta = float(dt), float(theta)
        self.n = n = tree.nv
        self.nq = tree.nq             # q has nq entries (quaternions), its error and v have n
        # variable-strain segments: the errors of q and v are those of the coordinates z (q = q0 + B z), nr of
        # them; else nr = n (T None: the identity)
        self.T = mech.basis
        self.nr = n if self.T is None else self.T.shape[1]
        self._Tp = None if self.T is None else np.linalg.solve(self.T.T @ self.T, self.T.T)    # T^+
        self.ws = Workspace(tree)
        self._act = actuator_arrays(tree)
        self._g = kernel_array(tree.gravity)
        self._zero_g = np.zeros(3)
        # --- the tip load: w, its selection S and where it acts ---
        self.wrench_mode, self.k = wrench, WRENCH_DIMS[wrench]
        self.tip = tip_frame(mech)
        ref = mech.frame(self.tip)
        self._tip_point = (int(ref.joint), float(ref.x))
        if wrench == "payload":
            if not np.linalg.norm(self._g) > 0:
                raise ValueError("wrench: 'payload' needs gravity (the robot's gravity is zero)")
            self.S = np.concatenate([self._g, np.zeros(3)])[:, None]    # w = mass [kg]: tip force m g
        elif force_directions is not None:                             # w = force along each direction [N]
            self.k = len(force_directions)
            self.S = np.vstack([force_directions.T, np.zeros((3, self.k))])
        else:
            self.S = np.eye(6)[:, :self.k]
        # --- inputs ---
        inp = make_inputs(mech, actuation, efforts, positions)
        self.u_nominal = inp.u.copy()
        self._effort_nominal = inp.effort.copy()
        self._pos_joints = mech.joints_with("position")
        self._pos_v = np.array([tree.idx_v[i] for i in self._pos_joints], dtype=np.int64)
        self._pos_q = np.array([tree.idx_q[i] for i in self._pos_joints], dtype=np.int64)
        self._q_cmd_nominal = inp.q_cmd.copy()
        self._tendon = np.array([a.kind == "tendon" for a in mech.actuators], dtype=bool)
        sig_u = np.full(len(mech.actuators), float(input_sigma))
        for s in self.sensors:
            if isinstance(s, sn.TensionSensor):
                sig_u[self._where[s.name]] = s.sigma
        self.sigma_u = sig_u
        self._tracking = servo_hz is None
        if servo_hz is None:               # deadbeat: the command is reached at the end of the step
            self._w, self._zeta = 1.0 / self.dt, 0.5
        else:
            self._w, self._zeta = 2.0 * np.pi * float(servo_hz), float(servo_damping)
        self._point_moments = any(a.tendon_model == "point_moment" for a in mech.actuators)
        # the process model steps the robot with its position-controlled joints driven by the servo's
        # efforts; its multipliers are the closed chains' reactions (none: the compiled O(n) integrator)
        self._servo_mech = replace(mech, control=tuple("effort" if c == "position" else c for c in mech.control))
        # (a closed chain's step factorises its KKT matrix afresh: its mean must be what the analytic Phi
        # linearises, to Newton's quadratic convergence, not to the tolerance a reused matrix stops at)
        # (up to 40 Newton iterations: a moving base's clamp converges linearly, 13 a step at 10 ms)
        self._sim = MechanismSimulator(self._servo_mech, self.dt, self.theta, tol=1e-9, max_iterations=40,
                                       max_substep_levels=4, full_newton=False,
                                       reuse_factorisation=mech.n_constraint_rows == 0)
        self._no_cmd = np.zeros(0)
        names = [c.name for c in mech.constraints]
        self._base_k = names.index("base") if mech.base_motion == "prescribed" else None
        self._base_row = sum(c.size for c in mech.constraints[:self._base_k]) if self._base_k is not None else 0
        self.gate = {m: float(chi2.ppf(gate_probability, m)) for m in range(1, 7)}
        self._gate_probability = gate_probability
        self.max_gated_run = int(max_gated_run)
        # --- noise ---
        rigid = np.zeros(n, dtype=bool)          # every coordinate of q of a rigid joint (a free base's six)
        for i, joint in enumerate(tree.joints):
            if joint.kind != SOFT:
                rigid[tree.idx_v[i]:tree.idx_v[i] + joint.nv] = True
        self.rigid = rigid
        self.nb = nb = len(self._pos_v)
        k = self.k
        pj_q, pj_v = process_noise_joint
        if process_noise_q is None:          # servoed joints drive the members with their tracking errors
            process_noise_q = 1.0 if nb else 0.2
        walk = np.array([wrench_walk[0]] * 3 + [wrench_walk[1]] * 3)[:k]
        w0 = np.array([sigma_wrench0[0]] * 3 + [sigma_wrench0[1]] * 3)[:k]
        if wrench == "payload":                            # in kg: the force levels over |g|
            walk, w0 = walk / np.linalg.norm(self._g), w0 / np.linalg.norm(self._g)
        qv = [np.where(rigid, pj_q ** 2, process_noise_q ** 2), np.where(rigid, pj_v ** 2, process_noise_v ** 2)]
        qv0 = [np.where(rigid, sigma_joint0 ** 2, sigma_q0 ** 2), np.full(n, sigma_v0 ** 2)]
        self.Q = block_diag([*_in_coordinates(self._Tp, qv), np.diag(np.full(nb, offset_walk ** 2)),
                             np.diag(walk ** 2)])
        self._P0 = block_diag([*_in_coordinates(self._Tp, qv0), np.diag(np.full(nb, sigma_offset0 ** 2)),
                               np.diag(w0 ** 2)])
        if q_init is None:   # the equilibrium under the inputs; where statics has none to find (a moving base,
            # ball joints: no static equilibrium solver on quaternions), the reference configuration
            statics = mech.base_motion == "fixed" and tree.nq == tree.nv
            q_init = solve_equilibrium(mech, actuation, efforts, positions).q if statics else tree.q0
        self._q_init = tree.check_q(np.array(q_init, dtype=float)).copy()
        if self.T is not None:
            on_basis(mech, basis_offset(mech, self._q_init), "q_init")
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, q=None):
        """Back to the initial estimate (or q), zero velocities, offsets and
        wrench, the initial covariance and inputs, counters cleared."""
        n = self.n
        self.x = np.zeros(self.nq + n + self.nb + self.k)
        self.x[:self.nq] = self._q_init if q is None else self.tree.check_q(np.asarray(q, dtype=float))
        self.P = self._P0.copy()
        self.t = 0.0
        self.a = np.zeros(n)
        self.u = self.u_nominal.copy()
        self.q_cmd = self._q_cmd_nominal.copy()
        self.effort_cmd = self._effort_nominal.copy()
        self.health = FilterHealth()
        self.last_report = UpdateReport()
        self._gated_run = {s.name: 0 for s in self.sensors}
        cons = self.mech.constraints
        self._targets = [c.target.copy() if c.b.joint < 0 else None for c in cons] if self._base_k is not None \
            else None                      # a prescribed base's target: where it starts
        self._target_rate = np.zeros(self.mech.n_constraint_rows)
        self.lam = self._rest_multipliers()

    def _rest_multipliers(self):
        """The closed chains' reactions at the current q at rest (empty
        without constraints): the warm start of the first step."""
        sim = self._sim
        if sim.lam.size == 0:
            return sim.lam.copy()
        sim.q, sim.v = self.q.copy(), np.zeros(self.n)
        effort, _ = self._servo(self.q, sim.v)
        sim.start_multipliers(self._inputs(effort, self._tip_loads()), self._targets)
        return sim.lam.copy()

    @property
    def q(self):
        return self.x[:self.nq]

    @property
    def v(self):
        return self.x[self.nq:self.nq + self.n]

    @property
    def offsets(self):
        """Estimated tracking offsets (position - command) of the
        position-controlled joints, in the order of ``mech.joints_with("position")``."""
        return self.x[self.nq + self.n:self.nq + self.n + self.nb]

    def joint_offsets(self):
        """{position-controlled joint: (offset [rad or m], standard deviation)}."""
        i0, p0 = self.nq + self.n, 2 * self.nr         # in x, in P (the errors: nr for q)
        return {self.tree.joints[i].name: (float(self.x[i0 + k]), float(np.sqrt(self.P[p0 + k, p0 + k])))
                for k, i in enumerate(self._pos_joints)}

    def wrench(self):
        """Estimated tip wrench [f; m] (6,), world axes (zeros where not estimated)."""
        return self.S @ self.x[self.nq + self.n + self.nb:]

    def wrench_std(self):
        """Standard deviations (6,) of :meth:`wrench` (zeros where not estimated)."""
        return np.sqrt(np.diag(self._wrench_cov()))

    def _wrench_cov(self):
        """Covariance (6, 6) of :meth:`wrench`: S P_w S^T."""
        i = 2 * self.nr + self.nb
        return self.S @ self.P[i:, i:] @ self.S.T

    def payload_mass_kg(self):
        """Mass [kg] whose weight explains the estimated tip force, and its std."""
        gn = np.linalg.norm(self._g)
        if self.k == 0 or gn == 0:
            return 0.0, float("inf")
        i = 2 * self.nr + self.nb
        if self.wrench_mode == "payload":
            return float(self.x[self.nq + self.n + self.nb]), float(np.sqrt(self.P[i, i]))
        d = self._g / gn
        Pf = self._wrench_cov()[:3, :3]
        return float(self.wrench()[:3] @ d / gn), float(np.sqrt(d @ Pf @ d) / gn)

    def set_inputs(self, actuation=None, positions=None, efforts=None, base_pose=None):
        """New inputs (each None: kept); ValueError naming a bad one.
        ``base_pose``: a prescribed base's world pose (4x4) at the end of the
        next step (it moves there from the last one; at the same pose it
        rests)."""
        if base_pose is not None:
            self._set_base_pose(base_pose)
        if actuation is not None:
            self.u = actuation_vector(self.mech, actuation)
        if positions is not None:
            cur = dict(zip([self.tree.joints[i].name for i in self._pos_joints], self.q_cmd))
            if isinstance(positions, dict):
                cur.update(positions)
                positions = cur
            self.q_cmd = joint_vector(self.mech, positions, "position", "position", "rad or m")
        if efforts is not None:
            eff = joint_vector(self.mech, efforts, "effort", "effort", "N m or N")
            for k, i in enumerate(self.mech.joints_with("effort")):
                self.effort_cmd[self.tree.idx_v[i]] = eff[k]

    def _set_base_pose(self, pose):
        if self._base_k is None:
            raise ValueError(f"base_pose: only for a prescribed base (this robot's is {self.mech.base_motion})")
        T = checked_rigid_transform(pose, "base_pose")
        k, r = self._base_k, self._base_row
        T0 = self._targets[k]
        self._target_rate[r:r + 3] = (T[:3, 3] - T0[:3, 3]) / self.dt          # the base's twist over the step,
        self._target_rate[r + 3:r + 6] = log_so3(T[:3, :3] @ T0[:3, :3].T) / self.dt   # world axes at its origin
        self._targets[k] = T.copy()

    def q_covariance(self):
        """Covariance (nv, nv) of the errors of q (of the coordinates z
        mapped by the strain basis, ``B P_zz B^T``, with variable-strain
        segments)."""
        nr = self.nr
        P = self.P[:nr, :nr]
        return P if self.T is None else self.T @ P @ self.T.T

    def joint_positions(self):
        """{revolute or prismatic joint: (position [rad or m], standard deviation)}."""
        out = {}
        Pq = self.q_covariance()
        for i in self.mech.rigid_joints:
            k = self.tree.idx_v[i]
            out[self.tree.joints[i].name] = (float(self.q[self.tree.idx_q[i]]), float(np.sqrt(Pq[k, k])))
        return out

    def _point(self, frame):
        ref = self.mech.frame(frame)
        return int(ref.joint), float(ref.x)

    def frame_pose(self, frame):
        """World pose (4x4) of a named frame of the robot at the estimate."""
        j, x = self._point(frame)
        return alg.point_poses(self.tree, self.ws, self.q, [j], [x])[0].copy()

    def frame_position_cov(self, frame):
        """Covariance (3, 3) [m^2] of a frame's position, ``Jp P_qq Jp^T``."""
        j, x = self._point(frame)
        _, Jw = alg.point_jacobian(self.tree, self.ws, self.q, j, x, "world")
        return Jw[:3] @ self.q_covariance() @ Jw[:3].T

    def tip_pose(self):
        """World pose (4x4) of the tip frame (:func:`mechanism.tip_frame`)."""
        return self.frame_pose(self.tip)

    def tip_position_cov(self):
        """Covariance (3, 3) [m^2] of the tip frame's position."""
        return self.frame_position_cov(self.tip)

    def member_backbone(self, member, points_per_section=4):
        """World poses (P, 4, 4) along a member at the estimate."""
        m = self.mech.member(member)
        path = self.tree.paths[m.path]
        s = np.linspace(0.0, path.length, points_per_section * len(path.joints) + 1)
        j, x = path.locate(s)
        return alg.point_poses(self.tree, self.ws, self.q, j, x)

    # ------------------------------------------------------------- prediction
    def _tip_loads(self):
        """LoadArrays of the estimated tip wrench (a dead load at the tip
        frame) and of the point-moment tendons' follower moments at the
        inputs (:func:`forces.point_moment_arrays`)."""
        j, x = self._tip_point
        tip = alg.make_loads(self.tree, [j], [x], [self.wrench() if self.k else np.zeros(6)], [True])
        return concat_loads(tip, point_moment_arrays(self.tree, self.u)) if len(self.u) else tip

    def _servo(self, q, v):
        """(effort (nv,), M) of the joints' servo model at (q, v)."""
        effort = self.effort_cmd.copy()
        M = alg.crba(self.tree, self.ws, q).copy()
        if len(self._pos_v):
            bias = alg.rnea(self.tree, self.ws, q, v, np.zeros(self.n)).copy()
            j = self._pos_v
            mjj = _servo_inertia(M, j)
            effort[j] = bias[j] + mjj * (self._w ** 2 * (self.q_cmd + self.offsets - q[self._pos_q])
                                         - 2 * self._zeta * self._w * v[j])
        return effort, M

    def linearisation(self):
        """(Phi, Gamma_u) of one step from the current state (module
        docstring), analytic: :func:`theta_step_jacobian` of the forces'
        Jacobians; the offsets and the tip wrench are random walks."""
        M, dq, dv, F, G = self._force_jacobians()
        T = self.T
        if T is not None:             # in the strain basis's coordinates: the Galerkin projection
            M, dq, dv, F, G = T.T @ M @ T, T.T @ dq @ T, T.T @ dv @ T, T.T @ F, G @ T
        N, n_ext, nr = self.P.shape[0], self.nb + self.k, self.nr
        steps = None
        if self.nq != self.n:     # quaternions: the step's map on the joints' groups, at vt ~ v (O(dt) as dF)
            steps = (*integrate_jacobians(self.tree, self.v, self.theta * self.dt),
                     *integrate_jacobians(self.tree, self.v, self.dt))
        if steps is not None and T is not None:       # E T = T E_z: the group joints are columns of their own
            steps = tuple(self._Tp @ E @ T for E in steps)
        J = theta_step_jacobian(M, dq, dv, F, G, self.dt, self.theta, steps)
        Phi = np.zeros((N, N))
        Phi[:2 * nr] = J[:, :N]
        Phi[2 * nr:, 2 * nr:] = np.eye(n_ext)
        Gamma = np.zeros((N, F.shape[1] - n_ext))
        Gamma[:2 * nr] = J[:, N:]
        return Phi, Gamma

    def _force_jacobians(self):
        """(M, dF/dq, dF/dv, F_x, G) at the current state: the mass matrix,
        the derivatives of the forces ``F = tau - effort - applied`` (the
        servo's effort, the geometric stiffness of the tip load, the
        follower moments, the tendons and the closed chains' reactions
        included), the generalised forces per unit offset, tip wrench and
        input ``F_x = [F_b, J_tip^T S, B]``, and the closed chains'
        constraint Jacobian G (m, nv)."""
        tree, ws, n, nb, k = self.tree, self.ws, self.n, self.nb, self.k
        q, v = np.ascontiguousarray(self.q), np.ascontiguousarray(self.v)
        dq, dv = alg.rnea_derivatives(tree, ws, q, v, self.a)          # inertia, gravity, K, D
        dq, dv = dq.copy(), dv.copy()
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
        if k or self._point_moments or self.lam.size:  # geometric stiffness: tip load, follower moments, reactions
            loads = self._tip_loads()
            if self.lam.size:
                loads = concat_loads(loads, constraint_loads(self._servo_mech, self.lam))
            passes.rnea_pass(ws.m, ws.w, loads, self._zero_g, np.empty(n), True)
            static_tangent_pass(ws.m, ws.w, loads, self._zero_g, dq)
        if len(self.u):
            actuation_tangent_pass(ws.m, ws.w, self._act, np.ascontiguousarray(self._act.unit @ self.u), dq)
        M = alg.crba(tree, ws, q).copy()
        j = self._pos_v
        Fb = np.zeros((n, nb))                                          # d effort / d offset
        if len(j):
            dq0, dv0 = alg.rnea_derivatives(tree, ws, q, v, np.zeros(n))
            mjj = _servo_inertia(M, j)
            dq[j] -= dq0[j]
            dv[j] -= dv0[j]
            dq[j, j] += mjj * self._w ** 2
            dv[j, j] += mjj * 2 * self._zeta * self._w
            Fb[j, np.arange(len(j))] = mjj * self._w ** 2
        cols = [Fb]
        if k:
            _, Js = alg.point_jacobian(tree, ws, q, *self._tip_point, "world")
            cols.append(Js.T @ self.S)                                  # generalised force per unit w
        cols.append(actuation_matrix(tree, ws, self._act, q) if len(self.u) else np.zeros((n, 0)))
        G = constraint_rows(self._servo_mech, ws, q)[1]
        return M, dq, dv, np.hstack(cols), G

    def _inputs(self, effort, loads):
        return Inputs(self.u, effort, self._no_cmd, None, loads, self._g)

    def _mean_step(self, q, v, effort, loads):
        """(q1, v1, lam1) of one step of the process model from (q, v) with
        these efforts and loads, or None when the step fails."""
        sim = self._sim
        sim.q, sim.v, sim.t, sim.a, sim.lam = q.copy(), v.copy(), self.t, self.a.copy(), self.lam.copy()
        try:
            sim.step(inputs=self._inputs(effort, loads), targets=self._targets)
        except StepError:
            return None
        return sim.q, sim.v, sim.lam

    def predict(self, actuation=None, positions=None, efforts=None, base_pose=None):
        """Advance the estimate by dt (inputs as :meth:`set_inputs`; None:
        the last ones). Returns True when the integrator step converged (else
        the mean stays where it was, the covariance grows and the failure is
        counted)."""
        self.set_inputs(actuation, positions, efforts, base_pose)
        Phi, Gamma = self.linearisation()
        n = self.n
        q, v = self.q.copy(), self.v.copy()
        effort, M = self._servo(q, v)
        loads = self._tip_loads()
        j = self._pos_v
        for _ in range(4):
            stepped = self._mean_step(q, v, effort, loads)
            if stepped is None or not (len(j) and self._tracking):
                break
            # the twin's tracking: correct the efforts until the joints land on their commands
            # (dq1 = theta h^2 d effort / m_j, the soft members free to bend)
            err = self.q_cmd + self.offsets - stepped[0][self._pos_q]
            if np.abs(err).max() <= 1e-9:
                break
            effort = effort.copy()
            effort[j] += _servo_inertia(M, j) * err / (self.theta * self.dt ** 2)
        if stepped is not None:
            q1, v1, self.lam = stepped
            self.a = (v1 - self.v) / self.dt
            self.x[:self.nq] = q1
            self.x[self.nq:self.nq + n] = v1
        else:
            self.health.integrator_failures += 1
        self.P = Phi @ self.P @ Phi.T + self.Q * self.dt + (Gamma * self.sigma_u ** 2) @ Gamma.T
        if self.lam.size:
            G = constraint_rows(self._servo_mech, self.ws, self.q)[1]
            self.P = constrained_covariance(self.P, G if self.T is None else G @ self.T)
        self.P = 0.5 * (self.P + self.P.T)
        self.t += self.dt
        self.health.predictions += 1
        return stepped is not None

    # ----------------------------------------------------------------- update
    def update(self, measurements):
        """Measurement update with ``{sensor name: reading}`` (see
        :func:`sensors.measurement_vector`; None or absent: dropped; a
        tension sensor's reading becomes the input of its actuator for the
        next predictions). Unknown names raise ValueError. Returns the
        :class:`UpdateReport`."""
        for name in measurements:
            if name not in self.by_name:
                raise ValueError(f"measurements: unknown sensor {name!r}; configured: {list(self.by_name)}")
        rep = UpdateReport()
        nr, N = self.nr, self.P.shape[0]
        q = None
        es, Hs, Rs = [], [], []
        for sen in self.sensors:
            z = measurements.get(sen.name)
            tension = isinstance(sen, sn.TensionSensor)
            if z is None:
                if not tension:
                    rep.dropped.append(sen.name)
                continue
            try:
                z = sn.measurement_vector(sen, z)
            except ValueError as err:
                rep.rejected[sen.name] = str(err)
                continue
            if tension:
                a = self._where[sen.name]
                self.u[a] = max(float(z), 0.0) if self._tendon[a] else float(z)
                continue
            if q is None:
                q = sn.forward(self.ws, self.q)
            ft_load = isinstance(sen, sn.BaseWrenchSensor) and self.k
            load = (*self._tip_point, self.wrench()) if ft_load else None
            e, Hq = sn.residual_and_jacobian(self.ws, q, sen, self._where[sen.name], z, point_load=load)
            H = np.zeros((len(e), N))
            H[:, :nr] = Hq if self.T is None else Hq @ self.T
            if ft_load:                     # the support carries the estimated tip load too
                i = 2 * nr + self.nb
                H[:, i:i + self.k] = sn.base_wrench_load_jacobian(self.tree, self.ws, q, *self._tip_point) @ self.S
            Rm = sen.noise_covariance()
            if not gate_reading(rep, sen.name, e, H, Rm, self.P, self._gate(len(e)), self._gated_run,
                                self.max_gated_run):
                continue
            es.append(e)
            Hs.append(H)
            Rs.append(Rm)
        if es:
            dx, self.P = kalman_update(self.P, es, Hs, Rs)
            self._correct(dx)
            if self.lam.size:
                self._onto_the_loops()
        tally_update(self.health, rep)
        self.last_report = rep
        return rep

    def _correct(self, dx):
        """x (+) dx: the correction dx (the errors' layout: nr for q and v)
        added, q moved on the joints' groups (:func:`integrators.integrate_pass`)."""
        n, nq, nr, T = self.n, self.nq, self.nr, self.T
        if T is None:
            self._move_q(dx[:n])
            self.x[nq:] += dx[n:]
        else:                      # the coordinates' corrections, mapped by the basis
            self._move_q(T @ dx[:nr])
            self.x[nq:nq + n] += T @ dx[nr:2 * nr]
            self.x[nq + n:] += dx[2 * nr:]

    def _move_q(self, dq):
        q1 = np.empty(self.nq)
        integrate_pass(self.ws.m, np.ascontiguousarray(self.q), np.ascontiguousarray(dq, dtype=float), 1.0, q1)
        self.x[:self.nq] = q1

    def _onto_the_loops(self, iterations=3):
        """Back onto the closed chains after an update, which moves along
        their tangent but leaves a second-order gap: the least change of q
        with Phi(q) = 0 (Gauss-Newton), then of v with G v = 0."""
        T = np.eye(self.n) if self.T is None else self.T       # (variable-strain segments: on their basis)
        for _ in range(iterations):
            phi, G = constraint_rows(self._servo_mech, self.ws, self.q, self._targets)
            if np.abs(phi).max(initial=0.0) <= 1e-13:
                break
            self._move_q(-T @ np.linalg.lstsq(G @ T, phi, rcond=None)[0])
        G = constraint_rows(self._servo_mech, self.ws, self.q)[1]
        rate = self._target_rate[:G.shape[0]]              # a prescribed base moves: G v is its twist
        self.x[self.nq:self.nq + self.n] -= T @ np.linalg.lstsq(G @ T, G @ self.v - rate, rcond=None)[0]

    def _gate(self, m):
        g = self.gate.get(m)
        if g is None:
            from scipy.stats import chi2
            g = self.gate[m] = float(chi2.ppf(self._gate_probability, m))
        return g

    def step(self, measurements, **inputs):
        """predict(**inputs) then update(measurements); returns the UpdateReport."""
        self.predict(**inputs)
        return self.update(measurements)


def unit_directions(x, name):
    """(k, 3) unit vectors from ``x`` (k = 1..3 independent directions,
    e.g. ``[[0, 0, 1]]``); ValueError naming ``name`` otherwise."""
    try:
        D = np.array(x, dtype=float)
    except (TypeError, ValueError):
        D = np.zeros((0, 0))
    if D.ndim == 1 and D.size % 3 == 0:
        D = D.reshape(-1, 3)
    if D.ndim != 2 or D.shape[1] != 3 or not 1 <= len(D) <= 3:
        raise ValueError(f"{name}: expected 1 to 3 directions of 3 components each, got {x!r}")
    norms = np.linalg.norm(D, axis=1)
    if not np.all(np.isfinite(D)) or np.any(norms == 0):
        raise ValueError(f"{name}: a direction is zero or not finite: {D.tolist()}")
    D = D / norms[:, None]
    if np.linalg.matrix_rank(D, tol=1e-6) < len(D):
        raise ValueError(f"{name}: the directions are not independent: {D.tolist()}")
    return D


def parse_directions(text, name):
    """'x,y,z' or 'x,y,z;x,y,z' (a command line's or a node parameter's
    text) -> :func:`unit_directions`; ValueError naming ``name``."""
    try:
        rows = [[float(c) for c in d.split(",")] for d in str(text).split(";")]
    except ValueError:
        raise ValueError(f"{name}: expected 'x,y,z' or 'x,y,z;x,y,z', got {text!r}") from None
    if any(len(r) != 3 for r in rows):
        raise ValueError(f"{name}: expected 'x,y,z' or 'x,y,z;x,y,z', got {text!r}")
    return unit_directions(rows, name)


def _in_coordinates(Tp, variances):
    """The covariances of independent errors of q and v (``variances``:
    per coordinate of q, then of v) in the coordinates z of ``q = q0 + T
    z`` (variable-strain segments; ``Tp`` = T^+ = (T^T T)^-1 T^T, None:
    unchanged): the least-squares projection ``T^+ diag(var) T^+^T``. The noise of
    a strain field that the sections carry independently, restricted to
    the basis: a coordinate spanning n sections gets 1/n of a section's
    variance, as the n sections' independent noises move its shape."""
    if Tp is None:
        return [np.diag(v) for v in variances]
    return [(Tp * v) @ Tp.T for v in variances]


def _check_supported(mech):
    """ValueError naming what the filter does not handle: other kinematic
    maps than the exponential (the process Jacobian's
    :func:`algorithms.rnea_derivatives`)."""
    if np.any(mech.tree.arrays.kmap != 0):
        raise ValueError("EKF: only exponential-map sections are supported (the process Jacobian uses "
                         "algorithms.rnea_derivatives)")


def theta_step_jacobian(M, dq, dv, F, G, h, theta, step_jacobians=None):
    """d(q1, v1) / d(q0, v0, e): the Jacobian (2n, 2n + n_e) of one theta
    step of the linearised dynamics with holonomic constraints,

        M da + dF/dq dq + dF/dv dv - G^T dlam = F de,

    by the integrator's own rule: ``q1 = q0 (+) h vt``, ``vt = (1 - theta)
    v0 + theta v1``, the forces at ``qt = q0 (+) theta h vt`` and the
    constraints at the end of the step, ``G dq1 = 0``; linearised
    (:func:`integrators.integrate_jacobians`) ``dqt = E_t dq0 + theta h J_t
    dvt`` and ``dq1 = E_1 dq0 + h J_1 dvt`` (``step_jacobians``: (E_t, J_t,
    E_1, J_1); None: identities, every joint a vector space). With the
    step's Newton matrix ``A_h = M / h + theta^2 h dF/dq J_t + theta dF/dv``
    each column solves

        [[A_h, -G^T], [theta h G J_1, 0]] [dv1; dlam] =
            [-dF/dq E_t dq0 + (M/h - theta (1 - theta) h dF/dq J_t - (1 - theta) dF/dv) dv0 + F de;
             -G E_1 dq0 - (1 - theta) h G J_1 dv0].

    Without constraints (G with no row) and on vector spaces this is the
    theta discretisation of ``xdot = A x + b e``: ``(I - theta h A)^-1
    [I + (1 - theta) h A, h b]``."""
    n, ne = M.shape[0], F.shape[1]
    I = np.eye(n)
    Et, Jt, E1, J1 = step_jacobians if step_jacobians is not None else (I, I, I, I)
    dqJ = dq @ Jt
    rhs = np.zeros((n, 2 * n + ne))
    rhs[:, :n] = -dq @ Et
    rhs[:, n:2 * n] = M / h - theta * (1.0 - theta) * h * dqJ - (1.0 - theta) * dv
    rhs[:, 2 * n:] = F
    GJ = G @ J1
    cons = np.zeros((G.shape[0], 2 * n + ne))
    cons[:, :n] = -G @ E1
    cons[:, n:2 * n] = -(1.0 - theta) * h * GJ
    A_h = M / h + theta ** 2 * h * dqJ + theta * dv
    if G.shape[0]:
        dv1, _ = solve_factored(factor_kkt(A_h, G, theta * h * GJ), -rhs, -cons)
    else:
        dv1 = np.linalg.solve(A_h, rhs)
    dvt = theta * dv1                  # d vt = (1 - theta) dv0 + theta dv1
    dvt[:, n:2 * n] += (1.0 - theta) * I
    dq1 = h * J1 @ dvt
    dq1[:, :n] += E1
    return np.vstack([dq1, dv1])


def constrained_covariance(P, G):
    """P conditioned on the constraints holding exactly, to first order:
    the Kalman update with the perfect measurements ``G dq = 0`` and ``G dv
    = 0`` (the state's first 2 nv entries), ``P - P H^T (H P H^T)^+ H P``."""
    n = G.shape[1]
    H = np.zeros((2 * G.shape[0], P.shape[0]))
    H[:G.shape[0], :n] = G
    H[G.shape[0]:, n:2 * n] = G
    PH = P @ H.T
    return P - PH @ np.linalg.pinv(H @ PH, rcond=1e-12, hermitian=True) @ PH.T


def _servo_inertia(M, j):
    """The inertia a joint's effort meets at once, ``1 / (M^-1)_jj`` (the soft
    members free to bend: less than M_jj), so that the servo model
    accelerates the joint at the rate its gains say."""
    return 1.0 / np.diag(np.linalg.inv(M))[j]


def gate_reading(rep, name, e, H, Rm, P, gate, runs, max_run):
    """The gate of one reading: its normalised
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


def kalman_update(P, es, Hs, Rs):
    """The EKF measurement update with the accepted sensors' residuals es
    (e = h(x) - z), Jacobians Hs and noise covariances Rs stacked: gain
    K = P H^T (H P H^T + R)^-1, the correction -K e of the state (in the
    errors' coordinates), and the covariance in Joseph form
    (I - K H) P (I - K H)^T + K R K^T, symmetrised. Returns (dx, P)."""
    e, H, Rm = np.concatenate(es), np.vstack(Hs), block_diag(Rs)
    PHt = P @ H.T
    K = np.linalg.solve(H @ PHt + Rm, PHt.T).T
    IKH = np.eye(P.shape[0]) - K @ H
    P = IKH @ P @ IKH.T + K @ Rm @ K.T
    return -K @ e, 0.5 * (P + P.T)


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


def nees(error, cov):
    """Normalised estimation error squared ``e^T P^-1 e``."""
    error = np.asarray(error, dtype=float)
    return float(error @ np.linalg.solve(cov, error))
