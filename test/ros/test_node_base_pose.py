"""A prescribed base carried at run time through the node (issue 29: an
arm on a manipulator's flange): ~/base_pose_command (geometry_msgs/
PoseStamped in the base frame) moves the base, checked at the door and
counted; the node in a second process, this process its client over real
rclpy."""

import math

import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from soft_twin.client import TwinClient, start_twin, stop_twin  # noqa: E402

pytestmark = pytest.mark.ros

ROBOT = """name: carried_arm
gravity: [0, 0, -9.81]
base: {motion: prescribed}
bodies:
  - name: arm
    type: member
    segments:
      - length: 0.2
        sections: 4
        cross_section: {shape: solid_circle, radius: 0.005}
        material: {youngs_modulus: 2.0e6, density: 1100, viscosity: 5.0}
        free_modes: bending
"""


def test_the_node_carries_a_prescribed_base_along_the_poses_it_is_sent(tmp_path):
    """Poses 0.5 mm apart along x, sent one after another (each waits for a
    state that reflects it, so the base moves in jerks: a step moved, some
    held): the backbone's first pose is the last one sent, 25 mm on; a pose in another frame is rejected (bad_frame), and
    one with a zero quaternion (non_finite), both counted; nothing fails."""
    from geometry_msgs.msg import PoseStamped
    name = "twin_carried"
    robot = tmp_path / "carried_arm.yaml"
    robot.write_text(ROBOT)
    proc, c = start_twin(name, ["-p", f"robot_description_file:={robot}", "-p", "diagnostics_rate_hz:=5.0"],
                         tmp_path / "node.log", TwinClient.TOPICS, 120.0)
    try:
        pub = c.node.create_publisher(PoseStamped, f"/{name}/base_pose_command", 10)
        assert c.wait_until(lambda: pub.get_subscription_count() > 0, 20.0)

        def pose(x, frame="base_link", w=1.0):
            msg = PoseStamped()
            msg.header.frame_id = frame
            msg.pose.position.x = x
            msg.pose.orientation.w = w
            return msg
        for k in range(1, 51):
            pub.publish(pose(0.0005 * k))
            assert c.wait_until(lambda: c.backbone is not None
                                and math.isclose(c.backbone.poses[0].position.x, 0.0005 * k, abs_tol=1e-9),
                                10.0), f"the base did not reach x = {0.0005 * k} m"
        pub.publish(pose(0.2, frame="world"))
        pub.publish(pose(0.2, w=0.0))
        d = c.wait_diagnostics(lambda d: d["rejected_base_pose_total"] == "2", 20.0)
        assert d is not None and d["rejected_bad_frame_total"] == "1" and d["rejected_non_finite_total"] == "1", d
        assert d["base_poses_received_total"] == "52" and d["base_poses_applied_total"] == "50", d
        assert d["solver_failures_total"] == "0" and d["internal_errors_total"] == "0", d
        assert abs(c.backbone.poses[0].position.x - 0.025) < 1e-9
    finally:
        stop_twin(proc, c)
