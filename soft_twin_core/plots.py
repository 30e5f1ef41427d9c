"""Figures (PNG and SVG, matplotlib's Agg backend): robot shapes (side, top
and 3D views, equal axes), tip position and velocity, internal wrenches
along a member, a statics solve and a statics sweep against reference
values (a dynamics run's set: :mod:`mechanism_plots`).

Every ``plot_*`` function writes ``<stem>.png`` and ``<stem>.svg`` into a
folder and returns the paths written; :func:`plot_statics` and
:func:`plot_sweep` write the whole set for a ``soft-twin-sim`` statics
run. Shapes are drawn from :class:`scene.Snapshot` lists
(members, rigid links), so any robot that can be turned into snapshots is
drawn by the same code.
"""

import os

import numpy as np

from .scene import bounds

FORMATS = ("png", "svg")
DPI = 110
_VIEWS = (("side", 0, 2, "side view (x-z)"), ("top", 0, 1, "top view (x-y)"))
_WRENCH = (("f_x", "N"), ("f_y", "N"), ("f_z", "N"), ("m_x", "N m"), ("m_y", "N m"), ("m_z", "N m"))


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, folder, stem):
    os.makedirs(folder, exist_ok=True)
    paths = []
    for ext in FORMATS:
        p = os.path.join(folder, f"{stem}.{ext}")
        fig.savefig(p, dpi=DPI)
        paths.append(p)
    _plt().close(fig)
    return paths


def equal_limits(ax, lo, hi, i, j):
    """Set the 2D axes limits to the box (lo, hi) on axes i, j, equal scale."""
    ax.set_xlim(lo[i], hi[i])
    ax.set_ylim(lo[j], hi[j])
    ax.set_aspect("equal", adjustable="box")


def equal_limits_3d(ax, lo, hi):
    """3D limits: the cube around the box (lo, hi), one scale on all axes."""
    c, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))


def pick(n, k):
    """Up to k indices spread evenly over range(n), first and last included."""
    if n <= k:
        return list(range(n))
    return sorted(set(np.round(np.linspace(0, n - 1, k)).astype(int).tolist()))


def draw_snapshot(axes, snap, color, label=None, lw=2.0):
    """Draw one snapshot on a dict of axes {'side', 'top', '3d'} (any subset)."""
    for name, ax in axes.items():
        for k, P in enumerate(snap.members):
            lab = label if k == 0 else None
            if name == "3d":
                ax.plot(P[:, 0], P[:, 1], P[:, 2], color=color, lw=lw, label=lab)
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(P[:, i], P[:, j], color=color, lw=lw, label=lab)
        for seg in snap.links:
            if name == "3d":
                ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="0.25", lw=lw + 1.5, solid_capstyle="round")
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(seg[:, i], seg[:, j], color="0.25", lw=lw + 1.5, solid_capstyle="round")
        rigid = [(P, 1.4, "0.3") for P in snap.solids] + [(P, 1.0, "k") for P in snap.joint_axes]
        for P, lw_s, col in rigid:                     # rigid links' shapes and joint axes
            if name == "3d":
                ax.plot(P[:, 0], P[:, 1], P[:, 2], color=col, lw=lw_s)
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(P[:, i], P[:, j], color=col, lw=lw_s)
        if len(snap.joints):
            J = snap.joints
            if name == "3d":
                ax.plot(J[:, 0], J[:, 1], J[:, 2], "o", mfc="w", mec="k", ms=5)
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(J[:, i], J[:, j], "o", mfc="w", mec="k", ms=5)
        tip = snap.tip
        if name == "3d":
            ax.plot([tip[0]], [tip[1]], [tip[2]], "o", color=color, ms=4)
        else:
            i, j = {"side": (0, 2), "top": (0, 1)}[name]
            ax.plot([tip[i]], [tip[j]], "o", color=color, ms=4)


def shapes_figure(snapshots, title, max_shapes=8):
    """Figure with side, top and 3D views of up to ``max_shapes`` snapshots
    (colour = order), equal axes in m, legend with the captions."""
    plt = _plt()
    fig = plt.figure(figsize=(14, 4.8))
    side = fig.add_subplot(1, 3, 1)
    top = fig.add_subplot(1, 3, 2)
    ax3 = fig.add_subplot(1, 3, 3, projection="3d")
    axes = {"side": side, "top": top, "3d": ax3}
    chosen = [snapshots[i] for i in pick(len(snapshots), max_shapes)]
    cmap = plt.get_cmap("viridis")
    for k, s in enumerate(chosen):
        draw_snapshot(axes, s, cmap(k / max(1, len(chosen) - 1)), s.caption or None)
    lo, hi = bounds(snapshots)
    for name, i, j, t in _VIEWS:
        ax = axes[name]
        ax.plot([0], [0], "ks", ms=7, label="base origin" if name == "side" else None)
        equal_limits(ax, lo, hi, i, j)
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_title(t)
        ax.grid(alpha=0.3)
    equal_limits_3d(ax3, lo, hi)
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.set_title("3D view")
    side.legend(fontsize=7, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_shapes(snapshots, folder, title="backbone shapes", stem="backbone_shapes"):
    return _save(shapes_figure(snapshots, title), folder, stem)


def plot_tip(out, folder, title="tip motion"):
    """Tip position [m] and, when the run has it, velocity [m/s] (world)
    against time [s]."""
    plt = _plt()
    t = np.asarray(out["time"])
    p = np.asarray(out["tip_position"]).reshape(len(t), 3)
    has_v = "tip_velocity" in out
    fig, axs = plt.subplots(2 if has_v else 1, 1, figsize=(8, 6.5 if has_v else 3.8), sharex=True, squeeze=False)
    a = axs[0, 0]
    for k, c in enumerate("xyz"):
        a.plot(t, p[:, k], label=f"{c}")
    a.set_ylabel("tip position [m]")
    if has_v:
        b = axs[1, 0]
        v = np.asarray(out["tip_velocity"]).reshape(len(t), 3)
        for k, c in enumerate("xyz"):
            b.plot(t, v[:, k], label=f"v_{c}")
        b.plot(t, np.linalg.norm(v, axis=1), "k--", lw=1, label="|v|")
        b.set_ylabel("tip velocity [m/s]")
    axs[-1, 0].set_xlabel("time [s]")
    for ax in axs[:, 0]:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, folder, "tip")


def wrench_figure(s_list, W_list, labels, title):
    """Internal wrench components (body frame) along the backbone, one line per sample."""
    plt = _plt()
    fig, axs = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    cmap = plt.get_cmap("viridis")
    for k, (s, W, lab) in enumerate(zip(s_list, W_list, labels)):
        W = np.asarray(W)
        for m, ax in enumerate(axs.ravel()):
            ax.plot(s, W[:, m], color=cmap(k / max(1, len(s_list) - 1)), label=lab if m == 0 else None)
    for m, ax in enumerate(axs.ravel()):
        name, unit = _WRENCH[m]
        ax.set_title(name)
        ax.set_ylabel(f"[{unit}]")
        ax.grid(alpha=0.3)
    for ax in axs[1]:
        ax.set_xlabel("arc length s [m]")
    axs[0, 0].legend(fontsize=7)
    fig.suptitle(title + " (body frame; the distal part on the proximal part)")
    fig.tight_layout()
    return fig


def plot_statics(result, snap, folder, name="statics"):
    """One equilibrium (``soft-twin-sim statics``) of any robot: its shape
    (``snap``, :func:`mechanism_scene.statics_snapshot`) and the internal
    wrench along every member (``internal_wrenches_<member>``)."""
    paths = _save(shapes_figure([snap], f"{name}: equilibrium"), folder, "backbone_shapes")
    for m, d in result["members"].items():
        fig = wrench_figure([d["s"]], [d["internal_wrench"]], ["equilibrium"],
                            f"{name}: internal wrench along member {m}")
        paths += _save(fig, folder, f"internal_wrenches_{m}")
    return paths


def plot_sweep(results, snaps, folder, reference=None, name="sweep"):
    """A statics sweep over the load angle (any robot): its tip frame's
    position [m] against the angle [deg], with the scenario's reference
    values (if any) as markers; and the shapes of every angle (``snaps``)."""
    plt = _plt()
    a = np.array([r["angle_deg"] for r in results])
    p = np.array([r["tip_position"] for r in results])
    fig, axs = plt.subplots(1, 3, figsize=(14, 4.6))
    for k, (c, ax) in enumerate(zip("xyz", axs)):
        ax.plot(a, 1e3 * p[:, k], "-", marker=".", color=f"C{k}", label="soft_twin")
        if reference:
            ra = np.asarray(reference["angle_deg"], dtype=float)
            rp = np.asarray(reference["tip_position"], dtype=float)
            ax.plot(ra, 1e3 * rp[:, k], "o", mfc="none", color="k", label=reference.get("label", "reference"))
        ax.set_xlabel("load angle [deg]")
        ax.set_ylabel(f"tip {c} [mm]")
        ax.set_title(f"tip {c}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"{name}: tip position (world) against the load angle")
    fig.tight_layout()
    paths = _save(fig, folder, "sweep_tip")
    return paths + plot_shapes(snaps, folder, f"{name}: equilibrium shapes", "sweep_shapes")
