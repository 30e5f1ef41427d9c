#!/usr/bin/env python3
"""Demo of the soft_twin digital twin (`make demo`).

Starts the twin node on the default robot (config/robots/tendon_arm.yaml, a
3-segment tendon-driven silicone arm) in dynamic mode in a second process,
hangs a 10 g payload on its tip, then drives it for 10 s from this process:
the tendon on the +z side lifts the arm, the one on the +y side swings it
sideways, then both are released. Prints a table of actuation -> tip position
and tip wrench, writes a PNG of the backbone shapes and an animation (GIF or
MP4, real time) of the whole run, has the node record it to MCAP (ROS 2 bag
format), stops the node (SIGINT, as Ctrl-C would), says where each file is
and exits.

    make demo                        # or: .venv/bin/python scripts/demo.py
    make demo ARGS="--out /tmp/demo.png --mode quasi_static --animation /tmp/demo.mp4 --record /tmp/demo.mcap"
"""

import argparse
import os
from pathlib import Path
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
PAYLOAD_N = 0.0981          # 10 g on the tip, along -z of the base frame
DURATION = 10.0             # s of sweep
COMMAND_RATE = 50.0         # Hz
SAMPLE_EVERY = 1.0          # s between table rows / drawn shapes
FRAME_RATE = 20.0           # Hz: backbone frames of the animation (plays in real time)


def say(msg):
    print(f"[demo] {msg}", flush=True)


def ramp(t, t0, t1):
    """0 -> 1 smoothly (raised cosine) between t0 and t1."""
    x = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def tensions(t):
    """Tendon tensions [N] at time t of the sweep: lift (+z tendon to 18 N),
    swing (+y tendon to 6 N), release both."""
    release = 1.0 - ramp(t, 7.0, 9.5)
    lift = 18.0 * ramp(t, 0.5, 3.5) * release
    swing = 6.0 * ramp(t, 3.5, 6.5) * release
    return [swing, 0.0, lift, 0.0]


def wait_for_node(proc, client, timeout=300.0):
    """Wait for the node (the first start compiles numba kernels), with progress."""
    t0 = time.monotonic()
    while True:
        try:
            client.wait_ready(timeout=5.0)
            return time.monotonic() - t0
        except TimeoutError:
            if not proc.alive():
                proc.stop()
                say("the node exited during start-up; its log:\n" + proc.output())
                sys.exit(1)
            waited = time.monotonic() - t0
            if waited > timeout:
                proc.stop()
                say(f"the node did not come up in {timeout:.0f} s; its log:\n" + proc.output())
                sys.exit(1)
            say(f"  still starting ({waited:.0f} s; the first run compiles the numba kernels) ...")


def static_tip(client, u):
    """The equilibrium tip position for the same inputs (statics_query: the
    twin's own state is not changed), or None."""
    from soft_twin.srv import StaticsQuery
    req = StaticsQuery.Request(actuator_names=NAMES, actuator_values=[float(x) for x in u])
    req.tip_wrench.force.z = -PAYLOAD_N
    resp = client.call("statics_query", req, timeout=10.0)
    return xyz(resp.tip_pose.position) if resp.success else None


def xyz(v):
    return np.array([v.x, v.y, v.z])


def frame(backbone, t, u):
    """A snapshot of the received backbone (base_link) for the animation."""
    from soft_twin_core.viz.scene import Snapshot
    P = np.array([[p.position.x, p.position.y, p.position.z] for p in backbone.poses])
    return Snapshot([P], time=t, caption=f"t = {t:5.2f} s   T(y+) = {u[0]:5.2f} N   T(z+) = {u[2]:5.2f} N")


def plot(samples, out, mode):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (side, top) = plt.subplots(1, 2, figsize=(11, 4.8))
    cmap = plt.get_cmap("viridis")
    for k, s in enumerate(samples):
        P = s["backbone"]
        c = cmap(k / max(1, len(samples) - 1))
        label = f"t={s['t']:.0f} s  T(y+)={s['u'][0]:.1f} N  T(z+)={s['u'][2]:.1f} N"
        side.plot(P[:, 0], P[:, 2], color=c, lw=2, label=label)
        side.plot(P[-1, 0], P[-1, 2], "o", color=c, ms=4)
        top.plot(P[:, 0], P[:, 1], color=c, lw=2)
        top.plot(P[-1, 0], P[-1, 1], "o", color=c, ms=4)
    for ax, (a, b) in ((side, ("x", "z")), (top, ("x", "y"))):
        ax.plot(0, 0, "ks", ms=8)
        ax.set_xlabel(f"{a} [m] (base_link)")
        ax.set_ylabel(f"{b} [m]")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    side.set_title("side view (gravity along -z)")
    top.set_title("top view")
    side.legend(fontsize=6.5, loc="lower left")
    fig.suptitle(f"soft_twin: tendon arm backbone ({mode} twin), 10 g payload on the tip")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "demo_backbones.png", help="PNG to write")
    ap.add_argument("--mode", choices=("dynamic", "quasi_static"), default="dynamic")
    ap.add_argument("--animation", type=Path, default=ROOT / "out" / "demo.gif",
                    help="animation of the run to write (.gif or .mp4; empty: none)")
    ap.add_argument("--record", type=Path, default=ROOT / "out" / "demo.mcap",
                    help="MCAP recording (ROS 2 bag format) the node makes of the run (empty: none)")
    args = ap.parse_args(argv)
    if args.animation.name and args.animation.suffix.lower() not in (".gif", ".mp4"):
        ap.error(f"--animation: expected a .gif or .mp4 file name, got {str(args.animation)!r}")
    if args.record.name and args.record.suffix.lower() != ".mcap":
        ap.error(f"--record: expected a .mcap file name, got {str(args.record)!r}")
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 101))   # our own ROS 2 domain
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    from soft_twin.client import NodeProcess, TwinClient

    say(f"starting the twin node (python -m soft_twin.node, mode {args.mode}, default robot) ...")
    node_args = ["-p", f"mode:={args.mode}", "-p", "wrench_rate_hz:=50.0"]
    if args.record.name:
        args.record.parent.mkdir(parents=True, exist_ok=True)
        node_args += ["-p", f"record_file:={args.record.resolve()}"]
    proc = NodeProcess(node_args, node_name="soft_twin_demo")
    sent = 0
    client = TwinClient("soft_twin_demo", client_name="soft_twin_demo_client")
    try:
        took = wait_for_node(proc, client)
        say(f"node up after {took:.1f} s: {len(client.backbone.poses)} backbone poses at "
            f"{'200 Hz' if args.mode == 'dynamic' else 'each new equilibrium'}")
        client.send_tip_wrench([0.0, 0.0, -PAYLOAD_N], [0.0, 0.0, 0.0], "base_link")
        client.send_actuation(NAMES, [0.0] * 4)
        sent += 1
        if not client.wait_until(lambda: client.tip_wrench is not None
                                 and abs(abs(client.tip_wrench.wrench.force.x) + abs(client.tip_wrench.wrench.force.y)
                                         + abs(client.tip_wrench.wrench.force.z) - 0.0) > 0.05, 10.0):
            raise RuntimeError("the twin did not take the payload")
        if args.mode == "dynamic":      # let the payload settle a little
            end = time.monotonic() + 1.5
            client.wait_until(lambda: time.monotonic() >= end, 2.0)
        say(f"sweeping the tendon tensions for {DURATION:.0f} s (commands at {COMMAND_RATE:.0f} Hz) ...")
        samples, frames = [], []
        t0 = time.monotonic()
        sweep_stamp = client.tip_pose.header.stamp         # the sweep's t = 0 on the node's clock (the recording's)
        next_cmd, next_sample, next_frame = t0, t0, t0
        while True:
            now = time.monotonic()
            t = now - t0
            if len(samples) > round(DURATION / SAMPLE_EVERY):    # rows at t = 0, 1, ..., DURATION
                break
            if now >= next_cmd:
                u = tensions(t)
                client.send_actuation(NAMES, u)
                sent += 1
                next_cmd += 1.0 / COMMAND_RATE
            if now >= next_sample:
                b, w, bw = client.backbone, client.tip_wrench, client.base_wrench
                u_now = tensions(min(t, DURATION))
                samples.append(dict(t=round(t), u=u_now, backbone=np.array(
                    [[p.position.x, p.position.y, p.position.z] for p in b.poses]),
                    tip_force=xyz(w.wrench.force), tip_torque=xyz(w.wrench.torque),
                    base_force=xyz(bw.wrench.force), base_torque=xyz(bw.wrench.torque),
                    static_tip=static_tip(client, u_now)))
                next_sample += SAMPLE_EVERY
            if now >= next_frame and args.animation.name:
                frames.append(frame(client.backbone, len(frames) / FRAME_RATE, tensions(min(t, DURATION))))
                next_frame += 1.0 / FRAME_RATE
            wake = min(next_cmd, next_sample, next_frame)
            client.wait_until(lambda: time.monotonic() >= wake, max(0.0, wake - time.monotonic()) + 0.01)
        # on a busy machine the node may still be taking the last commands: stop it (and its recording)
        # only once it has them all (at most 10 s)
        diag = client.wait_diagnostics(lambda d: int(d.get("commands_received_total", "0")) >= sent, 10.0) \
            or client.wait_diagnostics(timeout=3.0) or {}
    finally:
        client.close()
        rc = proc.stop()
    print()
    print("actuation -> tip position (base_link) and tip wrench (payload on the tip, tip_link axes);")
    print("base: the support's reaction on the arm (base_link, moment about its origin);")
    print("lag: distance of the (dynamic) tip from the static equilibrium for the same inputs")
    print(f"{'t':>4} {'T y+':>6} {'T z+':>6} | {'tip x':>7} {'tip y':>7} {'tip z':>7} {'lag':>6} | "
          f"{'F_tip x':>8} {'F_tip y':>8} {'F_tip z':>8} | {'base Fz':>8} {'base My':>8}")
    print(f"{'[s]':>4} {'[N]':>6} {'[N]':>6} | {'[mm]':>7} {'[mm]':>7} {'[mm]':>7} {'[mm]':>6} | "
          f"{'[N]':>8} {'[N]':>8} {'[N]':>8} | {'[N]':>8} {'[N m]':>8}")
    for s in samples:
        p = 1e3 * s["backbone"][-1]
        lag = (f"{1e3 * np.linalg.norm(s['backbone'][-1] - s['static_tip']):>6.1f}"
               if s["static_tip"] is not None else f"{'-':>6}")
        print(f"{s['t']:>4.0f} {s['u'][0]:>6.2f} {s['u'][2]:>6.2f} | {p[0]:>7.1f} {p[1]:>7.1f} {p[2]:>7.1f} {lag} | "
              f"{s['tip_force'][0]:>8.4f} {s['tip_force'][1]:>8.4f} {s['tip_force'][2]:>8.4f} | "
              f"{s['base_force'][2]:>8.4f} {s['base_torque'][1]:>8.4f}")
    print()
    if diag:
        say(f"twin: {diag.get('step_rate_hz')} steps/s, real-time factor {diag.get('real_time_factor')}, "
            f"step {diag.get('step_time_mean_ms')} ms mean, {diag.get('commands_applied_total')} commands applied, "
            f"{diag.get('solver_failures_total')} solver failures")
    plot(samples, args.out, args.mode)
    say(f"wrote the backbone shapes: {args.out}")
    if args.animation.name:
        from soft_twin_core.viz.animate import write_animation
        n, seconds = write_animation(frames, str(args.animation), FRAME_RATE,
                                     f"soft_twin demo: tendon arm ({args.mode} twin), 10 g payload")
        say(f"wrote the animation: {args.animation} ({n} frames, {seconds:.1f} s at {FRAME_RATE:g} fps)")
    if args.record.name and rc == 0:
        from soft_twin_core.files.mcap_salvage import topic_counts
        from soft_twin_core.files.recording import read_messages
        counts = topic_counts(str(args.record))            # (decoding every message would take seconds)
        msgs = read_messages(str(args.record), ["/soft_twin_demo/tip_pose"])
        say(f"the node recorded {sum(counts.values())} messages on {len(counts)} topics "
            f"({counts.get('/soft_twin_demo/actuation', 0)} of the {sent} commands sent): {args.record}")
        # the table's t = 0 in the recording's time (its first state): render and view take it as --t0
        ns = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs.get("/soft_twin_demo/tip_pose", [])]
        t0_rec = (sweep_stamp.sec * 10**9 + sweep_stamp.nanosec - min(ns)) * 1e-9 if ns else 0.0
        say(f"  replay as figures, t = 0 at the sweep's start as in the table: .venv/bin/soft-twin-sim render "
            f"{args.record} --robot tendon_arm --node /soft_twin_demo --t0 {t0_rec:.3f} --plot out/demo_figures")
    if rc != 0:
        say(f"the node exited with code {rc}; its log:\n{proc.output()}")
        return 1
    say("node shut down cleanly (exit code 0)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
