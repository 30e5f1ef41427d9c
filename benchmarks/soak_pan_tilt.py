"""Soak of the articulated twin: the pan-tilt arm node under a joint-command
flood with IK and plan calls alongside (issue 25, items 2 and 3).

The node (``pan_tilt_arm``, dynamic mode, 200 Hz) runs in a second process;
this process publishes ``~/joint_commands`` at ``--rate`` Hz (a share
``--invalid`` of them outside the tilt joint's limits, to be rejected) while
a thread calls ``~/inverse_kinematics`` and ``~/plan_path`` (plan only, not
executed) back to back. Reported, per 1 s diagnostics period inside the
flood and over the whole run:

* the step rate (mean, minimum, share of periods below 190 Hz), the step
  time max, the dropped steps;
* the accounting of the joint commands: sent = received + lost, received =
  applied + rejected (superseded: applied, but replaced before a step used
  them), and what is missing from every counter (must be 0);
* the service round trips (median, max) and their failures;
* the machine's load average at the start and the end.

Run: .venv/bin/python benchmarks/soak_pan_tilt.py [--duration 1800] [--rate 1000] [--no-services]
     [--json out/soak.json]
"""

import argparse
import json
import os
from pathlib import Path
import tempfile
import threading
import time

import numpy as np
import yaml
from geometry_msgs.msg import Pose

from _timing import machine
from soft_twin.client import start_twin, stop_twin
from soft_twin.srv import InverseKinematics, PlanPath

NODE = "soak_pan_tilt"


def _pose(p):
    m = Pose()
    m.position.x, m.position.y, m.position.z = (float(v) for v in p)
    m.orientation.w = 1.0
    return m


def call_services(client, stop, results):
    """IK and plan requests back to back until ``stop``: (name, ok, round trip s)."""
    tip = client.tip_pose.pose.position
    p0 = np.array([tip.x, tip.y, tip.z])
    path = {"type": "line", "start": p0.tolist(), "end": (p0 + [0.0, 0.02, 0.01]).tolist(), "duration": 1.0,
            "sample_period": 0.25}
    reqs = [("inverse_kinematics", InverseKinematics.Request(target=_pose(p0 + [0.0, 0.01, 0.01]),
                                                             position_only=True, tolerance=1e-6)),
            ("plan_path", PlanPath.Request(path_yaml=yaml.safe_dump(path), tolerance=1e-6, execute=False))]
    k = 0
    while not stop.is_set():
        name, req = reqs[k % len(reqs)]
        t = time.monotonic()
        try:
            ok = bool(client.call(name, req, timeout=120.0).success)
        except TimeoutError:
            ok = False
        results.append((name, ok, time.monotonic() - t))
        k += 1


def flood(client, rate_hz, duration, invalid, rng, loads):
    """Joint commands at rate_hz for duration s: (n_sent, n_invalid, t_start,
    t_end); the 1-minute load average appended to ``loads`` every minute."""
    n_sent = n_invalid = 0
    t_start = next_t = time.monotonic()
    next_load = t_start + 60.0
    while time.monotonic() - t_start < duration:
        if time.monotonic() >= next_load:
            loads.append(round(os.getloadavg()[0], 2))
            next_load += 60.0
        bad = rng.random() < invalid
        tilt = 2.0 if bad else rng.uniform(-0.3, 0.3)       # the tilt joint's limits: [-1.5, 1.5] rad
        client.send_joint_command(["pan", "tilt"], [rng.uniform(-0.5, 0.5), tilt])
        n_sent += 1
        n_invalid += bad
        next_t += 1.0 / rate_hz
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)      # pacing the flood
    return n_sent, n_invalid, t_start, time.monotonic()


def soak(duration, rate_hz, services=True, invalid=0.3, log_dir=None, extra_args=()):
    """Run the soak; returns the report (a dict)."""
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix="soak_"))
    load0 = os.getloadavg()
    proc, c = start_twin(NODE, ["-p", "robot_description_file:=pan_tilt_arm", "-p", "mode:=dynamic",
                                "-p", "diagnostics_rate_hz:=1.0", *extra_args], log_dir / "node.log",
                         ready=lambda c: c.pub_joints.get_subscription_count() > 0)
    stop, results, loads = threading.Event(), [], []
    try:
        # one command first: the node knows this publisher's sequence numbers from then on
        c.send_joint_command(["pan", "tilt"], [0.0, 0.0])
        assert c.wait_diagnostics(lambda d: d.get("joint_commands_received_total") == "1", 10.0), \
            "the first joint command never arrived"
        worker = threading.Thread(target=call_services, args=(c, stop, results))
        if services:
            worker.start()
        n_sent, n_invalid, t_start, t_end = flood(c, rate_hz, duration, invalid, np.random.default_rng(0),
                                                    loads)
        stop.set()
        if services:
            worker.join(timeout=150.0)
        # the counters settle once the queue is drained: wait until two periods agree
        prev = None
        for _ in range(20):
            d = c.wait_diagnostics(timeout=5.0)
            if prev is not None and d["joint_commands_received_total"] == prev["joint_commands_received_total"]:
                break
            prev = d
        alive = proc.alive()
    finally:
        stop.set()
        stop_twin(proc, c)
    windows = [w for t, w in c.history["diagnostics"] if t_start + 1.05 <= t <= t_end]
    rates = np.array([float(w["step_rate_hz"]) for w in windows])
    sent = n_sent + 1
    received, applied = int(d["joint_commands_received_total"]), int(d["joint_commands_applied_total"])
    rejected, lost = int(d["rejected_joint_total"]), int(d["joint_commands_lost_total"])
    superseded = int(d["joint_commands_superseded_total"])
    times = {n: [r[2] for r in results if r[0] == n] for n in ("inverse_kinematics", "plan_path")}
    return {
        "machine": machine(), "load_start": load0, "load_end": os.getloadavg(), "load_per_minute": loads,
        "node_alive": alive,
        "duration_s": t_end - t_start, "sent": sent, "sent_rate_hz": n_sent / (t_end - t_start),
        "sent_invalid": n_invalid, "received": received, "applied": applied, "superseded": superseded,
        "rejected": rejected, "lost": lost, "unaccounted": sent - (applied + rejected + lost),
        "step_rate_mean_hz": float(rates.mean()) if rates.size else float("nan"),
        "step_rate_per_minute_hz": [round(float(r.mean()), 2) for r in np.array_split(rates, max(1, rates.size // 60))],
        "step_rate_min_hz": float(rates.min()) if rates.size else float("nan"),
        "periods": int(rates.size), "periods_below_190_hz": int(np.sum(rates < 190.0)),
        "step_time_max_ms": max((float(w["step_time_max_ms"]) for w in windows), default=float("nan")),
        "dropped_steps": int(d["dropped_steps_total"]), "solver_failures": int(d["solver_failures_total"]),
        "internal_errors": int(d["internal_errors_total"]),
        "services": {n: {"calls": len(t), "median_s": float(np.median(t)) if t else None,
                         "max_s": max(t, default=None)} for n, t in times.items()},
        "service_failures": sum(not ok for _, ok, _ in results),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=1800.0, help="flood duration, s (default 30 min)")
    ap.add_argument("--rate", type=float, default=1000.0, help="joint commands per second (default 1000)")
    ap.add_argument("--invalid", type=float, default=0.3, help="share of commands outside the limits")
    ap.add_argument("--no-services", action="store_true", help="no IK/plan calls alongside")
    ap.add_argument("--json", help="write the report here too")
    a = ap.parse_args()
    rep = soak(a.duration, a.rate, not a.no_services, a.invalid)
    text = json.dumps(rep, indent=2)
    print(text)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(text)


if __name__ == "__main__":
    main()
