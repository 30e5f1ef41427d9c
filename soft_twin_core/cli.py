"""``soft-twin-sim``: run a statics or dynamics scenario file and print JSON/CSV.

    soft-twin-sim statics SCENARIO [--sections N] [--sweep-angle 0:90:15]
    soft-twin-sim dynamics SCENARIO --duration T --dt DT [--format json|csv]
                  [--output FILE] [--backbone-every K] [--record-every K] [--theta 0.5]
    soft-twin-sim study STUDY.yaml [-o OUT] [--scheduler ADDRESS | --workers N | --serial]
    soft-twin-sim workspace ROBOT_OR_SCENARIO [-o OUT] [--limit MAX] [--samples N]
    soft-twin-sim plan PLAN_FILE [--output PREFIX] [--no-dynamics] [--plot DIR] [--style paper]
    ... [--plot DIR [--style screen|paper|paper-wide]] [--animate FILE.gif|FILE.mp4] [--fps HZ]     (statics and dynamics)
    soft-twin-sim render RUN.json|RUN.mcap [--scenario S | --robot R] [--plot DIR] [--animate FILE] [--fps HZ]
    soft-twin-sim view RUN.json|RUN.mcap [--port 8080]      (live 3D view in the browser, in a loop)
    soft-twin-sim calibrate ROBOT --sensors S.yaml --data D.csv --fit PARAMS [--output R.yaml]
    soft-twin-sim estimate ROBOT --sensors S.yaml --data D.csv|D.mcap [--wrench payload] [--plot DIR] [-o E.csv]

(study and workspace: see soft_twin_core/studies/cli.py; plan: soft_twin_core/planning/plan_file.py.)

SCENARIO is a scenario file or the name of an example scenario
(``tendon_arm_dynamics``). Exit status: 0 success; 2 a bad argument or
scenario field (reported on stderr by name; nothing is written); 3 a solve
or a time step failed (the reason on stderr; a dynamics run still writes
its history up to the last converged step).

The dynamics CSV holds the same time histories as the JSON, one row per
recorded time, one column per value: ``<field>_<name>_<component>``, with
the names of the field's list (``joint_names``, ``frame_names``,
``section_names``, ``member_point_names`` ...) and its components (x/y/z
for positions and velocities, fx..mz for wrenches, the strain modes); the
member samples (``--backbone-every``) fill their columns on the rows of
the sample times, the others being empty.
"""

import argparse
import csv
import io
import json
import os
import sys
import time

import numpy as np

from soft_twin_core.viz import render


def _parse_sweep(text):
    try:
        a, b, step = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP:STEP in degrees, got {text!r}") from None
    if step <= 0 or b < a:
        raise argparse.ArgumentTypeError(f"expected START <= STOP and STEP > 0, got {text!r}")
    return np.arange(a, b + 1e-9 * max(1.0, abs(b)), step)


def _non_negative_seconds(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (v >= 0 and np.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, got {text!r}")
    return v


def _parser():
    p = argparse.ArgumentParser(prog="soft-twin-sim", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("statics", help="static equilibrium of a scenario (JSON on stdout)")
    s.add_argument("scenario")
    s.add_argument("--sections", type=int, help="sections per segment (overrides the scenario)")
    s.add_argument("--sweep-angle", type=_parse_sweep, metavar="START:STOP:STEP",
                   help="solve for each angle (deg) of the in_plane_force loads; prints a JSON list")
    s.add_argument("--points-per-section", type=int, default=10)
    s.add_argument("--time", type=_non_negative_seconds, metavar="T",
                   help="evaluate the scenario's time-varying inputs (actuation_profile, joint_trajectories, "
                        "load profiles) at T s; default: where every profile has reached its final value")
    s.add_argument("--path-steps", type=int, default=0, metavar="N",
                   help="solve at N equal times from 0 to the statics time, each from the one before, carrying "
                        "where the contacts stick (statics with a history: a gripper closes, then lifts what it "
                        "holds); default 0: the inputs at that time, in the scenario's load_steps")
    s.add_argument("--output", "-o", help="write to this file instead of stdout")
    render.add_visual_arguments(s, sweep=True)
    d = sub.add_parser("dynamics", help="time simulation of a scenario (JSON or CSV)")
    d.add_argument("scenario")
    d.add_argument("--duration", type=float, required=True, help="simulated time [s]")
    d.add_argument("--dt", type=float, default=1e-3, help="time step [s] (default 0.001)")
    d.add_argument("--sections", type=int)
    d.add_argument("--theta", type=float, default=0.5,
                   help="0.5 implicit midpoint (energy-conserving), 1.0 implicit Euler (L-stable)")
    d.add_argument("--format", choices=("json", "csv"), default="json")
    d.add_argument("--backbone-every", type=int, default=0, metavar="K",
                   help="also sample the backbone at t = 0 and every K steps (JSON and CSV)")
    d.add_argument("--record-every", type=int, default=1, metavar="K",
                   help="record the time histories every K steps (and the last one)")
    d.add_argument("--points-per-section", type=int, default=10)
    d.add_argument("--progress-every", type=_non_negative_seconds, default=1.0, metavar="SECONDS",
                   help="a progress line on stderr at most every SECONDS of wall time (default 1; 0: every step)")
    d.add_argument("--output", "-o", help="write to this file instead of stdout")
    # --- design studies and workspaces (issue 16): soft_twin_core/studies/cli.py
    from soft_twin_core.studies.cli import add_parsers
    add_parsers(sub)
    # --- issue 13: tip path planning ---
    pp = sub.add_parser("plan", help="plan the actuation sequence of a tip path (writes CSV and JSON)")
    pp.add_argument("plan_file", help="a plan file (robot, path, tracking, actuation, dynamics)")
    pp.add_argument("--output", "-o", metavar="PREFIX",
                    help="write PREFIX.csv and PREFIX.json (default: the plan file's name in the "
                         "current directory)")
    pp.add_argument("--no-dynamics", action="store_true", help="skip the dynamic verification")
    pp.add_argument("--plot", metavar="DIR", help="also write figures into DIR: plan_tip_path (planned vs "
                    "achieved tip path, error) and plan_actuation (inputs and joint commands), PNG and SVG")
    render.add_style_argument(pp)
    render.add_visual_arguments(d)
    d.add_argument("--mcap", metavar="FILE", help="also write the backbone samples as the twin node publishes "
                   "them (ROS 2 bag format: ~/backbone, ~/tip_pose, ~/strains of node soft_twin_sim; articulated robots: "
                   "~/joint_states, ~/backbones/<member>, ~/tip_pose, ~/strains, ~/joint_wrenches/<joint>, /tf)")
    r = sub.add_parser("render", help="figures and/or an animation of a saved run: the JSON of "
                       "soft-twin-sim dynamics, or an MCAP recording of the twin node")
    r.add_argument("run", help="a JSON file written by soft-twin-sim dynamics (with --backbone-every K), "
                   "or a .mcap recording of the node (record_file)")
    r.add_argument("--scenario", help="the run's scenario: members split at rigid offsets, energies")
    r.add_argument("--robot", help="the recorded node's robot (file or example name): energies, members")
    r.add_argument("--sections", type=int, help="sections per segment, as for the run")
    r.add_argument("--node", help="the twin node's name when the recording holds several")
    r.add_argument("--t0", type=float, metavar="SECONDS",
                   help="take this time of the run as t = 0, the samples before it dropped (`make demo` prints "
                        "the time of its sweep's start in its recording)")
    render.add_visual_arguments(r)
    v = sub.add_parser("view", help="play a saved run (JSON or MCAP) in the live 3D view in the browser")
    v.add_argument("run", help="as for render: a dynamics JSON (with --backbone-every K) or a .mcap of the node")
    v.add_argument("--scenario")
    v.add_argument("--robot")
    v.add_argument("--sections", type=int)
    v.add_argument("--node")
    v.add_argument("--t0", type=float, metavar="SECONDS", help="as for render")
    v.add_argument("--port", type=int, default=8080, help="http://127.0.0.1:PORT (default 8080)")
    v.add_argument("--radius", type=float, default=0.01, help="tube radius [m] (default 0.01)")
    v.add_argument("--seconds", type=float, help="stop after this many seconds (default: Ctrl-C)")
    # issue 14: calibration from recorded data (soft_twin_core.estimation.calibration)
    from soft_twin_core.estimation.cli import add_cli_parser
    add_cli_parser(sub)
    return p


def _run_estimate(args):
    """``soft-twin-sim estimate``: the filter replayed over a record
    (:func:`estimation.cli.estimate_run`), its figure (``--plot``), the JSON
    summary on stdout. Exit 0, or 2 for a bad argument or file."""
    from soft_twin_core.estimation.cli import estimate_run  # here: start-up (numba)
    from soft_twin_core.viz.plots import estimation_figure  # here: start-up (matplotlib)
    from soft_twin_core.viz.style import figure_style, save_figure  # here: start-up (matplotlib)
    run, report = estimate_run(args)
    if run is None:
        return report
    if args.plot:
        with figure_style(args.style):
            fig = estimation_figure(run, f"state estimation: {os.path.basename(args.data)}")
            report["figures"] = save_figure(fig, args.plot, "estimation")
    print(json.dumps(report, indent=1))
    return 0


def _run_plan(args):
    """``soft-twin-sim plan``: exit 0 when every sample is reached, 3 when
    some are not (the files are written either way), 2 on a bad file."""
    import os
    from soft_twin_core.errors import StaticsError
    from soft_twin_core.planning.paths import PathError
    from soft_twin_core.planning.plan_file import PlanFileError, load_plan_file, plan_csv, run_plan
    from soft_twin_core.planning.planner import PlanError
    from soft_twin_core.robot.model import ModelError
    try:
        model, path, opts, u0, dyn = load_plan_file(args.plan_file)
        t0 = time.monotonic()
        out = run_plan(model, path, opts, u0, None if args.no_dynamics else dyn)
    except (PlanFileError, PathError, PlanError, ModelError, ValueError) as e:
        print(f"soft-twin-sim: {e}", file=sys.stderr)
        return 2
    except StaticsError as e:
        print(f"soft-twin-sim: {e}", file=sys.stderr)
        return 3
    prefix = args.output or os.path.splitext(os.path.basename(args.plan_file))[0]
    with open(prefix + ".json", "w") as fh:
        json.dump(out, fh)
    with open(prefix + ".csv", "w") as fh:
        fh.write(plan_csv(out))
    s = out["summary"]
    err = s["max_error_reached_m"]
    print(f"soft-twin-sim: planned {s['samples']} samples in {time.monotonic() - t0:.1f} s: "
          f"{s['reached']} reached (max error {err if err is None else f'{1e3 * err:.3g} mm'}), "
          f"{s['unreachable']} unreachable {s['statuses']}", file=sys.stderr)
    if "dynamics" in out:
        d = out["dynamics"]
        comp = d.get("compensated")
        print(f"soft-twin-sim: dynamics: rms tracking error {1e3 * d['uncompensated']['rms_error_m']:.3g} mm "
              f"(max {1e3 * d['uncompensated']['max_error_m']:.3g} mm)"
              + (f"; with lag compensation {1e3 * comp['rms_error_m']:.3g} mm "
                 f"(max {1e3 * comp['max_error_m']:.3g} mm)" if comp else ""), file=sys.stderr)
    print(f"soft-twin-sim: wrote {prefix}.csv and {prefix}.json", file=sys.stderr)
    if args.plot:
        from soft_twin_core.viz.plan_plots import plot_plan
        from soft_twin_core.viz.style import figure_style
        with figure_style(args.style):
            written = plot_plan(out, args.plot)
        print(f"soft-twin-sim: wrote {len(written)} figure files into {args.plot}", file=sys.stderr)
    return 0 if s["unreachable"] == 0 else 3


_VEC3 = ("x", "y", "z")
_WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")
# per-row shapes of the history fields when no row was recorded
_LAST_AXIS = {"tip_position": _VEC3, "tip_velocity": _VEC3, "tip_orientation": ("x", "y", "z", "w"),
              "base_wrench": _WRENCH, "frame_positions": _VEC3, "member_positions": _VEC3,
              "member_velocities": _VEC3, "constraint_wrenches": _WRENCH, "transmitted_wrenches": _WRENCH,
              "member_internal_wrenches": _WRENCH, "contact_force": _VEC3}
# fields whose rows are one value per name in a name list of the run, and that list
_NAMED = {"joint_positions": "joint_names", "joint_velocities": "joint_names", "joint_accelerations": "joint_names",
          "joint_efforts": "joint_names", "peak_normal_stress": "member_names", "peak_shear_stress": "member_names",
          "frame_positions": "frame_names", "constraint_wrenches": "constraint_names",
          "transmitted_wrenches": "transmitted_names", "strains": "section_names", "strain_rates": "section_names",
          "member_positions": "member_point_names", "member_velocities": "member_point_names",
          "member_internal_wrenches": "member_point_names"}


def _components(field, width):
    """Names along a field's last axis of ``width`` values (None: a scalar per name)."""
    from soft_twin_core.robot.model import STRAIN_NAMES
    last = _LAST_AXIS.get(field) or (STRAIN_NAMES if field in ("strains", "strain_rates") else None)
    if width is None:
        return last or [None]
    if width == 1 and last is None:
        return [None]
    return last if last is not None and len(last) == width else [str(j) for j in range(width)]


def csv_columns(out):
    """(header, rows) of the dynamics CSV: the time-history fields of
    :func:`scenario.run_dynamics` (``history_fields``), then its member
    samples (``sample_fields``, on the rows of their sample times, empty on
    the others), one column per value: ``<field>[_<name>][_<component>]``
    with the names of the field's name list (joints, frames, sections,
    member points ...) and its components (x/y/z, fx..mz, the strain
    modes); values are Python's shortest round-trip repr."""
    n = len(out["time"])
    row_of = {t: i for i, t in enumerate(out["time"])}
    samples = [row_of[t] for t in out.get("members_time", ())]
    header, columns = [], []
    for field in list(out["history_fields"]) + list(out.get("sample_fields", ())):
        rows = samples if field in out.get("sample_fields", ()) else list(range(n))
        names = out[_NAMED[field]] if field in _NAMED else [None]
        if not names:                     # nothing per row (a robot without joints or constraints)
            continue
        a = np.asarray(out[field], dtype=float).reshape(len(rows), len(names), -1) if rows else None
        comps = _components(field, a.shape[-1] if a is not None else None)
        if field in ("time", "constraint_error", "newton_iterations", "contact_count"):
            comps = [None]
        labels = ["_".join(str(x) for x in (field, nm, c) if x is not None) for nm in names for c in comps]
        flat = a.reshape(len(rows), -1) if a is not None else np.zeros((0, len(labels)))
        col = [[""] * n for _ in labels]
        for r, values in zip(rows, flat):
            for c, v in zip(col, values):
                c[r] = int(v) if field == "newton_iterations" else float(v)
        header += labels
        columns += col
    return header, [[c[r] for c in columns] for r in range(n)]


def _csv(out):
    header, rows = csv_columns(out)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def unstable_message(r, angle=None):
    """The warning for a statics result flagged unstable."""
    ev = r.get("min_stiffness_eigenvalue")
    why = f" (smallest eigenvalue of the tangent stiffness {ev:.3g} < 0)" if ev is not None and ev == ev else ""
    at = f" at angle {angle:g} deg" if angle is not None else ""
    return (f"soft-twin-sim: warning: statics{at}: only an unstable equilibrium was found{why}: under these "
            f"loads the structure buckles or snaps through; the shape returned (\"stable\": false) is one it "
            f"cannot hold")


def show_plausibility_warnings(prog="soft-twin-sim"):
    """Print the plausibility warnings of the input files (a likely unit
    slip: soft_twin_core.robot.plausibility) as one plain line each on stderr,
    ``<prog>: warning: <field>: ...``, each once."""
    import warnings
    from soft_twin_core.files.mcap_salvage import TruncatedRecordingWarning      # a recording read up to its last chunk (issue 25)
    from soft_twin_core.limits import PlausibilityWarning
    previous = warnings.showwarning
    if getattr(previous, "soft_twin_plausibility", False):     # already installed (main called again)
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, (PlausibilityWarning, TruncatedRecordingWarning)):
            print(f"{prog}: warning: {message}", file=sys.stderr)
        else:
            previous(message, category, filename, lineno, file, line)
    show.soft_twin_plausibility = True
    warnings.showwarning = show
    warnings.filterwarnings("default", category=PlausibilityWarning)
    warnings.filterwarnings("always", category=TruncatedRecordingWarning)


def main(argv=None):
    from soft_twin_core._blas import blas_on_one_thread
    from soft_twin_core.errors import StaticsError
    from soft_twin_core.files.scenario import ScenarioError, load_scenario, run_dynamics, run_statics
    from soft_twin_core.files.timeline import n_steps_for
    from soft_twin_core.robot.model import ModelError
    args = _parser().parse_args(argv)
    show_plausibility_warnings()
    blas_on_one_thread()      # small matrices: a second BLAS thread would spin, not help
    # --- design studies and workspaces (issue 16): soft_twin_core/studies/cli.py
    if args.command in ("study", "workspace"):
        from soft_twin_core.studies.cli import main_study, main_workspace
        return main_study(args) if args.command == "study" else main_workspace(args)
    if args.command == "plan":
        return _run_plan(args)
    if args.command == "estimate":               # issue 29
        return _run_estimate(args)
    if args.command == "calibrate":              # issue 14
        from soft_twin_core.estimation.cli import cli_main
        return cli_main(args)
    failed = None
    for name in ("sections", "backbone_every", "record_every", "points_per_section", "path_steps"):
        v = getattr(args, name, None)
        low = 0 if name in ("backbone_every", "path_steps") else 1
        if v is not None and v < low:
            print(f"soft-twin-sim: --{name.replace('_', '-')} must be >= {low}, got {v}", file=sys.stderr)
            return 2
    from soft_twin_core.limits import MAX_POINTS_PER_SECTION, over_limit
    if getattr(args, "points_per_section", None) is not None and args.points_per_section > MAX_POINTS_PER_SECTION:
        print(f"soft-twin-sim: {over_limit('--points-per-section', args.points_per_section, MAX_POINTS_PER_SECTION)}",
              file=sys.stderr)
        return 2
    bad = render.check_visual_arguments(args)
    if bad:
        print(f"soft-twin-sim: {bad}", file=sys.stderr)
        return 2
    try:
        if args.command == "render":
            render.render_main(args)
            return 0
        if args.command == "view":
            render.view_main(args)
            return 0
        if args.command == "statics":
            angles = args.sweep_angle if args.sweep_angle is not None else [None]
            results = []
            note = None
            for a in angles:
                sc = load_scenario(args.scenario, args.sections, a)
                if note is None:
                    from soft_twin_core.files.scenario import statics_time
                    t_solve, note = statics_time(sc, args.time)
                    if note is not None:
                        print(f"soft-twin-sim: statics: {note}", file=sys.stderr)
                    note = note or ""
                r = run_statics(sc, args.points_per_section, args.time, args.path_steps)
                if r.get("stable") is False:
                    print(unstable_message(r, a), file=sys.stderr)
                if a is not None:
                    r = {"angle_deg": float(a), **r}
                    print(f"soft-twin-sim: angle {a:g} deg solved ({r['iterations']} iterations)",
                          file=sys.stderr)
                results.append(r)
            text = json.dumps(results if args.sweep_angle is not None else results[0], indent=1)
            title = os.path.splitext(os.path.basename(sc.source))[0]
            if note:                    # time-varying inputs: the figures say at which time
                title += f" (t = {t_solve:g} s)"
            render.render_statics(results, args, sc, args.sweep_angle is not None, title)
        else:
            n_steps_for(args.duration, args.dt)      # refuses impossible durations before any work
            sc = load_scenario(args.scenario, args.sections)
            clock = {"start": time.monotonic(), "ready": None}

            def progress(frac, elapsed):
                if clock["ready"] is None:
                    clock["ready"] = time.monotonic()
                    print(f"soft-twin-sim: kernels ready and t = 0 evaluated in "
                          f"{clock['ready'] - clock['start']:.1f} s (numba compilation or its disk cache; "
                          f"not counted below)", file=sys.stderr)
                elif frac > 0:
                    print(f"soft-twin-sim: {100 * frac:5.1f} % simulated, {elapsed:.1f} s elapsed, "
                          f"~{elapsed / frac - elapsed:.0f} s left", file=sys.stderr)
            out = run_dynamics(sc, args.duration, args.dt, render.backbone_every_for(args, args.dt), args.theta,
                               progress, args.points_per_section, args.record_every, args.progress_every)
            t_end = out["time"][-1] if out["time"] else 0.0
            wall = time.monotonic() - (clock["ready"] or clock["start"])
            print(f"soft-twin-sim: simulated {t_end:.6g} s in {wall:.2f} s wall time", file=sys.stderr)
            text = _csv(out) if args.format == "csv" else json.dumps(out)
            if "error" in out:
                failed = f"dynamics failed: {out['error']}"
            render.render_dynamics(out, args, sc.mech, os.path.splitext(os.path.basename(sc.source))[0])
    except (ScenarioError, ModelError, ValueError) as e:
        print(f"soft-twin-sim: {e}", file=sys.stderr)
        return 2
    except StaticsError as e:
        print(f"soft-twin-sim: {e}", file=sys.stderr)
        return 3
    if args.output:
        with open(args.output, "w") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text + ("\n" if not text.endswith("\n") else ""))
    if failed is not None:
        print(f"soft-twin-sim: {failed}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
