"""Calibration from a recording made by the estimator node itself: the node
(python -m soft_twin.estimator, ``record_file``) runs in a second process
and records every command and measurement it receives; this process plays a
static sweep of the "real" arm (the tracked arm with its Young's modulus 30
% above the twin's) over real rclpy: the twin's actuation commands and the
three pose sensors (PoseArray, 1 mm and 0.01 rad noise), stamped by the
sensors' clock. ``soft-twin-sim calibrate --data run.mcap`` then recovers
the modulus within 2 %. Every wait is for a condition with a timeout."""

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from soft_twin.conversions import pose_array  # noqa: E402
from estimator_client import Client, stop_estimator  # noqa: E402
from soft_twin.msg import ActuationCommand  # noqa: E402
from soft_twin_core.cli import main as cli_main  # noqa: E402
from soft_twin_core.estimation import sensors as sn  # noqa: E402
from soft_twin_core.robot.mechanism import from_robot_model  # noqa: E402
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file  # noqa: E402
from rod_statics import solve_statics

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[2]
NS = "/est_rec_test"
NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]
SENSORS = [{"name": f"em{i}", "type": "pose", "s": s, "sigma_position": 1.0e-3, "sigma_rotation": 0.01}
           for i, s in enumerate([0.16, 0.28, 0.40])]
T0, HOLD_S, READINGS = 1_700_000_000, 1.0, 10


def _sweep():
    U = []
    for k in range(4):
        for T in (8.0, 16.0):
            u = np.zeros(4)
            u[k] = T
            U.append(u)
    for a, b in ((0, 2), (1, 3)):
        u = np.zeros(4)
        u[[a, b]] = 12.0
        U.append(u)
    return np.array(U)


def _stamp(msg, t):
    ns = int(round(t * 1e9))
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return msg


def test_estimator_node_records_a_sweep_that_calibrates(tmp_path, capsys):
    (tmp_path / "sensors.yaml").write_text(yaml.safe_dump({"sensors": SENSORS}))
    record = tmp_path / "run.mcap"
    log = open(tmp_path / "node.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "soft_twin.estimator", "--ros-args", "-r",
                             f"__node:={NS[1:]}", "-p", "robot_description_file:=tracked_arm",
                             "-p", f"sensors_file:={tmp_path / 'sensors.yaml'}", "-p", f"record_file:={record}"],
                            cwd=ROOT, env=os.environ.copy(), stdout=log, stderr=subprocess.STDOUT, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("estimator_recording_client", context=ctx)
    pub_poses = node.create_publisher(PoseArray, f"{NS}/measurements/poses", 50)
    pub_act = node.create_publisher(ActuationCommand, "/soft_twin/actuation", 50)
    diag = {}

    def on_diag(msg):
        for s in msg.status:
            if s.name == "soft_twin_estimator":
                diag.update({kv.key: kv.value for kv in s.values})
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    th = threading.Thread(target=lambda: _spin(ex), daemon=True)
    th.start()
    try:
        assert Client.wait_until(lambda: pub_poses.get_subscription_count() > 0 and pub_act.get_subscription_count() > 0
                           and "recorded_inputs" in diag, 120.0), (tmp_path / "node.log").read_text()[-3000:]
        d = read_yaml_file(find_file("tracked_arm", "robots"))
        for seg in d["segments"]:
            seg["material"]["youngs_modulus"] = 1.3 * float(seg["material"]["youngs_modulus"])
        real = model_from_dict(d)
        real_mech = from_robot_model(real)
        sensors = sn.sensors_from_list(SENSORS, real_mech)
        rng = np.random.default_rng(8)
        sent, q = 0, None
        for k, u in enumerate(_sweep()):
            q = solve_statics(real, u, q_init=q).q
            T = [sn.sensor_pose(real_mech, q, s) for s in sensors]
            tc = T0 + k * HOLD_S
            pub_act.publish(_stamp(ActuationCommand(names=NAMES, values=[float(x) for x in u]), tc))
            sent += 1
            for j in range(READINGS):
                z = np.array([sn.simulate_measurement(s, Ti, rng) for Ti, s in zip(T, sensors)])
                pub_poses.publish(_stamp(pose_array(z), tc + (j + 0.5) * HOLD_S / READINGS))
                sent += 1
                time.sleep(0.004)         # the publishing rate (250 Hz), not a wait for ROS
        assert Client.wait_until(lambda: int(diag.get("recorded_inputs", 0)) >= sent, 30.0), (sent, diag)
        assert int(diag["recorded_inputs"]) == sent
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        stop_estimator(proc)
        log.close()
    out = (tmp_path / "node.log").read_text()
    assert proc.returncode == 0 and "Traceback" not in out, out[-3000:]
    assert "recording closed" in out
    code = cli_main(["calibrate", "tracked_arm", "--sensors", str(tmp_path / "sensors.yaml"), "--data", str(record),
                     "--measurements-ns", NS, "--fit", "youngs_modulus", "--holdout-every", "4"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    rep = json.loads(cap.out)
    print(cap.err)
    for name in ("youngs_modulus:proximal", "youngs_modulus:distal"):
        assert rep["parameters"][name]["fitted"] == pytest.approx(2.6e7, rel=0.02), cap.err
    assert rep["recording"]["rows"] == len(_sweep()) and rep["recording"]["skipped"] == {}
    assert rep["heldout"]["tip_rms_after_m"] < rep["heldout"]["tip_rms_before_m"]


def _spin(ex):
    try:
        ex.spin()
    except Exception:          # shutdown
        pass
