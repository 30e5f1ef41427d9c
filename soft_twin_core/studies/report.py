"""The summary of a design study: counts, failures, timings, output
ranges, sensitivities and plots.

Sensitivity of each output to each numeric parameter, over the cases that
succeeded:

- Spearman's rank correlation rho (``scipy.stats.spearmanr``): how
  monotonically the output follows the parameter, -1..1, any design;
- standardised regression coefficients (SRC): the least-squares fit
  ``y ~ b0 + sum_j b_j x_j`` scaled as ``b_j std(x_j) / std(y)``, with its
  R^2 (near 1: the linear model explains the output and SRC^2 are the
  shares of its variance; low: read rho instead).

Written to ``summary.json``, ``summary.md`` and ``plots/``:
``sensitivity.png`` (rho as a heat map), ``scatter.png`` (each output
against each parameter, the first 6 x 6), and for workspace studies
``workspace_clouds.png`` (the clouds of up to 12 cases) and
``workspace_case_<i>.png`` (the first 4 cases).
"""

import json
import math
from pathlib import Path

import numpy as np

from soft_twin_core.planning.reach import hull_summary
from soft_twin_core.viz.style import current_style, drawing_rc, drawn_size, save_figure

SKIP = {"case", "case_key", "status", "error", "compute_time_s", "started_unix_s", "worker"}


def _numeric(rows, col):
    out = []
    for r in rows:
        v = r.get(col)
        if isinstance(v, bool):
            v = float(v)
        out.append(float(v) if isinstance(v, (int, float)) and v is not None else math.nan)
    return np.array(out)


def numeric_columns(rows, names):
    """The columns of ``names`` with numbers that vary over ``rows``, less
    those at round-off level against their group (the columns of one
    vector, ``statics.base_wrench_fx`` against ``statics.base_wrench_*``:
    largest magnitude below 1e-12 of the group's), whose "sensitivities"
    would be noise."""
    data = {c: _numeric(rows, c) for c in names}
    group_max = {}
    for c, x in data.items():
        g = c.rsplit("_", 1)[0]
        f = np.abs(x[np.isfinite(x)])
        group_max[g] = max(group_max.get(g, 0.0), float(f.max()) if len(f) else 0.0)
    out = []
    for c, x in data.items():
        f = x[np.isfinite(x)]
        if len(f) >= 2 and np.ptp(f) > 0 and np.abs(f).max() > 1e-12 * group_max[c.rsplit("_", 1)[0]]:
            out.append(c)
    return out


def spearman_matrix(X, Y):
    """rho[i, j] between output Y[:, i] and parameter X[:, j] (rows with
    NaN in either dropped per pair; NaN if fewer than 3 remain or one is
    constant)."""
    from scipy.stats import spearmanr
    rho = np.full((Y.shape[1], X.shape[1]), np.nan)
    for i in range(Y.shape[1]):
        for j in range(X.shape[1]):
            ok = np.isfinite(X[:, j]) & np.isfinite(Y[:, i])
            if ok.sum() >= 3 and np.ptp(X[ok, j]) > 0 and np.ptp(Y[ok, i]) > 0:
                rho[i, j] = spearmanr(X[ok, j], Y[ok, i]).statistic
    return rho


def src_matrix(X, Y):
    """(SRC (n_out, n_par), R^2 (n_out,)): standardised regression
    coefficients of each output on all parameters (rows with any NaN
    dropped per output; NaN if too few rows)."""
    n_out, n_par = Y.shape[1], X.shape[1]
    src = np.full((n_out, n_par), np.nan)
    r2 = np.full(n_out, np.nan)
    for i in range(n_out):
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(Y[:, i])
        if ok.sum() < n_par + 2:
            continue
        x, y = X[ok], Y[ok, i]
        sx, sy = x.std(axis=0), y.std()
        if sy == 0 or np.any(sx == 0):
            continue
        A = np.column_stack([np.ones(len(x)), (x - x.mean(axis=0)) / sx])
        coef, *_ = np.linalg.lstsq(A, (y - y.mean()) / sy, rcond=None)
        src[i] = coef[1:]
        res = (y - y.mean()) / sy - A @ coef
        r2[i] = 1.0 - float(res @ res) / len(y)
    return src, r2


def _fmt(v):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def write_summary(study, rows, points, out_dir, run_info):
    """Write summary.json, summary.md and plots/ for the results ``rows``;
    returns the path of summary.md."""
    out = Path(out_dir)
    plots = out / "plots"
    plots.mkdir(exist_ok=True)
    ok = [r for r in rows if r["status"] == "ok"]
    cols = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    params = [c for c in cols if any(c == a or c.startswith(a + "[") for a in study.parameter_names)]
    outputs = [c for c in cols if c not in SKIP and c not in params]
    p_num = numeric_columns(ok, params)
    o_num = numeric_columns(ok, outputs)
    X = np.column_stack([_numeric(ok, c) for c in p_num]) if p_num and ok else np.zeros((len(ok), 0))
    Y = np.column_stack([_numeric(ok, c) for c in o_num]) if o_num and ok else np.zeros((len(ok), 0))
    rho = spearman_matrix(X, Y) if X.size and Y.size else np.zeros((len(o_num), len(p_num)))
    src, r2 = src_matrix(X, Y) if X.size and Y.size else (np.zeros((len(o_num), len(p_num))), np.zeros(len(o_num)))
    stats = {}
    for c in outputs:
        x = _numeric(ok, c)
        f = x[np.isfinite(x)]
        stats[c] = ({"min": float(f.min()), "max": float(f.max()), "mean": float(f.mean()),
                     "std": float(f.std())} if len(f) else None)
    # timings: does a worker's first case cost more than its later ones (numba compiling)?
    by_worker = {}
    for r in sorted((r for r in rows if r.get("started_unix_s") is not None), key=lambda r: r["started_unix_s"]):
        if r.get("worker") and r.get("compute_time_s") is not None:
            by_worker.setdefault(r["worker"], []).append(r["compute_time_s"])
    first = [v[0] for v in by_worker.values()]
    later = [x for v in by_worker.values() for x in v[1:]]
    timing = dict(run_info.get("timing", {}))
    timing.update({"workers": len(by_worker),
                   "first_case_s_per_worker": first,
                   "later_cases_median_s": float(np.median(later)) if later else None,
                   "later_cases_max_s": float(np.max(later)) if later else None})
    failures = [{"case": r["case"], "status": r["status"], "error": r["error"]} for r in rows if r["status"] != "ok"]
    summary = {
        "study": study.name, "source": study.source, "fingerprint": study.fingerprint,
        "design": study.design, "compute": study.compute, "record": list(study.record),
        "cases": len(rows), "ok": len(ok), "failed": sum(r["status"] == "failed" for r in rows),
        "lost": sum(r["status"] == "lost" for r in rows),
        "computed_this_run": run_info.get("computed"), "reused": run_info.get("reused"),
        "where": run_info.get("where"), "timing": timing, "failures": failures[:50],
        "worker_losses": run_info.get("worker_losses", []),
        "parameters": p_num, "outputs": stats,
        "sensitivity": {"outputs": o_num, "parameters": p_num, "spearman_rho": rho.tolist(),
                        "src": src.tolist(), "src_r2": r2.tolist()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=_json_default))
    figs = _plots(study, ok, p_num, o_num, X, Y, rho, points, plots)
    md = [f"# Study {study.name}", "",
          f"{len(rows)} cases ({study.design['type']}"
          + (f", {study.design.get('samples')} samples, seed {study.design['seed']}" if study.design['type'] != 'grid' else "")
          + f"): {summary['ok']} ok, {summary['failed']} failed" + (f", {summary['lost']} lost" if summary["lost"] else "")
          + f". Computed {run_info.get('computed')} this run on {run_info.get('where')}"
          + (f", {run_info.get('reused')} reused from earlier runs" if run_info.get("reused") else "") + ".", ""]
    t = timing
    md += [f"Timing: validation {t.get('validate_s', 0):.2f} s, cluster start {t.get('cluster_start_s', 0):.2f} s, "
           f"workers ready {t.get('workers_ready_s', 0):.2f} s, cases {t.get('compute_s', 0):.2f} s. "
           f"First case per worker: {', '.join(f'{x * 1e3:.1f}' for x in first)} ms; later cases: median "
           f"{_fmt(None if t['later_cases_median_s'] is None else t['later_cases_median_s'] * 1e3)} ms, max "
           f"{_fmt(None if t['later_cases_max_s'] is None else t['later_cases_max_s'] * 1e3)} ms.", ""]
    if summary["worker_losses"]:
        md += ["## Workers that died during the run", "", "| worker | cases | outcome |", "|---|---|---|"]
        md += [f"| {w['worker']} | {w['cases'][0]}..{w['cases'][-1]} | "
               f"{'re-run on another worker' if w['rerun'] else 'lost'} |" for w in summary["worker_losses"]]
        md += [""]
    if failures:
        md += ["## Failed cases", "", "| case | status | reason |", "|---:|---|---|"]
        md += [f"| {f['case']} | {f['status']} | {f['error'][:300].replace('|', '/')} |" for f in failures[:50]]
        md += [""]
    md += ["## Outputs (cases that succeeded)", "", "| output | min | max | mean | std |", "|---|---:|---:|---:|---:|"]
    for c, s in stats.items():
        if s:
            md.append(f"| {c} | {_fmt(s['min'])} | {_fmt(s['max'])} | {_fmt(s['mean'])} | {_fmt(s['std'])} |")
    if p_num and o_num:
        md += ["", "## Sensitivity", "",
               "Spearman's rank correlation rho (and the standardised regression coefficient SRC; R^2 of "
               "the linear fit per output):", "",
               "| output | R^2 | " + " | ".join(p_num) + " |", "|---|---:|" + "---:|" * len(p_num)]
        for i, c in enumerate(o_num):
            md.append(f"| {c} | {_fmt(float(r2[i]))} | "
                      + " | ".join(f"{_fmt(float(rho[i, j]))} ({_fmt(float(src[i, j]))})" for j in range(len(p_num)))
                      + " |")
    md += ["", "## Plots", ""] + [f"![{p.stem}](plots/{p.name})" for p in figs if p.suffix == ".png"]
    (out / "summary.md").write_text("\n".join(md) + "\n")
    return str(out / "summary.md")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# the unit of a column, by its name: a parameter's last key, an output's suffix or stem (issue 31: the
# scatter plots had none)
_PARAMETER_UNITS = {"youngs_modulus": "Pa", "shear_modulus": "Pa", "density": "kg/m^3", "radius": "m",
                    "inner_radius": "m", "outer_radius": "m", "length": "m", "offset": "m", "offset_end": "m",
                    "width": "m", "height": "m", "thickness": "m", "limit": "N", "damping": "N m s",
                    "viscosity": "Pa s", "stiffness": "N/m", "mass": "kg", "poisson_ratio": "-"}
_SUFFIX_UNITS = (("_m3", "m^3"), ("_m2", "m^2"), ("_m_s", "m/s"), ("_pa", "Pa"), ("_s", "s"), ("_m", "m"),
                 ("_n", "N"), ("_nm", "N m"))
_PREFIXES = {-3: "n", -2: "u", -1: "m", 0: "", 1: "k", 2: "M", 3: "G"}


def column_unit(name, parameter, study=None):
    """The SI unit of a study column (None: not known): a ``parameter``
    path's last key (``segments[0].material.youngs_modulus``: Pa), an
    actuator's input (``scenario.actuation.<name>``: N for a tendon, Pa for
    a chamber, from ``study``'s robot when given); an output's
    (``statics.max_stress_pa``) suffix (``_m``, ``_pa``, ``_m3``, ...) or
    stem (``tip_position_x``: m, ``base_wrench_fz``: N, ``base_wrench_my``:
    N m)."""
    import re
    last = re.sub(r"\[\d+\]$", "", name.split(".")[-1])
    if parameter:
        if name.startswith("scenario.actuation."):
            mech = getattr(getattr(study, "scenario", None), "mech", None)
            kinds = {a.name: a.kind for a in mech.actuators} if mech is not None else {}
            return "Pa" if kinds.get(last) == "chamber" else "N"
        return _PARAMETER_UNITS.get(last)
    stem = name.split(".")[-1]
    m = re.search(r"base_wrench_([fm])[xyz]$", stem)
    if m:
        return "N" if m.group(1) == "f" else "N m"
    if re.search(r"(tip_position|backbone_\d+)_[xyz]$", stem):
        return "m"
    if re.search(r"tip_velocity_[xyz]$", stem):
        return "m/s"
    for suffix, unit in _SUFFIX_UNITS:
        if stem.endswith(suffix):
            return unit
    return None


def scaled_axis(values, name, parameter, study=None):
    """(values scaled, axis label): the column's unit with an SI prefix
    putting its largest magnitude in [1, 1000) (``youngs_modulus [MPa]``),
    so that no offset or ``1e6`` factor sits at the axis' end where it ran
    into the label; a column of unknown unit keeps a ``x1e6`` in its label."""
    v = np.asarray(values, dtype=float)
    big = float(np.nanmax(np.abs(v))) if np.any(np.isfinite(v)) else 0.0
    k = int(np.clip(math.floor(math.log10(big) / 3), -3, 3)) if big > 0 else 0
    unit = column_unit(name, parameter, study)
    if unit in (None, "-"):
        return (v / 10.0 ** (3 * k), f"{name} [x1e{3 * k}]") if k else (v, name)
    if unit in ("m^3", "m^2", "kg/m^3", "m/s", "N m s", "Pa s", "N/m") or " " in unit:
        return (v / 10.0 ** (3 * k), f"{name} [x1e{3 * k} {unit}]") if k else (v, f"{name} [{unit}]")
    return v / 10.0 ** (3 * k), f"{name} [{_PREFIXES[k]}{unit}]"


def _stacked(label):
    """A long axis label on a paper figure's inch-wide panel, one line per
    part of its path and its unit: "statics.tip_position_x [mm]" ->
    "statics.\ntip_position_x\n[mm]"."""
    name, _, unit = label.partition(" [")
    return "\n".join([p + "." for p in name.split(".")[:-1]] + [name.split(".")[-1]] + (["[" + unit] if unit else []))


def _plots(study, ok, p_num, o_num, X, Y, rho, points, plots):
    """The study's figures in the figure style in force (:mod:`viz.style`:
    a paper style draws them at its width and type sizes); their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator
    from soft_twin_core.viz.plots import workspace_figure         # here: matplotlib, for the summary only
    paper = bool(current_style().width_in)
    figs = []
    with matplotlib.rc_context(drawing_rc()):
        if p_num and o_num:
            fig, ax = plt.subplots(figsize=drawn_size(2.0 + 1.1 * len(p_num), 1.2 + 0.32 * len(o_num)),
                                   layout="constrained")
            im = ax.imshow(np.nan_to_num(rho), cmap="RdBu_r", vmin=-1, vmax=1, aspect="auto")
            ax.set_xticks(range(len(p_num)), p_num, rotation=30, ha="right", fontsize=6 if paper else 7)
            ax.set_yticks(range(len(o_num)), o_num, fontsize=6 if paper else 7)
            for i in range(len(o_num)):
                for j in range(len(p_num)):
                    if np.isfinite(rho[i, j]):
                        ax.text(j, i, f"{rho[i, j]:.2f}", ha="center", va="center", fontsize=6,
                                color="white" if abs(rho[i, j]) > 0.6 else "black")
            fig.colorbar(im, ax=ax, label="Spearman rho")
            ax.set_title(f"{study.name}: sensitivity of each output to each parameter", fontsize=8 if paper else 9)
            figs += save_figure(fig, plots, "sensitivity", drawn=True)
            po, pp = o_num[:6], p_num[:6]
            fig, axes = plt.subplots(len(po), len(pp), figsize=drawn_size(2.6 * len(pp), 2.0 * len(po)),
                                     squeeze=False, layout="constrained")
            for i, c in enumerate(po):
                for j, p in enumerate(pp):
                    a = axes[i, j]
                    x, xlabel = scaled_axis(X[:, j], p, True, study)
                    y, ylabel = scaled_axis(Y[:, i], c, False, study)
                    a.scatter(x, y, s=2 if paper else 5)
                    a.ticklabel_format(useOffset=False, style="plain")
                    if paper:                         # (a panel an inch wide: three 6 pt labels)
                        a.xaxis.set_major_locator(MaxNLocator(3))
                        a.yaxis.set_major_locator(MaxNLocator(3))
                    if i == len(po) - 1:
                        a.set_xlabel(_stacked(xlabel) if paper else xlabel, fontsize=6 if paper else 7)
                    if j == 0:
                        a.set_ylabel(_stacked(ylabel) if paper else ylabel, fontsize=6 if paper else 7)
                    a.tick_params(labelsize=6 if paper else 6)
            figs += save_figure(fig, plots, "scatter", drawn=True)
        if points:
            by = {}
            for p in points:
                by.setdefault(p["case"], []).append((p["tip_position_x"], p["tip_position_y"], p["tip_position_z"]))
            cases = sorted(by)
            fig = plt.figure(figsize=drawn_size(7, 6), layout="constrained")
            ax = fig.add_subplot(projection="3d")
            for c in cases[:12]:
                P = np.array(by[c], dtype=float)
                ax.scatter(P[:, 0], P[:, 1], P[:, 2], s=3, label=f"case {c}")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
            ax.set_zlabel("z [m]")
            ax.legend(fontsize=6, markerscale=3)
            ax.set_title(f"{study.name}: workspace point clouds", fontsize=8 if paper else 9)
            figs += save_figure(fig, plots, "workspace_clouds", drawn=True)
    for c in (sorted(by)[:4] if points else []):
        P = np.array(by[c], dtype=float)
        figs += save_figure(workspace_figure(P, hull_summary(P), f"{study.name}, case {c}"), plots,
                            f"workspace_case_{c}", drawn=True)
    return [Path(f) for f in figs]
