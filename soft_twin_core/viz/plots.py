"""Figures (PNG and SVG, matplotlib's Agg backend) of any robot: its shapes
(side, top and 3D views, equal axes), the tip's motion, the joint states
(positions, velocities, efforts) and the wrenches the rigid joints
transmit, the frames' positions, the strains of every soft section, the
internal wrenches along every member, the energies, a statics solve, and a
statics sweep against reference values.

Every ``plot_*`` function writes ``<stem>.png`` and ``<stem>.svg`` into a
folder and returns the paths written; :func:`plot_dynamics`,
:func:`plot_statics` and :func:`plot_sweep` write the whole set for a
``soft-twin-sim`` run. A run is the JSON of ``soft-twin-sim dynamics``
(:func:`mechanism_scenario.run_mechanism_dynamics`) or a recording read back
by :mod:`recording`; fields a recording lacks are skipped (each figure needs
its own fields only). Shapes are drawn from :class:`scene.Snapshot` lists.
"""

import numpy as np

from soft_twin_core.robot.model import STRAIN_NAMES
from soft_twin_core.viz.scene import bounds, run_snapshots
from soft_twin_core.viz.style import current_style, drawing_rc, drawn_size, save_figure


_VIEWS = (("side", 0, 2, "side view (x-z)"), ("top", 0, 1, "top view (x-y)"))
_WRENCH = (("f_x", "N"), ("f_y", "N"), ("f_z", "N"), ("m_x", "N m"), ("m_y", "N m"), ("m_z", "N m"))


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, folder, stem):
    """Write ``fig`` in the figure style in force (:mod:`style`: PNG and
    SVG, or a paper style's PDF, SVG and PNG at a column's width)."""
    return save_figure(fig, folder, stem)


def equal_limits(ax, lo, hi, i, j, min_aspect=0.75):
    """Set the 2D axes limits to the box (lo, hi) on axes i, j, equal scale;
    the narrower side widened about its centre to at least ``min_aspect``
    of the wider (a vertical arm's side view was a sliver whose x ticks ran
    into each other, ``-0.0250.0000.025``), at most 4 ticks an axis."""
    from matplotlib.ticker import MaxNLocator
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    wi, wj = hi[i] - lo[i], hi[j] - lo[j]
    ci, cj = 0.5 * (lo[i] + hi[i]), 0.5 * (lo[j] + hi[j])
    wi, wj = max(wi, min_aspect * wj), max(wj, min_aspect * wi)
    ax.set_xlim(ci - 0.5 * wi, ci + 0.5 * wi)
    ax.set_ylim(cj - 0.5 * wj, cj + 0.5 * wj)
    ax.set_aspect("equal", adjustable="box")
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(4))


def equal_limits_3d(ax, lo, hi):
    """3D limits: the cube around the box (lo, hi), one scale on all axes."""
    c, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    from matplotlib.ticker import MaxNLocator
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):       # (7 ticks ran into each other at the corner)
        axis.set_major_locator(MaxNLocator(4))


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
        for P in snap.obstacles:                       # obstacles: thin grey, dashed
            if name == "3d":
                ax.plot(P[:, 0], P[:, 1], P[:, 2], color="0.55", lw=0.9, ls="--")
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(P[:, i], P[:, j], color="0.55", lw=0.9, ls="--")
        if len(snap.contacts):                         # contact points: red crosses
            C = snap.contacts
            if name == "3d":
                ax.plot(C[:, 0], C[:, 1], C[:, 2], "x", color="tab:red", ms=4)
            else:
                i, j = {"side": (0, 2), "top": (0, 1)}[name]
                ax.plot(C[:, i], C[:, j], "x", color="tab:red", ms=4)
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
    # the legend under the panels, never over the arm
    handles, labels = side.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=7, frameon=False)
    fig.suptitle(title)
    fig.set_layout_engine("tight", rect=(0.0, 0.04 * (1 + (len(labels) - 1) // 5), 1.0, 1.0))
    return fig


def side_legend(ax, *handles_labels, **kw):
    """The axes' legend (or one of these handles and labels) beside it, on
    the right (outside the data: a legend inside, even at matplotlib's
    "best" place, can hide a curve)."""
    return ax.legend(*handles_labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, **kw)


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
        side_legend(ax, fontsize=8)
    fig.suptitle(title)
    fig.set_layout_engine("tight")
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
    side_legend(axs[0, 2], *axs[0, 0].get_legend_handles_labels(), fontsize=7)
    fig.suptitle(title + " (body frame; the distal part on the proximal part)\n"
                 "steps inside a section: its weight and inertia act at its two quadrature points")
    fig.set_layout_engine("tight")
    return fig


def plot_statics(result, snap, folder, name="statics"):
    """One equilibrium (``soft-twin-sim statics``) of any robot: its shape
    (``snap``, :func:`scene.statics_snapshot`) and the internal
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
    values (if any: one or a list, :func:`files.scenario._reference`) as
    markers; and the shapes of every angle (``snaps``)."""
    plt = _plt()
    references = [] if not reference else [reference] if isinstance(reference, dict) else list(reference)
    a = np.array([r["angle_deg"] for r in results])
    p = np.array([r["tip_position"] for r in results])
    fig, axs = plt.subplots(1, 3, figsize=(14, 4.6))
    for k, (c, ax) in enumerate(zip("xyz", axs)):
        ax.plot(a, 1e3 * p[:, k], "-", marker=".", color=f"C{k}", label="soft_twin")
        for ref, marker in zip(references, "osD^v"):
            ra = np.asarray(ref["angle_deg"], dtype=float)
            rp = np.asarray(ref["tip_position"], dtype=float)
            if np.any(np.isfinite(rp[:, k])):
                ax.plot(ra, 1e3 * rp[:, k], marker, mfc="none", color="k", label=ref.get("label", "reference"))
        ax.set_xlabel("load angle [deg]")
        ax.set_ylabel(f"tip {c} [mm]")
        ax.set_title(f"tip {c}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"{name}: tip position (world) against the load angle")
    fig.set_layout_engine("tight")
    paths = _save(fig, folder, "sweep_tip")
    return paths + plot_shapes(snaps, folder, f"{name}: equilibrium shapes", "sweep_shapes")


_XYZ = "xyz"


def plot_joint_states(out, folder, title="joint states"):
    """Position [rad or m], velocity [rad/s or m/s] and effort [N m or N] of
    every rigid joint against time [s]."""
    plt = _plt()
    t = np.asarray(out["time"], dtype=float)
    names = out["joint_names"]
    fig, axs = plt.subplots(3, 1, figsize=(8.5, 8), sharex=True)
    for ax, key, lab in zip(axs, ("joint_positions", "joint_velocities", "joint_efforts"),
                            ("position [rad | m]", "velocity [rad/s | m/s]", "effort [N m | N]")):
        a = np.asarray(out[key], dtype=float).reshape(len(t), len(names))
        for k, n in enumerate(names):
            ax.plot(t, a[:, k], label=n)
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axs[-1].set_xlabel("time [s]")
    fig.suptitle(title + " (rotations in rad, N m; translations in m, N)")
    fig.set_layout_engine("tight")
    return _save(fig, folder, "joint_states")


def plot_joint_wrenches(out, folder, title="wrenches through the rigid joints"):
    """The wrench each rigid joint transmits (world axes, about its input
    origin): force [N] and moment [N m] components against time."""
    plt = _plt()
    t = np.asarray(out["time"], dtype=float)
    tn = list(out["transmitted_names"])
    names = [n for n in out["joint_names"] if n in tn]
    W = np.asarray(out["transmitted_wrenches"], dtype=float).reshape(len(t), len(tn), 6)
    fig, axs = plt.subplots(len(names), 2, figsize=(12, 2.8 * len(names) + 0.8), sharex=True, squeeze=False)
    for r, n in enumerate(names):
        w = W[:, tn.index(n)]
        for c, (lo, unit, what) in enumerate(((0, "N", "force"), (3, "N m", "moment"))):
            ax = axs[r, c]
            for k in range(3):
                ax.plot(t, w[:, lo + k], label=f"{what[0]}_{_XYZ[k]}")
            ax.set_ylabel(f"{n}: {what} [{unit}]")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, ncol=3)
    for ax in axs[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(title + " (world axes, about the joint's input origin)")
    fig.set_layout_engine("tight")
    return _save(fig, folder, "joint_wrenches")


def plot_frames(out, folder, title="frame positions", frames=None):
    """x, y, z [m] (world) of the robot's frames (default: every frame but
    the member section boundaries) against time [s]."""
    plt = _plt()
    t = np.asarray(out["time"], dtype=float)
    fn = list(out["frame_names"])
    names = [n for n in (frames or fn) if n in fn]
    P = np.asarray(out["frame_positions"], dtype=float).reshape(len(t), len(fn), 3)
    fig, axs = plt.subplots(3, 1, figsize=(8.5, 8), sharex=True)
    for k, ax in enumerate(axs):
        for n in names:
            ax.plot(t, P[:, fn.index(n), k], label=n)
        ax.set_ylabel(f"{_XYZ[k]} [m]")
        ax.grid(alpha=0.3)
    side_legend(axs[0], fontsize=7)
    axs[-1].set_xlabel("time [s]")
    fig.suptitle(title + " (world)")
    fig.set_layout_engine("tight")
    return _save(fig, folder, "frames")


def plot_section_strains(out, folder, title="strains of the soft sections"):
    """Each strain mode of every soft section (``section_names``) against
    time: stretch and shears [-], torsion and bending [1/m]."""
    plt = _plt()
    t = np.asarray(out["time"], dtype=float)
    names = out["section_names"]
    S = np.asarray(out["strains"], dtype=float).reshape(len(t), len(names), 6)
    owner = [n.rsplit("_", 1)[0] for n in names]          # soft joints are named <member>_<k>
    members = list(dict.fromkeys(owner))
    first = {mb: owner.index(mb) for mb in members}
    fig, axs = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    cmap, n = plt.get_cmap("plasma"), len(names)
    for m, ax in enumerate(axs.ravel()):
        for i, mb in enumerate(owner):
            if len(members) == 1:           # one member: its sections from base (dark) to tip (light)
                ax.plot(t, S[:, i, m], color=cmap(i / max(1, n - 1) * 0.85), lw=1.2,
                        label=f"section {i}" if m == 0 and (n <= 8 or i in (0, n - 1)) else None)
            else:
                ax.plot(t, S[:, i, m], color=f"C{members.index(mb) % 10}", lw=1.0, alpha=0.9,
                        label=mb if m == 0 and first[mb] == i else None)
        ax.set_title(STRAIN_NAMES[m])
        ax.set_ylabel("[-]" if m < 3 else "[1/m]")
        ax.grid(alpha=0.3)
    for ax in axs[1]:
        ax.set_xlabel("time [s]")
    axs[0, 0].legend(fontsize=7, title=None if len(members) == 1 else "member (one line per section)",
                     title_fontsize=7)
    fig.suptitle(title)
    fig.set_layout_engine("tight")
    return _save(fig, folder, "strains")


def plot_member_wrenches(out, folder, name="run", max_lines=6):
    """Internal wrench (body axes) along every member at up to ``max_lines``
    sample times; one figure ``internal_wrenches_<member>`` per member."""
    paths = []
    idx = pick(len(out["members_time"]), max_lines)
    for m in out["members"][0]:
        s = [out["members"][i][m]["s"] for i in idx]
        W = [out["members"][i][m]["internal_wrench"] for i in idx]
        labels = [f"t = {out['members_time'][i]:.2f} s" for i in idx]
        fig = wrench_figure(s, W, labels, f"{name}: internal wrench along member {m}")
        paths += _save(fig, folder, f"internal_wrenches_{m}")
    return paths


def plot_energies(out, folder, title="energies"):
    """Kinetic, elastic and gravitational energy [J] and their sum at the
    member samples (``energies`` of the run)."""
    plt = _plt()
    t = np.asarray(out["members_time"], dtype=float)
    E = np.asarray(out["energies"], dtype=float).reshape(len(t), 3)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for k, lab in enumerate(("kinetic", "elastic (members, joint springs)", "gravitational")):
        ax.plot(t, E[:, k], label=lab)
    ax.plot(t, E.sum(axis=1), "k--", label="sum")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("energy [J]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title + " (the sum changes by the inputs' work and damping)")
    fig.set_layout_engine("tight")
    return _save(fig, folder, "energies")


def plot_dynamics(out, folder, mech, name="run"):
    """The whole set of figures of any robot's run (each when the run has
    its fields, and the robot what it shows); returns the paths."""
    paths = []
    if out.get("members_time") and "frame_poses" in out:
        fig = shapes_figure(run_snapshots(out, mech), f"{name}: members and links")
        paths += _save(fig, folder, "backbone_shapes")
    if out.get("time"):
        if out.get("tip_position"):
            paths += plot_tip(out, folder, f"{name}: tip motion ({out.get('tip_frame', 'tip')}, world)")
        if out.get("joint_names") and out.get("joint_positions"):
            paths += plot_joint_states(out, folder, f"{name}: joint states")
        if out.get("joint_names") and out.get("transmitted_wrenches"):
            paths += plot_joint_wrenches(out, folder, f"{name}: wrenches through the rigid joints")
        if len(out.get("frame_names", ())) > 1:
            paths += plot_frames(out, folder, f"{name}: frame positions")
        if out.get("strains") and out.get("section_names"):
            paths += plot_section_strains(out, folder, f"{name}: strains of the soft sections")
    if out.get("members_time"):
        if all("internal_wrench" in m for m in out["members"][0].values()):
            paths += plot_member_wrenches(out, folder, name)
        if out.get("energies"):
            paths += plot_energies(out, folder, f"{name}: energies")
    return paths


def estimation_figure(run, title="state estimation"):
    """The figure of an estimation run (an ``EstimationRun`` of
    :mod:`soft_twin_core.estimation.replay`): the tip-most sensor's position
    measured (dots) and estimated (lines, 2-sigma band) [m]; the payload
    [g] (or the estimated force [N]) with its 2-sigma band; the NIS per
    dimension of each update against its 95 % band. Returns the figure."""
    from scipy.stats import chi2
    plt = _plt()
    has_load = run.wrench_mode is not None
    fig, axs = plt.subplots(3 if has_load else 2, 1, figsize=(8, 8.5 if has_load else 6), sharex=True)
    t = run.time
    a = axs[0]
    p0 = run.estimated[0]                  # (x, y and z moved from the start: one scale for the three)
    for k, (c, col) in enumerate(zip("xyz", ("C0", "C1", "C2"))):
        e, sd = 1e3 * (run.estimated[:, k] - p0[k]), 1e3 * run.estimated_std[:, k]
        a.plot(t, 1e3 * (run.measured[:, k] - p0[k]), ".", ms=2, color=col, alpha=0.5, label=f"{c} measured")
        a.plot(t, e, "-", lw=1.2, color=col, label=f"{c} estimated")
        a.fill_between(t, e - 2 * sd, e + 2 * sd, color=col, alpha=0.2, lw=0)
    a.set_ylabel(f"{run.sensor}: position - start [mm]")
    a.set_title(f"measured and estimated (2 sigma band); start ({', '.join(f'{x:.3f}' for x in p0)}) m",
                fontsize=9)
    a.legend(fontsize=7, ncol=3, loc="best")
    if has_load:
        b = axs[1]
        if run.wrench_mode == "payload":
            m, sd = 1e3 * run.payload, 1e3 * run.payload_std
            b.plot(t, m, "k-", lw=1.2, label="payload estimate")
            b.fill_between(t, m - 2 * sd, m + 2 * sd, color="k", alpha=0.15, lw=0, label="2 sigma")
            pad = 4 * float(np.median(sd))         # (the prior's wide band of the first steps left out)
            b.set_ylim(min(m.min(), 0.0) - pad, max(m.max(), 0.0) + pad)
            b.set_ylabel("payload [g]")
        else:
            for k, c in enumerate(("f_x", "f_y", "f_z")):
                b.plot(t, run.wrench[:, k], lw=1.2, label=c)
                b.fill_between(t, run.wrench[:, k] - 2 * run.wrench_std[:, k],
                               run.wrench[:, k] + 2 * run.wrench_std[:, k], alpha=0.15, lw=0)
            b.set_ylabel("tip force [N]")
        b.legend(fontsize=7, loc="best")
    c = axs[-1]
    ok = run.nis_dof > 0
    m = run.nis_dof[ok]
    c.plot(t[ok], run.nis[ok] / m, ".", ms=2, color="C3", label="NIS / dimension")
    mode = int(np.bincount(m).argmax()) if len(m) else 1
    lo, hi = chi2.ppf(0.025, mode) / mode, chi2.ppf(0.975, mode) / mode
    c.axhline(1.0, color="k", lw=0.8)
    c.axhline(lo, color="k", lw=0.8, ls="--")
    c.axhline(hi, color="k", lw=0.8, ls="--", label=f"95 % band ({mode} dimensions)")
    mean_nis, inside = run.consistency()
    c.set_title(f"mean NIS per dimension {mean_nis:.2f}, {100 * inside:.1f} % of the updates inside their "
                f"95 % band", fontsize=9)
    c.set_yscale("log")
    c.set_ylabel("NIS / dimension [-]")
    c.set_xlabel("time [s]")
    c.legend(fontsize=7, loc="best")
    for ax in axs:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.set_layout_engine("tight")
    return fig


def workspace_figure(points, hs, title="workspace", color=None, color_label=None, mark=None):
    """Figure of a point cloud (n, 3) [m]: a 3-D view with the hull's facets
    and the three projections (x-y, x-z, y-z) with the outline of each
    projection's convex hull. ``color``: a value per point (e.g. an input;
    its colour bar left of the 3-D view, clear of its z label);
    ``mark``: a mask of points drawn as red crosses (the actuation box's
    corners). Drawn for the figure style in force (a paper style: at its
    width, its type sizes, three ticks an axis, the legend under the
    panels): save it with ``save_figure(..., drawn=True)``."""
    import matplotlib
    from matplotlib.ticker import MaxNLocator
    from scipy.spatial import ConvexHull
    plt = _plt()
    paper = bool(current_style().width_in)
    P = np.asarray(points, dtype=float)
    ok = np.all(np.isfinite(P), axis=1)
    Q = P[ok]
    cvals = None if color is None else np.asarray(color, dtype=float)[ok]
    with matplotlib.rc_context(drawing_rc()):
        fig = plt.figure(figsize=drawn_size(11, 9), layout="constrained" if paper else None)
        ax = fig.add_subplot(2, 2, 1, projection="3d")
        sc = ax.scatter(Q[:, 0], Q[:, 1], Q[:, 2], s=2 if paper else 4, c=cvals if cvals is not None else "tab:blue")
        if len(hs["facets"]) and hs["dimension"] == 3:
            ax.plot_trisurf(P[:, 0], P[:, 1], P[:, 2], triangles=hs["facets"], alpha=0.12, color="tab:orange",
                            edgecolor="none")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        vol = hs["volume_m3"]
        ax.set_title(f"{title}\n{hs['n_points']} points, hull volume {vol * 1e6:.4g} cm^3"
                     + ("" if hs["dimension"] == 3 else f" (dimension {hs['dimension']})"),
                     fontsize=None if paper else 9)
        if cvals is not None:
            fig.colorbar(sc, ax=ax, shrink=0.6, location="left", pad=0.02, label=color_label or "")
        for k, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
            a = fig.add_subplot(2, 2, k + 2)
            a.scatter(Q[:, i], Q[:, j], s=1.5 if paper else 3, c=cvals if cvals is not None else "tab:blue")
            if mark is not None:
                M = P[np.asarray(mark, bool) & ok]
                a.plot(M[:, i], M[:, j], "x", color="red", ms=3 if paper else 5,
                       label="inputs at their limits (corners)")
                if k == 0 and not paper:
                    a.legend(fontsize=7, loc="best")
            xy = Q[:, [i, j]]
            if len(xy) >= 3 and np.linalg.matrix_rank(xy - xy.mean(0), tol=1e-12) == 2:
                h = ConvexHull(xy)
                loop = np.r_[h.vertices, h.vertices[:1]]
                a.plot(xy[loop, 0], xy[loop, 1], "-", color="tab:orange", lw=1)
            a.set_xlabel("xyz"[i] + " [m]")
            a.set_ylabel("xyz"[j] + " [m]")
            a.set_aspect("equal", adjustable="datalim")
            a.grid(alpha=0.3)
            if paper:                                    # (four 6 pt labels ran into each other on 1.5 in)
                a.xaxis.set_major_locator(MaxNLocator(3))
                a.yaxis.set_major_locator(MaxNLocator(3))
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):      # (8 ticks a side crowded the 3-D view's corners)
            axis.set_major_locator(MaxNLocator(3 if paper else 4))
            if paper:                                    # (a 1.5 in view: its numbers are the projections')
                axis.set_ticklabels([])
                axis.labelpad = -8
        if paper:                                        # (its z label ran into the next panel's)
            ax.set_zlabel("")
        if paper:
            if mark is not None:                         # under the panels, off the data
                fig.legend(*fig.axes[-3].get_legend_handles_labels(), loc="outside lower center", frameon=False)
        else:
            fig.tight_layout()
            fig.subplots_adjust(wspace=0.3)              # (tight_layout leaves the 3-D z label no room)
    return fig
