"""Figures of any robot's dynamics run (PNG and SVG, as :mod:`plots`): the
shapes of the members and rigid links (side, top, 3D), the tip's motion,
the joint states (positions, velocities, efforts) and the wrenches the
rigid joints transmit, the frames' positions, the strains of every soft
section, the internal wrenches along every member, and the energies.

The run is the JSON of ``soft-twin-sim dynamics``
(:func:`mechanism_scenario.run_mechanism_dynamics`) or a recording
read back by :mod:`mechanism_recording`; fields a recording lacks are
skipped (each figure needs its own fields only).
"""

import numpy as np

from .plots import _plt, _save, pick, shapes_figure, wrench_figure

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
    fig.tight_layout()
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
    fig.tight_layout()
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
    axs[0].legend(fontsize=7, ncol=2)
    axs[-1].set_xlabel("time [s]")
    fig.suptitle(title + " (world)")
    fig.tight_layout()
    return _save(fig, folder, "frames")


def plot_section_strains(out, folder, title="strains of the soft sections"):
    """Each strain mode of every soft section (``section_names``) against
    time: stretch and shears [-], torsion and bending [1/m]."""
    from .model import STRAIN_NAMES
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
    fig.tight_layout()
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
    fig.tight_layout()
    return _save(fig, folder, "energies")


def plot_dynamics(out, folder, mech, name="run"):
    """The whole set of figures of any robot's run (each when the run has
    its fields, and the robot what it shows); returns the paths."""
    from .mechanism_scene import run_snapshots
    from .plots import plot_tip
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
