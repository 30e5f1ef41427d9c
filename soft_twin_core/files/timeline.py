"""The time line of a run: input profiles over time, the time steps of a
dynamics run and the bounds on what a run records (shared by every
scenario runner; ground floor above the robot files)."""

import math
from decimal import Decimal

import numpy as np

from soft_twin_core.errors import ScenarioError
from soft_twin_core.limits import MAX_BACKBONE_POINTS, MAX_RECORDED_ROWS, MAX_TIME_STEPS
from soft_twin_core.robot.model import check_actuator_input, parse_numbers


def parse_profile(v, where):
    """(times, values) of a piecewise-linear profile [[t, value], ...] (times
    strictly increasing); ScenarioError naming ``where``."""
    try:
        a = parse_numbers(v, (None, 2), where, ScenarioError)
    except ScenarioError:
        raise ScenarioError(f"{where}: expected a list of [t, value] pairs, got {v!r}") from None
    if len(a) < 1:
        raise ScenarioError(f"{where}: expected a list of [t, value] pairs, got {v!r}")
    if np.any(np.diff(a[:, 0]) <= 0):
        raise ScenarioError(f"{where}: times must increase strictly, got {a[:, 0].tolist()}")
    return a[:, 0], a[:, 1]


def check_scenario_input(act, values, where, error):
    """Refuse (``error`` naming ``where``) any of ``values`` outside the
    actuator's declared range: the node's rule
    (:func:`model.check_actuator_input`), so a scenario cannot run offline
    with an input the node would reject. A profile is piecewise linear, so
    checking its points bounds every interpolated value."""
    for v in np.atleast_1d(np.asarray(values, dtype=float)):
        bad = check_actuator_input(act, v)
        if bad is not None:
            raise error(f"{where}: {bad[1]} [{bad[0]}]")


def positive_time(v, name):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ScenarioError(f"{name}: expected a positive, finite time in s, got {v!r}")
    return float(v)


def count(v, name, low):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ScenarioError(f"{name}: expected an integer >= {low}, got {v!r}")
    return int(v)


def check_output_size(n_steps, record_every, backbone_every, backbone_points):
    """Refuse a run whose recorded rows or backbone samples would exceed
    the limits of soft_twin_core.limits (before the run allocates them)."""
    rows = n_steps // record_every + 2
    if rows > MAX_RECORDED_ROWS:
        raise ScenarioError(f"record_every: {record_every} gives {rows} recorded rows over {n_steps} steps, "
                            f"which exceeds the limit of {MAX_RECORDED_ROWS} rows (soft_twin_core.limits); "
                            f"record every {-(-n_steps // MAX_RECORDED_ROWS)} steps or more")
    if backbone_every:
        points = (n_steps // backbone_every + 1) * backbone_points
        if points > MAX_BACKBONE_POINTS:
            raise ScenarioError(f"backbone_every: {backbone_every} gives {points} backbone points ("
                                f"{n_steps // backbone_every + 1} samples of {backbone_points} points), "
                                f"which exceeds the limit of {MAX_BACKBONE_POINTS} (soft_twin_core.limits)")


def n_steps_for(duration, dt):
    """Steps of size ``dt`` that cover ``duration`` (the last recorded time
    is ``n dt >= duration``, within 1e-9 relative); ScenarioError naming
    the argument if either is not a positive finite time or the duration
    is shorter than one step."""
    dt = positive_time(dt, "dt")
    duration = positive_time(duration, "duration")
    if duration < dt * (1.0 - 1e-9):
        raise ScenarioError(f"duration: {duration!r} s is shorter than one time step (dt = {dt!r} s): "
                            f"nothing to simulate")
    steps = duration / dt
    if steps > MAX_TIME_STEPS:          # a resource bound, before any allocation (soft_twin_core.limits)
        raise ScenarioError(f"duration / dt: {duration:g} s / {dt:g} s = {steps:.4g} time steps exceeds the "
                            f"limit of {MAX_TIME_STEPS} steps (soft_twin_core.limits)")
    return max(1, int(math.ceil(steps - 1e-9)))


def step_times(dt):
    """t(k): the time of step k, ``k * dt`` computed exactly in decimal from
    the shortest spelling of ``dt`` and rounded once (``0.1`` gives ``0.7``
    at k = 7, not 0.7000000000000001; no accumulation, so no drift)."""
    d = Decimal(repr(float(dt)))
    return lambda k: float(d * k)


class Spline:
    """A clamped cubic spline through [t, values...] rows (at rest at both
    ends), held constant outside its time span; ``velocity(t)`` its derivative."""

    def __init__(self, a, where):
        from scipy.interpolate import CubicSpline     # here: ~0.2 s of import, for trajectories only
        if len(a) < 1:
            raise ScenarioError(f"{where}: expected at least one [t, value...] row, got none")
        self.t0, self.t1 = a[0, 0], a[-1, 0]
        y = a[:, 1:] if a.shape[1] > 2 else a[:, 1]
        if len(a) == 1:
            self.sp = None
            self.value = y[0]
            return
        if np.any(np.diff(a[:, 0]) <= 0):
            raise ScenarioError(f"{where}: times must increase strictly, got {a[:, 0].tolist()}")
        self.sp = CubicSpline(a[:, 0], y, bc_type="clamped")
        self.dsp = self.sp.derivative()

    def __call__(self, t):
        if self.sp is None:
            return np.copy(self.value)
        return self.sp(min(max(t, self.t0), self.t1))

    def velocity(self, t):
        if self.sp is None or not self.t0 <= t <= self.t1:
            return 0.0 * np.asarray(self(t))
        return self.dsp(t)
