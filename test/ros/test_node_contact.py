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
