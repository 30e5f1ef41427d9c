"""``soft-twin-sim study`` and ``soft-twin-sim workspace`` (see cli.py).

    soft-twin-sim study STUDY.yaml [-o OUT] [--scheduler ADDRESS | --workers N | --serial]
                  [--chunk-size K] [--retry-failed] [--overwrite]
    soft-twin-sim workspace ROBOT_OR_SCENARIO [-o OUT] [--limit MAX] [--limits NAME=MAX|NAME=MIN:MAX ...]
                  [--actuators A,B] [--samples N] [--design lhs|random|grid] [--seed S] [--no-corners]

Exit status: 0 done, every case ok; 2 a bad study file, option or case
(every bad case listed by index and field; nothing run); 3 the study
finished but some cases failed or were lost (their reasons are in the
results and the summary), or the workspace had failed samples; 130
interrupted by SIGINT (Ctrl-C) or SIGTERM (the rows computed so far are
saved; run again to resume).
"""

import json
import os
import sys
import time
from pathlib import Path

from soft_twin_core.files.scenario import ScenarioError
from soft_twin_core.planning.reach import actuation_ranges, workspace_of
from soft_twin_core.robot.model import ModelError, find_file, read_yaml_file
from soft_twin_core.studies.cluster import (StudyInterrupted, _write_parquet, rows_to_table, run_study,
                                            write_csv)
from soft_twin_core.studies.study import (CaseValidationError, StudyError, build_scenario, load_study,
                                          study_from_dict)
from soft_twin_core.viz.style import STYLES, figure_style, save_figure


def add_parsers(sub):
    s = sub.add_parser("study", help="run a design study (parameter sweep) on Dask; Parquet + CSV + summary")
    s.add_argument("study", help="study file (YAML; see soft_twin_core/studies/study.py)")
    s.add_argument("--output", "-o", help="output folder (default out/<study name>)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler (tcp://host:8786); default: a local cluster")
    g.add_argument("--serial", action="store_true", help="run the cases in this process, one by one (no Dask)")
    s.add_argument("--workers", type=int, help="local cluster: worker processes (default: one per core)")
    s.add_argument("--chunk-size", type=int, help="cases per Dask task (default: automatic)")
    s.add_argument("--retry-failed", action="store_true", help="recompute the cases recorded as failed")
    s.add_argument("--overwrite", action="store_true", help="discard the results already in the output folder")
    s.add_argument("--flush-seconds", type=float, default=2.0, help="write finished rows at least this often")
    w = sub.add_parser("workspace", help="reachable tip positions over the actuation space (points, volume, plot)")
    w.add_argument("target", help="a robot or scenario file, or an example's name (tendon_arm)")
    w.add_argument("--output", "-o", help="output folder (default out/workspace_<name>)")
    w.add_argument("--limit", type=float, help="range [0, MAX] of every varied input (N or Pa)")
    w.add_argument("--limits", nargs="+", default=[], metavar="NAME=MAX",
                   help="per actuator: NAME=MAX or NAME=MIN:MAX")
    w.add_argument("--actuators", help="comma-separated actuators to vary (default all)")
    w.add_argument("--samples", type=int, default=200, help="design points inside the box (grid: per actuator)")
    w.add_argument("--design", choices=("lhs", "random", "grid"), default="lhs")
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--no-corners", action="store_true", help="do not add the corners of the actuation box")
    for p in (s, w):
        p.add_argument("--style", choices=tuple(STYLES), default="screen",
                       help="figures: screen (PNG and SVG, the default), paper (PDF, SVG and PNG at a journal's "
                            "column width, 3.5 in) or paper-wide (7.16 in)")


def _say(msg):
    print(f"soft-twin-sim: {msg}", file=sys.stderr, flush=True)


def main_study(args):
    for name in ("workers", "chunk_size"):
        v = getattr(args, name)
        if v is not None and v < 1:
            _say(f"--{name.replace('_', '-')} must be >= 1, got {v}")
            return 2
    import signal

    def _terminate(signum, frame):           # SIGTERM (a batch system, kill): save and stop as on Ctrl-C
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        study = load_study(args.study)
        out = args.output or os.path.join("out", study.name)
        with figure_style(args.style):             # the summary's figures (studies.report)
            res = run_study(study, out, scheduler=args.scheduler, n_workers=args.workers, serial=args.serial,
                            chunk_size=args.chunk_size, retry_failed=args.retry_failed, overwrite=args.overwrite,
                            flush_seconds=args.flush_seconds)
    except CaseValidationError as e:
        _say(str(e))
        return 2
    except (StudyError, ScenarioError, ModelError) as e:
        _say(str(e))
        return 2
    except StudyInterrupted as e:
        _say(str(e))
        return 130
    except KeyboardInterrupt:
        _say("interrupted before any case was computed")
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    _say(f"summary: {res.get('summary')}")
    return 0 if res["failed"] == 0 and res["lost"] == 0 else 3


def _target_kind(target):
    """'scenario' or 'robot' for a path or an example's name."""
    for kind in ("scenarios", "robots"):
        try:
            p = find_file(target, kind)
        except ModelError:
            continue
        if not Path(p).is_file():
            continue
        d = read_yaml_file(p)
        if isinstance(d, dict) and "segments" not in d and "robot" in d and not (
                isinstance(d["robot"], dict) and set(d) == {"robot"}):
            return "scenario"
        return "robot"
    return "robot"


def _with_unit(mech, actuator):
    """'name [N]' (a tendon's tension) or 'name [Pa]' (a chamber's pressure)."""
    kind = mech.actuators[list(mech.actuator_names).index(actuator)].kind
    return f"{actuator} [{'N' if kind == 'tendon' else 'Pa'}]"


def main_workspace(args):
    import numpy as np
    limits = {}
    for item in args.limits:
        name, _, r = item.partition("=")
        if not name or not r:
            _say(f"--limits: expected NAME=MAX or NAME=MIN:MAX, got {item!r}")
            return 2
        try:
            limits[name] = [float(x) for x in r.split(":")] if ":" in r else float(r)
        except ValueError:
            _say(f"--limits: expected numbers in {item!r}")
            return 2
    opts = {"samples": args.samples, "design": args.design, "seed": args.seed, "corners": not args.no_corners,
            "limits": limits}
    if args.limit is not None:
        opts["limit"] = args.limit
    if args.actuators:
        opts["actuators"] = [a.strip() for a in args.actuators.split(",") if a.strip()]
    try:
        kind = _target_kind(args.target)
        study = study_from_dict({kind: args.target, "compute": {"workspace": opts}}, os.getcwd(),
                                source=args.target, name=Path(args.target).stem)
        sc = build_scenario(study, {})
        opts = study.compute["workspace"]
        idx, lo, hi = actuation_ranges(sc.mech, opts, StudyError)
    except (StudyError, ScenarioError, ModelError) as e:
        _say(str(e))
        return 2
    out = Path(args.output or os.path.join("out", f"workspace_{study.name}"))
    out.mkdir(parents=True, exist_ok=True)
    names = sc.mech.actuator_names
    _say(f"workspace of {sc.mech.name}: {', '.join(f'{names[i]} in [{a:g}, {b:g}]' for i, a, b in zip(idx, lo, hi))}"
         f"; {opts['samples']} {opts['design']} samples" + (f" + {2 ** len(idx)} corners" if opts["corners"] else ""))
    t0 = time.monotonic()
    w = workspace_of(sc, opts)
    dt = time.monotonic() - t0
    hs = w["hull"]
    rows = []
    for i, (u, p) in enumerate(zip(w["U"], w["points"])):
        r = {"sample": i, "corner": bool(w["corner"][i])}
        r.update({nm: float(v) for nm, v in zip(names, u)})
        r.update({f"tip_position_{a}": float(v) for a, v in zip("xyz", p)})
        rows.append(r)
    table = rows_to_table(rows)
    _write_parquet(table, out / "points.parquet")
    write_csv(table, out / "points.csv")
    summary = {"robot": sc.mech.name, "samples": len(rows), "failed": [list(f) for f in w["failed"]],
               "ranges": {names[i]: [float(a), float(b)] for i, a, b in zip(idx, lo, hi)},
               "method": hs["method"], "dimension": hs["dimension"], "volume_m3": hs["volume_m3"],
               "hull_area_m2": hs["area_m2"], "length_m": hs["length_m"],
               "extent_min_m": hs["extent_min"].tolist(), "extent_max_m": hs["extent_max"].tolist(),
               "boundary_samples": hs["boundary"].tolist(), "seconds": dt}
    (out / "workspace.json").write_text(json.dumps(summary, indent=1))
    color = w["U"][:, idx[0]] if len(idx) else None
    from soft_twin_core.viz.plots import workspace_figure          # here: matplotlib, once the points are in
    with figure_style(args.style):
        figures = save_figure(workspace_figure(w["points"], hs, f"{sc.mech.name} workspace", color=color,
                                               color_label=_with_unit(sc.mech, names[idx[0]]) if len(idx) else None,
                                               mark=w["corner"]),
                              out, "workspace", drawn=True)
    ext = np.array(summary["extent_max_m"]) - np.array(summary["extent_min_m"])
    _say(f"{len(rows) - len(w['failed'])} of {len(rows)} samples solved in {dt:.1f} s; hull volume "
         f"{hs['volume_m3'] * 1e6:.4g} cm^3 (dimension {hs['dimension']}), extent "
         f"{', '.join(f'{e * 100:.2f}' for e in ext)} cm (x, y, z); {len(hs['boundary'])} boundary points; "
         f"written to {out}/ (points.parquet, points.csv, workspace.json, "
         f"{', '.join(os.path.basename(f) for f in figures)})")
    print(json.dumps({k: v for k, v in summary.items() if k != "boundary_samples"}))
    return 0 if not w["failed"] else 3
