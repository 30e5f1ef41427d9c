"""Tip paths for the planner (:mod:`soft_twin_core.planning.planner`): timed tip
positions, optionally with orientations, in the robot's *base* frame.

A path is a :class:`TipPath`: strictly increasing sample times [s] and one
target per time. Build it from waypoints (:func:`waypoints`, resampled by
linear interpolation of the positions and geodesic interpolation of the
orientations) or from a parametric curve traversed once over a duration
with a constant angular rate (:func:`line`, :func:`circle`,
:func:`figure_eight`), or from a mapping (:func:`path_from_dict`, the
``path:`` block of a plan file). Units: m, s, rad.
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core import lie
from soft_twin_core.errors import PathError
from soft_twin_core.robot.model import ModelError, pose_from_dict


@dataclass(frozen=True, eq=False)
class TipPath:
    """times (N,) [s], strictly increasing; positions (N, 3) [m] in the base
    frame; orientations (N, 3, 3) rotation matrices (base frame) or None
    (position only)."""
    times: np.ndarray
    positions: np.ndarray
    orientations: object = None

    def __post_init__(self):
        t = np.asarray(self.times, dtype=float)
        p = np.asarray(self.positions, dtype=float)
        if t.ndim != 1 or t.size < 1:
            raise PathError(f"times: expected a non-empty 1-D list of times in s, got shape {t.shape}")
        if p.shape != (t.size, 3):
            raise PathError(f"positions: expected shape ({t.size}, 3) (one [x, y, z] in m per time), "
                            f"got {p.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise PathError("times/positions: contain NaN or inf")
        if np.any(np.diff(t) <= 0):
            k = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise PathError(f"times: must be strictly increasing, got t[{k}] = {t[k]} s and "
                            f"t[{k + 1}] = {t[k + 1]} s")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "positions", p)
        if self.orientations is not None:
            R = np.asarray(self.orientations, dtype=float)
            if R.shape != (t.size, 3, 3):
                raise PathError(f"orientations: expected shape ({t.size}, 3, 3), got {R.shape}")
            err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max()
            if not np.isfinite(err) or err > 1e-6 or np.any(np.linalg.det(R) < 0):
                raise PathError("orientations: not rotation matrices (R^T R != I or det < 0)")
            object.__setattr__(self, "orientations", R)

    def __len__(self):
        return self.times.size

    @property
    def duration(self):
        return float(self.times[-1] - self.times[0])

    def with_positions(self, positions):
        """The same times and orientations with other positions (base frame)."""
        return TipPath(self.times, positions, self.orientations)

    def world_targets(self, base_pose):
        """Targets as world poses (N, 4, 4) for a base at ``base_pose``
        (world <- base); the rotation is the identity where none is given."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, 3] = self.positions
        if self.orientations is not None:
            T[:, :3, :3] = self.orientations
        return np.asarray(base_pose, dtype=float) @ T

    def interpolate(self, t):
        """Positions (len(t), 3) at times t, linear between samples, held
        outside [t_0, t_end]."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, self.times, self.positions[:, k]) for k in range(3)], axis=-1)


def _times(duration, sample_period, where):
    duration = _positive(duration, f"{where}.duration")
    sample_period = _positive(sample_period, f"{where}.sample_period")
    n = max(1, int(round(duration / sample_period)))
    return np.linspace(0.0, duration, n + 1)


def _positive(v, where):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise PathError(f"{where}: expected a number, got {v!r}") from None
    if not np.isfinite(x) or x <= 0:
        raise PathError(f"{where}: expected a finite number > 0, got {v!r}")
    return x


def _vec3(v, where):
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise PathError(f"{where}: expected [x, y, z] numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise PathError(f"{where}: expected 3 finite numbers, got {v!r}")
    return a


def _plane_axes(normal, where):
    """Two orthonormal in-plane axes (e1, e2) with e1 x e2 = n / |n|. e1 is
    the projection of the base y axis (of z when n is along y)."""
    n = _vec3(normal, where)
    nn = np.linalg.norm(n)
    if nn == 0:
        raise PathError(f"{where}: the plane normal must not be zero")
    n = n / nn
    ref = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def line(start, end, duration, sample_period=0.02):
    """Straight line from ``start`` to ``end`` [m] at constant speed."""
    a, b = _vec3(start, "line.start"), _vec3(end, "line.end")
    t = _times(duration, sample_period, "line")
    s = (t / t[-1])[:, None]
    return TipPath(t, a + s * (b - a))


def circle(center, radius, duration, normal=(1.0, 0.0, 0.0), sample_period=0.02, start_angle=0.0,
           turns=1.0):
    """Circle of ``radius`` [m] about ``center`` in the plane of ``normal``,
    ``turns`` turns at a constant rate, starting at ``start_angle`` [rad]
    from the first in-plane axis (the base y axis projected on the plane),
    counter-clockwise about the normal: p = c + r (cos a e1 + sin a e2)."""
    c = _vec3(center, "circle.center")
    r = _positive(radius, "circle.radius")
    e1, e2 = _plane_axes(normal, "circle.normal")
    t = _times(duration, sample_period, "circle")
    a = float(start_angle) + 2 * np.pi * float(turns) * t / t[-1]
    return TipPath(t, c + r * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2))


def figure_eight(center, size, duration, normal=(1.0, 0.0, 0.0), sample_period=0.02):
    """Figure eight (lemniscate of Gerono) of half-width ``size`` [m] about
    ``center``, in the plane of ``normal``, once over ``duration``:
    p = c + size (sin a e1 + sin a cos a e2), a = 2 pi t / duration."""
    c = _vec3(center, "figure_eight.center")
    h = _positive(size, "figure_eight.size")
    e1, e2 = _plane_axes(normal, "figure_eight.normal")
    t = _times(duration, sample_period, "figure_eight")
    a = 2 * np.pi * t / t[-1]
    return TipPath(t, c + h * (np.sin(a)[:, None] * e1 + (np.sin(a) * np.cos(a))[:, None] * e2))


def waypoints(times, positions, orientations=None, sample_period=None):
    """Timed waypoints (base frame). With ``sample_period`` the path is
    resampled: positions linearly, orientations along the geodesic
    ``R_k exp(s log(R_k^T R_k+1))``; the waypoints themselves are kept."""
    path = TipPath(times, positions, orientations)
    if sample_period is None or len(path) < 2:
        return path
    dt = _positive(sample_period, "waypoints.sample_period")
    ts = [path.times[:1]]
    for k in range(len(path) - 1):
        n = max(1, int(np.ceil((path.times[k + 1] - path.times[k]) / dt - 1e-9)))
        ts.append(np.linspace(path.times[k], path.times[k + 1], n + 1)[1:])
    t = np.concatenate(ts)
    P = path.interpolate(t)
    R = None
    if path.orientations is not None:
        k = np.clip(np.searchsorted(path.times, t, side="right") - 1, 0, len(path) - 2)
        s = (t - path.times[k]) / (path.times[k + 1] - path.times[k])
        Ra, Rb = path.orientations[k], path.orientations[k + 1]
        w = lie.log_so3(np.einsum("nji,njk->nik", Ra, Rb))
        R = Ra @ lie.exp_so3(s[:, None] * w)
    return TipPath(t, P, R)


def rotation_from(d, where):
    """A rotation matrix from ``{rpy: [r, p, y]}`` (rad, R = Rz(y) Ry(p) Rx(r))
    or ``{quaternion: [x, y, z, w]}``."""
    if not isinstance(d, dict) or len(set(d) & {"rpy", "quaternion"}) != 1 or set(d) - {"rpy", "quaternion"}:
        raise PathError(f"{where}: expected {{rpy: [r, p, y]}} or {{quaternion: [x, y, z, w]}}, got {d!r}")
    try:
        return pose_from_dict({"position": [0, 0, 0], **d}, where)[:3, :3]
    except ModelError as e:
        raise PathError(str(e)) from None


_KINDS = {"line": ({"start", "end"}, set()),
          "circle": ({"center", "radius"}, {"normal", "start_angle", "turns"}),
          "figure_eight": ({"center", "size"}, {"normal"}),
          "waypoints": ({"points"}, set())}


def path_from_dict(d, where="path"):
    """A TipPath from a mapping::

        {type: circle, center: [x, y, z], radius: r, normal: [nx, ny, nz],
         duration: T, sample_period: dt, start_angle: a, turns: n}
        {type: line, start: [...], end: [...], duration: T, sample_period: dt}
        {type: figure_eight, center: [...], size: h, normal: [...], duration: T, sample_period: dt}
        {type: waypoints, sample_period: dt (optional),
         points: [{t: 0.0, position: [...], orientation: {rpy: [...]}}, ...]}
    """
    if not isinstance(d, dict):
        raise PathError(f"{where}: expected a mapping with a 'type', got {d!r}")
    kind = d.get("type")
    if kind not in _KINDS:
        raise PathError(f"{where}.type: expected one of {sorted(_KINDS)}, got {kind!r}")
    required, optional = _KINDS[kind]
    common = {"type", "sample_period"} | ({"duration"} if kind != "waypoints" else set())
    missing = sorted((required | common - {"sample_period"}) - set(d))
    if missing:
        raise PathError(f"{where}.{missing[0]}: missing (required for a {kind})")
    unknown = sorted(set(d) - required - optional - common)
    if unknown:
        raise PathError(f"{where}.{unknown[0]}: unknown key for a {kind}; expected "
                        f"{sorted(required | optional | common)}")
    sp = d.get("sample_period", 0.02 if kind != "waypoints" else None)
    if kind == "line":
        return line(d["start"], d["end"], d["duration"], sp)
    if kind == "circle":
        return circle(d["center"], d["radius"], d["duration"], d.get("normal", (1.0, 0.0, 0.0)), sp,
                      float(d.get("start_angle", 0.0)), float(d.get("turns", 1.0)))
    if kind == "figure_eight":
        return figure_eight(d["center"], d["size"], d["duration"], d.get("normal", (1.0, 0.0, 0.0)), sp)
    pts = d["points"]
    if not isinstance(pts, list) or not pts:
        raise PathError(f"{where}.points: expected a non-empty list of {{t, position[, orientation]}}")
    times, pos, rots = [], [], []
    with_rot = [isinstance(p, dict) and "orientation" in p for p in pts]
    if any(with_rot) and not all(with_rot):
        raise PathError(f"{where}.points: give an orientation for every point or for none")
    for k, p in enumerate(pts):
        w = f"{where}.points[{k}]"
        if not isinstance(p, dict) or "t" not in p or "position" not in p:
            raise PathError(f"{w}: expected a mapping with t [s] and position [x, y, z] [m], got {p!r}")
        extra = sorted(set(p) - {"t", "position", "orientation"})
        if extra:
            raise PathError(f"{w}.{extra[0]}: unknown key; expected t, position, orientation")
        try:
            times.append(float(p["t"]))
        except (TypeError, ValueError):
            raise PathError(f"{w}.t: expected a time in s, got {p['t']!r}") from None
        pos.append(_vec3(p["position"], f"{w}.position"))
        if all(with_rot):
            rots.append(rotation_from(p["orientation"], f"{w}.orientation"))
    return waypoints(times, pos, np.array(rots) if rots else None, sp)
