"""The speed cost of compiling the kernels for a fixed CPU baseline instead
of the host's CPU (issue 30, "Ship compiled caches").

numba keys a cached kernel by the CPU it was compiled for (name and
features). A cache that travels in a wheel must therefore be built for a
baseline every user's CPU runs (an x86-64 microarchitecture level, or
LLVM's ``generic``), and loaded by processes that compile for the same
baseline. This script measures what that costs: for each target it runs,
in a process of its own with a cache directory of its own
(``NUMBA_CPU_NAME``, ``NUMBA_CPU_FEATURES=""`` for a named target;
``SOFT_TWIN_KERNEL_CPU=host`` for the host's), the engine's hot paths:

* statics of the 10-section benchmark cantilever from straight;
* 1 s of its dynamics at dt = 2 ms (the multi-step path);
* one ``MechanismSimulator.step()`` at a time, dt = 5 ms, for the pan-tilt
  arm (compiled contact step), the rigid four-bar (compiled KKT step) and the
  planar parallel robot.

The first round compiles each target's kernels (not timed); the timed
rounds are interleaved across targets, and the best of each round's repeats
is kept; the table gives the median over rounds (CPU time) and the ratio to
the host. It also prints how far each target's final dynamics state is from
the host's (the kernels use fastmath contract/reassoc, so the order of sums
may differ).

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_cpu_target.py [--rounds 3] [--targets host,x86-64-v3,generic]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def child():
    """Measure in this process; print one JSON line."""
    import time
    sys.path[:0] = [HERE, os.path.join(ROOT, "test"), os.path.join(ROOT, "test", "unit")]
    from bench_articulated import step_time
    from test_constrained import four_bar
    from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
    from soft_twin_core.robot.model import benchmark_cantilever_dict, find_file, model_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    from numba.core.registry import cpu_target
    out = {"cpu": cpu_target.target_context.codegen().magic_tuple()[1]}
    rod = from_robot_model(model_from_dict(benchmark_cantilever_dict(10, "all")))

    def best(f, n):
        ts = []
        for _ in range(n):
            c = time.process_time()
            f()
            ts.append(time.process_time() - c)
        return min(ts)
    out["statics_10"] = best(lambda: solve_equilibrium(rod), 20)
    state = {}

    def dyn():
        sim = MechanismSimulator(rod, 2e-3, 0.5)
        sim.step(n=500)
        state["q"] = sim.q.tolist()
    out["dynamics_1s_10"] = best(dyn, 3)
    out["q_end"] = state["q"]
    for name, mech in (("pan_tilt", load_mechanism(find_file("pan_tilt_arm", "robots"))),
                       ("four_bar", four_bar(1.0)),
                       ("parallel", load_mechanism(find_file("planar_parallel_robot", "robots")))):
        q = solve_equilibrium(mech).q
        out[name] = step_time(mech, q, 5e-3, 200)[1]
    print("RESULT " + json.dumps(out))


def run_child(target, cache):
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=ROOT)
    env.pop("NUMBA_CPU_NAME", None)
    env.pop("NUMBA_CPU_FEATURES", None)
    if target == "host":
        env["SOFT_TWIN_KERNEL_CPU"] = "host"           # (else the kernels choose x86-64-v3)
    else:
        env["NUMBA_CPU_NAME"], env["NUMBA_CPU_FEATURES"] = target, ""
    p = subprocess.run([sys.executable, os.path.abspath(__file__), "--child"], env=env, capture_output=True,
                       text=True, check=True)
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[7:])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--child", action="store_true")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--targets", default="host,x86-64-v3,x86-64-v2,generic")
    a = ap.parse_args()
    if a.child:
        return child()
    targets = a.targets.split(",")
    base = tempfile.mkdtemp(prefix="cpu_target_")
    caches = {t: os.path.join(base, t) for t in targets}
    for t in targets:                                  # compile (not timed)
        print(f"compiling for {t} ...", file=sys.stderr, flush=True)
        run_child(t, caches[t])
    rounds = {t: [] for t in targets}
    for r in range(a.rounds):
        for t in targets:
            rounds[t].append(run_child(t, caches[t]))
        print(f"round {r + 1}: load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
    keys = ["statics_10", "dynamics_1s_10", "pan_tilt", "four_bar", "parallel"]
    print(f"load {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs; CPU time, median of "
          f"{a.rounds} rounds (best of each round's repeats); ratio to the host")
    print(f"{'target':12s} {'LLVM cpu':12s} " + " ".join(f"{k:>20s}" for k in keys) + f" {'|q - q_host|':>13s}")
    med = {t: {k: float(np.median([x[k] for x in rounds[t]])) for k in keys} for t in targets}
    q_host = np.array(rounds[targets[0]][0]["q_end"])
    for t in targets:
        cells = " ".join(f"{med[t][k] * 1e3:10.3f} ms {med[t][k] / med[targets[0]][k]:5.2f}x" for k in keys)
        dq = np.abs(np.array(rounds[t][0]["q_end"]) - q_host).max()
        print(f"{t:12s} {rounds[t][0]['cpu']:12s} {cells} {dq:13.2e}")


if __name__ == "__main__":
    main()
