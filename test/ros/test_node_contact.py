"""The node with a robot lying on a table (issue 27), end to end: the node
in a second process, this process its client over real rclpy. It steps in
dynamic mode without failures, counts its active contacts in the
diagnostics, and draws the table and an arrow per contact in ~/markers."""

import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from soft_twin.client import TwinClient, start_twin, stop_twin  # noqa: E402

pytestmark = pytest.mark.ros


def test_the_arm_on_a_table_steps_and_shows_its_contacts(tmp_path):
    from visualization_msgs.msg import Marker, MarkerArray
    name = "twin_on_table"
    proc, c = start_twin(name, ["-p", "robot_description_file:=tendon_arm_on_table",
                                "-p", "diagnostics_rate_hz:=5.0"], tmp_path / "node.log", TwinClient.TOPICS, 120.0)
    try:
        got = c.subscribe(MarkerArray, f"/{name}/markers", depth=5)
        d = c.wait_diagnostics(lambda d: float(d["twin_time_s"]) > 1.0 and int(d["contacts_active"]) > 0, 30.0)
        assert d is not None, "the arm did not come to lie on the table"
        assert d["solver_failures_total"] == "0" and d["internal_errors_total"] == "0", d
        assert c.wait_until(lambda: any(m.ns == "contacts" and m.action == Marker.ADD
                                        for m in got[-1].markers) if got else False, 10.0), "no contact arrows"
        ms = got[-1].markers
        table = [m for m in ms if m.ns == "obstacles"]
        assert len(table) == 1 and table[0].type == Marker.CUBE
        assert abs(table[0].pose.position.z - (-0.0505)) < 1e-9          # the table top, less half its thickness
        arrows = [m for m in ms if m.ns == "contacts" and m.action == Marker.ADD]
        assert all(a.points[1].z > a.points[0].z for a in arrows)          # the table pushes up
    finally:
        stop_twin(proc, c)


def test_obstacles_from_a_file_and_the_obstacles_topic_and_the_contacts_they_make(tmp_path):
    """The default arm (tip drooping to z = -0.297 m) with a floor from
    ``obstacles_file`` at z = -0.29 m: it rests on it, ~/contacts says where;
    REMOVE takes the floor away (no contacts); a sphere ADDed under the tip
    is touched; a MOVE of an unknown name is rejected and counted."""
    from geometry_msgs.msg import Pose, PoseStamped
    from shape_msgs.msg import SolidPrimitive
    from soft_twin.msg import Contacts, Obstacle
    name = "twin_obstacles"
    f = tmp_path / "floor.yaml"
    f.write_text("obstacles:\n  - {name: floor, type: plane, point: [0, 0, -0.29], normal: [0, 0, 1]}\n")
    proc, c = start_twin(name, ["-p", f"obstacles_file:={f}", "-p", "diagnostics_rate_hz:=5.0"],
                         tmp_path / "node.log", TwinClient.TOPICS, 120.0)
    try:
        got = c.subscribe(Contacts, f"/{name}/contacts", depth=5)
        pub = c.node.create_publisher(Obstacle, f"/{name}/obstacles", 10)
        assert c.wait_until(lambda: pub.get_subscription_count() > 0, 20.0)
        assert c.wait_until(lambda: bool(got and got[-1].contacts), 20.0), "no contact with the floor"
        cs = got[-1].contacts
        assert {x.obstacle for x in cs} == {"floor"} and all(x.normal_force > 0 for x in cs)
        assert got[-1].header.frame_id == "base_link" and all(abs(x.normal.z - 1) < 1e-9 for x in cs)

        pub.publish(Obstacle(name="floor", operation=Obstacle.REMOVE))
        assert c.wait_diagnostics(lambda d: d["obstacles"] == "0", 20.0) is not None
        assert c.wait_until(lambda: bool(got) and not got[-1].contacts, 20.0), "the floor's contacts stayed"

        # the tip, let go, swings about its hanging pose (7 mm up and down at first): the ball goes where the
        # tip comes to rest, not wherever one reading caught it; and on the tip's axis (its frame's x, the
        # backbone's tangent; the tip hangs tilted ~60 degrees): 2 mm into its flat end face
        tips = c.subscribe(PoseStamped, f"/{name}/tip_pose", depth=50)

        def at_rest(n=60, tol=3e-4):   # the last n tip poses (0.3 s at 200 Hz) within 0.3 mm in x and in z
            xz = [(m.pose.position.x, m.pose.position.z) for m in tips[-n:]]
            return len(xz) == n and all(max(v) - min(v) < tol for v in zip(*xz))
        assert c.wait_until(at_rest, 30.0), "the tip did not come to rest after the floor went"
        tip = tips[-1].pose
        q = tip.orientation
        axis = (1 - 2 * (q.y ** 2 + q.z ** 2), 2 * (q.x * q.y + q.w * q.z), 2 * (q.x * q.z - q.w * q.y))
        ball = Obstacle(name="ball", operation=Obstacle.ADD, pose=Pose(),
                        primitive=SolidPrimitive(type=SolidPrimitive.SPHERE, dimensions=[0.03]))
        p = tip.position
        ball.pose.position.x, ball.pose.position.y, ball.pose.position.z = (
            x0 + (0.03 - 0.002) * a for x0, a in zip((p.x, p.y, p.z), axis))
        ball.pose.orientation.w = 1.0
        pub.publish(ball)
        assert c.wait_until(lambda: bool(got and got[-1].contacts)
                            and {x.obstacle for x in got[-1].contacts} == {"ball"}, 20.0), "the ball is not touched"

        pub.publish(Obstacle(name="ghost", operation=Obstacle.MOVE))
        d = c.wait_diagnostics(lambda d: d["rejected_obstacle_total"] == "1", 20.0)
        assert d is not None and d["rejected_unknown_name_total"] == "1" and "ghost" in d["last_rejection"]
        assert d["obstacle_updates_received_total"] == "3" and d["obstacle_updates_applied_total"] == "2", d
        assert d["solver_failures_total"] == "0" and d["internal_errors_total"] == "0", d
    finally:
        stop_twin(proc, c)
