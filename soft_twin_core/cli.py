"""``soft-twin-sim``: run a statics or dynamics scenario file and print JSON/CSV.

    soft-twin-sim statics SCENARIO [--sections N] [--sweep-angle 0:90:15]
    soft-twin-sim dynamics SCENARIO --duration T --dt DT [--format json|csv]
                  [--output FILE] [--backbone-every K] [--record-every K] [--theta 0.5]
    soft-twin-sim calibrate ROBOT --sensors S.yaml --data D.csv --fit PARAMS [--output R.yaml]

SCENARIO is a scenario file or the name of an example scenario
(``tendon_arm_dynamics``). Exit status: 0 success; 2 a bad argument or
scenario field (reported on stderr by name; nothing is written); 3 a solve
or a time step failed (the reason on stderr; a dynamics run still writes
its history up to the last converged step).

The dynamics CSV holds the same time histories as the JSON, one row per
recorded time: a field of shape (N, a, b) becomes the columns
``field_<i>_<j>`` (labels: x/y/z for positions and velocities,
fx..mz for wrenches, the section index and the strain mode for strains),
and the backbone fields (``--backbone-every``) fill their columns on the
rows of the sample times, the others being empty.
"""

import argparse
import csv
import io
import json
import sys
import time

import numpy as np


def _parse_sweep(text):
    try:
        a, b, step = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP:STEP in degrees, got {text!r}") from None
    if step <= 0 or b < a:
        raise argparse.ArgumentTypeError(f"expected START <= STOP and STEP > 0, got {text!r}")
    return np.arange(a, b + 1e-9 * max(1.0, abs(b)), step)


def _parser():
    p = argparse.ArgumentParser(prog="soft-twin-sim", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("statics", help="static equilibrium of a scenario (JSON on stdout)")
    s.add_argument("scenario")
    s.add_argument("--sections", type=int, help="sections per segment (overrides the scenario)")
    s.add_argument("--sweep-angle", type=_parse_sweep, metavar="START:STOP:STEP",
                   help="solve for each angle (deg) of the in_plane_force loads; prints a JSON list")
    s.add_argument("--points-per-section", type=int, default=10)
    s.add_argument("--output", "-o", help="write to this file instead of stdout")
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
    d.add_argument("--output", "-o", help="write to this file instead of stdout")
    # issue 14: calibration from recorded data (soft_twin_core.calibration)
    from .calibration import add_cli_parser
    add_cli_parser(sub)
    return p


_VEC3 = ("x", "y", "z")
_WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")
# per-row shapes of the history fields when no row was recorded
_EMPTY_SHAPES = {"tip_position": lambda n: (3,), "tip_velocity": lambda n: (3,),
                 "base_wrench": lambda n: (6,), "strains": lambda n: (n, 6), "strain_rates": lambda n: (n, 6)}


def _labels(field, shape):
    """Column labels of one row of ``field`` with per-row ``shape``."""
    from .model import STRAIN_NAMES
    if not shape:
        return [field]
    last = {"strains": STRAIN_NAMES, "strain_rates": STRAIN_NAMES, "base_wrench": _WRENCH,
            "internal_wrenches": _WRENCH, "tip_position": _VEC3, "tip_velocity": _VEC3, "backbone": _VEC3,
            "backbone_velocity": _VEC3, "backbone_acceleration": _VEC3}.get(field)
    if last is None or len(last) != shape[-1]:
        last = [str(j) for j in range(shape[-1])]
    cols = [""]
    for n in shape[:-1]:
        cols = [f"{c}_{i}" for c in cols for i in range(n)]
    return [f"{field}{c}_{lab}" for c in cols for lab in last]


def csv_columns(out):
    """(header, rows) of the dynamics CSV: the time-history fields of
    :func:`scenario.run_dynamics` flattened row by row (see the module
    docstring); values are Python's shortest round-trip repr."""
    from .scenario import BACKBONE_FIELDS, HISTORY_FIELDS
    n = len(out["time"])
    header, columns = [], []
    row_of = {t: i for i, t in enumerate(out["time"])}
    fields = HISTORY_FIELDS + BACKBONE_FIELDS
    named = {}                            # field -> names along its last axis
    if "history_fields" in out:           # an articulated robot's run: its own fields, named columns
        fields = tuple(out["history_fields"])
        named.update(joint_positions=out["joint_names"], joint_velocities=out["joint_names"],
                      joint_accelerations=out["joint_names"], joint_efforts=out["joint_names"],
                      peak_normal_stress=out["member_names"], peak_shear_stress=out["member_names"])
    for field in fields:
        if field not in out or field == "backbone_time":    # backbone_time: the rows' own time
            continue
        a = np.asarray(out[field], dtype=float)
        if a.ndim > 1 and a.size == 0 and n:       # nothing per row (a robot without constraints)
            continue
        if field in BACKBONE_FIELDS:
            rows = [row_of[t] for t in out["backbone_time"]]   # a sample time is a recorded time
        else:
            rows = list(range(n))
        shape = a.shape[1:] if a.size else _EMPTY_SHAPES.get(field, lambda m: ())(out.get("n_sections", 0))
        labels = _labels(field, shape)
        if field in named and shape == (len(named[field]),):
            labels = [f"{field}_{nm}" for nm in named[field]]
        elif field in ("frame_positions", "constraint_wrenches") and len(shape) == 2:
            names = out["frame_names" if field == "frame_positions" else "constraint_names"]
            last = _VEC3 if field == "frame_positions" else _WRENCH
            labels = [f"{field}_{nm}_{lab}" for nm in names for lab in last]
        flat = a.reshape(len(rows), -1) if len(rows) else np.zeros((0, len(labels)))
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


def main(argv=None):
    from .model import ModelError
    from .scenario import ScenarioError, load_scenario, n_steps_for, run_dynamics, run_statics
    from .statics import StaticsError
    args = _parser().parse_args(argv)
    if args.command == "calibrate":              # issue 14
        from .calibration import cli_main
        return cli_main(args)
    failed = None
    for name in ("sections", "backbone_every", "record_every", "points_per_section"):
        v = getattr(args, name, None)
        low = 0 if name == "backbone_every" else 1
        if v is not None and v < low:
            print(f"soft-twin-sim: --{name.replace('_', '-')} must be >= {low}, got {v}", file=sys.stderr)
            return 2
    try:
        if args.command == "statics":
            angles = args.sweep_angle if args.sweep_angle is not None else [None]
            results = []
            for a in angles:
                sc = load_scenario(args.scenario, args.sections, a)
                r = run_statics(sc, args.points_per_section)
                if a is not None:
                    r = {"angle_deg": float(a), **r}
                    print(f"soft-twin-sim: angle {a:g} deg solved ({r['iterations']} iterations)",
                          file=sys.stderr)
                results.append(r)
            text = json.dumps(results if args.sweep_angle is not None else results[0], indent=1)
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
            out = run_dynamics(sc, args.duration, args.dt, args.backbone_every, args.theta,
                               progress, args.points_per_section, args.record_every)
            t_end = out["time"][-1] if out["time"] else 0.0
            wall = time.monotonic() - (clock["ready"] or clock["start"])
            print(f"soft-twin-sim: simulated {t_end:.6g} s in {wall:.2f} s wall time", file=sys.stderr)
            text = _csv(out) if args.format == "csv" else json.dumps(out)
            if "error" in out:
                failed = f"dynamics failed: {out['error']}"
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
