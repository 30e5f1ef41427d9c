"""The estimator node (python -m soft_twin.estimator) on a closed chain
(planar_parallel_robot: two steel rods clamped to one platform) in a second
process, this process playing the real robot over real rclpy: the same robot
with an unknown 1 N sideways push on its platform. The filter, with a pose
sensor on the platform and the tip force estimated (``wrench:=force``),
follows the pushed platform that the open-loop twin misses, and estimates
the push. Every wait is for a condition with a timeout."""

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import PoseStamped  # noqa: E402

from estimator_client import Client, stop_estimator  # noqa: E402
from soft_twin.conversions import pose_msg  # noqa: E402
from soft_twin_core.engine import algorithms as alg  # noqa: E402
from soft_twin_core.engine.workspace import Workspace  # noqa: E402
from soft_twin_core.estimation import sensors as ts  # noqa: E402
from soft_twin_core.robot.mechanism import load_mechanism  # noqa: E402
from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[2]
NS = "/closed_est_test"
PUSH = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])            # N, world, at the tip frame (rod2_tip, on the platform)
SENSORS = [{"name": "platform_pose", "type": "pose", "frame": "platform", "sigma_position": 2.0e-4,
            "sigma_rotation": 0.005}]
TOL = 0.001             # m


def _position(mech, q, frame):
    ref = mech.frame(frame)
    return alg.point_poses(mech.tree, Workspace(mech.tree), q, [ref.joint], [ref.x])[0][:3, 3]


def test_the_filter_follows_a_pushed_parallel_robot_and_estimates_the_push(tmp_path):
    (tmp_path / "sensors.yaml").write_text(yaml.safe_dump({"sensors": SENSORS}))
    log = open(tmp_path / "node.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "soft_twin.estimator", "--ros-args", "-r",
                             f"__node:={NS[1:]}", "-p", "robot_description_file:=planar_parallel_robot",
                             "-p", f"sensors_file:={tmp_path / 'sensors.yaml'}", "-p", "rate_hz:=50.0",
                             "-p", "wrench:=force"],
                            cwd=ROOT, env=os.environ.copy(), stdout=log, stderr=subprocess.STDOUT, text=True)
    client = Client(NS, "closed_chain_estimator_test_client", backbones=("rod1", "rod2"))
    stop = threading.Event()
    streamer = None
    try:
        assert client.wait_until(lambda: client.tip_count > 0 and client.pub_pose.get_subscription_count() > 0,
                                 120.0), "estimator node did not come up:\n" + (tmp_path / "node.log").read_text()[-3000:]
        mech = load_mechanism("planar_parallel_robot")
        truth = solve_equilibrium(mech, point_loads=[FrameLoad("rod2_tip", PUSH, "world")])
        rest = solve_equilibrium(mech)
        tip_true, tip_rest = _position(mech, truth.q, "rod2_tip"), _position(mech, rest.q, "rod2_tip")
        assert np.linalg.norm(tip_true - tip_rest) > 3 * TOL              # the open-loop twin misses it
        sensors = ts.sensors_from_list(SENSORS, mech)
        _, where = ts.check_sensors(mech, sensors)
        ws = Workspace(mech.tree)
        alg.forward_kinematics(mech.tree, ws, truth.q)
        z_true = ts.predict_measurement(ws, truth.q, sensors[0], where["platform_pose"])
        rng = np.random.default_rng(3)

        def stream():             # the platform's pose sensor at about 100 Hz (the publishing rate, not a wait)
            while not stop.is_set():
                ps = PoseStamped()
                ps.header.frame_id = "platform_pose"
                ps.pose = pose_msg(ts.simulate_measurement(sensors[0], z_true, rng))
                client.pub_pose.publish(ps)
                stop.wait(0.01)
        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()

        def settled(n=50):
            tips = client.tips[-n:]
            return len(tips) == n and np.median([np.linalg.norm(t - tip_true) for t in tips]) < TOL

        assert client.wait_until(lambda: client.diag and int(client.diag["measurements_accepted"]) > 200
                                 and settled(), 90.0), (client.tips[-1:], tip_true, client.diag)
        assert client.wait_until(lambda: client.wrench is not None, 10.0)
        f = client.wrench.wrench.force
        assert f.x == pytest.approx(PUSH[0], abs=0.2) and abs(f.z) < 0.5, (f.x, f.y, f.z)
        assert client.diag["integrator_failures"] == "0", client.diag
    finally:
        stop.set()
        if streamer is not None:     # (done publishing before the client's publisher is destroyed)
            streamer.join(10.0)
        client.close()
        stop_estimator(proc)
        log.close()
    out = (tmp_path / "node.log").read_text()
    assert proc.returncode == 0 and "Traceback" not in out, out[-3000:]
