"""Estimation: time of one filter step (predict + update) of
:class:`soft_twin_core.estimation.ekf.EKF` on the 5-section tracked arm (a
classic rod, three pose sensors) per wrench mode, and on the pan-tilt arm
(a soft member on two position-controlled joints: encoders and two pose
sensors); the node needs >= 100 Hz (< 10 ms a step). Prints the machine's
load (the numbers are wall-clock times, so they grow with other processes
on the machine).

Run: .venv/bin/python benchmarks/bench_estimation.py
"""

import os
import time

import numpy as np

from _timing import fmt, machine
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import load_mechanism


def _case(robot):
    mech = load_mechanism(robot)
    if robot == "tracked_arm":
        sensors = [sn.PoseSensor(f"em{i}", 1e-3, 0.01, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]
        return mech, sensors, {"actuation": [10.0, 0.0, 5.0, 0.0]}
    sensors = [sn.JointStateSensor("encoders", ("pan", "tilt"), np.array([1e-3, 1e-3])),
               sn.PoseSensor("em_mid", 1e-3, 0.01, member="arm", s=0.15),
               sn.PoseSensor("em_tool", 1e-3, 0.01, frame="tool")]
    return mech, sensors, {"actuation": [4.0, 0.0, 0.0, 0.0], "positions": {"pan": 0.3, "tilt": -0.2}}


def main():
    print(f"machine: {machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    rng = np.random.default_rng(0)
    for robot, modes in (("tracked_arm", (None, "payload", "wrench")), ("pan_tilt_arm", (None, "payload"))):
        mech, sensors, inputs = _case(robot)
        for mode in modes:
            ekf = es.EKF(mech, sensors, 0.01, wrench=mode, **inputs)
            _, where = sn.check_sensors(mech, sensors)
            clean = sn.predict_readings(Workspace(mech.tree), ekf.q, sensors, where)
            meas = [{s.name: sn.simulate_measurement(s, clean[s.name], rng) for s in sensors} for _ in range(50)]
            for m in meas[:5]:
                ekf.step(m)                                     # compile, warm up
            times = {"predict": [], "update": []}
            for m in meas:
                t0 = time.perf_counter()
                ekf.predict()
                t1 = time.perf_counter()
                ekf.update(m)
                t2 = time.perf_counter()
                times["predict"].append(t1 - t0)
                times["update"].append(t2 - t1)
            step = np.add(times["predict"], times["update"])
            print(f"{robot:12s} ({ekf.n:2d} coordinates), wrench={mode!s:8} state {len(ekf.x):2d}: "
                  f"step median {fmt(np.median(step))} (predict {fmt(np.median(times['predict']))}, "
                  f"update {fmt(np.median(times['update']))}), best {fmt(step.min())} -> "
                  f"{1 / np.median(step):6.0f} Hz median")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
