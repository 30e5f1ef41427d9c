"""The twin node end to end: achieved step rate and command -> backbone latency.

For 3-, 5- and 10-section tendon arms in dynamic and quasi-static mode, the
node runs in a second process (python -m soft_twin.node) and this process is
its client over real rclpy. Reported:

* dynamic mode: the step rate and real-time factor the node reports in its
  diagnostics (1 s periods, idle and while commands stream), the mean and
  max compute time of a step;
* latency: time from publishing an ActuationCommand to receiving the first
  backbone (PoseArray) computed with it, matched exactly through
  Strains.last_command (dynamic: commands 40-60 ms apart, so with the default
  step_on_command the node steps at once on arrival; quasi-static: includes
  the equilibrium solve); "in node": the node's own share (command callback
  -> state published), from its diagnostics.

Goal (issue 7): 200 Hz dynamic stepping of a 5-section arm, < 5 ms latency.

Run: .venv/bin/python benchmarks/bench_node.py [--commands 60] [--sections 3 5 10]
"""

import argparse
import os
from pathlib import Path
import statistics
import tempfile
import time

import numpy as np
import yaml

from _timing import machine
from soft_twin.client import NodeProcess, TwinClient

NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]


def arm_yaml(n_sections, folder):
    """A 0.45 m silicone arm (r = 10 mm, E = 2 MPa, the default arm's
    material) with n PCS sections and the default arm's four tendons."""
    d = {
        "name": f"tendon_arm_{n_sections}",
        "gravity": [0.0, 0.0, -9.81],
        "segments": [{
            "name": "arm", "length": 0.45, "sections": n_sections,
            "cross_section": {"shape": "solid_circle", "radius": 0.010},
            "material": {"youngs_modulus": 2.0e6, "poisson_ratio": 0.5, "density": 1100.0, "viscosity": 2.0e3},
            "free_modes": "bending_torsion",
        }],
        "actuators": [
            {"name": "tendon_y_pos", "offset": [0.007, 0.0]},
            {"name": "tendon_y_neg", "offset": [-0.007, 0.0]},
            {"name": "tendon_z_pos", "offset": [0.0, 0.007], "end": 0.30},
            {"name": "tendon_z_neg", "offset": [0.0, -0.007], "end": 0.30},
        ],
    }
    path = Path(folder) / f"arm_{n_sections}.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def latency_run(c, n_commands, spacing, rng):
    """Publish n commands `spacing` s apart; latency of each (s)."""
    lat = []
    for _ in range(n_commands):
        u = rng.uniform(0.0, 0.3, 4)
        t_pub = time.monotonic()
        stamp = c.send_actuation(NAMES, u)
        if not c.wait_until(lambda: c.state_after(stamp), 10.0):
            raise RuntimeError("a command was never applied")
        backbone, _ = c.state_after(stamp)
        t_recv = c.arrival("backbone", backbone)
        lat.append(t_recv - t_pub)
        # next command at a random phase relative to the node's step clock
        end = time.monotonic() + spacing * rng.uniform(0.8, 1.2)
        c.wait_until(lambda: time.monotonic() >= end, spacing * 2)
    return np.array(lat)


def bench(n, mode, robot, n_commands, log_dir, rate=200.0):
    name = f"bench_{mode}_{n}"
    args = ["-p", f"robot_description_file:={robot}", "-p", f"mode:={mode}", "-p", "diagnostics_rate_hz:=1.0",
            "-p", f"step_rate_hz:={rate}"]
    out = {"sections": n, "mode": mode, "rate": rate}
    with NodeProcess(args, node_name=name, log_path=Path(log_dir) / f"{name}.log") as proc, \
            TwinClient(name, client_name=f"{name}_client", topics=("backbone", "strains")) as c:
        c.wait_ready(180.0)
        rng = np.random.default_rng(n)
        if mode == "dynamic":
            c.wait_diagnostics(timeout=5.0)
            idle = [c.wait_diagnostics(timeout=5.0) for _ in range(3)]
            out["rate_idle"] = statistics.median(float(d["step_rate_hz"]) for d in idle)
            out["rtf"] = statistics.median(float(d["real_time_factor"]) for d in idle)
            out["step_mean_ms"] = statistics.median(float(d["step_time_mean_ms"]) for d in idle)
            out["step_max_ms"] = max(float(d["step_time_max_ms"]) for d in idle)
            out["publish_ms"] = statistics.median(float(d["publish_time_mean_ms"]) for d in idle)
            t0 = time.monotonic()
            lat = latency_run(c, n_commands, 0.05, rng)
            busy = [d for t, d in c.history["diagnostics"] if t > t0 + 1.05]
            out["rate_busy"] = min(float(d["step_rate_hz"]) for d in busy) if busy else float("nan")
            node_side = [float(d["command_in_node_mean_ms"]) for d in busy]
            out["node_ms"] = statistics.median(node_side) if node_side else float("nan")
        else:
            t0 = time.monotonic()
            lat = latency_run(c, n_commands, 0.1, rng)
            c.wait_diagnostics(timeout=5.0)
            busy = [d for t, d in c.history["diagnostics"] if t > t0 + 1.05
                    and d["command_to_publish_mean_ms"] != "nan"]
            out["step_mean_ms"] = statistics.median(float(d["step_time_mean_ms"]) for d in busy)
            out["node_ms"] = statistics.median(float(d["command_in_node_mean_ms"]) for d in busy)
        out["lat_median_ms"] = 1e3 * float(np.median(lat))
        out["lat_p95_ms"] = 1e3 * float(np.percentile(lat, 95))
        out["lat_max_ms"] = 1e3 * float(lat.max())
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commands", type=int, default=60, help="latency samples per case")
    ap.add_argument("--sections", type=int, nargs="+", default=[3, 5, 10])
    ap.add_argument("--modes", nargs="+", default=["dynamic", "quasi_static"])
    ap.add_argument("--rate", type=float, default=200.0, help="step_rate_hz of the node")
    args = ap.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 101))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    print(f"machine: {machine()}, {os.cpu_count()} CPUs; node at {args.rate:g} Hz, {args.commands} commands per case")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sections:
            robot = arm_yaml(n, tmp)
            for mode in args.modes:
                r = bench(n, mode, robot, args.commands, tmp, args.rate)
                rows.append(r)
                print(f"  done: {n} sections, {mode}", flush=True)
    print(f"\n{'sections':>8} {'mode':>12} {'steps/s idle':>12} {'min busy':>9} {'RTF':>6} "
          f"{'step ms':>8} {'max':>6} {'pub ms':>7} | {'latency ms: median':>18} {'p95':>6} {'max':>6} "
          f"{'in node':>8}")
    for r in rows:
        dyn = r["mode"] == "dynamic"
        print(f"{r['sections']:>8} {r['mode']:>12} "
              + (f"{r['rate_idle']:>12.1f} {r['rate_busy']:>9.1f} {r['rtf']:>6.3f} " if dyn else f"{'-':>12} {'-':>9} {'-':>6} ")
              + f"{r['step_mean_ms']:>8.2f} " + (f"{r['step_max_ms']:>6.1f} {r['publish_ms']:>7.2f}" if dyn else f"{'-':>6} {'-':>7}")
              + f" | {r['lat_median_ms']:>18.2f} {r['lat_p95_ms']:>6.2f} {r['lat_max_ms']:>6.2f} {r['node_ms']:>8.2f}")
    print("\nstep ms: compute time of one integration step (dynamic) or one equilibrium solve (quasi-static);\n"
          "pub ms: building and publishing backbone, tip pose and strains; latency: ActuationCommand published ->\n"
          "first backbone computed with it received (dynamic: the node steps on arrival, step_on_command); in node:\n"
          "mean time from the node receiving a command to publishing the first state with it (node diagnostics).")


if __name__ == "__main__":
    main()
