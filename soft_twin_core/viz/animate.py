"""Animations (GIF or MP4) of a list of :class:`scene.Snapshot`: side, top
and 3D views with one fixed camera framing the whole motion, the caption
(time) on every frame, played at a given frame rate (real time when the
snapshots are 1/fps apart; :func:`scene.sample_times` picks them).

Frames are drawn with matplotlib (Agg) and written with imageio: GIF by
Pillow, MP4 (H.264, yuv420p) by the ffmpeg binary shipped in the
imageio-ffmpeg wheel. Progress goes to ``progress`` (default stderr).
"""

import os
import sys
import time

import numpy as np

from soft_twin_core.viz.plots import equal_limits, equal_limits_3d
from soft_twin_core.viz.scene import bounds

SIZE_PX = (1120, 448)          # width, height: multiples of 16 for H.264
DPI = 80
_PLANES = {"side": (0, 2), "top": (0, 1)}


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


class FrameDrawer:
    """Draws snapshots into one reused figure; :meth:`frame` returns the
    RGB image (H, W, 3) uint8 of one snapshot."""

    def __init__(self, snapshots, title=""):
        plt = _plt()
        w, h = SIZE_PX
        self.fig = plt.figure(figsize=(w / DPI, h / DPI), dpi=DPI)
        self.axes = {"side": self.fig.add_subplot(1, 3, 1), "top": self.fig.add_subplot(1, 3, 2),
                     "3d": self.fig.add_subplot(1, 3, 3, projection="3d")}
        lo, hi = bounds(snapshots)
        for name, (i, j) in _PLANES.items():
            ax = self.axes[name]
            equal_limits(ax, lo, hi, i, j)
            ax.plot([0], [0], "ks", ms=6)
            ax.set_xlabel(f"{'xyz'[i]} [m]")
            ax.set_ylabel(f"{'xyz'[j]} [m]")
            ax.set_title(f"{name} view ({'xyz'[i]}-{'xyz'[j]})", fontsize=10)
            ax.grid(alpha=0.3)
        ax3 = self.axes["3d"]
        equal_limits_3d(ax3, lo, hi)
        ax3.set_xlabel("x [m]")
        ax3.set_ylabel("y [m]")
        ax3.set_zlabel("z [m]")
        ax3.set_title("3D view", fontsize=10)
        self.fig.suptitle(title, fontsize=11)
        self.caption = self.fig.text(0.01, 0.025, "", fontsize=15, family="monospace", weight="bold",
                                     animated=True)
        self.fig.tight_layout(rect=(0, 0.05, 1, 1))
        n_members = max(len(s.members) for s in snapshots)
        n_links = max(len(s.links) for s in snapshots)
        n_solids = max(len(s.solids) for s in snapshots)
        n_axes = max(len(s.joint_axes) for s in snapshots)
        self.lines, self.rigid = {}, {}
        for name, ax in self.axes.items():
            mk = ((lambda **kw: ax.plot([], [], [], animated=True, **kw)[0]) if name == "3d"
                  else (lambda **kw: ax.plot([], [], animated=True, **kw)[0]))
            self.lines[name] = ([mk(color=f"C{k % 10}", lw=2.5) for k in range(n_members)],
                                [mk(color="0.25", lw=4, solid_capstyle="round") for _ in range(n_links)],
                                mk(color="C3", marker="o", ms=5, ls="none"))
            # rigid links' visual shapes (wire outlines), joint axes and joint markers (articulated robots)
            self.rigid[name] = ([mk(color="0.3", lw=1.6) for _ in range(n_solids)],
                                [mk(color="k", lw=1.2) for _ in range(n_axes)],
                                mk(color="k", marker="o", mfc="w", ms=6, ls="none"))
        # blitting: the axes, grids and labels (fixed camera) are drawn once;
        # each frame restores them and draws the moving artists only
        self.fig.canvas.draw()
        self.background = self.fig.canvas.copy_from_bbox(self.fig.bbox)

    def frame(self, snap):
        for name, (members, links, tip) in self.lines.items():
            for k, line in enumerate(members):
                self._set(name, line, snap.members[k] if k < len(snap.members) else np.zeros((0, 3)))
            for k, line in enumerate(links):
                self._set(name, line, snap.links[k] if k < len(snap.links) else np.zeros((0, 3)))
            self._set(name, tip, snap.tip[None, :])
        for name, (solids, axes, joints) in self.rigid.items():
            for k, line in enumerate(solids):
                self._set(name, line, snap.solids[k] if k < len(snap.solids) else np.zeros((0, 3)))
            for k, line in enumerate(axes):
                self._set(name, line, snap.joint_axes[k] if k < len(snap.joint_axes) else np.zeros((0, 3)))
            self._set(name, joints, snap.joints)
        self.caption.set_text(snap.caption)
        canvas = self.fig.canvas
        canvas.restore_region(self.background)
        for (members, links, tip), (solids, axes, joints) in zip(self.lines.values(), self.rigid.values()):
            for line in solids + members + links + axes + [joints, tip]:
                line.axes.draw_artist(line)
        self.fig.draw_artist(self.caption)
        rgba = np.asarray(self.fig.canvas.buffer_rgba())
        return np.ascontiguousarray(rgba[..., :3])

    @staticmethod
    def _set(name, line, P):
        if name == "3d":
            line.set_data_3d(P[:, 0], P[:, 1], P[:, 2])
        else:
            i, j = _PLANES[name]
            line.set_data(P[:, i], P[:, j])

    def close(self):
        _plt().close(self.fig)


_STDERR = object()


def write_animation(snapshots, path, fps, title="", progress=_STDERR):
    """Render ``snapshots`` (one per frame) to ``path`` (.gif or .mp4) at
    ``fps`` frames/s. Returns (frames, seconds of video). GIF frame
    durations are whole centiseconds: choose fps dividing 100 (10, 20, 25,
    50) for exact real time. ``progress``: a text stream (default: the
    current sys.stderr) or None."""
    if progress is _STDERR:
        progress = sys.stderr
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".gif", ".mp4"):
        raise ValueError(f"animation file: expected a .gif or .mp4 name, got {path!r}")
    if not snapshots:
        raise ValueError("animation: no snapshots to draw")
    if not (fps > 0 and np.isfinite(fps)):
        raise ValueError(f"fps: expected a positive frame rate, got {fps!r}")
    import imageio.v2 as iio
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    drawer = FrameDrawer(snapshots, title)
    if ext == ".gif":
        writer = iio.get_writer(path, mode="I", duration=1000.0 / fps, loop=0)
    else:
        writer = iio.get_writer(path, fps=fps, codec="libx264", quality=7, pixelformat="yuv420p",
                                macro_block_size=16, ffmpeg_log_level="error")
    t0 = last = time.monotonic()
    n = len(snapshots)
    try:
        for k, snap in enumerate(snapshots):
            writer.append_data(drawer.frame(snap))
            if progress is not None and (time.monotonic() - last > 1.0 or k == n - 1):
                last = time.monotonic()
                print(f"animation: frame {k + 1}/{n} ({100 * (k + 1) / n:.0f} %), "
                      f"{last - t0:.1f} s", file=progress, flush=True)
    finally:
        writer.close()
        drawer.close()
    return n, n / fps
