"""The state estimator on variable-strain segments (issue 28): its state,
its step's cost and its accuracy, against PCS filters of the same arm.

The arm: config/robots/tracked_arm.yaml (two segments, 0.24 + 0.16 m,
torsion and two bendings free, four tendons). Truth: the arm with 16 PCS
sections a segment (96 strains), simulated at a 2 ms step to a tight Newton
tolerance (1e-9) through the manoeuvre of test/unit/test_estimation.py (two
smooth tendon swings, then a 15 N step at 2 s; 3 s), observed by three
pose sensors (1 mm, 0.01 rad) at 100 Hz. Filters at 10 ms, a tip force
estimated, default noise settings: PCS with 3+2, 8+8 and 16+16 sections,
and the robot file's ``strain_basis: {type: legendre, order: p}`` on 8+8
and 16+16 sections (the same backbone; 3 (p + 1) coordinates a segment).

For each: the size of the covariance (2 nz + 3), the open-loop tip error
of its model (the same inputs, no readings; max over the run), the
filter's tip error (median and max after 0.2 s) and its CPU time a step
(predict + update, median of 3 runs).

Run: PYTHONPATH=. .venv/bin/python benchmarks/gvs_filter.py
"""

import time

import numpy as np

from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium

DT, STEPS = 0.01, 300
SENSORS = [sn.PoseSensor(f"em{i}", 1e-3, 0.01, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]
TIP = sn.PoseSensor("tip", 1.0, 1.0, s=0.40)


def arm(sections, order=None):
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for seg in d["segments"]:
        seg["sections"] = sections
        if order is not None:
            seg["strain_basis"] = {"type": "legendre", "order": order}
    return from_robot_model(model_from_dict(d))


def inputs(t):
    """Tendon tensions [N]: two smooth swings, then a 15 N step at 2 s."""
    if t < 2.0:
        return np.array([10 * (1 - np.cos(np.pi * t)), 0.0, 8 * (1 - np.cos(1.6 * np.pi * t)), 0.0])
    return np.array([0.0, 15.0, 0.0, 0.0])


def tip(mech, q):
    return sn.sensor_pose(mech, q, TIP)[:3, 3]


def simulate(mech):
    """Tip positions at the filter's times (2 ms steps, tight tolerance)."""
    sim = MechanismSimulator(mech, 0.002, q=solve_equilibrium(mech).q, tol=1e-9, max_iterations=30)
    out = []
    for _ in range(STEPS):
        for _ in range(5):
            sim.step(inputs(sim.t + 0.001))
        out.append((tip(mech, sim.q), sim.q.copy()))
    return out


def run_filter(mech, readings, tips):
    ekf = es.EKF(mech, SENSORS, DT, wrench="force")
    err = []
    t0 = time.process_time()
    for k in range(STEPS):
        ekf.predict(inputs((k + 0.5) * DT))
        ekf.update(readings[k])
        err.append(np.linalg.norm(ekf.tip_pose()[:3, 3] - tips[k]))
    return ekf.P.shape[0], np.array(err[20:]), (time.process_time() - t0) / STEPS


def main():
    truth = arm(16)
    states = simulate(truth)
    tips = [s[0] for s in states]
    rng = np.random.default_rng(7)
    readings = [{s.name: sn.simulate_measurement(s, sn.sensor_pose(truth, q, s), rng) for s in SENSORS}
                for _, q in states]
    print(f"{'filter':24s} {'state':>5s} {'open loop max':>14s} {'median':>8s} {'max':>8s} {'ms/step':>8s}")
    for label, mech in [("PCS 3+2 sections", arm_default()), ("PCS 8+8", arm(8)),
                        ("PCS 16+16", arm(16)), ("Legendre 2 on 8+8", arm(8, 2)),
                        ("Legendre 2 on 16+16", arm(16, 2)), ("Legendre 4 on 16+16", arm(16, 4))]:
        open_loop = max(np.linalg.norm(a[0] - b) for a, b in zip(simulate(mech), tips))
        runs = [run_filter(mech, readings, tips) for _ in range(3)]
        n, err, _ = runs[0]
        cpu = np.median([r[2] for r in runs])
        print(f"{label:24s} {n:5d} {open_loop * 1e3:11.3f} mm {np.median(err) * 1e3:5.2f} mm "
              f"{err.max() * 1e3:5.2f} mm {cpu * 1e3:8.2f}", flush=True)


def arm_default():
    """The robot file as it is (3 + 2 sections)."""
    return from_robot_model(model_from_dict(read_yaml_file(find_file("tracked_arm", "robots"))))


if __name__ == "__main__":
    main()
