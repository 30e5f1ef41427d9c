"""Calibration of a robot's parameters from a recorded static sweep by
nonlinear least squares (scipy.optimize.least_squares, trust region
reflective) with analytic sensitivities, for every robot file (a classic
rod, a tree robot: one :class:`mechanism.Mechanism` path).

Data: a :class:`Recording` -- per row the actuator inputs u (N or Pa), the
position commands of the position-controlled joints (rad or m; default
their references), the efforts of the effort-controlled joints (N m or N;
default 0), the known external wrenches on named frames or member points
(a hung weight, a force gauge; N, N m) and the readings of pose sensors
and position markers (:mod:`sensors`) at the equilibrium all these reach
(a static sweep; CSV format in :func:`read_csv`).

Parameters (names as given to :func:`calibrate`, SI units):

- ``youngs_modulus:<segment>`` [Pa] of a segment (its shear modulus
  follows at the fixed Poisson ratio; the stiffness is linear in E); a
  segment name used by two members of a tree is ``<member>/<segment>``;
  ``youngs_modulus:<a>+<b>``: one modulus shared by segments a and b (one
  material; starting from the mean of their values);
- ``tendon_offset:<actuator>`` [m]: the distance of a straight tendon from
  the centre line, along its nominal direction;
- ``payload_mass`` [kg]: a point mass at the tip frame (its weight, a dead
  load; starts at 0; :func:`mechanism.tip_frame`);
- ``sensor_offset:<sensor>:<x|y|z>`` [m]: the position of a marker or pose
  sensor in its cross-section frame.

Residual of row r and sensor i: ``e_ri(theta) / sigma_i`` (the sensor's
residual, :func:`sensors.residual_and_jacobian`, at the equilibrium
``q_r(theta)`` of the robot with parameters theta,
:func:`constrained.solve_equilibrium`). Sensitivities by the implicit
function theorem at each equilibrium ``R(q, lam, theta) = 0``, ``Phi(q) =
0`` (constraint rows and the position-controlled joints' rows, which do
not depend on theta):

    [[K_t, -G^T], [G, 0]] [dq; dlam] = -[dR/dtheta; 0],   de/dtheta = H dq/dtheta + de/dtheta|_q

with K_t the statics tangent and, analytically,
``dR/dE_j = K_j (q - q0) / E_j`` (K_j: the stiffness rows of member j),
``dR/dr_a = -d tau_act/dr_a`` (the derivative of the tendon's distributed
wrench ``T [t; d x t]``, ``t = n/|n|``, ``n = nu + kappa x d``, with
``d = r_a e_a``), ``dR/dm = -J_tip,world^T [g; 0]`` and, for a sensor
offset, ``de_p/dt = R_section``.

A dynamic recording (a time series: a release test, a payload step, a
swing) also carries the damping and the mass: :func:`calibrate_dynamic`
fits ``viscosity:<segment>`` [Pa s], ``density:<segment>`` [kg/m^3] and any
of the above but the payload (known loads go in the record) by simulating
the recording, with central-difference sensitivities of the simulated
trajectory; :func:`calibrate_damping` is its viscosity-only form.

Confidence intervals: ``cov = s^2 (J^T J)^-1`` with the residual variance
``s^2 = |r|^2 / (N - p)`` (J: the weighted Jacobian at the solution), 95 %
intervals ``+- t_{0.975, N-p} sqrt(diag cov)``. Held-out rows (every k-th)
are left out of the fit and report the error before and after.
"""

import copy
import csv
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import tension_factors
from soft_twin_core.engine.joint_kinds import PRISMATIC
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import CalibrationError, CalibrationFailed
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.lie import log_so3
from soft_twin_core.robot.mechanism import from_robot_model, is_tree_file, mechanism_from_dict, tip_frame
from soft_twin_core.robot.model import check_actuator_input, model_from_dict
from soft_twin_core.solve import constrained as cs
from soft_twin_core.solve.constrained import FrameLoad, MechanismSimulator, StepError, solve_equilibrium


def _marker(s):
    return isinstance(s, sn.PoseSensor) and s.position_only


STATIC_KINDS = (sn.PoseSensor, sn.JointStateSensor, sn.BaseWrenchSensor)


def _measuring(mech, sensors, kinds=(sn.PoseSensor,)):
    """(the sensors of ``kinds``, {name: where}) of a sensor list checked
    against the robot (:func:`sensors.check_sensors`); tension sensors are
    left out (the recording's inputs are the tensions), other kinds refused
    by name. A static sweep reads :data:`STATIC_KINDS` (pose sensors and
    markers, joint encoders, a base force/torque sensor); a dynamic record
    pose sensors and markers."""
    sensors, where = sn.check_sensors(mech, sensors)
    other = [s.name for s in sensors if not isinstance(s, kinds + (sn.TensionSensor,))]
    if other:
        raise CalibrationError(f"sensors {other}: this calibration reads "
                               f"{', '.join(k.__name__ for k in kinds)} only")
    return [s for s in sensors if isinstance(s, kinds)], where


def _sigma(sensor, m):
    """The noise standard deviations (m,) of a reading of ``sensor``."""
    if isinstance(sensor, sn.JointStateSensor):
        return np.asarray(sensor.sigma, dtype=float)
    if isinstance(sensor, sn.BaseWrenchSensor):
        return np.array([sensor.sigma_force_n] * 3 + [sensor.sigma_moment_nm] * 3)
    sig = np.full(m, sensor.sigma_position_m)
    if m == 6:
        sig[3:] = sensor.sigma_rotation_rad
    return sig


def _sensor_columns(s):
    """The CSV columns of a sensor's reading (:func:`read_csv`)."""
    if isinstance(s, sn.JointStateSensor):
        return [f"{s.name}.{j}" for j in s.joints]
    if isinstance(s, sn.BaseWrenchSensor):
        return [f"{s.name}.{c}" for c in _WRENCH_COLS]
    return [f"{s.name}.{c}" for c in (_POSE_COLS[:3] if _marker(s) else _POSE_COLS)]


def _support_loads(mech, loads):
    """The dead loads a base F/T sensor's support carries besides gravity,
    as :func:`sensors.base_wrench_and_jacobian` takes them: [(joint,
    abscissa, [f; m] world)] of FrameLoads (CalibrationError for a follower
    load: its direction turns with the robot)."""
    out = []
    for ld in loads:
        if ld.axes != "world":
            raise CalibrationError(f"a base force/torque sensor with a follower load on {ld.frame!r}: not supported "
                                   f"(record it as a dead load, world axes)")
        ref = mech.frame(ld.frame)
        out.append((ref.joint, ref.x, np.asarray(ld.wrench, dtype=float)))
    return out


@dataclass
class Recording:
    """A static sweep: inputs (N, n_actuators), per sensor name an array of
    readings (N, 4, 4) for pose sensors or (N, 3) for markers (NaN rows: not
    seen), times (N,) [s] or None, the position commands (N, n_joints)
    [rad or m] of the position-controlled joints (None: their references),
    the efforts {joint: (N,)} [N m or N] of effort-controlled joints (the
    others' 0), and the known loads ``wrenches`` {(point, axes): (N, 6)}
    ([fx, fy, fz, mx, my, mz], N and N m, at a frame of the robot or a
    member's point ``"<member>@<s>"``; axes "world": a dead load, "body":
    a follower along the point's axes; a zero row: no load then)."""
    inputs: np.ndarray
    readings: dict
    time: np.ndarray = None
    joints: np.ndarray = None
    efforts: dict = field(default_factory=dict)
    wrenches: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.inputs)

    def rows(self, idx):
        idx = np.asarray(idx)
        return Recording(self.inputs[idx], {k: v[idx] for k, v in self.readings.items()},
                         None if self.time is None else self.time[idx],
                         None if self.joints is None else self.joints[idx],
                         {k: np.asarray(v)[idx] for k, v in self.efforts.items()},
                         {k: np.asarray(v)[idx] for k, v in self.wrenches.items()})

    def row_loads(self, r):
        """The known point loads of row r (FrameLoads)."""
        return tuple(FrameLoad(p, np.asarray(W[r], dtype=float), axes) for (p, axes), W in self.wrenches.items()
                     if np.any(np.asarray(W[r]) != 0.0))

    def row_efforts(self, r):
        """{joint: effort} of row r, or None."""
        return {j: float(e[r]) for j, e in self.efforts.items()} or None


def position_joints(robot):
    """Names of the position-controlled joints of a mechanism (() for a
    classic model)."""
    if not hasattr(robot, "joints_with"):
        return ()
    return tuple(robot.tree.joints[i].name for i in robot.joints_with("position"))


def effort_joints(robot):
    """Names of the effort-controlled joints of a mechanism (() for a
    classic model)."""
    if not hasattr(robot, "joints_with"):
        return ()
    return tuple(robot.tree.joints[i].name for i in robot.joints_with("effort"))


def mechanism_of(robot_dict, n_sections=None, base_dir=None):
    """The mechanism of a robot mapping of either schema; ``n_sections``
    (classic robots only) replaces every segment's section count."""
    if is_tree_file(robot_dict):
        if n_sections is not None:
            raise CalibrationError("sections: a tree robot's sections come from its file (--sections is for "
                                   "classic robots)")
        return mechanism_from_dict(robot_dict, base_dir)
    return from_robot_model(model_from_dict(robot_dict, n_sections), robot_dict)


def as_mechanism(robot):
    """A mechanism from a mechanism or a classic model (its frames, the
    points of its member "backbone")."""
    return robot if hasattr(robot, "joints_with") else from_robot_model(robot)


def _segments_of(d):
    """{segment key: its mapping} of a robot mapping of either schema, and
    {segment key: member name} (a segment name that two members use is keyed
    ``<member>/<segment>``)."""
    if "bodies" not in d:
        return {str(s.get("name", f"segment{k}")): s for k, s in enumerate(d.get("segments") or [])}, \
            {str(s.get("name", f"segment{k}")): "backbone" for k, s in enumerate(d.get("segments") or [])}
    pairs = [(str(b.get("name")), str(s.get("name", f"segment{k}")), s) for b in d.get("bodies") or []
             if b.get("type") == "member" for k, s in enumerate(b.get("segments") or [])]
    counts = {}
    for _, n, _ in pairs:
        counts[n] = counts.get(n, 0) + 1
    segs, member = {}, {}
    for m, n, sd in pairs:
        key = n if counts[n] == 1 else f"{m}/{n}"
        segs[key], member[key] = sd, m
    return segs, member


def _actuators_of(d):
    """{actuator name: its mapping} of a robot mapping of either schema."""
    lists = [d.get("actuators") or []] + [b.get("actuators") or [] for b in d.get("bodies") or []]
    return {a["name"]: a for lst in lists for a in lst if isinstance(a, dict) and "name" in a}


def _segment_rows(mech, d):
    """{segment key: boolean mask (nv,) of its sections' strain
    coordinates}: each member's joints by the segment each belongs to
    (``Member.segments``), else shared out over its segments by their
    section counts (an equal split when a count override applied)."""
    segs, member_of = _segments_of(d)
    arrays = Workspace(mech.tree).arrays
    out = {}
    for m in mech.members:
        keys = [k for k in segs if member_of[k] == m.name]
        if m.segments:
            for k in keys:
                name = k[len(m.name) + 1:] if k.startswith(m.name + "/") and k not in m.segments else k
                mask = np.zeros(mech.tree.nv, dtype=bool)
                for i, seg in zip(m.joints, m.segments):
                    if seg == name:
                        mask[arrays.iv[i]:arrays.iv[i] + arrays.nv[i]] = True
                out[k] = mask
            continue
        counts = [int(segs[k].get("sections", 1)) for k in keys]
        if sum(counts) != len(m.joints) and keys and len(m.joints) % len(keys) == 0:
            counts = [len(m.joints) // len(keys)] * len(keys)
        j = 0
        for k, n in zip(keys, counts):
            mask = np.zeros(mech.tree.nv, dtype=bool)
            for i in m.joints[j:j + n]:
                mask[arrays.iv[i]:arrays.iv[i] + arrays.nv[i]] = True
            out[k] = mask
            j += n
    return out


# ----------------------------------------------------------------------------
# CSV
# ----------------------------------------------------------------------------

_POSE_COLS = ("x", "y", "z", "qx", "qy", "qz", "qw")
_WRENCH_COLS = ("fx", "fy", "fz", "mx", "my", "mz")
_NEWTON_METRE = ("N m", "N*m", "Nm", "N.m", "N\u00b7m")


def csv_header(model, sensors, recording=None):
    """Columns: ``t``, one per actuator (its name), one per
    position-controlled joint (its name, rad or m), then per marker
    ``<name>.x .y .z`` and per pose sensor also ``.qx .qy .qz .qw``; with a
    ``recording``, also the columns of its efforts (the joints' names) and
    known loads (``wrench:<point>.fx`` .. ``.mz``), as :func:`write_csv`
    writes them."""
    cols = ["t"] + list(model.actuator_names) + list(position_joints(model))
    if recording is not None:
        cols += list(recording.efforts)
        for (point, axes) in recording.wrenches:
            if axes != "world":
                raise CalibrationError(f"wrench on {point!r}: a CSV holds dead loads (world axes) only; "
                                       f"a follower load is recorded in an MCAP file")
            cols += [f"wrench:{point}.{c}" for c in _WRENCH_COLS]
    for s in sensors:
        if isinstance(s, STATIC_KINDS):
            cols += _sensor_columns(s)
    return cols


def column_units(model, name):
    """The units a column's header may name (``name [unit]``), the first
    the one written; None: a column :func:`read_csv` does not read. SI
    only: a column in mm, g or ms is refused, not converted."""
    kinds = {j.name: j.kind for j in model.tree.joints} if hasattr(model, "tree") else {}
    if name == "t":
        return ("s",)
    if name in model.actuator_names:
        kind = model.actuators[list(model.actuator_names).index(name)].kind
        return ("N",) if kind == "tendon" else ("Pa",)
    if name in position_joints(model):
        return ("m",) if kinds[name] == PRISMATIC else ("rad",)
    if name in effort_joints(model):
        return ("N",) if kinds[name] == PRISMATIC else _NEWTON_METRE
    if name.startswith("wrench:"):
        comp = name.rsplit(".", 1)[-1]
        return ("N",) if comp.startswith("f") else _NEWTON_METRE
    if name.startswith("mass:"):
        return ("kg",)
    comp = name.rsplit(".", 1)[-1]
    if comp in _WRENCH_COLS:                         # a base force/torque sensor's
        return ("N",) if comp.startswith("f") else _NEWTON_METRE
    if comp in kinds and "." in name:                # an encoder's joint
        return ("m",) if kinds[comp] == PRISMATIC else ("rad",)
    if comp in ("x", "y", "z"):
        return ("m",)
    if comp in ("qx", "qy", "qz", "qw"):
        return ("1", "-", "")
    return None


def _split_unit(header):
    """(name, unit or None) of a header ``name`` or ``name [unit]``."""
    h = header.strip()
    if h.endswith("]") and "[" in h:
        name, _, unit = h[:-1].rpartition("[")
        return name.strip(), unit.strip()
    return h, None


def write_csv(path, model, sensors, rec):
    """Write a recording as :func:`read_csv` reads it: a header of
    :func:`csv_header`'s columns with their units (``tendon_y [N]``), one
    row per sample; a reading not seen is an empty group of cells."""
    from scipy.spatial.transform import Rotation
    cols = csv_header(model, sensors, rec)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([c if not (column_units(model, c) or ("",))[0] else f"{c} [{column_units(model, c)[0]}]"
                    for c in cols])
        t = np.arange(len(rec), dtype=float) if rec.time is None else rec.time

        def cells(values):
            v = np.asarray(values, dtype=float).ravel()
            return [repr(float(x)) for x in v] if np.all(np.isfinite(v)) else [""] * len(v)
        for r in range(len(rec)):
            row = cells([t[r]]) + cells(rec.inputs[r])
            if position_joints(model):
                row += cells(_joint_rows(model, rec)[r])
            row += [repr(float(e[r])) for e in rec.efforts.values()]
            for W in rec.wrenches.values():
                row += cells(W[r])
            for s in sensors:
                z = rec.readings.get(s.name)
                if _marker(s) or isinstance(s, (sn.JointStateSensor, sn.BaseWrenchSensor)):
                    row += cells(z[r])
                elif isinstance(s, sn.PoseSensor):
                    ok = np.all(np.isfinite(z[r]))
                    row += cells(z[r][:3, 3] if ok else np.full(3, np.nan))
                    row += cells(Rotation.from_matrix(z[r][:3, :3]).as_quat() if ok else np.full(4, np.nan))
            w.writerow(row)


def read_csv(path, model, sensors):
    """A :class:`Recording` from a CSV file (the column reference is in the
    docs; :func:`write_csv` writes one):

    - ``t`` [s], optional, strictly increasing;
    - one column per actuator (its name; N for a tendon, Pa for a chamber)
      and per position-controlled joint (rad or m), required;
    - optional: one per effort-controlled joint (N m or N; missing: 0);
      known loads, ``wrench:<point>.fx .fy .fz .mx .my .mz`` [N, N m] (a
      dead load, world axes, about the point; the components not given are
      0) and hung weights ``mass:<point>`` [kg] (the weight m g along the
      robot's gravity), ``<point>`` a frame of the robot or a member's
      point ``<member>@<s>``;
    - per marker ``<name>.x .y .z`` [m], per pose sensor also ``.qx .qy
      .qz .qw`` (x y z w), required; a reading not seen is a row whose
      cells of that sensor are all empty (or nan).

    A header may name its unit, ``tendon_y [N]``: SI units only. Any order;
    columns it does not know are ignored. Raises CalibrationError naming a
    missing or repeated column, a unit that does not match, a value that
    is not a number (row, column), a non-finite input or load, time that
    does not increase, a reading with some of its cells empty, an unknown
    point or effort joint."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as e:
        raise CalibrationError(f"data file {path}: {e.strerror}") from None
    if not rows:
        raise CalibrationError(f"data file {path}: empty")
    if len(rows) < 2:
        raise CalibrationError(f"data file {path}: a header but no data row")
    model = as_mechanism(model)
    header = []
    for raw in rows[0]:
        name, unit = _split_unit(raw)
        if name in header:
            raise CalibrationError(f"data file {path}: column {name!r} appears twice")
        allowed = column_units(model, name)
        if unit is not None and allowed is not None and unit not in allowed:
            raise CalibrationError(f"data file {path}, column {raw.strip()!r}: unit [{unit}], expected "
                                   f"[{allowed[0]}] (SI units: convert the column)")
        header.append(name)
    need = [c for c in csv_header(model, sensors) if c != "t"]
    missing = [c for c in need if c not in header]
    if missing:
        raise CalibrationError(f"data file {path}: missing column(s) {missing}")
    data = np.empty((len(rows) - 1, len(header)))
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise CalibrationError(f"data file {path}, row {i + 2}: expected {len(header)} values, got {len(row)}")
        for j, v in enumerate(row):
            try:
                data[i, j] = float(v) if v.strip() else np.nan
            except ValueError:
                raise CalibrationError(f"data file {path}, row {i + 2}, column {header[j]}: "
                                       f"not a number: {v!r}") from None
    col = {h: data[:, j] for j, h in enumerate(header)}

    def finite(names, what):
        for name in names:
            bad = np.flatnonzero(~np.isfinite(col[name]))
            if len(bad):
                raise CalibrationError(f"data file {path}, row {bad[0] + 2}, column {name}: {what} must be a "
                                       f"finite number, got {rows[bad[0] + 1][header.index(name)]!r}")
    finite(model.actuator_names, "an actuator input")
    finite(position_joints(model), "a joint position")
    u = np.stack([col[a] for a in model.actuator_names], axis=1) if model.actuators else np.zeros((len(data), 0))
    joints = np.stack([col[n] for n in position_joints(model)], axis=1) if position_joints(model) else None
    time = col.get("t")
    if time is not None:
        finite(["t"], "the time")
        back = np.flatnonzero(np.diff(time) <= 0)
        if len(back):
            raise CalibrationError(f"data file {path}, row {back[0] + 3}, column t: the time must increase "
                                   f"({time[back[0] + 1]:g} s after {time[back[0]]:g} s)")
    efforts = {n: col[n] for n in effort_joints(model) if n in col}
    finite(efforts, "a joint effort")
    wrenches = _known_loads(path, model, header, col, finite)
    readings = {}
    for s in sensors:
        if not isinstance(s, STATIC_KINDS):
            continue
        names = _sensor_columns(s)
        v = np.stack([col[n] for n in names], axis=1)
        inf = np.flatnonzero(np.any(np.isinf(v), axis=1))
        if len(inf):
            raise CalibrationError(f"data file {path}, row {inf[0] + 2}: sensor {s.name!r} reads an infinite value")
        seen = np.isfinite(v)
        part = np.flatnonzero(np.any(seen, axis=1) & ~np.all(seen, axis=1))
        if len(part):
            r = part[0]
            blank = names[int(np.flatnonzero(~seen[r])[0])]
            raise CalibrationError(f"data file {path}, row {r + 2}, column {blank}: sensor {s.name!r} has some "
                                   f"of its cells empty (a reading not seen leaves all of them empty)")
        if not isinstance(s, sn.PoseSensor) or _marker(s):
            readings[s.name] = v
        else:
            T = np.full((len(v), 4, 4), np.nan)
            for r in np.flatnonzero(np.all(seen, axis=1)):
                if not np.linalg.norm(v[r, 3:]) > 1e-6:
                    raise CalibrationError(f"data file {path}, row {r + 2}: sensor {s.name!r} has a zero quaternion")
                T[r] = sn.pose_from_position_quaternion(v[r, :3], v[r, 3:])
            readings[s.name] = T
    return Recording(u, readings, time, joints, efforts, wrenches)


def _known_loads(path, model, header, col, finite):
    """{(point, "world"): (N, 6)} of the ``wrench:<point>.<c>`` and
    ``mass:<point>`` columns (:func:`read_csv`)."""
    out = {}

    def point_of(name, prefix):
        point = name[len(prefix):]
        if prefix == "wrench:":
            point, _, comp = point.rpartition(".")
            if comp not in _WRENCH_COLS:
                raise CalibrationError(f"data file {path}, column {name}: expected wrench:<point>.<component>, "
                                       f"the component one of {list(_WRENCH_COLS)}")
        try:
            model.frame(point)
        except KeyError as e:
            raise CalibrationError(f"data file {path}, column {name}: {e.args[0]}") from None
        return point
    n = len(next(iter(col.values())))
    for name in header:
        for prefix in ("wrench:", "mass:"):
            if not name.startswith(prefix):
                continue
            point = point_of(name, prefix)
            finite([name], "a known load")
            W = out.setdefault((point, "world"), np.zeros((n, 6)))
            if prefix == "wrench:":
                W[:, _WRENCH_COLS.index(name.rsplit(".", 1)[1])] += col[name]
                continue
            g = np.asarray(model.tree.gravity, dtype=float)
            if np.any(col[name] < 0):
                raise CalibrationError(f"data file {path}, column {name}: a mass must be >= 0 kg")
            if not np.any(g):
                raise CalibrationError(f"data file {path}, column {name}: the robot has no gravity to weigh the "
                                       f"mass; give its weight as wrench:{point}.fx .. .fz")
            W[:, :3] += col[name][:, None] * g[None, :]
    return out


def _joint_rows(mech, rec):
    """(N, n_joints) position commands of a recording (the joints'
    references where it has none)."""
    names = position_joints(mech)
    if rec.joints is not None:
        return np.asarray(rec.joints, dtype=float).reshape(len(rec), len(names))
    ref = [mech.tree.joints[i].q_ref for i in mech.joints_with("position")] if names else []
    return np.tile(np.asarray(ref, dtype=float), (len(rec), 1))


def check_recording(mech, rec, source="recording"):
    """Refuse (CalibrationError naming the field) a recording's efforts of a
    joint that is not effort-controlled, known loads on an unknown point,
    with unknown axes, of the wrong shape or not finite."""
    n = len(rec)
    for j, e in rec.efforts.items():
        if j not in effort_joints(mech):
            raise CalibrationError(f"{source}.efforts: {j!r} is not an effort-controlled joint; this robot's are "
                                   f"{list(effort_joints(mech))}")
        if np.shape(e) != (n,) or not np.all(np.isfinite(e)):
            raise CalibrationError(f"{source}.efforts[{j!r}]: expected {n} finite values [N m or N]")
    for key, W in rec.wrenches.items():
        if not (isinstance(key, tuple) and len(key) == 2 and key[1] in ("world", "body")):
            raise CalibrationError(f"{source}.wrenches: keys are (point, 'world' | 'body'), got {key!r}")
        try:
            mech.frame(key[0])
        except KeyError as e:
            raise CalibrationError(f"{source}.wrenches: {e.args[0]}") from None
        if np.shape(W) != (n, 6) or not np.all(np.isfinite(W)):
            raise CalibrationError(f"{source}.wrenches[{key!r}]: expected {n} finite rows [fx, fy, fz, mx, my, mz] "
                                   f"(N, N m)")


def check_recording_inputs(model, inputs, source="recording"):
    """Refuse (CalibrationError naming the row, the actuator, the value and
    the bound) a recorded input outside the actuator's declared range
    (:func:`model.check_actuator_input`, the node's rule): such a row cannot
    come from this robot as declared (wrong units, wrong robot file, or a
    bound the robot file should not declare), and fitting it would
    calibrate the model to inputs the twin refuses."""
    u = np.asarray(inputs, dtype=float)
    if u.ndim != 2 or u.shape[1] != len(model.actuators):
        return
    for k, a in enumerate(model.actuators):
        if np.all((u[:, k] >= a.lower) & (u[:, k] <= a.upper)):
            continue
        for i in range(len(u)):
            bad = check_actuator_input(a, u[i, k])
            if bad is not None:
                raise CalibrationError(f"{source}, row {i + 1}, actuator {a.name}: {bad[1]} [{bad[0]}]")


def record_static_sweep(robot, sensors, inputs, rng, loads=None, joints=None, point_loads=(), *, efforts=None,
                        wrenches=None):
    """Simulated recording: the equilibria of ``robot`` (a mechanism or a
    classic model) under each row of ``inputs`` and ``joints`` (position
    commands, rad or m; default the references), ``efforts`` {joint: (N,)}
    and the known loads ``wrenches`` {(point, axes): (N, 6)} (kept in the
    recording, as a lab logs what it applied), and the loads no log holds
    (``loads``, ``point_loads``: FrameLoads), read by the sensors with their
    noise. The inputs must lie in the actuators' declared ranges."""
    mech = as_mechanism(robot)
    check_recording_inputs(mech, inputs, "inputs")
    sensors, where = _measuring(mech, sensors, STATIC_KINDS)
    if loads is not None and any(isinstance(s, sn.BaseWrenchSensor) for s in sensors):
        raise CalibrationError("record_static_sweep: a base force/torque sensor with path loads: give point_loads")
    ws = Workspace(mech.tree)
    names = position_joints(mech)
    inputs = np.asarray(inputs, dtype=float)
    rec = Recording(inputs, {}, None, None if joints is None else np.asarray(joints, dtype=float),
                    {k: np.asarray(v, dtype=float) for k, v in (efforts or {}).items()},
                    {k: np.asarray(v, dtype=float) for k, v in (wrenches or {}).items()})
    check_recording(mech, rec, "record_static_sweep")
    jrows = _joint_rows(mech, rec)
    q = None
    readings = {s.name: [] for s in sensors}
    for r, u in enumerate(inputs):
        row_loads = tuple(point_loads) + rec.row_loads(r)
        q = solve_equilibrium(mech, u, rec.row_efforts(r), dict(zip(names, jrows[r])) if names else None, loads,
                              row_loads, q_init=q).q
        truth = sn.predict_readings(ws, q, sensors, where)
        for s in sensors:
            if isinstance(s, sn.BaseWrenchSensor):          # the support carries the loads too
                truth[s.name] = sn.predict_measurement(ws, sn.forward(ws, q), s, None,
                                                       point_load=_support_loads(mech, row_loads))
        for s in sensors:
            readings[s.name].append(sn.simulate_measurement(s, truth[s.name], rng))
    rec.readings = {k: np.array(v) for k, v in readings.items()}
    return rec


# ----------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------

@dataclass
class _Param:
    name: str
    kind: str
    target: str
    axis: int = 0
    nominal: float = 0.0
    scale: float = 1.0


MATERIAL_KINDS = ("youngs_modulus", "viscosity", "density")      # a segment's material, > 0
DYNAMIC_ONLY = ("viscosity", "density")          # (no analytic static sensitivity: fitted by simulation)


def _params(names, robot_dict, sensors):
    segs = _segments_of(robot_dict)[0]
    acts = _actuators_of(robot_dict)
    by_name = {s.name: s for s in sensors}
    out = []
    for name in names:
        kind, _, rest = name.partition(":")
        if kind in MATERIAL_KINDS:
            keys = rest.split("+")                # one value shared by the segments "a+b"
            for key in keys:
                if key not in segs or "material" not in segs[key]:
                    raise CalibrationError(f"parameter {name!r}: no segment {key!r} with a material "
                                           f"(segments: {list(segs)})")
            if len(set(keys)) != len(keys):
                raise CalibrationError(f"parameter {name!r}: a segment named twice")
            v = float(np.mean([float(segs[k]["material"].get(kind, 0.0)) for k in keys]))
            if not v > 0:
                raise CalibrationError(f"parameter {name!r}: its starting value must be > 0 (set {kind} in the "
                                       f"robot file), got {v}")
            out.append(_Param(name, kind, rest, 0, v, v))
        elif kind == "tendon_offset":
            a = acts.get(rest)
            if a is None or a.get("routing", "straight") != "straight":
                raise CalibrationError(f"parameter {name!r}: no straight tendon {rest!r} "
                                       f"(actuators: {list(acts)})")
            out.append(_Param(name, kind, rest, 0, float(np.linalg.norm(np.asarray(a["offset"], float))), 1e-3))
        elif name == "payload_mass":
            out.append(_Param(name, "payload_mass", "", 0, 0.0, 0.01))
        elif kind == "sensor_offset":
            sname, _, ax = rest.partition(":")
            s = by_name.get(sname)
            if not isinstance(s, sn.PoseSensor) or ax not in ("x", "y", "z"):
                raise CalibrationError(f"parameter {name!r}: expected sensor_offset:<marker or pose sensor>:<x|y|z> "
                                       f"(sensors: {list(by_name)})")
            i = "xyz".index(ax)
            out.append(_Param(name, kind, sname, i, float(np.asarray(s.placement)[i, 3]), 1e-3))
        else:
            raise CalibrationError(f"parameter {name!r}: expected youngs_modulus:<member>, viscosity:<member>, "
                                   f"density:<member>, tendon_offset:<tendon>, payload_mass or "
                                   f"sensor_offset:<sensor>:<axis>")
    if len({p.name for p in out}) != len(out):
        raise CalibrationError(f"parameters: duplicates in {list(names)}")
    return out


def apply_parameters(robot_dict, sensors, params, theta):
    """(robot dict, sensors, payload mass [kg]) with the parameter values theta."""
    d = copy.deepcopy(robot_dict)
    segs = _segments_of(d)[0]
    acts = _actuators_of(d)
    placements = {s.name: np.array(s.placement, dtype=float) for s in sensors
                  if isinstance(s, sn.PoseSensor)}
    mass = 0.0
    for p, v in zip(params, theta):
        if p.kind in MATERIAL_KINDS:
            for key in p.target.split("+"):
                segs[key]["material"][p.kind] = float(v)
        elif p.kind == "tendon_offset":
            off = np.asarray(acts[p.target]["offset"], dtype=float)
            acts[p.target]["offset"] = [float(x) for x in off / np.linalg.norm(off) * v]
        elif p.kind == "payload_mass":
            mass = float(v)
        else:
            placements[p.target][p.axis, 3] = v
    new = [dataclasses.replace(s, placement=placements[s.name]) if s.name in placements else s for s in sensors]
    return d, new, mass


def _payload(mech, mass):
    """The payload's weight as a dead load on the tip frame (FrameLoads)."""
    if mass == 0.0:
        return ()
    return (FrameLoad(tip_frame(mech), np.concatenate([mass * np.asarray(mech.tree.gravity, float), np.zeros(3)]),
                      "world"),)


def _tendon_offset_derivative(model, ws, act, k, u_k, out):
    """out (nv,) = d tau_act / d r_k for the straight tendon k at the strains
    of the last forward pass of ws: per quadrature point with coefficient c,
    ``d/dr c [t; d x t] = c [dt; e x t + d x dt]``, ``dt = (I - t t^T) (kappa x e)/|n|``;
    with sheath friction c carries the capstan factor exp(-mu theta), whose
    own change with r is left out (none without torsion and shear: the
    tendon's tangent is then the backbone's)."""
    m, w = ws.arrays, ws.work
    pts = np.flatnonzero(act.unit[:, k])
    fac = tension_factors(ws.w, act)
    for p in pts:
        c = act.unit[p, k] * u_k * fac[p]
        joints = [(i, f) for i, f in zip(act.mixed[p], act.mix[p]) if i >= 0]
        d = act.d[p]
        e = d / np.linalg.norm(d)
        xi = sum(f * w.strain[i] for i, f in joints)      # the point's strain (on a field pair the field's)
        n = xi[:3] + np.cross(xi[3:], d) + act.dd[p]
        nn = np.linalg.norm(n)
        t = n / nn
        dn = np.cross(xi[3:], e)
        dt = (dn - t * (t @ dn)) / nn
        dwr = c * np.concatenate([dt, np.cross(e, t) + np.cross(d, dt)])
        for i, f in joints:
            iv, nv = m.iv[i], m.nv[i]
            out[iv:iv + nv] += f * dwr[m.modes[i, :nv]]


# ----------------------------------------------------------------------------
# The least-squares problem
# ----------------------------------------------------------------------------

class Problem:
    """Residuals and their analytic Jacobian of a recording, as functions of
    the parameter values theta (SI), for a robot mapping of either schema."""

    def __init__(self, robot_dict, sensors, recording, names, n_sections=None, base_dir=None):
        self.robot_dict, self.n_sections, self.base_dir = robot_dict, n_sections, base_dir
        mech = mechanism_of(robot_dict, n_sections, base_dir)
        self.sensors, self.where = _measuring(mech, sensors, STATIC_KINDS)     # the points stay with theta
        if not self.sensors:
            raise CalibrationError("sensors: calibration needs at least one pose sensor, marker, encoder or "
                                   "base force/torque sensor")
        if any(isinstance(s, sn.BaseWrenchSensor) for s in self.sensors):
            for r in range(len(recording)):
                _support_loads(mech, recording.row_loads(r))          # (dead loads only: refused at the door)
        check_recording_inputs(mech, recording.inputs)      # the declared actuator ranges
        names_j = position_joints(mech)
        if recording.joints is not None and np.shape(recording.joints) != (len(recording), len(names_j)):
            raise CalibrationError(f"recording.joints: expected {len(recording)} rows of the position-controlled "
                                   f"joints {list(names_j)}, got shape {np.shape(recording.joints)}")
        check_recording(mech, recording)
        self.rec = recording
        self.params = _params(names, robot_dict, self.sensors)
        self.rows_of = _segment_rows(mech, robot_dict) if any(p.kind == "youngs_modulus" for p in self.params) \
            else {}
        self.theta0 = np.array([p.nominal for p in self.params])
        self.scale = np.array([p.scale for p in self.params])
        self._q = [None] * len(recording)
        self._joints = _joint_rows(mech, recording)
        self._names_j = names_j

    def model(self, theta):
        """(mechanism, sensors, payload mass [kg]) with the parameter values theta."""
        d, sensors, mass = apply_parameters(self.robot_dict, self.sensors, self.params, theta)
        return mechanism_of(d, self.n_sections, self.base_dir), sensors, mass

    def equilibrium(self, mech, r, mass):
        """The equilibrium of row r (warm-started from the last one found)."""
        pos = dict(zip(self._names_j, self._joints[r])) if self._names_j else None
        eq = solve_equilibrium(mech, self.rec.inputs[r], self.rec.row_efforts(r), pos, None,
                               _payload(mech, mass) + self.rec.row_loads(r), q_init=self._q[r], check_stability=False)
        self._q[r] = eq.q
        return eq

    def evaluate(self, theta, jacobian=True, rows=None):
        """(weighted residuals (M,), Jacobian (M, p) d r / d theta, or None)."""
        theta = np.asarray(theta, dtype=float)
        mech, sensors, mass = self.model(theta)
        tree = mech.tree
        ws = Workspace(tree)
        act = cs.actuator_arrays(tree) if mech.actuators else None
        K = cs.dense_stiffness_damping(tree)[0] if self.rows_of else None
        rows = range(len(self.rec)) if rows is None else rows
        res, jac = [], []
        for r in rows:
            u = self.rec.inputs[r]
            eq = self.equilibrium(mech, r, mass)
            q = eq.q
            if jacobian:
                pb = cs._Equilibrium(mech, eq.inputs)
                Kt = pb.tangent(q, eq.lam)
                _, phi, G = pb.residual(q, eq.lam)
                fac = cs.factor_kkt(Kt, G, G)
                dR = np.zeros((tree.nv, len(self.params)))
                sn.forward(ws, q)
                for j, p in enumerate(self.params):
                    if p.kind == "youngs_modulus":
                        rows_j = np.any([self.rows_of[k] for k in p.target.split("+")], axis=0)
                        dR[rows_j, j] = (K @ (q - tree.q0))[rows_j] / theta[j]
                    elif p.kind == "tendon_offset":
                        k = list(mech.actuator_names).index(p.target)
                        col = np.zeros(tree.nv)
                        _tendon_offset_derivative(mech, ws, act, k, u[k], col)
                        dR[:, j] = -col
                    elif p.kind == "payload_mass":
                        ref = mech.frame(tip_frame(mech))
                        _, Jw = alg.point_jacobian(tree, ws, q, ref.joint, ref.x, "world")
                        dR[:, j] = -Jw.T @ np.concatenate([tree.gravity, np.zeros(3)])
                        sn.forward(ws, q)
                zero = np.zeros(len(phi))
                if pb.T is not None:      # variable-strain segments: the KKT system in their coordinates
                    dR = pb.T.T @ dR
                dq = pb.lift(np.column_stack([cs.solve_factored(fac, dR[:, j], zero)[0]
                                              for j in range(len(self.params))])) if self.params \
                    else np.zeros((tree.nv, 0))
            qc = sn.forward(ws, q)
            for s in sensors:
                z = self.rec.readings[s.name][r]
                if not np.all(np.isfinite(z)):
                    continue
                ft = isinstance(s, sn.BaseWrenchSensor)
                held = _support_loads(mech, _payload(mech, mass) + self.rec.row_loads(r)) if ft else None
                e, H = sn.residual_and_jacobian(ws, qc, s, self.where[s.name], z, point_load=held)
                sig = _sigma(s, len(e))
                res.append(e / sig)
                if jacobian:
                    J = H @ dq
                    if ft:                                # the payload's weight at fixed q
                        ref = mech.frame(tip_frame(mech))
                        D = sn.base_wrench_load_jacobian(tree, ws, qc, ref.joint, ref.x)
                        for j, p in enumerate(self.params):
                            if p.kind == "payload_mass":
                                J[:, j] += D @ np.concatenate([tree.gravity, np.zeros(3)])
                    for j, p in enumerate(self.params):
                        if p.kind == "sensor_offset" and p.target == s.name:
                            T, _ = sn.point_pose_and_body_jacobian(ws, *self.where[s.name], np.asarray(s.placement))
                            # p_sensor = p_section + R_section t: d/dt = R_section = R_sensor P_R^T
                            R_sec = T[:3, :3] @ np.asarray(s.placement)[:3, :3].T
                            J[:3, j] += R_sec[:, p.axis]
                    jac.append(J / sig[:, None])
        r = np.concatenate(res)
        return r, (np.vstack(jac) if jacobian else None)


@dataclass
class CalibrationResult:
    """Fitted values (SI), their standard errors and 95 % confidence
    half-widths, the nominal values, the residual standard deviation (in
    units of the stated sensor noise: about 1 when the model fits), held-out
    errors before/after, the calibrated robot dict, sensors and payload."""
    names: list
    nominal: np.ndarray
    values: np.ndarray
    std: np.ndarray
    ci95: np.ndarray
    residual_sigma: float
    n_residuals: int
    iterations: int
    robot_dict: dict
    sensors: list
    payload_mass: float
    heldout: dict = field(default_factory=dict)
    correlation: np.ndarray = None
    warnings: list = field(default_factory=list)

    def table(self):
        lines = [f"{'parameter':32s} {'nominal':>12s} {'fitted':>12s} {'std error':>12s} {'95 % CI':>12s}"]
        for n, a, b, s, c in zip(self.names, self.nominal, self.values, self.std, self.ci95):
            lines.append(f"{n:32s} {a:12.6g} {b:12.6g} {s:12.3g} {'+-':>3s}{c:9.3g}")
        lines.append(f"residual sigma (in sensor-noise units): {self.residual_sigma:.3f} "
                     f"over {self.n_residuals} residuals")
        if self.correlation is not None and len(self.names) > 1:
            lines.append("correlations: " + ", ".join(
                f"{self.names[i]} ~ {self.names[j]} {self.correlation[i, j]:+.3f}"
                for i in range(len(self.names)) for j in range(i + 1, len(self.names))))
        for k, v in self.heldout.items():
            lines.append(f"held-out {k}: {v:.6g}")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def fit_statistics(names, r, J_scaled, scale, values):
    """The statistics of a least-squares fit at its solution, from its
    weighted residuals r (M,) and Jacobian in the scaled parameters
    ``theta / scale`` (M, p): {std, ci95, residual_sigma, n_residuals,
    correlation, warnings} (:class:`CalibrationResult`'s fields). ``cov =
    s^2 (J^T J)^-1`` with ``s^2 = |r|^2 / (M - p)``, 95 % intervals from
    Student's t, the correlations ``cov_ij / (std_i std_j)``, and the
    warnings of :func:`identifiability` and of correlations beyond 0.99."""
    from scipy.stats import t as student_t
    m, p = len(r), len(values)
    dof = max(m - p, 1)
    s2 = float(r @ r) / dof
    cov = s2 * scale[:, None] * np.linalg.pinv(J_scaled.T @ J_scaled) * scale[None, :]
    std = np.sqrt(np.diag(cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.clip(cov / np.outer(std, std), -1.0, 1.0)
    corr[~np.isfinite(corr)] = 0.0
    np.fill_diagonal(corr, 1.0)
    warn = identifiability(names, J_scaled, values, std)
    warn += [f"{names[i]} and {names[j]}: correlated {corr[i, j]:+.3f} (the data hardly tell them apart)"
             for i in range(p) for j in range(i + 1, p) if abs(corr[i, j]) > 0.99]
    return dict(std=std, ci95=student_t.ppf(0.975, dof) * std, residual_sigma=float(np.sqrt(s2)), n_residuals=m,
                correlation=corr, warnings=warn)


def identifiability(names, J_scaled, values, std):
    """Warnings on what a fit could not identify, from its weighted Jacobian
    in scaled parameters: a parameter the residuals do not depend on, a
    combination they hardly see (the smallest singular value of the
    column-normalised Jacobian below 1e-3 of the largest: its direction
    names the parameters), a standard error over half the value, a
    correlation beyond 0.99."""
    out = []
    norms = np.linalg.norm(J_scaled, axis=0)
    dead = norms <= 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)
    for n in np.asarray(names)[dead]:
        out.append(f"{n}: not identifiable, the readings do not depend on it (no sensitivity)")
    live = np.flatnonzero(~dead)
    if len(live) > 1:
        _, sv, Vt = np.linalg.svd(J_scaled[:, live] / norms[live], full_matrices=False)
        if sv[-1] < 1e-3 * sv[0]:
            v = Vt[-1]
            involved = [names[live[k]] for k in np.flatnonzero(np.abs(v) > 0.2)]
            out.append(f"{' and '.join(involved)}: not identifiable apart (the readings see only a combination; "
                       f"condition {sv[0] / max(sv[-1], 1e-300):.3g}): add rows that move them differently")
    for n, x, s in zip(names, values, std):
        if np.isfinite(s) and s > 0.5 * abs(x) and n in [names[k] for k in live]:
            out.append(f"{n}: poorly identified (standard error {s:.3g} against a value of {x:.3g})")
    return out


def _tip_sensor(mech, sensors):
    """The pose sensor or marker nearest the tip: one on the tip frame, else
    the farthest along the main member, else the last (None: none)."""
    sensors = [s for s in sensors if isinstance(s, sn.PoseSensor)]
    if not sensors:
        return None
    tip = tip_frame(mech)
    on_tip = [s for s in sensors if s.frame == tip]
    if on_tip:
        return on_tip[0]
    along = [s for s in sensors if s.frame is None]
    return max(along, key=lambda s: s.s) if along else sensors[-1]


def tip_errors(problem, theta, rows, truth_tips=None):
    """(RMS, max) [m] over ``rows`` of the distance between the model's
    prediction of the sensor nearest the tip and its reading (or the given
    true positions (R, 3))."""
    mech, sensors, mass = problem.model(theta)
    tip = _tip_sensor(mech, sensors)
    ws = Workspace(mech.tree)
    d = []
    for k, r in enumerate(rows):
        q = problem.equilibrium(mech, r, mass).q
        T = sn.predict_readings(ws, q, [tip], problem.where)[tip.name]
        p = T[:3, 3] if np.shape(T) == (4, 4) else T
        z = problem.rec.readings[tip.name][r] if truth_tips is None else truth_tips[k]
        z = z[:3, 3] if np.shape(z) == (4, 4) else z
        d.append(np.linalg.norm(p - z))
    d = np.array(d)
    return float(np.sqrt(np.mean(d ** 2))), float(d.max())


def calibrate(robot_dict, sensors, recording, names, *, holdout_every=4, n_sections=None, verbose=0,
              base_dir=None, max_evaluations=None):
    """Fit the parameters ``names`` (module docstring) to the recording of a
    robot (a mapping of either schema; ``base_dir``: where its relative
    files are); every ``holdout_every``-th row (0: none) is held out and
    reports the tip-sensor error before and after. Returns a
    :class:`CalibrationResult` (standard errors, correlations, warnings on
    what the data cannot identify: :func:`identifiability`); raises
    CalibrationFailed, with the last residual, when the fit does not
    converge in ``max_evaluations`` residual evaluations (default:
    scipy's, 100 per parameter)."""
    from scipy.optimize import least_squares
    for name in names:
        if name.partition(":")[0] in DYNAMIC_ONLY:
            raise CalibrationError(f"parameter {name!r}: fitted from a time series (calibrate_dynamic; "
                                   f"soft-twin-sim calibrate --dynamic), not from a static sweep")
    n = len(recording)
    held = np.arange(n)[holdout_every - 1::holdout_every] if holdout_every else np.zeros(0, int)
    fit_rows = np.setdiff1d(np.arange(n), held)
    pb = Problem(robot_dict, sensors, recording.rows(fit_rows), names, n_sections, base_dir)
    s = pb.scale

    def fun(x):
        return pb.evaluate(x * s, jacobian=False)[0]

    def jac(x):
        return pb.evaluate(x * s)[1] * s

    x0 = pb.theta0 / s
    # a modulus stays positive (a trust-region step of a poorly seen one could otherwise cross 0)
    lower = np.array([1e-3 * p.nominal / p.scale if p.kind == "youngs_modulus" else -np.inf for p in pb.params])
    sol = least_squares(fun, x0, jac=jac, method="trf", x_scale=1.0, verbose=verbose, bounds=(lower, np.inf),
                        max_nfev=max_evaluations)
    m, p = len(sol.fun), len(sol.x)
    dof = max(m - p, 1)
    if not sol.success:
        raise CalibrationFailed(f"the fit did not converge in {sol.nfev} evaluations ({sol.message}); its last "
                                f"residual sigma {np.sqrt(float(sol.fun @ sol.fun) / dof):.4g} (in sensor-noise "
                                f"units) at {dict(zip([q.name for q in pb.params], (sol.x * s).tolist()))}: no "
                                f"result written")
    theta = sol.x * s
    r, J = pb.evaluate(theta)
    names_fit = [q.name for q in pb.params]
    stats = fit_statistics(names_fit, r, J * s, s, theta)
    d, new_sensors, mass = apply_parameters(robot_dict, pb.sensors, pb.params, theta)
    out = CalibrationResult(names=names_fit, nominal=pb.theta0, values=theta, iterations=int(sol.nfev),
                            robot_dict=d, sensors=new_sensors, payload_mass=mass, **stats)
    if len(held) and _tip_sensor(mechanism_of(robot_dict, n_sections, base_dir), pb.sensors) is not None:
        hp = Problem(robot_dict, sensors, recording.rows(held), names, n_sections, base_dir)
        before = tip_errors(hp, hp.theta0, range(len(held)))
        after = tip_errors(hp, theta, range(len(held)))
        out.heldout = {"rows": len(held), "tip_rms_before_m": before[0], "tip_max_before_m": before[1],
                       "tip_rms_after_m": after[0], "tip_max_after_m": after[1]}
    return out


def write_robot_file(path, robot_dict, header=""):
    """Write a robot description (YAML) with an optional comment header."""
    import yaml
    with open(path, "w") as fh:
        if header:
            fh.write("".join(f"# {line}\n" for line in header.splitlines()))
        yaml.safe_dump(robot_dict, fh, sort_keys=False, default_flow_style=None)


# ----------------------------------------------------------------------------
# Damping from a dynamic recording
# ----------------------------------------------------------------------------

def simulate_readings(robot, sensors, times, inputs, dt, theta=0.5, joints=None, *, efforts=None, wrenches=None):
    """Noise-free readings {sensor: (N, ...)} of a time series of any robot
    (a mechanism or a classic model): it starts at rest in equilibrium
    under the first row's inputs -- ``inputs[0]``, ``joints[0]`` (the
    position commands of the position-controlled joints, rad or m; None:
    their references), and the known loads ``efforts`` {joint: (N,)} and
    ``wrenches`` {(point, axes): (N, 6)} (:class:`Recording`): an arm held
    deflected by a known load, released when the next rows drop it, or
    loaded by a payload step -- at ``times[0]``; each row's actuator inputs
    and loads are held until the next row's time (zero-order hold), the
    joints move linearly from one row's command to the next (as a servo
    tracking the recorded commands does: a held command would jump the
    joint within one integrator step, at a speed set by the step);
    integrator steps of about ``dt`` [s]
    (:class:`constrained.MechanismSimulator`). Raises CalibrationFailed if
    a step fails, CalibrationError if the times do not increase."""
    mech = as_mechanism(robot)
    sensors, where = _measuring(mech, sensors)
    ws = Workspace(mech.tree)
    times = np.asarray(times, dtype=float)
    if np.any(np.diff(times) <= 0):
        raise CalibrationError("t: the times of a dynamic recording must increase")
    names = position_joints(mech)
    known = Recording(np.asarray(inputs, dtype=float), {}, times, None, dict(efforts or {}), dict(wrenches or {}))

    def positions(r):
        return None if joints is None else dict(zip(names, joints[r]))

    q0 = solve_equilibrium(mech, inputs[0], known.row_efforts(0), positions(0), None, known.row_loads(0)).q
    sim = MechanismSimulator(mech, dt, theta, q=q0, full_newton=False)
    sim.t = float(times[0])
    out = {s.name: [] for s in sensors}
    for r in range(len(times)):
        if r > 0:
            span = times[r] - times[r - 1]
            n = max(1, int(round(span / dt)))
            if n * sim.dt != span:                # the rows' spacing in whole steps
                t, q, v = sim.t, sim.q, sim.v
                sim = MechanismSimulator(mech, span / n, theta, q=q, v=v, full_newton=False)
                sim.t = t
            held = dict(efforts=known.row_efforts(r - 1), point_loads=known.row_loads(r - 1))
            try:
                if joints is None:
                    sim.step(inputs[r - 1], n=n, **held)
                else:                             # the joints' commands: linear from row to row
                    for k in range(1, n + 1):
                        c = joints[r - 1] + (k / n) * (np.asarray(joints[r]) - joints[r - 1])
                        sim.step(inputs[r - 1], positions=dict(zip(names, c)), **held)
            except StepError as e:
                raise CalibrationFailed(f"row {r}: the simulation failed ({e})") from None
        for name, z in sn.predict_readings(ws, sim.q, sensors, where).items():
            out[name].append(z)
    return {k: np.array(v) for k, v in out.items()}


def record_dynamic(robot, sensors, times, inputs, rng, dt=1e-3, joints=None, *, efforts=None, wrenches=None):
    """Simulated noisy recording of a time series of any robot (see
    :func:`simulate_readings`; the known loads kept in the recording)."""
    clean = simulate_readings(robot, sensors, times, inputs, dt, joints=joints, efforts=efforts, wrenches=wrenches)
    by_name = {s.name: s for s in sensors}
    readings = {k: np.array([sn.simulate_measurement(by_name[k], z, rng) for z in v]) for k, v in clean.items()}
    return Recording(np.asarray(inputs, dtype=float), readings, np.asarray(times, dtype=float),
                     None if joints is None else np.asarray(joints, dtype=float),
                     {k: np.asarray(v, dtype=float) for k, v in (efforts or {}).items()},
                     {k: np.asarray(v, dtype=float) for k, v in (wrenches or {}).items()})


def calibrate_dynamic(robot_dict, sensors, recording, names, *, dt=5e-3, n_sections=None, verbose=0,
                      base_dir=None, max_evaluations=None):
    """Fit the parameters ``names`` (module docstring: ``viscosity:``,
    ``density:``, ``youngs_modulus:``, ``tendon_offset:``,
    ``sensor_offset:``; not ``payload_mass``: a known load goes in the
    record, an unknown one is the filter's) of a robot of either schema to
    a dynamic recording: rows at increasing times ``t``, the robot at rest
    at the first row under its inputs and known loads -- a release test
    holds it deflected by a known load that the next rows drop --, its
    joint commands in ``recording.joints``; each evaluation simulates the
    record (:func:`simulate_readings`, step ``dt``). Sensitivities: central
    differences of the simulated trajectory (``least_squares(jac=
    "3-point")``; no analytic sensitivity through the integrator is
    implemented). A material parameter stays within 1e-3..1e3 of its
    starting value. Returns a :class:`CalibrationResult` (no held-out
    rows); raises CalibrationFailed, with the last residual, when the fit
    does not converge in ``max_evaluations`` simulations."""
    from scipy.optimize import least_squares
    if recording.time is None:
        raise CalibrationError("dynamic fit: the recording needs a time column t")
    if not (np.isfinite(dt) and dt > 0):
        raise CalibrationError(f"dynamic fit: dt must be a positive step in s, got {dt}")
    mech0 = mechanism_of(robot_dict, n_sections, base_dir)
    check_recording_inputs(mech0, recording.inputs)         # the declared actuator ranges
    check_recording(mech0, recording)
    sensors = _measuring(mech0, sensors)[0]
    params = _params(names, robot_dict, sensors)
    if any(p.kind == "payload_mass" for p in params):
        raise CalibrationError("dynamic fit: payload_mass is not fitted from a time series (give the known "
                               "load in the record: its mass:/wrench: columns)")
    nominal = np.array([p.nominal for p in params])
    scale = np.array([p.scale for p in params])
    material = np.array([p.kind in MATERIAL_KINDS for p in params])
    lower = np.where(material, (1e-3 - 1.0) * nominal / scale, -np.inf)
    upper = np.where(material, (1e3 - 1.0) * nominal / scale, np.inf)

    def fun(x):
        d, sens, _ = apply_parameters(robot_dict, sensors, params, nominal + scale * x)
        mech = mechanism_of(d, n_sections, base_dir)
        pred = simulate_readings(mech, sens, recording.time, recording.inputs, dt, joints=recording.joints,
                                 efforts=recording.efforts, wrenches=recording.wrenches)
        res = []
        for s in sens:
            for r in range(len(recording)):
                z = recording.readings[s.name][r]
                if not np.all(np.isfinite(z)):
                    continue
                if s.position_only:
                    res.append((pred[s.name][r] - z) / s.sigma_position_m)
                else:
                    e_p = (pred[s.name][r][:3, 3] - z[:3, 3]) / s.sigma_position_m
                    e_r = _log_so3(z[:3, :3].T @ pred[s.name][r][:3, :3]) / s.sigma_rotation_rad
                    res.append(np.concatenate([e_p, e_r]))
        return np.concatenate(res)

    sol = least_squares(fun, np.zeros(len(params)), jac="3-point", diff_step=1e-3, bounds=(lower, upper),
                        verbose=verbose, max_nfev=max_evaluations)
    names_fit = [p.name for p in params]
    values = nominal + scale * sol.x
    if not sol.success:
        dof = max(len(sol.fun) - len(sol.x), 1)
        raise CalibrationFailed(f"the fit did not converge in {sol.nfev} simulations ({sol.message}); its last "
                                f"residual sigma {np.sqrt(float(sol.fun @ sol.fun) / dof):.4g} (in sensor-noise "
                                f"units) at {dict(zip(names_fit, values.tolist()))}: no result written")
    stats = fit_statistics(names_fit, sol.fun, sol.jac, scale, values)       # (sol.jac: d r / d (theta / scale))
    d, new_sensors, _ = apply_parameters(robot_dict, sensors, params, values)
    return CalibrationResult(names=names_fit, nominal=nominal, values=values, iterations=int(sol.nfev),
                             robot_dict=d, sensors=new_sensors, payload_mass=0.0, **stats)


def calibrate_damping(robot_dict, sensors, recording, members=None, *, dt=5e-3, n_sections=None, verbose=0,
                      base_dir=None):
    """:func:`calibrate_dynamic` of the viscosities [Pa s] of the segments
    ``members`` (keys as in the static fit: a segment's name,
    ``<member>/<segment>`` where names repeat, ``<a>+<b>`` one viscosity
    for both; default: every segment with a material), the other
    parameters as in the robot dict (calibrate them first from a static
    sweep, or fit them here with :func:`calibrate_dynamic`)."""
    if members is None:
        members = [k for k, sd in _segments_of(robot_dict)[0].items() if "material" in sd]
    return calibrate_dynamic(robot_dict, sensors, recording, [f"viscosity:{m}" for m in members], dt=dt,
                             n_sections=n_sections, verbose=verbose, base_dir=base_dir)


def _log_so3(R):
    return log_so3(R)


# ----------------------------------------------------------------------------
# Command line: soft-twin-sim calibrate
# ----------------------------------------------------------------------------

def _expand(names, robot_dict):
    out = []
    for n in names:
        if n in MATERIAL_KINDS:
            out += [f"{n}:{k}" for k, s in _segments_of(robot_dict)[0].items() if "material" in s]
        elif n == "tendon_offset":
            out += [f"tendon_offset:{name}" for name, a in _actuators_of(robot_dict).items()
                    if a.get("type", "tendon") == "tendon" and a.get("routing", "straight") == "straight"]
        else:
            out.append(n)
    return out
