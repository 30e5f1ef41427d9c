"""Measurement models of the sensors a soft arm carries, with analytic
Jacobians (for the estimator, :mod:`soft_twin_core.estimation`, and the
calibration, :mod:`soft_twin_core.calibration`).

Sensors sit on the classic robot's backbone (a :class:`model.RobotModel`)
at arc length ``s`` [m]; their frame is the cross-section frame ``g(s)``
followed by a fixed ``placement`` (4x4, in the cross-section frame):

    T_world_sensor(q) = g(s; q) @ placement

- :class:`PoseSensor` (an electromagnetic tracker): measures the position
  p [m] and rotation R of its frame, noise ``sigma_position_m`` on each
  position axis and ``sigma_rotation_rad`` on each axis of the rotation
  error vector.
- :class:`PositionMarker` (motion capture): the position only, of the point
  ``offset_m`` (3,) in the cross-section frame.

Every sensor gives a *residual* ``e(q) = h(q) [-] z`` in its tangent space
(zero when the model explains the measurement z exactly):

    position:  e_p = p(q) - p_meas                       (world axes, m)
    rotation:  e_R = log(R_meas^T R(q))                  (rad, sensor axes)

and its analytic Jacobian ``de/dq`` from the body Jacobian of the sensor
frame ``J_sensor = Ad(placement)^-1 J_body(s)``
(:func:`algorithms.point_jacobian`):

    de_p/dq = R_sensor J_sensor[:3]
    de_R/dq = Jr(e_R)^-1 J_sensor[3:]

(Jr: the right Jacobian of SO(3), :func:`lie.T_so3`; right perturbation
``R(q + dq) = R(q) exp(hat(J_sensor[3:] dq))``.) A Kalman filter's
innovation is ``-e`` with ``H = de/dq``. The measurement noise covariance
of the residual is ``diag(sigma_position^2 I3, sigma_rotation^2 I3)`` (for
rotation noise ``R_meas = R_true exp(hat(n))``, ``e_R = -n`` at the truth).

:class:`TensionSensor`: a measured tendon tension [N] (or chamber pressure
[Pa]) is an *input* of the twin, not a function of q; the estimator feeds
it to the process model and turns its noise into process noise through the
actuation matrix ``B(q) = d tau_act / d u`` (:func:`actuation_matrix`,
exact: the actuation force is linear in the inputs).

Units SI; conventions of docs/CONVENTIONS.md.
"""

from dataclasses import dataclass, field

import numpy as np

from . import lie


@dataclass(frozen=True, eq=False)
class PoseSensor:
    """A 6-dof pose sensor at arc length ``s`` [m] (see the module docstring)."""
    name: str
    s: float
    sigma_position_m: float
    sigma_rotation_rad: float
    placement: np.ndarray = field(default_factory=lambda: np.eye(4))
    size = 6

    def noise_covariance(self):
        return np.diag([self.sigma_position_m ** 2] * 3 + [self.sigma_rotation_rad ** 2] * 3)


@dataclass(frozen=True, eq=False)
class PositionMarker:
    """A position-only marker at arc length ``s`` [m], ``offset_m`` (3,) from
    the centre line in the cross-section frame."""
    name: str
    s: float
    sigma_position_m: float
    offset_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size = 3

    @property
    def placement(self):
        P = np.eye(4)
        P[:3, 3] = self.offset_m
        return P

    def noise_covariance(self):
        return self.sigma_position_m ** 2 * np.eye(3)


@dataclass(frozen=True, eq=False)
class TensionSensor:
    """A measured input of actuator ``actuator`` (tension [N] or pressure
    [Pa]) with noise ``sigma`` in the same unit."""
    name: str
    actuator: str
    sigma: float
    size = 0


def check_sensors(model, sensors):
    """Validate a list of sensors against a robot model; returns it as a
    tuple. Raises ValueError naming the bad sensor and field."""
    names = set()
    out = []
    for k, sen in enumerate(sensors):
        where = f"sensors[{k}] ({getattr(sen, 'name', '?')!r})"
        if not isinstance(sen, (PoseSensor, PositionMarker, TensionSensor)):
            raise ValueError(f"{where}: expected a PoseSensor, PositionMarker or TensionSensor, got {type(sen)}")
        if not isinstance(sen.name, str) or not sen.name:
            raise ValueError(f"{where}.name: expected a non-empty string")
        if sen.name in names:
            raise ValueError(f"{where}.name: duplicate sensor name {sen.name!r}")
        names.add(sen.name)
        if isinstance(sen, TensionSensor):
            if sen.actuator not in model.actuator_names:
                raise ValueError(f"{where}.actuator: unknown actuator {sen.actuator!r}; "
                                 f"this robot has {list(model.actuator_names)}")
            if not (np.isfinite(sen.sigma) and sen.sigma > 0):
                raise ValueError(f"{where}.sigma: expected a positive noise level, got {sen.sigma!r}")
        else:
            if not (np.isfinite(sen.s) and -1e-12 <= sen.s <= model.total_length + 1e-12):
                raise ValueError(f"{where}.s: expected an arc length in [0, {model.total_length}] m, got {sen.s!r}")
            sig = [sen.sigma_position_m] + ([sen.sigma_rotation_rad] if isinstance(sen, PoseSensor) else [])
            if not all(np.isfinite(x) and x > 0 for x in sig):
                raise ValueError(f"{where}: noise standard deviations must be positive, got {sig}")
            P = np.asarray(sen.placement, dtype=float)
            if P.shape != (4, 4) or not np.all(np.isfinite(P)):
                raise ValueError(f"{where}.placement: expected a finite 4x4 transform")
        out.append(sen)
    return tuple(out)


def sensor_pose(model, q, sensor, ws=None):
    """World pose (4x4) of the sensor frame at configuration q."""
    return pose_and_jacobian(model, q, sensor, ws)[0]


def _located(model, sensor):
    """(joint, abscissa) of the sensor's arc length on the backbone, cached."""
    cache = model.__dict__.get("_sensor_locations")
    if cache is None:
        cache = {}
        object.__setattr__(model, "_sensor_locations", cache)
    key = float(sensor.s)
    loc = cache.get(key)
    if loc is None:
        joint, x = model.tree.path("backbone").locate(np.array([key]))
        loc = cache[key] = (int(joint[0]), float(x[0]))
    return loc


def pose_and_jacobian(model, q, sensor, ws=None, kinematics_done=False):
    """(T_world_sensor 4x4, body Jacobian of the sensor frame 6 x n_dof).
    ``kinematics_done``: the forward pass of ``ws`` is already at q (several
    sensors share one pass)."""
    from .kernels import passes
    from .kernels.frames import spatial_jacobian
    from .workspace import thread_workspace
    tree = model.tree
    ws = thread_workspace(tree) if ws is None else ws
    if not kinematics_done:
        q = np.ascontiguousarray(model.check_q(q), dtype=float)
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    joint, x = _located(model, sensor)
    g = np.empty((4, 4))
    Js = np.empty((6, tree.nv))
    spatial_jacobian(ws.m, ws.w, joint, x, g, Js)
    T = g @ np.asarray(sensor.placement, dtype=float)
    return T, lie.Ad_inv(T) @ Js


def measurement_vector(sensor, z):
    """A measurement as an array: a pose sensor takes a 4x4 pose or
    (position (3,), quaternion [x, y, z, w]) as 7 numbers; a marker a
    position (3,). Raises ValueError for a wrong shape or non-finite values
    (the estimator counts those as rejected)."""
    z = np.asarray(z, dtype=float)
    if isinstance(sensor, PoseSensor):
        if z.shape == (7,):
            z = pose_from_position_quaternion(z[:3], z[3:])
        if z.shape != (4, 4):
            raise ValueError(f"sensor {sensor.name!r}: expected a 4x4 pose or 7 numbers "
                             f"(position, quaternion x y z w), got shape {z.shape}")
    elif isinstance(sensor, PositionMarker):
        if z.shape != (3,):
            raise ValueError(f"sensor {sensor.name!r}: expected a position of 3 numbers, got shape {z.shape}")
    else:
        if z.shape not in ((), (1,)):
            raise ValueError(f"sensor {sensor.name!r}: expected one number, got shape {z.shape}")
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


def residual(model, q, sensor, z, ws=None):
    """Residual ``e(q) = h(q) [-] z`` of one measurement (see the module
    docstring): (6,) for a pose sensor, (3,) for a marker."""
    return residual_and_jacobian(model, q, sensor, z, ws)[0]


def residual_and_jacobian(model, q, sensor, z, ws=None, kinematics_done=False):
    """(e (m,), de/dq (m, n_dof)) of one pose sensor or marker measurement z
    (a 4x4 pose / a position (3,)), analytic (module docstring)."""
    T, J = pose_and_jacobian(model, q, sensor, ws, kinematics_done)
    R = T[:3, :3]
    Hp = R @ J[:3]
    if isinstance(sensor, PositionMarker):
        return T[:3, 3] - z, Hp
    e_rot = lie.log_so3(z[:3, :3].T @ R)
    Hr = lie.T_so3_inv(e_rot) @ J[3:]
    return np.concatenate([T[:3, 3] - z[:3, 3], e_rot]), np.vstack([Hp, Hr])


def predict_measurement(model, q, sensor, ws=None):
    """What the sensor would read at q (no noise): a 4x4 pose, or a position (3,)."""
    T = sensor_pose(model, q, sensor, ws)
    return T[:3, 3].copy() if isinstance(sensor, PositionMarker) else T


def simulate_measurement(model_or_pose, sensor, rng, q=None):
    """A noisy reading of ``sensor``: from a model at q, or from a given
    true sensor pose (4x4). Position noise N(0, sigma_p^2 I); rotation noise
    ``R_true exp(hat(n))``, n ~ N(0, sigma_r^2 I)."""
    T = model_or_pose if q is None else sensor_pose(model_or_pose, q, sensor)
    if isinstance(sensor, PositionMarker):
        return T[:3, 3] + sensor.sigma_position_m * rng.standard_normal(3)
    out = T.copy()
    out[:3, 3] += sensor.sigma_position_m * rng.standard_normal(3)
    out[:3, :3] = T[:3, :3] @ lie.exp_so3(sensor.sigma_rotation_rad * rng.standard_normal(3))
    return out


def actuation_matrix(model, q, ws=None):
    """B(q) = d tau_act / d u (n_dof, n_actuators): the generalised actuation
    force per unit input at q, exact (the actuation force is linear in u:
    column k is the engine's actuation force for the unit input e_k)."""
    from .forces import actuation_pass
    from .kernels import passes
    from .statics import _actuators
    from .workspace import thread_workspace
    if any(a.tendon_model == "point_moment" for a in model.actuators):
        raise NotImplementedError("actuation_matrix: point-moment tendons are not supported "
                                  "(use the distributed tendon model)")
    tree = model.tree
    ws = thread_workspace(tree) if ws is None else ws
    act = _actuators(model)
    q = np.ascontiguousarray(model.check_q(q), dtype=float)
    z = np.zeros(tree.nv)
    passes.forward_pass(ws.m, ws.w, q, z, z, 0)
    B = np.zeros((tree.nv, len(model.actuators)))
    for k in range(len(model.actuators)):
        out = np.zeros(tree.nv)
        actuation_pass(ws.m, ws.w, act, np.ascontiguousarray(act.unit[:, k]), out)
        B[:, k] = out
    return B


# ----------------------------------------------------------------------------
# Sensor files
# ----------------------------------------------------------------------------

def sensors_from_list(items, model, where="sensors"):
    """Sensors from plain dicts (the YAML schema of a sensors file)::

        - {name: em0, type: pose, s: 0.16, sigma_position: 1.0e-3, sigma_rotation: 0.01,
           offset: [0, 0, 0], rpy: [0, 0, 0]}            # placement in the cross-section frame
        - {name: tip, type: marker, s: 0.40, sigma_position: 5.0e-4, offset: [0, 0, 0]}
        - {name: t_y, type: tension, actuator: tendon_y_pos, sigma: 0.2}

    (m, rad, N). Raises ValueError naming the bad entry and field."""
    from .model import ModelError, parse_number, pose_from_dict
    if not isinstance(items, list) or not items:
        raise ValueError(f"{where}: expected a non-empty list of sensors")
    out = []
    for k, d in enumerate(items):
        w = f"{where}[{k}]"
        if not isinstance(d, dict):
            raise ValueError(f"{w}: expected a mapping")
        kind = d.get("type")
        allowed = {"pose": {"name", "type", "s", "sigma_position", "sigma_rotation", "offset", "rpy"},
                   "marker": {"name", "type", "s", "sigma_position", "offset"},
                   "tension": {"name", "type", "actuator", "sigma"}}
        if kind not in allowed:
            raise ValueError(f"{w}.type: expected pose, marker or tension, got {kind!r}")
        extra = set(d) - allowed[kind]
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
            elif kind == "marker":
                off = np.asarray(d.get("offset", [0.0, 0.0, 0.0]), dtype=float)
                if off.shape != (3,):
                    raise ValueError(f"{w}.offset: expected 3 numbers [m], got {d.get('offset')!r}")
                out.append(PositionMarker(name, num("s"), num("sigma_position"), off))
            else:
                P = pose_from_dict({"position": d.get("offset", [0.0, 0.0, 0.0]), "rpy": d.get("rpy", [0.0, 0.0, 0.0])},
                                   f"{w}")
                out.append(PoseSensor(name, num("s"), num("sigma_position"), num("sigma_rotation"), P))
        except ModelError as e:
            raise ValueError(str(e)) from None
        except TypeError as e:
            raise ValueError(f"{w}: {e}") from None
    return check_sensors(model, out)


def load_sensors(path, model):
    """Sensors of a YAML file (a list, or a mapping with a ``sensors:`` list)."""
    from .model import read_yaml_file
    d = read_yaml_file(path, ValueError, "sensors file")
    if isinstance(d, dict):
        d = d.get("sensors")
    return sensors_from_list(d, model, f"sensors file {path}")


def sensors_to_list(sensors):
    """The plain-dict form of sensors (inverse of :func:`sensors_from_list`)."""
    out = []
    for s in sensors:
        if isinstance(s, TensionSensor):
            out.append({"name": s.name, "type": "tension", "actuator": s.actuator, "sigma": float(s.sigma)})
        elif isinstance(s, PositionMarker):
            out.append({"name": s.name, "type": "marker", "s": float(s.s), "sigma_position": float(s.sigma_position_m),
                        "offset": [float(x) for x in s.offset_m]})
        else:
            from scipy.spatial.transform import Rotation
            rpy = Rotation.from_matrix(s.placement[:3, :3]).as_euler("xyz")
            out.append({"name": s.name, "type": "pose", "s": float(s.s), "sigma_position": float(s.sigma_position_m),
                        "sigma_rotation": float(s.sigma_rotation_rad),
                        "offset": [float(x) for x in s.placement[:3, 3]], "rpy": [float(x) for x in rpy]})
    return out
