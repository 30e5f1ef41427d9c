"""Write the example calibration dataset of docs/estimation.md (issue 29):
a lab's sweep of known loads on the tracked arm, as CSV, and its sensors
file.

The "real" arm is the tracked arm at 4x the sections (32) with both
Young's moduli 30 % above the robot file's (2.6e7 Pa instead of 2.0e7);
three markers on the backbone (0.16, 0.28, 0.40 m) read it with 0.3 mm
noise. No tendon is pulled. Twelve rows: weights hung on the tip (0 to
200 g, column ``mass:tip [kg]``) and a force gauge pushing the backbone's
point at 0.2 m sideways or up (``wrench:backbone@0.2.fy [N]``, ``.fz``).
Fitting ``youngs_modulus`` on the 8-section twin recovers 2.6e7 within
2 % (test/unit/test_calibration_known_loads.py).

    PYTHONPATH=. .venv/bin/python scripts/calibration_example.py [DIR]   (default docs/data)
"""

import sys
from pathlib import Path

import numpy as np
import yaml

from soft_twin_core.estimation import calibration as cal
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file

TRUE_E = 2.6e7                     # Pa: 1.3 x the robot file's 2.0e7, both segments
CSV_NAME, SENSORS_NAME = "known_loads.csv", "known_loads_sensors.yaml"


def nominal():
    """The tracked arm's robot mapping (the moduli as floats)."""
    d = read_yaml_file(find_file("tracked_arm", "robots"))
    for s in d["segments"]:
        s["material"]["youngs_modulus"] = float(s["material"]["youngs_modulus"])
    return d


def markers():
    return [sn.marker(f"mk{i}", 3e-4, s=s) for i, s in enumerate([0.16, 0.28, 0.40])]


def experiment():
    """(tip masses [kg] (12,), gauge wrenches at backbone@0.2 (12, 6) [N])."""
    m = np.array([0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.0, 0.0, 0.0, 0.0, 0.05, 0.1])
    F = np.zeros((len(m), 6))
    F[6:8, 1] = [0.3, 0.6]
    F[8, 1] = -0.3
    F[9, 2] = 0.5
    F[10:12, 1] = [0.4, -0.4]
    return m, F


def record(seed=3):
    """The experiment on the true arm: a calibration.Recording."""
    d = nominal()
    for s in d["segments"]:
        s["material"]["youngs_modulus"] = TRUE_E
    truth = from_robot_model(model_from_dict(d, 16), d)
    m, F = experiment()
    W_tip = np.zeros((len(m), 6))
    W_tip[:, :3] = m[:, None] * np.asarray(truth.tree.gravity, dtype=float)
    return cal.record_static_sweep(truth, markers(), np.zeros((len(m), 4)), np.random.default_rng(seed),
                                   wrenches={("tip", "world"): W_tip, ("backbone@0.2", "world"): F})


def write_example(directory):
    """Write the CSV (as a lab logs it: the weights in kg, the gauge in N,
    readings to 0.01 mm) and the sensors file into ``directory``; returns
    their paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rec = record()
    m, F = experiment()
    names = [f"{s.name}.{c}" for s in markers() for c in "xyz"]
    head = ["t [s]", "tendon_y_pos [N]", "tendon_y_neg [N]", "tendon_z_pos [N]", "tendon_z_neg [N]",
            "mass:tip [kg]", "wrench:backbone@0.2.fy [N]", "wrench:backbone@0.2.fz [N]"] + [f"{n} [m]" for n in names]
    lines = [",".join(head)]
    for r in range(len(m)):
        z = np.concatenate([rec.readings[s.name][r] for s in markers()])
        lines.append(",".join([f"{10.0 * r:g}", "0", "0", "0", "0", f"{m[r]:g}", f"{F[r, 1]:g}", f"{F[r, 2]:g}"]
                              + [f"{x:.5f}" for x in z]))
    csv_path, sensors_path = directory / CSV_NAME, directory / SENSORS_NAME
    csv_path.write_text("\n".join(lines) + "\n")
    sensors_path.write_text("# The markers of docs/data/known_loads.csv (scripts/calibration_example.py)\n"
                            + yaml.safe_dump({"sensors": sn.sensors_to_list(markers())}, sort_keys=False))
    return csv_path, sensors_path


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "docs" / "data"
    for p in write_example(out):
        print(f"wrote {p}")
