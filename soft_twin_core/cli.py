"""``soft-twin-sim``: run a statics or dynamics scenario file and print JSON/CSV.

    soft-twin-sim statics SCENARIO.yaml [--sections N] [--sweep-angle 0:90:15]
    soft-twin-sim dynamics SCENARIO.yaml --duration T --dt DT [--format json|csv]
                  [--output FILE] [--backbone-every K] [--record-every K] [--theta 0.5]

Errors in the scenario are reported on stderr with the offending field and
exit status 2; nothing is written to the output file then.
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
                   help="also sample the backbone every K steps (JSON only)")
    d.add_argument("--record-every", type=int, default=1, metavar="K")
    d.add_argument("--points-per-section", type=int, default=10)
    d.add_argument("--output", "-o", help="write to this file instead of stdout")
    return p


def _csv(out):
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["time_s", "tip_x_m", "tip_y_m", "tip_z_m", "base_fx_N", "base_fy_N", "base_fz_N",
                "base_mx_Nm", "base_my_Nm", "base_mz_Nm"])
    for t, p, f in zip(out["time"], out["tip_position"], out["base_wrench"]):
        w.writerow([f"{t:.9g}"] + [f"{v:.12g}" for v in p] + [f"{v:.12g}" for v in f])
    return buf.getvalue()


def main(argv=None):
    from .model import ModelError
    from .scenario import ScenarioError, load_scenario, run_dynamics, run_statics
    from .statics import StaticsError
    args = _parser().parse_args(argv)
    for name in ("sections", "backbone_every", "record_every", "points_per_section"):
        v = getattr(args, name, None)
        if v is not None and v < (0 if name == "backbone_every" else 1):
            print(f"soft-twin-sim: --{name.replace('_', '-')} must be >= 1, got {v}", file=sys.stderr)
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
            if not (np.isfinite(args.dt) and args.dt > 0):
                print(f"soft-twin-sim: --dt must be a positive time step in s, got {args.dt}", file=sys.stderr)
                return 2
            sc = load_scenario(args.scenario, args.sections)
            t0 = time.monotonic()

            def progress(frac):
                el = time.monotonic() - t0
                print(f"soft-twin-sim: {100 * frac:5.1f} % simulated, {el:.1f} s elapsed, "
                      f"~{el / max(frac, 1e-9) - el:.0f} s left", file=sys.stderr)
            out = run_dynamics(sc, args.duration, args.dt, args.backbone_every, args.theta,
                               progress, args.points_per_section, args.record_every)
            print(f"soft-twin-sim: simulated {out['time'][-1]:.4g} s in {time.monotonic() - t0:.2f} s "
                  f"wall time", file=sys.stderr)
            if "error" in out:
                print(f"soft-twin-sim: {out['error']}", file=sys.stderr)
            text = _csv(out) if args.format == "csv" else json.dumps(out)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
