"""The estimator node (python -m soft_twin.estimator) on an arm whose base is
prescribed (issue 29: carried by a manipulator), in a second process: it
takes the base's pose from the twin's ~/base_pose_command topic (checked as
the twin checks it) and carries its estimate along; this process publishes
over real rclpy. Every wait is for a condition with a timeout."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import PoseStamped  # noqa: E402

from estimator_client import Client, stop_estimator  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[2]
NS = "/carried_est_test"
ROBOT = {"name": "carried_arm", "gravity": [0, 0, -9.81], "base": {"motion": "prescribed"},
         "bodies": [{"name": "arm", "type": "member", "segments": [{
             "length": 0.2, "sections": 4, "cross_section": {"shape": "solid_circle", "radius": 0.005},
             "material": {"youngs_modulus": 2.0e8, "density": 1100, "viscosity": 5.0}, "free_modes": "bending"}]}]}
SENSORS = [{"name": "em_tip", "type": "pose", "frame": "arm_tip", "sigma_position": 1.0e-3, "sigma_rotation": 0.01}]


def test_the_estimator_carries_a_prescribed_base_along_the_poses_sent(tmp_path):
    """Base poses 1 mm apart along x at the filter's rate: the estimated
    backbone's first pose reaches the last one sent (x = 50 mm) and its
    tip follows; a pose in another frame is rejected and counted."""
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(ROBOT))
    (tmp_path / "sensors.yaml").write_text(yaml.safe_dump({"sensors": SENSORS}))
    log = open(tmp_path / "node.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "soft_twin.estimator", "--ros-args", "-r",
                             f"__node:={NS[1:]}", "-p", f"robot_description_file:={tmp_path / 'robot.yaml'}",
                             "-p", f"sensors_file:={tmp_path / 'sensors.yaml'}", "-p", "rate_hz:=50.0"],
                            cwd=ROOT, env=os.environ.copy(), stdout=log, stderr=subprocess.STDOUT, text=True)
    c = Client(NS, "carried_estimator_test_client")
    try:
        pub = c.node.create_publisher(PoseStamped, "/soft_twin/base_pose_command", 10)
        ok = c.wait_until(lambda: c.tip_count > 0 and pub.get_subscription_count() > 0, 120.0)
        assert ok, "estimator node did not come up:\n" + (tmp_path / "node.log").read_text()[-3000:]

        def pose(x, frame="base_link"):
            msg = PoseStamped()
            msg.header.frame_id = frame
            msg.pose.position.x = x
            msg.pose.orientation.w = 1.0
            return msg
        start = c.tips[-1][0]
        for k in range(1, 51):
            pub.publish(pose(0.001 * k))
            n = c.tip_count
            assert c.wait_until(lambda: c.tip_count > n + 1, 10.0)         # a filter step with it
        assert c.wait_until(lambda: "main" in c.backbones
                            and abs(c.backbones["main"].poses[0].position.x - 0.05) < 1e-9, 10.0), \
            "the estimate's base did not reach x = 50 mm"
        assert abs(c.tips[-1][0] - start - 0.05) < 3e-3, "the tip did not follow"    # (a stiff arm: sags 1.7 mm)
        pub.publish(pose(0.06, frame="world"))
        assert c.wait_until(lambda: c.diag is not None and c.diag.get("rejected_base_pose") == "1", 20.0), c.diag
        assert "frame_id" in c.diag["last_rejection"] and c.diag["integrator_failures"] == "0", c.diag
    finally:
        c.close()
        stop_estimator(proc)
        log.close()
    out = (tmp_path / "node.log").read_text()
    assert proc.returncode == 0 and "Traceback" not in out, out[-3000:]
