"""Sensors of a soft articulated robot (a tree robot,
:class:`mechanism.Mechanism`), with analytic measurement Jacobians, for the
tree estimator (:mod:`soft_twin_core.tree_estimation`).

- :class:`JointStateSensor` (encoders, ``sensor_msgs/JointState``
  positions): the positions [rad or m] of named 1-dof rigid joints, noise
  ``sigma`` per joint. Residual ``e = q_j - z``, Jacobian: rows of the
  identity at the joints' velocity indices (the joints are additive).
- :class:`FramePoseSensor`: the pose (or, ``sigma_rotation_rad`` None, the
  position only: a marker) of a frame on the tree, named by a frame of the
  robot file (``frame: tool``) or by arc length on a member (``member:
  arm, s: 0.15``), followed by a fixed ``placement`` (4x4). Residuals and
  Jacobians as :mod:`sensors` (``e_p = p - p_meas`` in world axes, ``e_R =
  log(R_meas^T R)`` with ``de_R/dq = Jr(e_R)^-1 J_body[3:]``), with the body
  Jacobian of the point from the compiled kernel
  (:func:`kernels.frames.spatial_jacobian`) through every rigid and soft
  joint on its path.

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
  differentiated). Noise ``sigma_force_n``, ``sigma_moment_nm`` per axis.

Units SI; conventions of docs/CONVENTIONS.md.
"""

from dataclasses import dataclass, field

import numpy as np

from . import lie


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
class FramePoseSensor:
    """A pose sensor (or a marker: ``sigma_rotation_rad`` None) on the frame
    ``frame`` of the robot, or at arc length ``s`` [m] of member ``member``."""
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


@dataclass(frozen=True, eq=False)
class BaseWrenchSensor:
    """A base force/torque sensor (module docstring), noise per axis [N], [N m]."""
    name: str
    sigma_force_n: float
    sigma_moment_nm: float
    size = 6

    def noise_covariance(self):
        return np.diag([self.sigma_force_n ** 2] * 3 + [self.sigma_moment_nm ** 2] * 3)


def base_wrench_and_jacobian(tree, ws, q, jacobian=True):
    """(W (6,) the support's wrench on the robot at rest, world axes about
    the base origin; dW/dq (6, nv) or None), module docstring."""
    from . import algorithms as alg
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
    if not jacobian:
        return W, None
    S = np.empty((3, tree.nv))
    for a in range(3):
        S[a] = -alg.rnea(tree, ws, q, z, z, None, np.eye(3)[a], elastic=False)
    H = np.zeros((6, tree.nv))
    H[3:] = lie.hat(g) @ S
    return W, H


def locate(mech, sensor):
    """(joint, abscissa) of a FramePoseSensor's point on the tree (ValueError naming the field)."""
    if sensor.frame is not None:
        try:
            ref = mech.frame(sensor.frame)
        except KeyError as e:
            raise ValueError(f"sensor {sensor.name!r}.frame: {e.args[0]}") from None
        return int(ref.joint), float(ref.x)
    try:
        m = mech.member(sensor.member)
    except KeyError as e:
        raise ValueError(f"sensor {sensor.name!r}.member: {e.args[0]}") from None
    path = mech.tree.paths[m.path]
    try:
        j, x = path.locate(np.array([float(sensor.s)]))
    except ValueError as e:
        raise ValueError(f"sensor {sensor.name!r}.s: {e}") from None
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


def check_tree_sensors(mech, sensors):
    """Validate the sensors against the mechanism; returns
    (sensors tuple, {name: (joint, x) or joint velocity indices})."""
    names, where_of = set(), {}
    for k, s in enumerate(sensors):
        w = f"sensors[{k}] ({getattr(s, 'name', '?')!r})"
        if not isinstance(s, (JointStateSensor, FramePoseSensor, BaseWrenchSensor)):
            raise ValueError(f"{w}: expected a JointStateSensor, FramePoseSensor or BaseWrenchSensor, "
                             f"got {type(s).__name__}")
        if not isinstance(s.name, str) or not s.name or s.name in names:
            raise ValueError(f"{w}.name: expected a unique non-empty string")
        names.add(s.name)
        if isinstance(s, JointStateSensor):
            if not s.joints or len(set(s.joints)) != len(s.joints):
                raise ValueError(f"{w}.joints: expected distinct joint names, got {list(s.joints)}")
            sig = np.asarray(s.sigma, dtype=float)
            if sig.shape != (len(s.joints),) or not np.all(np.isfinite(sig) & (sig > 0)):
                raise ValueError(f"{w}.sigma_position: expected {len(s.joints)} positive values, got {s.sigma!r}")
            where_of[s.name] = joint_velocity_indices(mech, s.joints, f"{w}.joints")
        elif isinstance(s, BaseWrenchSensor):
            if not all(np.isfinite(x) and x > 0 for x in (s.sigma_force_n, s.sigma_moment_nm)):
                raise ValueError(f"{w}: noise standard deviations must be positive")
            if mech.base_motion != "fixed":
                raise ValueError(f"{w}: a base wrench sensor needs a fixed base")
            where_of[s.name] = None
        else:
            if (s.frame is None) == (s.member is None):
                raise ValueError(f"{w}: give either frame or member (with s)")
            sig = [s.sigma_position_m] + ([] if s.position_only else [s.sigma_rotation_rad])
            if not all(np.isfinite(x) and x > 0 for x in sig):
                raise ValueError(f"{w}: noise standard deviations must be positive, got {sig}")
            P = np.asarray(s.placement, dtype=float)
            if P.shape != (4, 4) or not np.all(np.isfinite(P)):
                raise ValueError(f"{w}.placement: expected a finite 4x4 transform")
            where_of[s.name] = locate(mech, s)
    return tuple(sensors), where_of


def point_pose_and_body_jacobian(ws, joint, x, placement):
    """(T_world 4x4, body Jacobian 6 x nv) of the point (joint, x) followed by
    ``placement``, at the forward pass already done in ``ws``."""
    from .kernels.frames import spatial_jacobian
    g = np.empty((4, 4))
    Js = np.empty((6, ws.zeros_v.shape[0]))
    spatial_jacobian(ws.m, ws.w, joint, x, g, Js)
    T = g @ placement
    return T, lie.Ad_inv(T) @ Js


def measurement_vector(sensor, z):
    """A reading as an array: joint positions (size,), a pose (4x4, or
    position + quaternion x y z w as 7 numbers) or a position (3,).
    ValueError for a wrong shape or non-finite values."""
    from .sensors import pose_from_position_quaternion
    z = np.asarray(z, dtype=float)
    if isinstance(sensor, BaseWrenchSensor):
        if z.shape != (6,):
            raise ValueError(f"sensor {sensor.name!r}: expected a wrench of 6 numbers [f; m], got shape {z.shape}")
    elif isinstance(sensor, JointStateSensor):
        if z.shape != (sensor.size,):
            raise ValueError(f"sensor {sensor.name!r}: expected {sensor.size} joint positions "
                             f"{list(sensor.joints)}, got shape {z.shape}")
    elif sensor.position_only:
        if z.shape != (3,):
            raise ValueError(f"sensor {sensor.name!r}: expected a position of 3 numbers, got shape {z.shape}")
    else:
        if z.shape == (7,):
            z = pose_from_position_quaternion(z[:3], z[3:])
        if z.shape != (4, 4):
            raise ValueError(f"sensor {sensor.name!r}: expected a 4x4 pose or 7 numbers, got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError(f"sensor {sensor.name!r}: measurement contains NaN or inf")
    return z


def residual_and_jacobian(ws, q, sensor, where, z):
    """(e (m,), de/dq (m, nv)) of one reading at q (the forward pass of ``ws``
    done at q); ``where``: the sensor's entry of :func:`check_tree_sensors`."""
    nv = ws.zeros_v.shape[0]
    if isinstance(sensor, BaseWrenchSensor):
        W, H = base_wrench_and_jacobian(ws.model, ws, q)
        return W - z, H
    if isinstance(sensor, JointStateSensor):
        H = np.zeros((sensor.size, nv))
        H[np.arange(sensor.size), where] = 1.0
        return q[where] - z, H
    T, J = point_pose_and_body_jacobian(ws, where[0], where[1], np.asarray(sensor.placement, dtype=float))
    R = T[:3, :3]
    Hp = R @ J[:3]
    if sensor.position_only:
        return T[:3, 3] - z, Hp
    e_rot = lie.log_so3(z[:3, :3].T @ R)
    return np.concatenate([T[:3, 3] - z[:3, 3], e_rot]), np.vstack([Hp, lie.T_so3_inv(e_rot) @ J[3:]])


def predict_measurement(ws, q, sensor, where):
    """Noise-free reading at q (forward pass of ``ws`` done at q)."""
    if isinstance(sensor, BaseWrenchSensor):
        return base_wrench_and_jacobian(ws.model, ws, q, jacobian=False)[0]
    if isinstance(sensor, JointStateSensor):
        return q[where].copy()
    T, _ = point_pose_and_body_jacobian(ws, where[0], where[1], np.asarray(sensor.placement, dtype=float))
    return T[:3, 3].copy() if sensor.position_only else T


def simulate_measurement(sensor, truth, rng):
    """A noisy reading from the noise-free one ``truth``."""
    if isinstance(sensor, BaseWrenchSensor):
        return truth + np.repeat([sensor.sigma_force_n, sensor.sigma_moment_nm], 3) * rng.standard_normal(6)
    if isinstance(sensor, JointStateSensor):
        return truth + np.asarray(sensor.sigma) * rng.standard_normal(sensor.size)
    if sensor.position_only:
        return truth + sensor.sigma_position_m * rng.standard_normal(3)
    out = truth.copy()
    out[:3, 3] += sensor.sigma_position_m * rng.standard_normal(3)
    out[:3, :3] = truth[:3, :3] @ lie.exp_so3(sensor.sigma_rotation_rad * rng.standard_normal(3))
    return out


def tree_sensors_from_list(items, mech, where="sensors"):
    """Sensors of a tree robot from plain dicts (YAML)::

        - {name: encoders, type: joint_state, joints: [pan, tilt], sigma_position: [1.0e-3, 1.0e-3]}
        - {name: em_mid, type: pose, member: arm, s: 0.15, sigma_position: 1.0e-3, sigma_rotation: 0.01,
           offset: [0, 0, 0], rpy: [0, 0, 0]}
        - {name: em_tool, type: pose, frame: tool, sigma_position: 1.0e-3, sigma_rotation: 0.01}
        - {name: mk, type: marker, frame: tool, sigma_position: 5.0e-4, offset: [0, 0, 0]}
        - {name: ft, type: base_wrench, sigma_force: 0.05, sigma_moment: 0.005}

    (m, rad; ``sigma_position`` of a joint_state: one value or one per
    joint, rad or m). Raises ValueError naming the bad entry and field."""
    from .model import ModelError, parse_number, pose_from_dict
    if not isinstance(items, list) or not items:
        raise ValueError(f"{where}: expected a non-empty list of sensors")
    allowed = {"joint_state": {"name", "type", "joints", "sigma_position"},
               "pose": {"name", "type", "frame", "member", "s", "sigma_position", "sigma_rotation", "offset", "rpy"},
               "marker": {"name", "type", "frame", "member", "s", "sigma_position", "offset"},
               "base_wrench": {"name", "type", "sigma_force", "sigma_moment"}}
    out = []
    for k, d in enumerate(items):
        w = f"{where}[{k}]"
        if not isinstance(d, dict):
            raise ValueError(f"{w}: expected a mapping")
        kind = d.get("type")
        if kind not in allowed:
            raise ValueError(f"{w}.type: expected joint_state, pose, marker or base_wrench, got {kind!r}")
        extra = set(d) - allowed[kind]
        if extra:
            raise ValueError(f"{w}: unknown field(s) {sorted(extra)} for a {kind} sensor")
        name = d.get("name")

        def num(key, value=None):
            if key not in d and value is None:
                raise ValueError(f"{w}.{key}: missing")
            try:
                return parse_number(d.get(key, value), f"{w}.{key}")
            except ModelError as e:
                raise ValueError(str(e)) from None
        try:
            if kind == "joint_state":
                joints = d.get("joints")
                if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
                    raise ValueError(f"{w}.joints: expected a list of joint names, got {joints!r}")
                sig = d.get("sigma_position")
                sig = [sig] * len(joints) if not isinstance(sig, list) else sig
                sig = [parse_number(x, f"{w}.sigma_position") for x in sig]
                out.append(JointStateSensor(name, tuple(joints), np.array(sig, dtype=float)))
                continue
            if kind == "base_wrench":
                out.append(BaseWrenchSensor(name, num("sigma_force"), num("sigma_moment")))
                continue
            P = pose_from_dict({"position": d.get("offset", [0.0, 0.0, 0.0]), "rpy": d.get("rpy", [0.0, 0.0, 0.0])}, w)
            s = num("s", 0.0) if "member" in d else 0.0
            rot = num("sigma_rotation") if kind == "pose" else None
            out.append(FramePoseSensor(name, num("sigma_position"), rot, d.get("frame"), d.get("member"), s, P))
        except ModelError as e:
            raise ValueError(str(e)) from None
    return check_tree_sensors(mech, out)[0]


def load_tree_sensors(path, mech):
    """Sensors of a YAML file (a list, or a mapping with a ``sensors:`` list)."""
    from .model import read_yaml_file
    d = read_yaml_file(path, ValueError, "sensors file")
    if isinstance(d, dict):
        d = d.get("sensors")
    return tree_sensors_from_list(d, mech, f"sensors file {path}")
