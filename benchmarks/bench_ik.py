"""IK service timing (issue 13): the answer of ~/inverse_kinematics for the
default robot, warm-started from the twin's current state (at rest, no
actuation), for reachable tip positions and full poses (tips and poses of
random least-tension actuations, 0..3 N) and for unreachable ones.

Run: .venv/bin/python benchmarks/bench_ik.py [--node]

Without --node: the service's body in
this process (the twin's IK, soft_twin_core.twin.Twin.inverse_kinematics, on a copy of the twin). With --node: the real service round trip to a node in a
second process (dynamic mode, 200 Hz stepping in that process), this
process a real rclpy client subscribed to the strains only (``--all-topics``:
every state topic, as before). The node computes in its service thread.
Prints the CPU time the node process spends per request. ``--autogroup-nice -10`` (root)
puts the benchmark's sessions ahead of other sessions on a shared machine. Prints the median and 90th percentile, the
share of successes and the machine's load (the 2 CPUs may be shared).
"""

import argparse
import os
import time

import numpy as np

from _timing import machine
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import load_model
from soft_twin_core.solve.constrained import solve_equilibrium


def targets(model, n, seed=0):
    """(4x4 poses) of the equilibria of random least-tension actuations:
    one tendon of each antagonistic pair slack, the other 0..3 N."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        u = np.zeros(4)
        u[rng.integers(0, 2)] = rng.uniform(0, 3)
        u[2 + rng.integers(0, 2)] = rng.uniform(0, 3)
        out.append(kin.tip_pose(model, solve_equilibrium(from_robot_model(model), u).q))
    return out


def report(label, times, ok, cpu=None):
    t = 1e3 * np.asarray(times)
    extra = "" if cpu is None else f"  (CPU time of this process: median {1e3 * np.median(cpu):5.1f} ms)"
    print(f"{label:42s} median {np.median(t):6.1f} ms  p90 {np.percentile(t, 90):6.1f} ms  "
          f"success {sum(ok)}/{len(ok)}{extra}")
    return float(np.median(t))


def in_process(model, poses):
    """The service's body: the twin's IK (Twin.inverse_kinematics) on a copy
    of the twin at rest, as the node runs it for a classic rod."""
    from soft_twin_core import twin as tw
    from soft_twin_core.robot.mechanism import load_mechanism
    twin = tw.Twin(load_mechanism("tendon_arm"), tw.TwinSettings(mode="quasi_static"))   # the default robot
    twin.step()

    def ik(T, position_only):
        return twin.query_copy().inverse_kinematics(T[:3, 3] if position_only else T, 1e-6)
    ik(poses[0], True)                                               # warm-up
    res = {}
    for label, po in (("position only", True), ("full pose", False)):
        ts, cpu, ok = [], [], []
        for T in poses:
            t0, c0 = time.perf_counter(), time.process_time()
            r = ik(T, po)
            ts.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            ok.append(r.reached)
        res[label] = report(f"in process, {label}", ts, ok, cpu)
    ts, cpu, ok = [], [], []
    for T in poses[:10]:
        T = T.copy()
        T[:3, 3] += [0.0, 0.03, 0.05]           # off the tendons' reachable surface
        t0, c0 = time.perf_counter(), time.process_time()
        r = ik(T, True)
        ts.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        ok.append(not r.reached)
    report("in process, unreachable (flagged)", ts, ok, cpu)
    return res


def _cpu_s(pid, thread=None):
    """utime + stime [s] of a process (or one of its threads) from /proc."""
    f = f"/proc/{pid}/task/{thread}/stat" if thread else f"/proc/{pid}/stat"
    st = open(f).read()
    x = st[st.rindex(")") + 2:].split()
    return (int(x[11]) + int(x[12])) / os.sysconf("SC_CLK_TCK")


def _threads_cpu(pid):
    return {t: _cpu_s(pid, t) for t in os.listdir(f"/proc/{pid}/task")}


def _autogroup_nice(pid, value):
    """Give a process's scheduling group (its session, with the kernel's
    autogroup) the nice value ``value``; --autogroup-nice: our processes ahead
    of other sessions' work on a shared machine (nice alone only ranks
    processes inside one session). Root only; silently skipped otherwise."""
    try:
        with open(f"/proc/{pid}/autogroup", "w") as fh:
            fh.write(str(value))
        return True
    except OSError:
        return False


AUTOGROUP_NICE = None
CLIENT_TOPICS = ("strains",)


def through_node(poses, idle_s=3.0):
    """The service round trip through a node in a second process; with the
    CPU time the node process (per thread) spends."""
    import rclpy  # noqa: F401
    from soft_twin.client import NodeProcess, TwinClient
    from soft_twin.conversions import pose_msg
    from soft_twin.srv import InverseKinematics
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 101))
    with NodeProcess([], node_name="bench_ik") as proc:
        # subscribed to the strains only (wait_ready needs them) and /diagnostics: a client that calls
        # the IK service, not one that also takes every 200 Hz state topic in Python (that client
        # alone used ~half a CPU of the two, which the node then lacked)
        c = TwinClient("bench_ik", client_name="bench_ik_client", topics=CLIENT_TOPICS)
        try:
            c.wait_ready(120.0)
            pid = proc.proc.pid
            a, t0 = _threads_cpu(pid), time.monotonic()
            time.sleep(idle_s)
            b, T = _threads_cpu(pid), time.monotonic() - t0
            busy = sorted(((b[k] - a.get(k, 0.0)) / T for k in b), reverse=True)
            print(f"node at rest (no requests): {100 * sum(busy):.0f} % of one CPU in all its threads "
                  f"(busiest: {', '.join(f'{100 * x:.0f} %' for x in busy[:4])})")
            c.call("inverse_kinematics", InverseKinematics.Request(target=pose_msg(poses[0]), position_only=True))
            for label, po in (("position only", True), ("full pose", False)):
                ts, ok = [], []
                n0, w0 = _cpu_s(pid), time.monotonic()
                for T in poses:
                    t0 = time.perf_counter()
                    r = c.call("inverse_kinematics", InverseKinematics.Request(target=pose_msg(T), position_only=po))
                    ts.append(time.perf_counter() - t0)
                    ok.append(r.success)
                n1, w1 = _cpu_s(pid), time.monotonic()
                report(f"node round trip{' (client on all topics)' if len(CLIENT_TOPICS) > 1 else ''}, {label}",
                       ts, ok)
                print(f"    CPU per request: node process {1e3 * (n1 - n0) / len(poses):.1f} ms "
                      f"(incl. its 200 Hz twin); wall per request {1e3 * (w1 - w0) / len(poses):.1f} ms")
        finally:
            c.close()
        del proc


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--node", action="store_true", help="also time the service through a node")
    ap.add_argument("--autogroup-nice", type=int, default=None, metavar="N",
                    help="run this benchmark's sessions (this process and the node) at autogroup nice N "
                         "(e.g. -10): ahead of other sessions on a shared machine; restored to 0 at the end")
    ap.add_argument("--all-topics", action="store_true",
                    help="the client also takes every state topic (backbone, tip pose, strains, wrenches: "
                         "~1000 messages/s in Python), as the benchmark did before")
    ap.add_argument("-n", type=int, default=40)
    args = ap.parse_args()
    global AUTOGROUP_NICE, CLIENT_TOPICS
    if args.all_topics:
        from soft_twin.client import TwinClient
        CLIENT_TOPICS = TwinClient.TOPICS
    if args.autogroup_nice is not None and _autogroup_nice(os.getpid(), args.autogroup_nice):
        AUTOGROUP_NICE = args.autogroup_nice
        print(f"autogroup nice {AUTOGROUP_NICE} for this benchmark's sessions")
    print(f"machine: {machine()}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (1 min)")
    model = load_model("tendon_arm")
    poses = targets(model, args.n)
    in_process(model, poses)
    if args.node:
        through_node(poses)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if AUTOGROUP_NICE is not None:
        _autogroup_nice(os.getpid(), 0)


if __name__ == "__main__":
    main()
