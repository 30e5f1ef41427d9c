"""Playback of a saved run or a recording in the browser view (issue 31):
the clock of a run played in a loop (play, pause, speed, seek), the sample
shown at a run time, and the signals a person can plot beside the 3D view.

    clock = PlaybackClock(t0, t1, now=time.monotonic())
    clock.seek(1.5, now)               # scrub: the run time 1.5 s, from now on
    clock.set_speed(0.25, now)         # slow motion
    k = sample_at(times, clock.time(now))

No browser or server here (:func:`soft_twin_core.viz.render.view_main`
wires it to :class:`soft_twin_core.viz.live_view.LiveView`).
"""

import numpy as np


class PlaybackClock:
    """Run time [s] of a run from ``t0`` to ``t1`` played in a loop on a
    wall clock (any monotonic seconds the caller gives as ``now``):
    ``speed`` run seconds per wall second while playing; paused, it
    stands; ``seek`` sets it. Every change keeps the time it had then."""

    def __init__(self, t0, t1, now, speed=1.0):
        self.t0, self.t1 = float(t0), float(t1)
        if not self.t1 >= self.t0:
            raise ValueError(f"playback: the run ends ({t1}) before it starts ({t0})")
        self.speed = _checked_speed(speed)
        self.playing = True
        self._at, self._wall = self.t0, float(now)       # run time at wall time _wall

    def time(self, now):
        """The run time at wall time ``now``: in [t0, t1), wrapping round."""
        if not self.playing or self.t1 == self.t0:
            return self._at
        span = self.t1 - self.t0
        return self.t0 + (self._at - self.t0 + self.speed * (float(now) - self._wall)) % span

    def seek(self, t, now):
        """Show run time ``t`` [s] (clipped to [t0, t1]) at ``now``, playing on from it if playing."""
        self._at, self._wall = float(min(max(t, self.t0), self.t1)), float(now)

    def set_playing(self, playing, now):
        self._at, self._wall = self.time(now), float(now)
        self.playing = bool(playing)

    def set_speed(self, speed, now):
        self._at, self._wall = self.time(now), float(now)
        self.speed = _checked_speed(speed)


def _checked_speed(speed):
    speed = float(speed)
    if not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"playback speed: must be a number > 0, got {speed!r}")
    return speed


def sample_at(times, t):
    """Index of the sample shown at run time ``t``: the latest at or before
    it (the first before the run starts); ``times`` increasing."""
    k = int(np.searchsorted(np.asarray(times, dtype=float), float(t), side="right")) - 1
    return min(max(k, 0), len(times) - 1)


def frame_signals(frame_names, frame_poses):
    """{label: values (n,)} of the positions of a run's named frames at its
    samples (``frame_poses``: per sample, a 4x4 world pose per name, as a
    run or recording holds them with its member samples), a signal per
    axis, labelled with its unit: ``"tip z [m]"``; in ``frame_names``
    order."""
    P = np.asarray(frame_poses, dtype=float)[:, :, :3, 3]          # (samples, frames, 3)
    if P.shape[1] != len(frame_names):
        raise ValueError(f"frame_poses: {P.shape[1]} frames a sample, but {len(frame_names)} names")
    return {f"{name} {axis} [m]": P[:, f, a] for f, name in enumerate(frame_names) for a, axis in enumerate("xyz")}
