"""Design studies on Dask (issue 16): 200 statics cases of the default robot,
serial against a local cluster of 1 and of 2 single-threaded worker
processes; the results must equal the serial run case by case.

Run: .venv/bin/python benchmarks/bench_study.py [--cases 200] [--repeat 3]

Times are those of the cases (first task submitted -> last result in), on a
cluster already started and with its workers' kernels loaded (that start-up
is printed apart); best of ``--repeat`` runs, with the 1-minute load
average before each, since the machine may be shared.
"""

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _timing import machine
from soft_twin_core.studies.cluster import META_COLUMNS, read_rows, run_study, start_local_cluster
from soft_twin_core.studies.study import study_from_dict

ROOT = Path(__file__).resolve().parents[1]


def bench_study(n):
    return study_from_dict({
        "name": "bench_200_statics", "scenario": "tendon_arm_statics",
        "parameters": [
            {"path": "segments[0].material.youngs_modulus", "range": [1.0e6, 4.0e6], "scale": "log"},
            {"path": "segments[2].cross_section.radius", "range": [0.006, 0.010]},
            {"path": "actuators[0].offset[0]", "range": [0.004, 0.010]},
            {"path": "scenario.actuation.tendon_y_pos", "range": [0.0, 4.0]}],
        "design": {"type": "lhs", "samples": n, "seed": 1},
        "compute": {"statics": {"points_per_section": 10}},
        "record": ["tip_pose", "base_wrench", "max_stress", "iterations", "residual", "stable"]},
        str(ROOT / "config" / "studies"))


def max_difference(a, b):
    worst = 0.0
    for ra, rb in zip(a, b):
        for k, x in ra.items():
            if k in META_COLUMNS:          # timings and the worker's name differ by nature
                continue
            y = rb[k]
            if isinstance(x, float):
                worst = max(worst, abs(x - y) / max(1.0, abs(x)))
            elif x != y:
                return float("inf")
    return worst


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    st = bench_study(args.cases)
    logging.getLogger("distributed").setLevel(logging.ERROR)     # two clusters: keep both quiet
    tmp = Path(tempfile.mkdtemp(prefix="bench_study_"))
    quiet = lambda m: None      # noqa: E731
    print(f"machine: {machine()}, {os.cpu_count()} CPUs; {args.cases} statics cases of the default robot")
    try:
        from soft_twin_core.studies.case import _warm
        _warm()
        times = {}
        best = float("inf")
        for _ in range(args.repeat):
            load = os.getloadavg()[0]
            res = run_study(st, tmp / "serial", serial=True, overwrite=True, log=quiet, summary=False)
            best = min(best, res["timing"]["compute_s"])
            print(f"  serial (this process): {res['timing']['compute_s']:.2f} s (load {load:.2f})")
        times["serial"] = best
        serial_rows = read_rows(tmp / "serial" / "results.parquet")
        clusters = {}
        try:
            for n in (1, 2):
                t0 = time.monotonic()
                cluster, client = start_local_cluster(n)
                t_start = time.monotonic() - t0
                t0 = time.monotonic()
                client.run(_warm)
                t_warm = time.monotonic() - t0
                clusters[n] = (cluster, client)
                print(f"  {n} worker(s): cluster started in {t_start:.2f} s, kernels loaded in {t_warm:.2f} s")
            # alternate 1 and 2 workers, so that a change of the machine's load hits both alike
            best = {1: float("inf"), 2: float("inf")}
            for rep in range(args.repeat):
                pair = {}
                for n in (1, 2):
                    load = os.getloadavg()[0]
                    res = run_study(st, tmp / f"dask{n}", client=clusters[n][1], overwrite=True, log=quiet,
                                    summary=False)
                    rows = read_rows(tmp / f"dask{n}" / "results.parquet")
                    diff = max_difference(serial_rows, rows)
                    per_case = sorted(r["compute_time_s"] for r in rows)
                    pair[n] = res["timing"]["compute_s"]
                    print(f"  {n} worker(s): {pair[n]:.2f} s (load {load:.2f}); {res['ok']} ok; "
                          f"max difference from serial {diff:.1e}; per case median "
                          f"{per_case[len(per_case) // 2] * 1e3:.1f} ms")
                    if diff > 1e-12 or res["ok"] != args.cases:
                        print("  MISMATCH with the serial run")
                        return 1
                    best[n] = min(best[n], pair[n])
                print(f"  repeat {rep + 1}: 2 workers {pair[1] / pair[2]:.2f}x faster than 1")
        finally:
            for cluster, client in clusters.values():
                client.close()
                cluster.close()
        times.update(best)
        print(f"best: serial {times['serial']:.2f} s, 1 worker {times[1]:.2f} s, 2 workers {times[2]:.2f} s; "
              f"speed-up 2 vs 1 workers: {times[1] / times[2]:.2f}x; load now {os.getloadavg()[0]:.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
