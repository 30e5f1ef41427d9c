"""Estimation: time of one filter step (predict + update with three pose
sensors) of the 5-section tracked arm, per wrench mode; the node needs
>= 100 Hz (< 10 ms a step). Prints the machine's load (the numbers are
wall-clock times, so they grow with other processes on the machine).

Run: .venv/bin/python benchmarks/bench_estimation.py
"""

import os
import time

import numpy as np

from _timing import fmt, machine
from soft_twin_core import estimation as es
from soft_twin_core import sensors as sn
from soft_twin_core.model import load_model


def main():
    print(f"machine: {machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    model = load_model("tracked_arm")
    sensors = [sn.PoseSensor(f"em{i}", s, 1e-3, 0.01) for i, s in enumerate([0.16, 0.28, 0.40])]
    rng = np.random.default_rng(0)
    u = np.array([10.0, 0.0, 5.0, 0.0])
    for mode in (None, "payload", "wrench"):
        ekf = es.StrainEKF(model, sensors, 0.01, wrench=mode, actuation=u)
        T = [sn.sensor_pose(model, ekf.q, s) for s in sensors]
        meas = [{s.name: sn.simulate_measurement(Ts, s, rng) for s, Ts in zip(sensors, T)} for _ in range(50)]
        for m in meas[:5]:
            ekf.step(m, u)                                     # compile, warm up
        times = {"predict": [], "update": []}
        for m in meas:
            t0 = time.perf_counter()
            ekf.predict(u)
            t1 = time.perf_counter()
            ekf.update(m)
            t2 = time.perf_counter()
            times["predict"].append(t1 - t0)
            times["update"].append(t2 - t1)
        step = np.add(times["predict"], times["update"])
        print(f"5 sections ({model.n_dof} strain modes), wrench={mode!s:8} state {len(ekf.x):2d}: "
              f"step median {fmt(np.median(step))} (predict {fmt(np.median(times['predict']))}, "
              f"update {fmt(np.median(times['update']))}), best {fmt(step.min())} -> "
              f"{1 / np.median(step):6.0f} Hz median")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
