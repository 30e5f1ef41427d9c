"""TwinClient.wait_ready returns only once every subscribed state topic has a
message, so that a caller can read client.backbone at once (`make demo`
crashed with "'NoneType' object has no attribute 'poses'" on a busy machine:
wait_ready had waited for the strains only).

A stand-in twin made of real rclpy entities (the node's service servers, its
input subscriptions and state publishers) publishes the strains but holds the
backbone back: wait_ready must time out, then return once a backbone came.
"""
import threading

import pytest

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseArray, PoseStamped, WrenchStamped   # noqa: E402
from rclpy.executors import SingleThreadedExecutor                   # noqa: E402
from sensor_msgs.msg import JointState                               # noqa: E402
from std_srvs.srv import SetBool, Trigger                            # noqa: E402

from soft_twin.client import TwinClient                              # noqa: E402
from soft_twin.msg import ActuationCommand, Strains                  # noqa: E402
from soft_twin.srv import ForwardKinematics, InverseKinematics, PlanPath, StaticsQuery   # noqa: E402

pytestmark = pytest.mark.ros


class StandInTwin:
    """A node named like a twin with its services and inputs; publishes on demand."""

    def __init__(self, name):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        n = self.node = rclpy.create_node(name, context=self.context)
        for srv, sname in ((ForwardKinematics, "forward_kinematics"), (InverseKinematics, "inverse_kinematics"),
                           (StaticsQuery, "statics_query"), (Trigger, "reset"), (PlanPath, "plan_path"),
                           (Trigger, "cancel_plan"), (SetBool, "pause"), (Trigger, "step")):
            n.create_service(srv, f"~/{sname}", lambda req, resp: resp)
        n.create_subscription(ActuationCommand, "~/actuation", lambda m: None, 10)
        n.create_subscription(WrenchStamped, "~/tip_wrench_command", lambda m: None, 10)
        n.create_subscription(JointState, "~/joint_commands", lambda m: None, 10)
        self.pubs = dict(strains=n.create_publisher(Strains, "~/strains", 10),
                         tip_pose=n.create_publisher(PoseStamped, "~/tip_pose", 10),
                         backbone=n.create_publisher(PoseArray, "~/backbone", 10))
        self.publishing = set()
        n.create_timer(0.02, self._tick)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:
            pass

    def _tick(self):
        for name in list(self.publishing):
            self.pubs[name].publish(dict(strains=Strains, tip_pose=PoseStamped, backbone=PoseArray)[name]())

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=5.0)


def test_wait_ready_waits_for_the_backbone_not_only_the_strains():
    twin = StandInTwin("stand_in_twin")
    client = TwinClient("stand_in_twin", client_name="stand_in_twin_client")
    try:
        twin.publishing = {"strains", "tip_pose"}
        assert client.wait_until(lambda: client.counts["strains"] > 0 and client.counts["tip_pose"] > 0, 30.0)
        with pytest.raises(TimeoutError):
            client.wait_ready(timeout=1.0)        # strains and tip pose arrive, no backbone yet
        assert client.backbone is None
        twin.publishing = {"strains", "tip_pose", "backbone"}
        client.wait_ready(timeout=30.0)
        assert client.backbone is not None and client.strains is not None and client.tip_pose is not None
    finally:
        client.close()
        twin.close()


def test_wait_ready_of_a_strains_only_client_needs_no_backbone():
    twin = StandInTwin("stand_in_twin_strains")
    client = TwinClient("stand_in_twin_strains", client_name="stand_in_strains_client", topics=("strains",))
    try:
        twin.publishing = {"strains"}
        client.wait_ready(timeout=30.0)
        assert client.strains is not None
    finally:
        client.close()
        twin.close()
