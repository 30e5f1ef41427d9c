"""The loads the engine takes (point and distributed wrenches along a robot's
arc length, dead or follower, gravity on or scaled) and the point moments of
point-moment actuators. :mod:`engine.forces` turns them into generalised
forces; :mod:`soft_twin_core.reference.loads` is the numpy reference of that
map on the classic rod.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PointLoad:
    """A wrench [fx, fy, fz, mx, my, mz] (N, N m) applied at arc length s [m]
    of a soft member. frame: "world" (dead load) or "body" (follower load).
    member: the member's name (None: the robot's first member, a classic
    rod's backbone)."""
    s: float
    wrench: tuple
    frame: str = "world"
    member: str = None


@dataclass(frozen=True)
class DistributedLoad:
    """A uniform wrench per unit length [N/m, N m/m] over [start, end] m of
    a soft member (end None = its distal end). frame: "world" or "body";
    member as for :class:`PointLoad`."""
    wrench: tuple
    frame: str = "world"
    start: float = 0.0
    end: float = None
    member: str = None


@dataclass(frozen=True)
class Loads:
    """External loads; gravity uses the model's gravity vector and density."""
    point: tuple = ()
    distributed: tuple = ()
    gravity: bool = True

    def scaled(self, factor):
        """The same loads times ``factor`` (for load stepping); gravity is
        scaled too (``gravity`` becomes the factor)."""
        return _ScaledLoads(self, factor)


@dataclass(frozen=True)
class _ScaledLoads:
    base: Loads
    factor: float

    @property
    def point(self):
        return tuple(PointLoad(p.s, tuple(self.factor * np.asarray(p.wrench)), p.frame, p.member)
                     for p in self.base.point)

    @property
    def distributed(self):
        return tuple(DistributedLoad(tuple(self.factor * np.asarray(d.wrench)), d.frame, d.start, d.end, d.member)
                     for d in self.base.distributed)

    @property
    def gravity(self):
        return self.factor if self.base.gravity else 0.0


def tip_load(model, force=(0, 0, 0), moment=(0, 0, 0), frame="world"):
    return PointLoad(model.total_length, tuple(force) + tuple(moment), frame)


def validate_loads(model, loads):
    for i, p in enumerate(loads.point):
        w = np.asarray(p.wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"loads.point[{i}].wrench: expected 6 finite numbers, got {p.wrench!r}")
        if p.frame not in ("world", "body"):
            raise ValueError(f"loads.point[{i}].frame: expected 'world' or 'body', got {p.frame!r}")
        if not -1e-12 <= p.s <= model.total_length + 1e-12:
            raise ValueError(f"loads.point[{i}].s: must lie in [0, {model.total_length}] m, got {p.s}")
    for i, d in enumerate(loads.distributed):
        w = np.asarray(d.wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"loads.distributed[{i}].wrench: expected 6 finite numbers, got {d.wrench!r}")
        if d.frame not in ("world", "body"):
            raise ValueError(f"loads.distributed[{i}].frame: expected 'world' or 'body', got {d.frame!r}")


def actuator_point_loads(model, u):
    """Follower point moments of the actuators using the point-moment model
    (slides part C, model (b)): the pure moment ``-c u d(end) x e_x`` at the
    termination (c = 1 for tendons, -area for chambers). No force: the
    tendon's compression is balanced along the arm by its channel."""
    out = []
    for a, val in zip(model.actuators, u):
        if a.tendon_model != "point_moment" or val == 0.0:
            continue
        d, _ = a.offset_at(np.array([a.end]))
        f = -a.force_per_unit_input * val * np.array([1.0, 0.0, 0.0])
        out.append(PointLoad(a.end, (0.0, 0.0, 0.0) + tuple(np.cross(d[0], f)), "body"))
    return tuple(out)
