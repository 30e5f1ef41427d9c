"""Figures of a plan (``soft-twin-sim plan PLAN.yaml --plot DIR``), drawn with
the visualisation tools of :mod:`soft_twin_core.viz.plots` (Agg backend, PNG and
SVG):

* ``plan_tip_path``: the planned (target) against the achieved tip path
  (the quasi-static prediction of the plan; with dynamics also the
  simulated tip without and with lag compensation) in the top (x-y), side
  (x-z) and front (y-z) views at equal scale, unreachable samples marked,
  and the tracking error [mm] against time. An axis the plan leaves free
  (position weight 0) shows the target at the achieved coordinate, the
  view's title saying so.
* ``plan_actuation``: the actuator inputs against time (tendon tensions [N],
  pressures [Pa]; the compensated sequence dashed when present) and, for an
  articulated robot, the joint commands [rad or m] with their limits.

Input: the result dict of :func:`plan_file.run_plan`.
"""

import numpy as np

from soft_twin_core.viz.plots import _plt, _save

_VIEWS = (("top view (x-y)", 0, 1), ("side view (x-z)", 0, 2), ("front view (y-z)", 1, 2))


def plot_plan_path(out, folder, title=None):
    """Planned vs achieved tip path and the error against time; paths written."""
    return _save(plan_path_figure(out, title), folder, "plan_tip_path")


def plan_path_figure(out, title=None):
    """The figure of :func:`plot_plan_path`."""
    plt = _plt()
    t = np.asarray(out["time"])
    tgt = np.asarray(out["target"]).reshape(len(t), 3)
    tip = np.asarray(out["predicted_tip"]).reshape(len(t), 3)
    reached = np.asarray(out["reached"], bool)
    dyn = out.get("dynamics")
    # an axis the plan does not track (position weight 0) is where the arm puts it: the target is
    # drawn there at the achieved coordinate (its nominal one read as a miss of tens of mm that no
    # tracking error has), and the views say so
    free = [a for a, w in enumerate(out.get("position_weights", (1, 1, 1))) if w == 0]
    shown = tgt.copy()
    shown[:, free] = tip[:, free]
    curves = [("planned (target)", shown, dict(color="k", lw=2.5, alpha=0.35)),
              ("achieved (statics)", tip, dict(color="C0", lw=1.2))]
    if dyn:
        curves.append(("simulated", np.asarray(dyn["simulated_tip"]), dict(color="C3", lw=1.0)))
        if "compensated_tip" in dyn:
            curves.append(("simulated, compensated", np.asarray(dyn["compensated_tip"]), dict(color="C2", lw=1.0)))
    fig = plt.figure(figsize=(12, 7.5))
    allp = np.vstack([c[1] for c in curves])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    half = 0.55 * max(float(np.max(hi - lo)), 1e-3)
    mid = 0.5 * (lo + hi)
    for k, (name, i, j) in enumerate(_VIEWS):
        ax = fig.add_subplot(2, 3, k + 1)
        for label, p, kw in curves:
            ax.plot(p[:, i], p[:, j], label=label, **kw)
        loose = [f"{'xyz'[a]}" for a in (i, j) if a in free]
        if loose:
            name = f"{name}, {' and '.join(loose)} free (not tracked)"
        if np.any(~reached):
            ax.plot(shown[~reached, i], shown[~reached, j], "rx", ms=5, label="unreachable sample")
        ax.set_xlim(mid[i] - half, mid[i] + half)
        ax.set_ylim(mid[j] - half, mid[j] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 1, 2)
    ax.plot(t, 1e3 * np.asarray(out["error_m"]), color="C0", label="statics (planned inputs)")
    if dyn:
        ax.plot(t, 1e3 * np.asarray(dyn["simulated_error_m"]), color="C3", label="dynamics")
        if "compensated_error_m" in dyn:
            ax.plot(t, 1e3 * np.asarray(dyn["compensated_error_m"]), color="C2", label="dynamics, compensated")
    if np.any(~reached):
        ax.plot(t[~reached], 1e3 * np.asarray(out["error_m"])[~reached], "rx", ms=4, label="unreachable")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("tracking error [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    s = out["summary"]
    fig.suptitle(title or f"{out['robot']}: tip path, {s['reached']} of {s['samples']} samples reached")
    fig.set_layout_engine("tight")
    return fig


def plot_plan_actuation(out, folder, title=None):
    """Actuator inputs (and joint commands) against time; paths written."""
    plt = _plt()
    t = np.asarray(out["time"])
    names = list(out["actuator_names"])
    joints = list(out.get("joint_names") or [])
    n_ax = (1 if names else 0) + (1 if joints else 0)
    fig, axs = plt.subplots(max(n_ax, 1), 1, figsize=(9, max(5.5, 3.6 * n_ax)), sharex=True, squeeze=False)
    k = 0
    if names:
        ax = axs[k, 0]
        u = np.asarray(out["actuation"]).reshape(len(t), len(names))
        units = out["units"]["inputs"]
        for i, n in enumerate(names):
            ax.plot(t, u[:, i], color=f"C{i}", label=f"{n} [{units[n]}]")
        dyn = out.get("dynamics")
        if dyn and "compensated_actuation" in dyn:
            uf = np.asarray(dyn["compensated_actuation"]).reshape(len(t), len(names))
            for i, n in enumerate(names):
                ax.plot(t, uf[:, i], "--", color=f"C{i}", lw=0.9, label=f"{n}, compensated")
        ax.set_ylabel(f"actuator inputs [{', '.join(sorted({units[n] for n in names}))}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        k += 1
    if joints:
        ax = axs[k, 0]
        qj = np.asarray(out["joints"]).reshape(len(t), len(joints))
        ju = out["units"]["joints"]
        for i, n in enumerate(joints):
            ax.plot(t, qj[:, i], color=f"C{i}", label=f"{n} [{ju[n]}]")
            for lim in (out["joint_lower"][i], out["joint_upper"][i]):
                if lim is not None and abs(lim - qj[:, i]).min() < 0.25 * max(np.ptp(qj[:, i]), 0.1):
                    ax.axhline(lim, color=f"C{i}", ls=":", lw=0.8)
        ax.set_ylabel(f"joint commands [{', '.join(sorted({ju[n] for n in joints}))}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axs[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title or f"{out['robot']}: planned {'joint commands and ' if joints else ''}actuation")
    fig.set_layout_engine("tight")
    return _save(fig, folder, "plan_actuation")


def plot_plan(out, folder):
    """Both figures; the paths written."""
    return plot_plan_path(out, folder) + plot_plan_actuation(out, folder)


__all__ = ["plot_plan", "plot_plan_path", "plot_plan_actuation"]
