"""Sensors of a robot (any :class:`mechanism.Mechanism`: a classic rod, a
tree, a soft articulated arm), with analytic measurement Jacobians, for the
estimator (:mod:`soft_twin_core.estimation.ekf`) and the calibration
(:mod:`soft_twin_core.estimation.calibration`).

- :class:`PoseSensor` (an electromagnetic tracker; with
  ``sigma_rotation_rad`` None a position-only *marker*, motion capture):
  the pose of a frame on the robot, named by a frame of the robot file
  (``frame: tool``) or by arc length on a member (``member: arm, s:
  0.15``; ``member`` may be left out on a robot with one member, e.g. a
  classic rod), followed by a fixed ``placement`` (4x4, in that frame)::

      T_world_sensor(q) = g(point; q) @ placement

  Residuals in the tangent space (zero when the model explains the reading
  z exactly) and their Jacobians from the body Jacobian ``J`` of the
  sensor frame (the point's, :func:`kernels.frames.spatial_jacobian`,
  through every rigid and soft joint on its path, then ``Ad(T)^-1``):

      e_p = p(q) - p_meas          de_p/dq = R J[:3]            (world axes, m)
      e_R = log(R_meas^T R(q))     de_R/dq = Jr(e_R)^-1 J[3:]   (rad, sensor axes)

  (Jr: the right Jacobian of SO(3), :func:`lie.T_so3`; right perturbation
  ``R(q + dq) = R(q) exp(hat(J[3:] dq))``.) A Kalman filter's innovation
  is ``-e`` with ``H = de/dq``. Noise covariance ``diag(sigma_position^2
  I3, sigma_rotation^2 I3)`` (rotation noise ``R_meas = R_true
  exp(hat(n))``, so ``e_R = -n`` at the truth).
- :class:`JointStateSensor` (encoders, ``sensor_msgs/JointState``
  positions): the positions [rad or m] of named 1-dof rigid joints, noise
  ``sigma`` per joint. ``e = q_j - z``, Jacobian: rows of the identity at
  the joints' velocity indices (the joints are additive).
- :class:`BaseWrenchSensor` (a force/torque sensor under the base,
  ``geometry_msgs/WrenchStamped``): the wrench the support exerts on the
  robot [N; N m], world axes, about the base origin, in the quasi-static
  approximation (inertial forces neglected: a robot at rest or moving
  slowly): ``h(q) = [-m g; hat(g) c(q)]`` with m the total mass and
  ``c = sum_k m_k p_k`` the first mass moment, computed as the root joints'
  transmitted wrench of inverse dynamics at rest; Jacobian ``[0; hat(g)
  S]`` with ``S = dc/dq = sum_k m_k Jp_k = -[tau_x, tau_y, tau_z]^T``, the
  columns being the generalised gravity forces of inverse dynamics under a
  unit gravity along x, y, z (the gravity potential ``-m_k g . p_k``
  differentiated). A dead load ``[f; m]`` (world axes) on a point p of the
  robot -- the filter's estimated tip load -- is carried by the support
  too: ``h -= [f; p x f + m]``, ``dh/dq += [0; hat(f) Jp]`` (Jp the point's
  world velocity Jacobian; :func:`base_wrench_and_jacobian`), and in the
  load ``dh/d[f; m] = -[[I, 0], [hat(p), I]]``. Noise ``sigma_force_n``,
  ``sigma_moment_nm`` per axis.
- :class:`TensionSensor`: a measured tendon tension [N] (or chamber
  pressure [Pa]) is an *input* of the twin, not a function of q; the
  estimator feeds it to the process model and turns its noise into process
  noise through the actuation matrix ``B(q) = d tau_act / d u``
  (:func:`forces.actuation_matrix`, exact: the actuation force is linear in u).

:func:`check_sensors` validates a list against the robot once and returns
where each sensor sits (``where``: a point (joint, abscissa), or the
joints' velocity indices); the measurement functions take it.

Units SI; conventions of docs/CONVENTIONS.md.
"""

from dataclasses import dataclass, field

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.frames import spatial_jacobian
from soft_twin_core.engine.workspace import thread_workspace
from soft_twin_core.robot.model import ModelError, parse_number, pose_from_dict, read_yaml_file


@dataclass(frozen=True, eq=False)
class PoseSensor:
    """A pose sensor (or a marker: ``sigma_rotation_rad`` None) on the frame
    ``frame`` of the robot, or at arc length ``s`` [m] of member ``member``
    (module docstring); ``placement`` (4x4) in that frame."""
    name: str
    sigma_position_m: float
    sigma_rotation_rad: float = None
    frame: str = None
    member: str = None
    s: float = 0.0
    placement: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def position_only(self):
        return self.sigma_rotation_rad is None

    @property
    def size(self):
        return 3 if self.position_only else 6

    def noise_covariance(self):
        if self.position_only:
            return self.sigma_position_m ** 2 * np.eye(3)
        return np.diag([self.sigma_position_m ** 2] * 3 + [self.sigma_rotation_rad ** 2] * 3)


def marker(name, sigma_position_m, offset_m=(0.0, 0.0, 0.0), **where):
    """A position-only :class:`PoseSensor` at ``offset_m`` (3,) [m] from its
    point, in the point's frame (``where``: frame=, or member= and s=)."""
    P = np.eye(4)
    P[:3, 3] = np.asarray(offset_m, dtype=float)
    return PoseSensor(name, sigma_position_m, None, placement=P, **where)


@dataclass(frozen=True, eq=False)
class JointStateSensor:
    """Positions of the joints ``joints`` (names), noise ``sigma`` (one per joint) [rad or m]."""
    name: str
    joints: tuple
    sigma: np.ndarray

    @property
    def size(self):
        return len(self.joints)

    def noise_covariance(self):
        return np.diag(np.asarray(self.sigma, dtype=float) ** 2)


@dataclass(frozen=True, eq=False)
class BaseWrenchSensor:
    """A base force/torque sensor (module docstring), noise per axis [N], [N m]."""
    name: str
    sigma_force_n: float
    sigma_moment_nm: float
    size = 6

    def noise_covariance(self):
        return np.diag([self.sigma_force_n ** 2] * 3 + [self.sigma_moment_nm ** 2] * 3)


@dataclass(frozen=True, eq=False)
class TensionSensor:
    """A measured input of actuator ``actuator`` (tension [N] or pressure
    [Pa]) with noise ``sigma`` in the same unit."""
    name: str
    actuator: str
    sigma: float
    size = 0


SENSOR_TYPES = (PoseSensor, JointStateSensor, BaseWrenchSensor, TensionSensor)


# ----------------------------------------------------------------------------
# Validation (once, at the door)
# ----------------------------------------------------------------------------

def locate(mech, sensor):
    """(joint, abscissa) of a PoseSensor's point (ValueError naming the field)."""
    if sensor.frame is not None:
        try:
            ref = mech.frame(sensor.frame)
        except KeyError as e:
            raise ValueError(f"sensor {sensor.name!r}.frame: {e.args[0]}") from None
        return int(ref.joint), float(ref.x)
    member = sensor.member
    if member is None:
        if len(mech.members) != 1:
            raise ValueError(f"sensor {sensor.name!r}: give frame, or member and s (this robot has the members "
                             f"{[m.name for m in mech.members]})")
        member = mech.members[0].name
    try:
        m = mech.member(member)
    except KeyError as e:
        raise ValueError(f"sensor {sensor.name!r}.member: {e.args[0]}") from None
    path = mech.tree.paths[m.path]
    s = float(sensor.s)
    if not (np.isfinite(s) and -1e-12 <= s <= path.length + 1e-12):
        raise ValueError(f"sensor {sensor.name!r}.s: expected an arc length in [0, {path.length:g}] m on member "
                         f"{member!r}, got {sensor.s!r}")
    j, x = path.locate(np.array([min(max(s, 0.0), path.length)]))
    return int(j[0]), float(x[0])


def joint_velocity_indices(mech, joints, where="joints"):
    """Velocity indices of named 1-dof rigid joints (ValueError naming an unknown one)."""
    names = mech.joint_names
    out = []
    for n in joints:
        if n not in names:
            raise ValueError(f"{where}: unknown joint {n!r}; the rigid joints are {list(names)}")
        out.append(int(mech.tree.idx_v[mech.rigid_joints[names.index(n)]]))
    return np.array(out, dtype=np.int64)


def position_indices(model, velocity_indices):
    """The configuration indices of 1-dof joints given by their velocity
    indices (they differ after a ball joint or a floating base, whose
    quaternions take one entry more than their velocities)."""
    q_of_v = {int(model.idx_v[i]): int(model.idx_q[i]) for i, j in enumerate(model.joints) if j.nv == 1}
    return np.array([q_of_v[int(k)] for k in velocity_indices], dtype=np.int64)


def _positive(values):
    return all(isinstance(x, (int, float, np.floating)) and np.isfinite(x) and x > 0 for x in values)


def check_sensors(mech, sensors):
    """Validate the sensors against the robot; returns (sensors tuple,
    {name: where}): a PoseSensor's point (joint, abscissa), a
    JointStateSensor's velocity indices, the actuator index of a
    TensionSensor, None for a base wrench sensor. ValueError naming the
    bad sensor and field."""
    names, where_of = set(), {}
    for k, s in enumerate(sensors):
        w = f"sensors[{k}] ({getattr(s, 'name', '?')!r})"
        if not isinstance(s, SENSOR_TYPES):
            raise ValueError(f"{w}: expected one of {[c.__name__ for c in SENSOR_TYPES]}, got {type(s).__name__}")
        if not isinstance(s.name, str) or not s.name:
            raise ValueError(f"{w}.name: expected a non-empty string")
        if s.name in names:
            raise ValueError(f"{w}.name: duplicate sensor name {s.name!r}")
        names.add(s.name)
        if isinstance(s, JointStateSensor):
            if not s.joints or len(set(s.joints)) != len(s.joints):
                raise ValueError(f"{w}.joints: expected distinct joint names, got {list(s.joints)}")
            sig = np.asarray(s.sigma, dtype=float)
            if sig.shape != (len(s.joints),) or not np.all(np.isfinite(sig) & (sig > 0)):
                raise ValueError(f"{w}.sigma_position: expected {len(s.joints)} positive values, got {s.sigma!r}")
            where_of[s.name] = joint_velocity_indices(mech, s.joints, f"{w}.joints")
        elif isinstance(s, BaseWrenchSensor):
            if not _positive((s.sigma_force_n, s.sigma_moment_nm)):
                raise ValueError(f"{w}: noise standard deviations must be positive")
            if mech.base_motion != "fixed":
                raise ValueError(f"{w}: a base wrench sensor needs a fixed base")
            where_of[s.name] = None
        elif isinstance(s, TensionSensor):
            if s.actuator not in mech.actuator_names:
                raise ValueError(f"{w}.actuator: unknown actuator {s.actuator!r}; "
                                 f"this robot has {list(mech.actuator_names)}")
            if not _positive((s.sigma,)):
                raise ValueError(f"{w}.sigma: expected a positive noise level, got {s.sigma!r}")
            where_of[s.name] = list(mech.actuator_names).index(s.actuator)
        else:
            if s.frame is not None and s.member is not None:
                raise ValueError(f"{w}: give either frame or member (with s), not both")
            sig = [s.sigma_position_m] + ([] if s.position_only else [s.sigma_rotation_rad])
            if not _positive(sig):
                raise ValueError(f"{w}: noise standard deviations must be positive, got {sig}")
            P = np.asarray(s.placement, dtype=float)
            if P.shape != (4, 4) or not np.all(np.isfinite(P)):
                raise ValueError(f"{w}.placement: expected a finite 4x4 transform")
            try:
                where_of[s.name] = locate(mech, s)
            except ValueError as e:
                raise ValueError(f"{w}: {e}") from None
    return tuple(sensors), where_of


def measurement_vector(sensor, z):
    """A reading as an array: a pose (4x4, or position + quaternion x y z w
    as 7 numbers), a position (3,), joint positions (size,), a wrench (6,),
    a tension (one number). ValueError for a wrong shape or non-finite
    values (the estimator counts those as rejected)."""
    z = np.asarray(z, dtype=float)
    if isinstance(sensor, BaseWrenchSensor):
        if z.shape != (6,):
            raise ValueError(f"sensor {sensor.name!r}: expected a wrench of 6 numbers [f; m], got shape {z.shape}")
    elif isinstance(sensor, JointStateSensor):
        if z.shape != (sensor.size,):
            raise ValueError(f"sensor {sensor.name!r}: expected {sensor.size} joint positions "
                             f"{list(sensor.joints)}, got shape {z.shape}")
    elif isinstance(sensor, TensionSensor):
        if z.shape not in ((), (1,)):
            raise ValueError(f"sensor {sensor.name!r}: expected one number, got shape {z.shape}")
    elif sensor.position_only:
        if z.shape != (3,):
            raise ValueError(f"sensor {sensor.name!r}: expected a position of 3 numbers, got shape {z.shape}")
    else:
        if z.shape == (7,):
            z = pose_from_position_quaternion(z[:3], z[3:])
        if z.shape != (4, 4):
            raise ValueError(f"sensor {sensor.name!r}: expected a 4x4 pose or 7 numbers "
                             f"(position, quaternion x y z w), got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError(f"sensor {sensor.name!r}: measurement contains NaN or inf")
    return z


def pose_from_position_quaternion(p, quat_xyzw):
    """4x4 pose from a position and a unit quaternion [x, y, z, w] (normalised)."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=float) / np.linalg.norm(quat_xyzw)
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = p
    return T


# ----------------------------------------------------------------------------
# Measurement models (the forward pass of ``ws`` done at q)
# ----------------------------------------------------------------------------

def point_pose_and_body_jacobian(ws, joint, x, placement):
    """(T_world 4x4, body Jacobian 6 x nv) of the point (joint, x) followed by
    ``placement``, at the forward pass already done in ``ws``."""
    g = np.empty((4, 4))
    Js = np.empty((6, ws.zeros_v.shape[0]))
    spatial_jacobian(ws.m, ws.w, joint, x, g, Js)
    T = g @ placement
    return T, lie.Ad_inv(T) @ Js


def base_wrench_and_jacobian(tree, ws, q, jacobian=True, point_load=None):
    """(W (6,) the support's wrench on the robot at rest, world axes about
    the base origin; dW/dq (6, nv) or None), module docstring;
    ``point_load``: (joint, abscissa, [f; m] (6,) world axes) a dead load
    on that point, which the support balances too, or a list of them."""
    q = np.ascontiguousarray(q, dtype=float)
    z = np.zeros(tree.nv)
    g = np.asarray(tree.gravity, dtype=float)
    alg.rnea(tree, ws, q, z, z, None, g, elastic=False)
    W = np.zeros(6)
    for i in np.flatnonzero(tree.parents < 0):
        G = ws.work.g_in[i]
        R, p = G[:3, :3], G[:3, 3]
        f, m = R @ ws.work.f_in[i, :3], R @ ws.work.f_in[i, 3:]
        W += np.concatenate([f, m + np.cross(p, f)])
    loads = [] if point_load is None or not len(point_load) else \
        [point_load] if isinstance(point_load[0], (int, np.integer)) else list(point_load)
    arms = []
    for joint, x, w in loads:
        T, Jw = alg.point_jacobian(tree, ws, q, joint, x, "world")
        f, m = np.asarray(w[:3], dtype=float), np.asarray(w[3:], dtype=float)
        W -= np.concatenate([f, np.cross(T[:3, 3], f) + m])
        arms.append((f, Jw[:3]))
    if not jacobian:
        return W, None
    S = np.empty((3, tree.nv))
    for a in range(3):
        S[a] = -alg.rnea(tree, ws, q, z, z, None, np.eye(3)[a], elastic=False)
    H = np.zeros((6, tree.nv))
    H[3:] = lie.hat(g) @ S
    for f, Jp in arms:
        H[3:] += lie.hat(f) @ Jp
    return W, H


def base_wrench_load_jacobian(tree, ws, q, joint, x):
    """d W / d [f; m] (6, 6) of :func:`base_wrench_and_jacobian` in its
    point load on (joint, x): ``-[[I, 0], [hat(p), I]]``."""
    p = alg.point_jacobian(tree, ws, q, joint, x, "world")[0][:3, 3]
    D = -np.eye(6)
    D[3:, :3] = -lie.hat(p)
    return D


def residual_and_jacobian(ws, q, sensor, where, z, point_load=None):
    """(e (m,), de/dq (m, nv)) of one reading z (:func:`measurement_vector`)
    at q, the forward pass of ``ws`` done at q; ``where``: the sensor's
    entry of :func:`check_sensors`; ``point_load``: a dead load the base
    wrench sensor's support carries too (:func:`base_wrench_and_jacobian`).
    Module docstring."""
    nv = ws.zeros_v.shape[0]
    if isinstance(sensor, BaseWrenchSensor):
        W, H = base_wrench_and_jacobian(ws.model, ws, q, point_load=point_load)
        return W - z, H
    if isinstance(sensor, JointStateSensor):
        H = np.zeros((sensor.size, nv))
        H[np.arange(sensor.size), where] = 1.0
        return q[position_indices(ws.model, where)] - z, H
    T, J = point_pose_and_body_jacobian(ws, where[0], where[1], np.asarray(sensor.placement, dtype=float))
    R = T[:3, :3]
    Hp = R @ J[:3]
    if sensor.position_only:
        return T[:3, 3] - z, Hp
    e_rot = lie.log_so3(z[:3, :3].T @ R)
    return np.concatenate([T[:3, 3] - z[:3, 3], e_rot]), np.vstack([Hp, lie.T_so3_inv(e_rot) @ J[3:]])


def predict_measurement(ws, q, sensor, where, point_load=None):
    """Noise-free reading at q (the forward pass of ``ws`` done at q): a 4x4
    pose, a position (3,), joint positions, a wrench (6,) (with a dead
    ``point_load`` its support carries: :func:`base_wrench_and_jacobian`)."""
    if isinstance(sensor, BaseWrenchSensor):
        return base_wrench_and_jacobian(ws.model, ws, q, jacobian=False, point_load=point_load)[0]
    if isinstance(sensor, JointStateSensor):
        return q[position_indices(ws.model, where)]
    T, _ = point_pose_and_body_jacobian(ws, where[0], where[1], np.asarray(sensor.placement, dtype=float))
    return T[:3, 3].copy() if sensor.position_only else T


def forward(ws, q):
    """The forward pass of ``ws`` at q (the measurement models' precondition);
    returns q as a contiguous array."""
    q = np.ascontiguousarray(q, dtype=float)
    passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    return q


def sensor_pose(mech, q, sensor, ws=None):
    """World pose (4x4) of a PoseSensor's frame at q (one forward pass;
    ``ws``: a workspace of the robot's tree, else the thread's)."""
    ws = thread_workspace(mech.tree) if ws is None else ws
    j, x = locate(mech, sensor)
    forward(ws, q)
    return point_pose_and_body_jacobian(ws, j, x, np.asarray(sensor.placement, dtype=float))[0]


def predict_readings(ws, q, sensors, where):
    """{name: noise-free reading} of the measuring sensors (not the tension
    sensors) at q, one forward pass."""
    q = forward(ws, q)
    return {s.name: predict_measurement(ws, q, s, where[s.name]) for s in sensors
            if not isinstance(s, TensionSensor)}


def simulate_measurement(sensor, truth, rng):
    """A noisy reading from the noise-free one ``truth``: position noise
    N(0, sigma_p^2 I), rotation noise ``R_true exp(hat(n))``, n ~ N(0,
    sigma_r^2 I), joint and wrench noise per axis."""
    if isinstance(sensor, BaseWrenchSensor):
        return truth + np.repeat([sensor.sigma_force_n, sensor.sigma_moment_nm], 3) * rng.standard_normal(6)
    if isinstance(sensor, JointStateSensor):
        return truth + np.asarray(sensor.sigma) * rng.standard_normal(sensor.size)
    if isinstance(sensor, TensionSensor):
        return float(truth) + sensor.sigma * rng.standard_normal()
    if sensor.position_only:
        return truth + sensor.sigma_position_m * rng.standard_normal(3)
    out = np.array(truth, dtype=float)
    out[:3, 3] += sensor.sigma_position_m * rng.standard_normal(3)
    out[:3, :3] = out[:3, :3] @ lie.exp_so3(sensor.sigma_rotation_rad * rng.standard_normal(3))
    return out


# ----------------------------------------------------------------------------
# Sensor files
# ----------------------------------------------------------------------------

_FIELDS = {"pose": {"name", "type", "frame", "member", "s", "sigma_position", "sigma_rotation", "offset", "rpy"},
           "marker": {"name", "type", "frame", "member", "s", "sigma_position", "offset"},
           "joint_state": {"name", "type", "joints", "sigma_position"},
           "base_wrench": {"name", "type", "sigma_force", "sigma_moment"},
           "tension": {"name", "type", "actuator", "sigma"}}


def sensors_from_list(items, mech, where="sensors"):
    """Sensors from plain dicts (the YAML schema of a sensors file)::

        - {name: em0, type: pose, s: 0.16, sigma_position: 1.0e-3, sigma_rotation: 0.01,
           offset: [0, 0, 0], rpy: [0, 0, 0]}            # a robot with one member
        - {name: em_mid, type: pose, member: arm, s: 0.15, sigma_position: 1.0e-3, sigma_rotation: 0.01}
        - {name: em_tool, type: pose, frame: tool, sigma_position: 1.0e-3, sigma_rotation: 0.01}
        - {name: mk, type: marker, s: 0.40, sigma_position: 5.0e-4, offset: [0, 0, 0.01]}
        - {name: encoders, type: joint_state, joints: [pan, tilt], sigma_position: [1.0e-3, 1.0e-3]}
        - {name: ft, type: base_wrench, sigma_force: 0.05, sigma_moment: 0.005}
        - {name: t_y, type: tension, actuator: tendon_y_pos, sigma: 0.2}

    (m, rad, N, Pa; ``offset``/``rpy``: the placement in the point's frame;
    ``sigma_position`` of a joint_state: one value or one per joint, rad or
    m). Returns the checked tuple; ValueError naming the bad entry and field."""
    if not isinstance(items, list) or not items:
        raise ValueError(f"{where}: expected a non-empty list of sensors")
    out = []
    for k, d in enumerate(items):
        w = f"{where}[{k}]"
        if not isinstance(d, dict):
            raise ValueError(f"{w}: expected a mapping")
        kind = d.get("type")
        if kind not in _FIELDS:
            raise ValueError(f"{w}.type: expected one of {list(_FIELDS)}, got {kind!r}")
        extra = set(d) - _FIELDS[kind]
        if extra:
            raise ValueError(f"{w}: unknown field(s) {sorted(extra)} for a {kind} sensor")
        name = d.get("name")
        if not isinstance(name, str) or not name:
            raise ValueError(f"{w}.name: expected a non-empty string, got {name!r}")

        def num(key, default=None):
            if key not in d:
                if default is None:
                    raise ValueError(f"{w}.{key}: missing")
                return default
            try:
                return parse_number(d[key], f"{w}.{key}")
            except ModelError as e:
                raise ValueError(str(e)) from None
        try:
            if kind == "tension":
                out.append(TensionSensor(name, str(d.get("actuator")), num("sigma")))
            elif kind == "base_wrench":
                out.append(BaseWrenchSensor(name, num("sigma_force"), num("sigma_moment")))
            elif kind == "joint_state":
                joints = d.get("joints")
                if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
                    raise ValueError(f"{w}.joints: expected a list of joint names, got {joints!r}")
                sig = d.get("sigma_position")
                sig = [sig] * len(joints) if not isinstance(sig, list) else sig
                sig = [parse_number(x, f"{w}.sigma_position") for x in sig]
                out.append(JointStateSensor(name, tuple(joints), np.array(sig, dtype=float)))
            else:
                for key in ("frame", "member"):
                    if key in d and not isinstance(d[key], str):
                        raise ValueError(f"{w}.{key}: expected a name, got {d[key]!r}")
                off = d.get("offset", [0.0, 0.0, 0.0])
                if not (isinstance(off, list) and len(off) == 3):
                    raise ValueError(f"{w}.offset: expected 3 numbers [m], got {off!r}")
                P = pose_from_dict({"position": off, "rpy": d.get("rpy", [0.0, 0.0, 0.0])}, w)
                rot = num("sigma_rotation") if kind == "pose" else None
                s = num("s") if "frame" not in d else 0.0
                out.append(PoseSensor(name, num("sigma_position"), rot, d.get("frame"), d.get("member"), s, P))
        except ModelError as e:
            raise ValueError(str(e)) from None
    return check_sensors(mech, out)[0]


def load_sensors(path, mech):
    """Sensors of a YAML file (a list, or a mapping with a ``sensors:`` list)."""
    d = read_yaml_file(path, ValueError, "sensors file")
    if isinstance(d, dict):
        d = d.get("sensors")
    return sensors_from_list(d, mech, f"sensors file {path}")


def sensors_to_list(sensors):
    """The plain-dict form of sensors (inverse of :func:`sensors_from_list`)."""
    from scipy.spatial.transform import Rotation
    out = []
    for s in sensors:
        if isinstance(s, TensionSensor):
            out.append({"name": s.name, "type": "tension", "actuator": s.actuator, "sigma": float(s.sigma)})
        elif isinstance(s, BaseWrenchSensor):
            out.append({"name": s.name, "type": "base_wrench", "sigma_force": float(s.sigma_force_n),
                        "sigma_moment": float(s.sigma_moment_nm)})
        elif isinstance(s, JointStateSensor):
            out.append({"name": s.name, "type": "joint_state", "joints": list(s.joints),
                        "sigma_position": [float(x) for x in s.sigma]})
        else:
            d = {"name": s.name, "type": "marker" if s.position_only else "pose"}
            if s.frame is not None:
                d["frame"] = s.frame
            else:
                if s.member is not None:
                    d["member"] = s.member
                d["s"] = float(s.s)
            d["sigma_position"] = float(s.sigma_position_m)
            if not s.position_only:
                d["sigma_rotation"] = float(s.sigma_rotation_rad)
            P = np.asarray(s.placement, dtype=float)
            d["offset"] = [float(x) for x in P[:3, 3]]
            if not s.position_only:
                d["rpy"] = [float(x) for x in Rotation.from_matrix(P[:3, :3]).as_euler("xyz")]
            out.append(d)
    return out
