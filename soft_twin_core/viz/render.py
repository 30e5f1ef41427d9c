"""``soft-twin-sim`` options that make a run visible: ``--plot DIR``
(PNG + SVG figures, :mod:`plots`), ``--animate FILE.gif|.mp4``
(:mod:`animate`), ``--fps``; and the ``render`` command, which draws the
same from a saved run (the JSON of ``soft-twin-sim dynamics``).

Kept apart from cli.py so the runner's own options stay where they are.
"""

import json
import os
import sys
from dataclasses import replace

import numpy as np

from soft_twin_core.limits import MAX_NESTING
from soft_twin_core.viz.playback import PlaybackClock, frame_signals, sample_at
from soft_twin_core.viz.style import STYLES, figure_style

DEFAULT_FPS = 25.0           # dynamics: real time at 25 frames/s (40 ms, exact in GIF)
DEFAULT_SWEEP_FPS = 2.0      # a statics sweep: two angles per second


def add_visual_arguments(p, sweep=False):
    p.add_argument("--plot", metavar="DIR", help="write PNG and SVG figures of the run into DIR")
    add_style_argument(p)
    p.add_argument("--animate", metavar="FILE", help="write an animation (.gif or .mp4) of the run"
                   + (" (with --sweep-angle: one frame per angle)" if sweep else ""))
    p.add_argument("--fps", type=float, default=None, metavar="HZ",
                   help=f"animation frame rate (default {DEFAULT_SWEEP_FPS if sweep else DEFAULT_FPS:g}"
                   + ("" if sweep else "; the run plays in real time") + ")")


def add_style_argument(p):
    p.add_argument("--style", choices=tuple(STYLES), default="screen",
                   help="figure style: screen (PNG and SVG, the default), paper (PDF, SVG and a 300 dpi PNG at "
                   "a journal's column width, 3.5 in, 8 pt type) or paper-wide (the text width, 7.16 in)")


def check_visual_arguments(args):
    """Reason a visual option is bad, or None."""
    if getattr(args, "fps", None) is not None and not (np.isfinite(args.fps) and 0 < args.fps <= 100):
        return f"--fps must lie in (0, 100] frames/s, got {args.fps}"
    port = getattr(args, "port", None)
    if port is not None and not 1 <= port <= 65535:
        return f"--port must lie in 1..65535, got {port}"
    if getattr(args, "radius", None) is not None and not (np.isfinite(args.radius) and args.radius > 0):
        return f"--radius must be a positive length in m, got {args.radius}"
    mc = getattr(args, "mcap", None)
    if mc is not None and not mc.lower().endswith(".mcap"):
        return f"--mcap: expected a file name ending in .mcap, got {mc!r}"
    anim = getattr(args, "animate", None)
    if anim and os.path.splitext(anim)[1].lower() not in (".gif", ".mp4"):
        return f"--animate: expected a file name ending in .gif or .mp4, got {anim!r}"
    return None


def backbone_every_for(args, dt):
    """Backbone sampling (steps) an animation needs: one sample per frame at
    least (``--backbone-every`` wins when given)."""
    if args.backbone_every or not (args.animate or args.plot or getattr(args, "mcap", None)):
        return args.backbone_every
    fps = args.fps or DEFAULT_FPS
    return max(1, int(round(1.0 / (fps * dt))))


def say(msg):
    print(f"soft-twin-sim: {msg}", file=sys.stderr, flush=True)


def render_dynamics(out, args, mech, name="run"):
    """--plot, --animate and --mcap of any robot's run: its members, rigid
    links (visual shapes) and joints (:mod:`scene`,
    :mod:`plots`, :mod:`recording`)."""
    if args.plot:
        from soft_twin_core.viz.plots import plot_dynamics  # here: start-up (numba)
        with figure_style(args.style):
            paths = plot_dynamics(out, args.plot, mech, name)
        say(f"wrote {len(paths)} figures into {args.plot}: " + ", ".join(os.path.basename(p) for p in paths))
        if not out.get("members_time"):
            say("warning: the run has no member samples, so the backbone_shapes, member internal wrench and "
                "energies figures are left out: run dynamics with --backbone-every K (K >= 1)")
    if args.animate:
        from soft_twin_core.viz.animate import write_animation  # here: start-up (numba)
        from soft_twin_core.viz.scene import run_snapshots  # here: start-up (numba)
        from soft_twin_core.viz.scene import sample_times  # here: start-up (numba)
        fps = args.fps or DEFAULT_FPS
        snaps = run_snapshots(out, mech)
        idx = sample_times([s.time for s in snaps], fps)
        n, seconds = write_animation([snaps[i] for i in idx], args.animate, fps, name)
        say(f"wrote {args.animate} ({n} frames at {fps:g} fps, {seconds:.2f} s)")
    if getattr(args, "mcap", None) and out.get("members_time"):
        from soft_twin_core.files.recording import write_articulated_mcap  # here: start-up (numba)
        n = write_articulated_mcap(out, mech, args.mcap)
        say(f"wrote {args.mcap} ({n} states as /soft_twin_sim/joint_states, backbones/<member>, tip_pose, /tf)")


def render_statics(results, args, sc, sweep, name="statics"):
    """--plot and --animate of a statics solve or sweep of any robot (one
    frame an equilibrium): its members, links and joints, the internal
    wrench along every member, and for a sweep the tip against the angle."""
    from soft_twin_core.viz.plots import plot_statics, plot_sweep  # here: start-up (numba)
    from soft_twin_core.viz.scene import statics_snapshot  # here: start-up (numba)
    snaps = [statics_snapshot(r, sc.mech, f"load angle {r['angle_deg']:g} deg" if sweep else "equilibrium")
             for r in results]
    if args.plot:
        with figure_style(args.style):
            paths = (plot_sweep(results, snaps, args.plot, sc.reference, name) if sweep
                     else plot_statics(results[-1], snaps[-1], args.plot, name))
        say(f"wrote {len(paths)} figures into {args.plot}: " + ", ".join(os.path.basename(p) for p in paths))
    if args.animate:
        from soft_twin_core.viz.animate import write_animation  # here: start-up (numba)
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
    except RecursionError:
        raise ValueError(f"{path}: not a JSON run of soft-twin-sim dynamics (nested deeper than a run is; "
                         f"the limit is {MAX_NESTING} levels)") from None
    if not isinstance(out, dict) or "time" not in out:
        raise ValueError(f"{path}: not a run of soft-twin-sim dynamics (no 'time' field)")
    return out


def render_main(args):
    """``soft-twin-sim render RUN [--scenario S [--sections N] | --robot R] [--node NAME]
    --plot DIR --animate FILE``: RUN is the JSON of ``soft-twin-sim dynamics`` or an
    MCAP recording of the twin node (its ``record_file``)."""
    if not (args.plot or args.animate):
        raise ValueError("render: nothing to do; give --plot DIR and/or --animate FILE")
    out, mech, name = read_run(args)
    render_dynamics(out, args, mech, name or os.path.splitext(os.path.basename(args.run))[0])


def _readable(args):
    """ValueError if the run's file cannot be opened (before the robot is asked for)."""
    try:
        open(args.run, "rb").close()
    except OSError as e:
        raise ValueError(f"{args.command}: cannot read the run {args.run!r}: {e.strerror or e}") from None


def robot_of(args):
    """(Mechanism, scenario name or None) of ``--scenario`` / ``--robot``, a
    classic or a tree robot file."""
    from soft_twin_core.files.scenario import load_scenario  # here: start-up (numba)
    from soft_twin_core.robot.mechanism import load_mechanism  # here: start-up (numba)
    from soft_twin_core.robot.model import find_file  # here: start-up (numba)
    if getattr(args, "scenario", None) and getattr(args, "robot", None):
        raise ValueError(f"{args.command}: give --scenario or --robot, not both")
    if getattr(args, "scenario", None):
        sc = load_scenario(args.scenario, args.sections)
        return sc.mech, os.path.splitext(os.path.basename(sc.source))[0]
    if getattr(args, "robot", None):
        return load_mechanism(find_file(args.robot, "robots"), sections=getattr(args, "sections", None)), None
    raise ValueError(f"{args.command}: give the run's robot: --scenario S or --robot R")


def read_run(args):
    """(run, Mechanism, scenario name or None) of ``render`` and ``view``:
    RUN is the JSON of ``soft-twin-sim dynamics`` (read first: a bad file
    is named before the robot is asked for) or an MCAP recording of the
    twin node (:func:`recording.read_node_recording`), of the
    robot of ``--scenario`` or ``--robot``; with ``--t0``, from that time
    on, taken as t = 0 (:func:`runs.shifted_run`)."""
    out, mech, name = _read_run(args)
    t0 = getattr(args, "t0", None)
    if t0 is not None:
        from soft_twin_core.files.runs import shifted_run  # here: start-up (numba)
        out = shifted_run(out, t0)
    return out, mech, name


def _read_run(args):
    out = None
    if not args.run.lower().endswith(".mcap"):
        out = load_run(args.run)
        if "history_fields" not in out:
            raise ValueError(f"{args.run}: a run of an older soft-twin-sim (no joint or member histories): run "
                             f"the scenario again to draw it")
    else:
        _readable(args)
    mech, name = robot_of(args)
    if out is None:
        from soft_twin_core.files.recording import read_node_recording  # here: start-up (numba)
        return read_node_recording(args.run, mech, args.node), mech, name
    if out.get("member_names", []) != [m.name for m in mech.members] or (
            out.get("n_sections") is not None and out["n_sections"] != len(mech.tree.soft_joints)):
        raise ValueError(f"{args.run}: a run of another robot or discretisation (members {out.get('member_names')}, "
                         f"{out.get('n_sections')} sections) than {mech.name!r} (members "
                         f"{[m.name for m in mech.members]}, {len(mech.tree.soft_joints)} sections): give the "
                         f"run's --scenario or --robot and --sections")
    return out, mech, name


def view_main(args, stop=None):
    """``soft-twin-sim view RUN [--scenario S | --robot R] [--port P] [--radius R] [--seconds T]``:
    plays a saved run (JSON or MCAP, as for ``render``) in the live 3D view
    in real time, in a loop, until Ctrl-C (or ``--seconds`` of wall time).
    The page's "playback" folder pauses it, scrubs it (a time slider),
    changes its speed and plots a signal (a frame's x, y or z [m]) up to
    the time shown, in step with the 3D view (issue 31)."""
    import time as _time
    from soft_twin_core.viz.live_view import LiveView  # here: start-up (numba)
    from soft_twin_core.viz.scene import bounds  # here: start-up (numba)
    from soft_twin_core.viz.scene import member_radii, run_snapshots  # here: start-up (numba)
    out, mech, _ = read_run(args)
    snaps = run_snapshots(out, mech)
    # the run's own samples: a node recording's at the section boundaries, a run's at its points per section
    radii = args.radius or member_radii(mech, {m.name: len(P) for m, P in zip(mech.members, snaps[0].members)})
    try:
        view = LiveView(port=args.port)
    except OSError as e:
        raise ValueError(f"view: cannot serve on port {args.port}: {e}") from None
    view.frame(*bounds(snaps, pad=0.3))           # one camera framing the whole motion
    times = np.array([s.time for s in snaps], dtype=float)
    t0, t_end = float(times[0]), float(times[-1])
    say(f"live 3D view of {args.run}: {view.url} ({len(snaps)} states, "
        f"{t_end - t0:.2f} s, in a loop; Ctrl-C to stop)")
    signals = frame_signals(list(out["frame_names"]), out["frame_poses"])
    label = [next((k for k in signals if k.endswith(" z [m]")), next(iter(signals)))]
    clock = PlaybackClock(t0, t_end, _time.monotonic())
    step = float(np.median(np.diff(times))) if len(times) > 1 else 0.01
    view.set_playback(t0, t_end, step, [label[0]] + [k for k in signals if k != label[0]],
                      on_play=lambda on: clock.set_playing(on, _time.monotonic()),
                      on_seek=lambda t: clock.seek(t, _time.monotonic()),
                      on_speed=lambda x: clock.set_speed(x, _time.monotonic()),
                      on_signal=lambda name: label.__setitem__(0, name))
    start = _time.monotonic()
    shown = None
    try:
        while args.seconds is None or _time.monotonic() - start < args.seconds:
            if stop is not None and stop.is_set():
                break
            t = clock.time(_time.monotonic())
            k = sample_at(times, t)
            name = label[0]
            if (k, name, clock.playing) != shown:
                s = replace(snaps[k], caption=f"t = {times[k]:.4f} s")       # the sample's own time
                view.show(s, radii, tip_pose=_tip_pose(s), base_pose=np.eye(4),
                          text=f"{'' if clock.playing else '(paused) '}{name}: {signals[name][k]:.6g}")
                view.show_playback(float(times[k]), times, name, signals[name])
                shown = (k, name, clock.playing)
            _time.sleep(0.02)
    except KeyboardInterrupt:
        pass
    finally:
        view.close()
    return view.updates


def _tip_pose(snap):
    """A frame at the tip: x along the last backbone segment."""
    P = snap.members[-1]
    T = np.eye(4)
    T[:3, 3] = P[-1]
    if len(P) >= 2:
        x = P[-1] - P[-2]
        x /= np.linalg.norm(x) or 1.0
        a = np.eye(3)[np.argmin(np.abs(x))]
        y = np.cross(a, x)
        y /= np.linalg.norm(y)
        T[:3, :3] = np.c_[x, y, np.cross(x, y)]
    return T
