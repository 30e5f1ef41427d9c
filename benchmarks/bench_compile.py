"""Where a new process's no-cache start goes: numba's compilation of the engine (issue 10).

A child process with an empty ``NUMBA_CACHE_DIR`` runs what bench_engine.py's
item 5 times (import, the first statics solve and the first 1 s of dynamics of
the 10-section benchmark cantilever) while numba's event API records every
compilation (``numba:compile``, one per dispatcher and signature, nested when
a kernel's compilation compiles its callees) and the LLVM lock
(``numba:llvm_lock``: LLVM's optimisation and machine code). Printed:

  - the phases' wall times and the number of compilations;
  - per kernel, its exclusive compile time (its callees' compilations taken
    out), split into LLVM and numba's front end (bytecode analysis, type
    inference, lowering to LLVM IR: Python code);
  - for the entry points, numba's own pass timings (inclusive of the
    callees they compile): type inference, native lowering (which finalises
    the library: LLVM optimises and emits the kernel together with all its
    callees' code, linked in), IR inlining.

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_compile.py [--top 25] [--env NUMBA_OPT=0 ...]
(one run takes about as long as the compilation: 60-70 s on the project machine.)
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

from _timing import machine

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENTRY_POINTS = ("integrators.run_steps", "integrators.residual_pass", "static_newton.static_newton",
                "tangent.static_tangent_pass")

CHILD = r'''
import collections, json, sys, time
t0 = time.perf_counter()
from numba.core import event as ev
cm_c, cm_l = ev.install_recorder("numba:compile"), ev.install_recorder("numba:llvm_lock")
rec_c, rec_l = cm_c.__enter__(), cm_l.__enter__()      # (the context managers must stay referenced)
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
t1 = time.perf_counter()
m = from_robot_model(model_from_dict(benchmark_cantilever_dict(10, "all")))
solve_equilibrium(m)
t2 = time.perf_counter()
MechanismSimulator(m, 2e-3, tol=1e-4, max_iterations=10).step(n=500)
t3 = time.perf_counter()


def name_of(data):
    d = data["dispatcher"]
    return str(d.py_func.__module__).split(".")[-1] + "." + d.py_func.__qualname__


# exclusive time of each compilation (nested ones taken out) and the LLVM
# time spent while it was the innermost compilation
events = sorted([(ts, "c", e) for ts, e in rec_c.buffer] + [(ts, "l", e) for ts, e in rec_l.buffer],
                key=lambda x: x[0])
stack, excl, llvm, count = [], collections.Counter(), collections.Counter(), collections.Counter()
depth, l_start, owner, passes = 0, None, None, {}
for ts, kind, e in events:
    if kind == "c":
        if e.is_start:
            stack.append([name_of(e.data), ts, 0.0])
        else:
            name, t_s, child = stack.pop()
            excl[name] += ts - t_s - child
            count[name] += 1
            if stack:
                stack[-1][2] += ts - t_s
    elif e.is_start:
        depth += 1
        if depth == 1:
            l_start, owner = ts, (stack[-1][0] if stack else "(outside any compilation)")
    else:
        depth -= 1
        if depth == 0:
            llvm[owner] += ts - l_start
entry_points = json.loads(sys.argv[1])
for ts, e in rec_c.buffer:
    name = name_of(e.data)
    if e.is_start and name in entry_points and name not in passes:
        cres = next(iter(e.data["dispatcher"].overloads.values()))
        tot = collections.Counter()
        for pipe in cres.metadata.get("pipeline_times", {}).values():
            for k, v in pipe.items():
                tot[k.split("_", 1)[1]] += v.run
        passes[name] = dict(tot.most_common(4))
print(json.dumps({"import": t1 - t0, "statics": t2 - t1, "dynamics": t3 - t2,
                  "excl": excl, "llvm": llvm, "count": count, "passes": passes}))
'''


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=25, help="kernels listed, by exclusive compile time")
    ap.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE",
                    help="extra environment of the child (e.g. NUMBA_OPT=0)")
    args = ap.parse_args()
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    for kv in args.env:
        k, sep, v = kv.partition("=")
        if not sep:
            ap.error(f"--env wants NAME=VALUE, got {kv!r}")
        env[k] = v
    print(f"{machine()}, load {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs"
          + (f"; child environment {' '.join(args.env)}" if args.env else ""))
    with tempfile.TemporaryDirectory(prefix="numba_empty_") as d:
        env["NUMBA_CACHE_DIR"] = d
        p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(ENTRY_POINTS)], env=env, capture_output=True, text=True, cwd=ROOT)
    if p.returncode != 0:
        sys.exit(f"the child failed:\n{p.stderr}")
    r = json.loads(p.stdout.strip().splitlines()[-1])
    excl, llvm, count = r["excl"], r["llvm"], r["count"]
    total, total_llvm = sum(excl.values()), sum(llvm.values())
    print(f"import {r['import']:.1f} s, first statics {r['statics']:.1f} s, first 1 s of dynamics "
          f"{r['dynamics']:.1f} s (10 sections, 2 ms), empty numba cache")
    print(f"{sum(count.values())} compilations of {len(count)} kernels and numba overloads: {total:.1f} s, "
          f"of which LLVM {total_llvm:.1f} s and numba's front end {total - total_llvm:.1f} s")
    print(f"\n{'exclusive':>9} {'LLVM':>7} {'front':>7}  kernel (x compilations)")
    for name, t in sorted(excl.items(), key=lambda kv: -kv[1])[:args.top]:
        ll = llvm.get(name, 0.0)
        print(f"{t:8.2f}s {ll:6.2f}s {t - ll:6.2f}s  {name}" + (f" (x{count[name]})" if count[name] > 1 else ""))
    print("\nnumba's pass timings of the entry points (inclusive of the callees they compile) [s]:")
    for name in ENTRY_POINTS:
        ps = r["passes"].get(name)
        if ps:
            print(f"  {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in ps.items()))


if __name__ == "__main__":
    main()
