"""Calibration data from an MCAP recording (ROS 2 bag format): the
actuation commands and the sensor readings of named topics, aligned in
time, as a :class:`calibration.Recording` (the same fit as from CSV).

Topics (all optional but the commands; decoded with ``mcap`` and
``mcap-ros2-support``, messages read by attribute, no ROS import):

- the commands, ``actuation_topic`` (default ``/soft_twin/actuation``,
  soft_twin/ActuationCommand: ``names``, ``values``; a command naming some
  actuators keeps the others, as the twin does; before the first one every
  input is 0);
- the joint commands of a robot with position-controlled joints,
  ``joint_command_topic`` (default ``/soft_twin/joint_commands``,
  sensor_msgs/JointState: ``name``, ``position``, as the twin's node takes
  and records them; a command naming some joints keeps the others; before
  the first one each joint is at its reference; the efforts of
  effort-controlled joints are not read);
- the known loads, as the twin's node takes them: ``point_wrench_topic``
  (default ``/soft_twin/point_wrench_command``, soft_twin/PointWrench:
  ``point``, ``wrench``; ``header.frame_id`` the point itself: a follower
  load, else a dead load along the base axes) and ``tip_wrench_topic``
  (default ``/soft_twin/tip_wrench_command``, geometry_msgs/WrenchStamped
  on the tip frame; ``header.frame_id`` the base frame ``base_frame``
  (default ``base_link``): a dead load, else a follower). A wrench replaces
  the one before on its point (the tip's command and a point command on
  the tip are apart, as in the node), all zeros removes it; before the
  first, none. A point that is not the robot's is skipped
  (``bad_load``);
- the estimator node's measurement topics under ``measurements_ns``
  (default ``/soft_twin_estimator``): ``<ns>/measurements/poses``
  (PoseArray, one pose per pose sensor in the sensors file's order),
  ``<ns>/measurements/pose`` (PoseStamped, ``header.frame_id`` = sensor
  name), ``<ns>/measurements/position`` (PointStamped, a marker's name),
  ``<ns>/measurements/joint_states`` (JointState: an encoder sensor reads
  when the message names all its joints) and
  ``<ns>/measurements/base_wrench`` (WrenchStamped: the base force/torque
  sensor's reading);
- per sensor a topic of its own (``topics={sensor: topic}``, e.g. a tip
  tracker): PoseStamped, PoseWithCovarianceStamped, TransformStamped or
  PointStamped (the position only, for a marker).

Time of a message: its ``header.stamp`` (the sensor's clock), or the log
time when the stamp is zero. Readings that are not finite, of the wrong
length, or name an unknown sensor are skipped and counted (``skipped``).

**Static sweep** (:func:`read_static_sweep`): the commands cut the time
into holds of a constant input (a repeated identical command does not);
each hold with readings gives one row: its input, and per sensor the mean
of its readings from ``settle_s`` after the hold's start to its end (the
arm has settled; default: the second half of each hold) -- position the
arithmetic mean, rotation the mean rotation matrix projected onto SO(3).
The time before the first command is a hold of zero input.

**Time series** (:func:`read_time_series`, for damping): one row per
reading time of the first sensor that has readings; the input held at that
time (zero-order hold) and per sensor the reading nearest in time within
``tolerance_s`` (else NaN: not seen).
"""

import numpy as np

from soft_twin_core.estimation import sensors as sn
from soft_twin_core.estimation.calibration import CalibrationError, Recording, as_mechanism, position_joints
from soft_twin_core.files.mcap_salvage import read_decoded
from soft_twin_core.robot.mechanism import tip_frame

DEFAULT_ACTUATION_TOPIC = "/soft_twin/actuation"
DEFAULT_JOINT_COMMAND_TOPIC = "/soft_twin/joint_commands"
DEFAULT_MEASUREMENTS_NS = "/soft_twin_estimator"
DEFAULT_POINT_WRENCH_TOPIC = "/soft_twin/point_wrench_command"
READ_KINDS = (sn.PoseSensor, sn.JointStateSensor, sn.BaseWrenchSensor)
DEFAULT_TIP_WRENCH_TOPIC = "/soft_twin/tip_wrench_command"


def is_mcap(path):
    """True when the file starts with the MCAP magic bytes."""
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return False


def _time_ns(msg, log_time):
    h = getattr(msg, "header", None)
    st = getattr(h, "stamp", None)
    if st is not None:
        ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
        if ns:
            return ns
    return int(log_time)


def _iter(path, topics):
    """(topic, time [ns], decoded message) of the topics, in log-time order."""
    # a recording cut short is read up to its last complete chunk, with a warning
    return [(channel.topic, _time_ns(decoded, message.log_time), decoded)
            for channel, message, decoded in read_decoded(path, list(topics), CalibrationError,
                                                          what="data file")]


def _pose_of(p):
    """4x4 from a message pose-like (position + orientation), or ValueError."""
    pos = np.array([p.position.x, p.position.y, p.position.z], dtype=float)
    o = p.orientation
    quat = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise ValueError("not finite")
    if not np.linalg.norm(quat) > 1e-6:
        raise ValueError("zero quaternion")
    return sn.pose_from_position_quaternion(pos, quat)


def _reading(sensor, msg):
    """A reading of one sensor from a PoseStamped, PoseWithCovarianceStamped,
    TransformStamped or PointStamped message, or an encoder's or F/T
    sensor's values already read (ValueError when unusable)."""
    if isinstance(msg, np.ndarray):
        return sn.measurement_vector(sensor, msg)
    if hasattr(msg, "point"):
        z = np.array([msg.point.x, msg.point.y, msg.point.z], dtype=float)
        if not sensor.position_only:
            raise ValueError(f"a point for pose sensor {sensor.name!r}")
        return sn.measurement_vector(sensor, z)
    if hasattr(msg, "transform"):
        t = msg.transform
        T = _pose_of(type("P", (), {"position": t.translation, "orientation": t.rotation}))
    else:
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        T = _pose_of(pose)
    return sn.measurement_vector(sensor, T[:3, 3] if sensor.position_only else T)


def _joint_references(model, joints):
    tree = model.tree
    return np.array([next(j.q_ref for j in tree.joints if j.name == name) for name in joints], dtype=float)


def read_events(path, model, sensors, *, actuation_topic=DEFAULT_ACTUATION_TOPIC,
                joint_command_topic=DEFAULT_JOINT_COMMAND_TOPIC, measurements_ns=DEFAULT_MEASUREMENTS_NS,
                topics=None, point_wrench_topic=DEFAULT_POINT_WRENCH_TOPIC, tip_wrench_topic=DEFAULT_TIP_WRENCH_TOPIC,
                base_frame="base_link"):
    """The commands and readings of a recording: (commands [(t_ns, (input,
    loads))] with the full input after each command -- the actuation u
    (n_act,) followed by the position commands of the position-controlled
    joints (:func:`calibration.position_joints`) -- and the known loads
    then (a tuple of ((slot, point, axes), wrench 6-tuple))), the first entry
    ``(None, ...)`` the input before any command; readings {sensor: [(t_ns,
    reading)]}, skipped {reason: count}). Raises CalibrationError naming a
    bad topic mapping or an empty recording."""
    sensors = [s for s in sensors if isinstance(s, READ_KINDS)]
    by_name = {s.name: s for s in sensors}
    topics = dict(topics or {})
    for name in topics:
        if name not in by_name:
            raise CalibrationError(f"--topic {name}=...: unknown sensor {name!r}; sensors: {list(by_name)}")
    ns = "/" + measurements_ns.strip("/") if measurements_ns.strip("/") else ""
    t_poses, t_pose, t_pos = f"{ns}/measurements/poses", f"{ns}/measurements/pose", f"{ns}/measurements/position"
    t_joints, t_ft = f"{ns}/measurements/joint_states", f"{ns}/measurements/base_wrench"
    own = {topic: name for name, topic in topics.items()}
    joints = list(position_joints(model))
    events = _iter(path, {actuation_topic, t_poses, t_pose, t_pos, t_joints, t_ft, point_wrench_topic,
                          tip_wrench_topic, *own} | ({joint_command_topic} if joints else set()))
    pose_sensors = [s for s in sensors if isinstance(s, sn.PoseSensor) and not s.position_only]
    names = list(model.actuator_names)
    u = np.concatenate([np.zeros(len(names)), _joint_references(model, joints) if joints else []])
    loads = {}                                          # {(slot, point, axes): wrench 6-tuple}
    mech = None                                         # (the loaded points' robot, made at the first load)
    commands, readings = [(None, (u.copy(), ()))], {s.name: [] for s in sensors}
    skipped = {}

    def skip(reason):
        skipped[reason] = skipped.get(reason, 0) + 1

    def take(sensor, t, msg):
        try:
            readings[sensor.name].append((t, _reading(sensor, msg)))
        except (ValueError, AttributeError):
            skip("bad_reading")

    for topic, t, msg in events:
        if topic == actuation_topic:
            new = u.copy()
            ok = len(msg.names) == len(msg.values)
            for n, v in zip(msg.names, msg.values) if ok else ():
                if n not in names or not np.isfinite(v):
                    ok = False
                    break
                new[names.index(n)] = v
            if not ok:
                skip("bad_command")
                continue
            u = new
            commands.append((t, (u.copy(), tuple(sorted(loads.items())))))
        elif topic == joint_command_topic:
            new = _joint_command(u, msg, joints, len(names))
            if new is None:
                skip("bad_joint_command")
                continue
            if len(msg.position):
                u = new
                commands.append((t, (u.copy(), tuple(sorted(loads.items())))))
        elif topic in (point_wrench_topic, tip_wrench_topic):
            mech = as_mechanism(model) if mech is None else mech
            if not _load_command(loads, mech, msg, topic == tip_wrench_topic, base_frame):
                skip("bad_load")
                continue
            commands.append((t, (u.copy(), tuple(sorted(loads.items())))))
        elif topic in own:
            take(by_name[own[topic]], t, msg)
        elif topic == t_joints:
            value = dict(zip(msg.name, msg.position)) if len(msg.name) == len(msg.position) else None
            if value is None:
                skip("wrong_length")
                continue
            for s in sensors:
                if isinstance(s, sn.JointStateSensor) and all(j in value for j in s.joints):
                    take(s, t, np.array([value[j] for j in s.joints], dtype=float))
        elif topic == t_ft:
            ft = [s for s in sensors if isinstance(s, sn.BaseWrenchSensor)]
            if not ft:
                skip("unknown_sensor")
                continue
            f, m = msg.wrench.force, msg.wrench.torque
            take(ft[0], t, np.array([f.x, f.y, f.z, m.x, m.y, m.z], dtype=float))
        elif topic == t_poses:
            if len(msg.poses) != len(pose_sensors):
                skip("wrong_length")
                continue
            for s, p in zip(pose_sensors, msg.poses):
                take(s, t, type("M", (), {"pose": p}))
        else:
            s = by_name.get(msg.header.frame_id)
            if not isinstance(s, sn.PoseSensor) or s.position_only != (topic == t_pos):
                skip("unknown_sensor")
                continue
            take(s, t, msg)
    if len(commands) == 1:
        where = repr(actuation_topic) + (f" or {joint_command_topic!r}" if joints else "")
        raise CalibrationError(f"data file {path}: no actuation command on {where}, nor a known load on "
                               f"{point_wrench_topic!r} or {tip_wrench_topic!r}")
    if not any(readings.values()):
        raise CalibrationError(f"data file {path}: no sensor reading on "
                               f"{sorted({t_poses, t_pose, t_pos, t_joints, t_ft, *own})}")
    return commands, readings, skipped


def _load_command(loads, model, msg, tip, base_frame):
    """Apply one known-load command (soft_twin/PointWrench, or the tip's
    WrenchStamped when ``tip``) to ``loads`` {(slot, point, axes): wrench};
    False (and ``loads`` unchanged) for a point that is not the robot's or
    a wrench that is not finite."""
    try:
        point = tip_frame(model) if tip else str(msg.point)
        model.frame(point)
        f, m = msg.wrench.force, msg.wrench.torque
        w = tuple(float(x) for x in (f.x, f.y, f.z, m.x, m.y, m.z))
    except (KeyError, AttributeError, TypeError, ValueError):
        return False
    if not np.all(np.isfinite(w)):
        return False
    frame = msg.header.frame_id
    axes = ("world" if frame == base_frame else "body") if tip else ("body" if frame == point else "world")
    slot = "tip" if tip else "point"
    for key in [k for k in loads if k[:2] == (slot, point)]:
        del loads[key]
    if any(w):
        loads[(slot, point, axes)] = w
    return True


def _joint_command(u, msg, joints, n_act):
    """The input u with the positions of a JointState command (None: a name
    that is not a joint of the robot, a position that is not finite, or
    positions not one per name; efforts of effort-controlled joints are
    left to the twin)."""
    names, pos = list(msg.name), list(msg.position)
    if pos and len(pos) != len(names):
        return None
    new = u.copy()
    for n, v in zip(names, pos):
        if n not in joints or not np.isfinite(v):
            return None
        new[n_act + joints.index(n)] = v
    return new


def _recording(model, inputs, rows, times):
    """A :class:`calibration.Recording` of input rows ([u; joint positions],
    known loads) (:func:`read_events`): the loads summed per (point, axes)."""
    loads = [ld for _, ld in inputs]
    inputs = np.array([u for u, _ in inputs])
    n_act = len(model.actuator_names)
    joints = inputs[:, n_act:] if inputs.shape[1] > n_act else None
    keys = sorted({(point, axes) for ld in loads for (_, point, axes), _ in ld})
    wrenches = {k: np.zeros((len(inputs), 6)) for k in keys}
    for r, ld in enumerate(loads):
        for (_, point, axes), w in ld:
            wrenches[(point, axes)][r] += w
    return Recording(inputs[:, :n_act], {k: np.array(v) for k, v in rows.items()}, times, joints,
                     wrenches=wrenches)


def _not_seen(s):
    """The NaN reading of a sensor not seen in a row."""
    if isinstance(s, sn.JointStateSensor):
        return np.full(len(s.joints), np.nan)
    if isinstance(s, sn.BaseWrenchSensor):
        return np.full(6, np.nan)
    return np.full(3 if s.position_only else (4, 4), np.nan)


def _mean_reading(zs):
    zs = np.asarray(zs)
    if zs.ndim == 2:                                  # positions (k, 3)
        return zs.mean(axis=0)
    T = np.eye(4)
    T[:3, 3] = zs[:, :3, 3].mean(axis=0)
    U, _, Vt = np.linalg.svd(zs[:, :3, :3].mean(axis=0))
    T[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return T


def _holds(commands, t_first):
    """[(t_start, t_end, u)] of constant inputs (the first from t_first at
    the input before any command, ``commands[0]``)."""
    out = []
    (_, u), commands = commands[0], commands[1:]
    start = min(t_first, commands[0][0])
    for t, v in commands:
        if np.array_equal(v[0], u[0]) and v[1] == u[1]:
            continue
        if t > start:
            out.append((start, t, u))
        start, u = t, v
    out.append((start, None, u))
    return out


def read_static_sweep(path, model, sensors, *, settle_s=None, **topic_args):
    """A :class:`Recording` of a static sweep (module docstring) and a report
    dict (holds, rows, readings averaged, skipped messages)."""
    commands, readings, skipped = read_events(path, model, sensors, **topic_args)
    sensors = [s for s in sensors if isinstance(s, READ_KINDS)]
    if settle_s is not None and not (np.isfinite(settle_s) and settle_s >= 0):
        raise CalibrationError(f"--settle must be >= 0 s, got {settle_s}")
    t_first = min(t for r in readings.values() for t, _ in r)
    t_last = max(t for r in readings.values() for t, _ in r)
    holds = _holds(commands, t_first)
    inputs, rows, times, averaged = [], {s.name: [] for s in sensors}, [], []
    for start, end, u in holds:
        end = t_last + 1 if end is None else end
        settle = 0.5 * (end - start) if settle_s is None else settle_s * 1e9
        lo = start + settle
        got = {s.name: [z for t, z in readings[s.name] if lo <= t < end] for s in sensors}
        if not any(got.values()):
            continue
        inputs.append(u)
        times.append(1e-9 * (start - holds[0][0]))
        for s in sensors:
            z = got[s.name]
            rows[s.name].append(_mean_reading(z) if z else _not_seen(s))
        averaged.append(sum(len(z) for z in got.values()))
    if not inputs:
        raise CalibrationError(f"data file {path}: no hold of the commands has readings after settling")
    rec = _recording(model, inputs, rows, np.array(times))
    report = {"holds": len(holds), "rows": len(inputs), "readings_averaged": int(sum(averaged)),
              "skipped": skipped}
    return rec, report


def read_time_series(path, model, sensors, *, tolerance_s=None, **topic_args):
    """A :class:`Recording` of a time series (module docstring) and a report."""
    commands, readings, skipped = read_events(path, model, sensors, **topic_args)
    sensors = [s for s in sensors if isinstance(s, READ_KINDS)]
    lead = next(s for s in sensors if readings[s.name])
    times = np.array([t for t, _ in readings[lead.name]], dtype=np.int64)
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        keep = np.concatenate([[True], np.diff(times) > 0])
        times = times[keep]
    if tolerance_s is not None:
        tol = tolerance_s * 1e9
    else:                                          # half the lead sensor's sample period
        tol = 0.5 * float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    u0 = commands[0][1]                                   # the input before the first command
    ct = np.array([t for t, _ in commands[1:]], dtype=np.int64)
    cu = [u for _, u in commands[1:]]
    inputs = []
    for t in times:
        k = np.searchsorted(ct, t, side="right") - 1
        inputs.append(cu[k] if k >= 0 else u0)
    rows = {}
    for s in sensors:
        st = np.array([t for t, _ in readings[s.name]], dtype=np.int64)
        zs = [z for _, z in readings[s.name]]
        out = []
        for t in times:
            if len(st) == 0:
                out.append(_not_seen(s))
                continue
            k = int(np.argmin(np.abs(st - t)))
            out.append(zs[k] if abs(st[k] - t) <= tol else _not_seen(s))
        rows[s.name] = np.array(out)
    rec = _recording(model, inputs, rows, 1e-9 * (times - times[0]))
    return rec, {"rows": len(times), "commands": len(commands) - 1, "skipped": skipped}
