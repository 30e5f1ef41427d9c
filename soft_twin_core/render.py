"""``soft-twin-sim`` options that make a run visible: ``--plot DIR``
(PNG + SVG figures, :mod:`plots`), ``--animate FILE.gif|.mp4``
(:mod:`animate`), ``--fps``; and the ``render`` command, which draws the
same from a saved run (the JSON of ``soft-twin-sim dynamics``).

Kept apart from cli.py so the runner's own options stay where they are.
"""

import json
import os
import sys

import numpy as np

DEFAULT_FPS = 25.0           # dynamics: real time at 25 frames/s (40 ms, exact in GIF)
DEFAULT_SWEEP_FPS = 2.0      # a statics sweep: two angles per second


def add_visual_arguments(p, sweep=False):
    p.add_argument("--plot", metavar="DIR", help="write PNG and SVG figures of the run into DIR")
    p.add_argument("--animate", metavar="FILE", help="write an animation (.gif or .mp4) of the run"
                   + (" (with --sweep-angle: one frame per angle)" if sweep else ""))
    p.add_argument("--fps", type=float, default=None, metavar="HZ",
                   help=f"animation frame rate (default {DEFAULT_SWEEP_FPS if sweep else DEFAULT_FPS:g}"
                   + ("" if sweep else "; the run plays in real time") + ")")


def check_visual_arguments(args):
    """Reason a visual option is bad, or None."""
    if getattr(args, "fps", None) is not None and not (np.isfinite(args.fps) and 0 < args.fps <= 100):
        return f"--fps must lie in (0, 100] frames/s, got {args.fps}"
    anim = getattr(args, "animate", None)
    if anim and os.path.splitext(anim)[1].lower() not in (".gif", ".mp4"):
        return f"--animate: expected a file name ending in .gif or .mp4, got {anim!r}"
    return None


def backbone_every_for(args, dt):
    """Backbone sampling (steps) an animation needs: one sample per frame at
    least (``--backbone-every`` wins when given)."""
    if args.backbone_every or not (args.animate or args.plot):
        return args.backbone_every
    fps = args.fps or DEFAULT_FPS
    return max(1, int(round(1.0 / (fps * dt))))


def say(msg):
    print(f"soft-twin-sim: {msg}", file=sys.stderr, flush=True)


def animate_dynamics(out, path, fps, model=None, title=""):
    """Animation of a dynamics run's backbone samples, real time at ``fps``."""
    from .animate import write_animation
    from .scene import dynamics_snapshots, sample_times
    snaps = dynamics_snapshots(out, model)
    idx = sample_times([s.time for s in snaps], fps)
    n, seconds = write_animation([snaps[i] for i in idx], path, fps, title)
    say(f"wrote {path} ({n} frames at {fps:g} fps, {seconds:.2f} s)")
    return n, seconds


def render_dynamics(out, args, model=None, gravity=True, name="run"):
    from .plots import plot_dynamics
    if args.plot:
        paths = plot_dynamics(out, args.plot, model, gravity, name)
        say(f"wrote {len(paths)} figures into {args.plot}: " + ", ".join(os.path.basename(p) for p in paths))
    if args.animate:
        animate_dynamics(out, args.animate, args.fps or DEFAULT_FPS, model, name)


def render_statics(results, args, sc, sweep, name="statics"):
    from .plots import plot_statics, plot_sweep
    if args.plot:
        if sweep:
            paths = plot_sweep(results, args.plot, sc.reference, sc.model, name)
        else:
            paths = plot_statics(results[0], args.plot, sc.model, name)
        say(f"wrote {len(paths)} figures into {args.plot}: " + ", ".join(os.path.basename(p) for p in paths))
    if args.animate:
        from .animate import write_animation
        from .scene import statics_snapshot
        snaps = [statics_snapshot(r, sc.model, f"load angle {r['angle_deg']:g} deg" if sweep else "equilibrium")
                 for r in results]
        fps = args.fps or DEFAULT_SWEEP_FPS
        n, seconds = write_animation(snaps, args.animate, fps, name)
        say(f"wrote {args.animate} ({n} frames at {fps:g} fps, {seconds:.2f} s)")


def load_run(path):
    """A saved dynamics run: the JSON of ``soft-twin-sim dynamics``."""
    try:
        with open(path) as fh:
            out = json.load(fh)
    except OSError as e:
        raise ValueError(f"render: cannot read the run {path!r}: {e.strerror or e}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a JSON run of soft-twin-sim dynamics ({e})") from None
    if not isinstance(out, dict) or "time" not in out:
        raise ValueError(f"{path}: not a run of soft-twin-sim dynamics (no 'time' field)")
    return out


def render_main(args):
    """``soft-twin-sim render RUN [--scenario S [--sections N] | --robot R] [--node NAME]
    --plot DIR --animate FILE``: RUN is the JSON of ``soft-twin-sim dynamics`` or an
    MCAP recording of the twin node (its ``record_file``)."""
    from .model import load_model
    from .scenario import load_scenario
    if not (args.plot or args.animate):
        raise ValueError("render: nothing to do; give --plot DIR and/or --animate FILE")
    if args.scenario and args.robot:
        raise ValueError("render: give --scenario or --robot, not both")
    model, gravity, name = None, True, os.path.splitext(os.path.basename(args.run))[0]
    if args.scenario:
        sc = load_scenario(args.scenario, args.sections)
        model, gravity = sc.model, sc.gravity
        name = os.path.splitext(os.path.basename(sc.source))[0]
    elif args.robot:
        model = load_model(args.robot, args.sections)
    if args.run.lower().endswith(".mcap"):
        from .recording import read_node_run
        out = read_node_run(args.run, args.node, model)
    else:
        out = load_run(args.run)
    if model is not None and out.get("n_sections", model.n_sections) != model.n_sections:
        raise ValueError(f"render: the run has {out['n_sections']} sections, the model "
                         f"{model.n_sections}; pass the run's --sections")
    render_dynamics(out, args, model, gravity, name)
