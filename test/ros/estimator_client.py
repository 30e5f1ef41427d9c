"""The estimator node's test client: publishers of the commands and
measurements, the estimates and the diagnostics as they arrive (a private
rclpy context spun in a thread), for the estimator tests of test/ros."""

import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from soft_twin.client import interrupt
from soft_twin.conversions import matrix_from_pose
from soft_twin.msg import ActuationCommand


class Client:
    """Publishers of the commands and measurements; the estimate and the
    diagnostics as they arrive (a private context, spun in a thread)."""

    def __init__(self, NS, name, backbones=("arm",)):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        n = self.node = rclpy.create_node(name, context=self.context)
        self.pub_joints = n.create_publisher(JointState, f"{NS}/measurements/joint_states", 50)
        self.pub_pose = n.create_publisher(PoseStamped, f"{NS}/measurements/pose", 50)
        self.pub_poses = n.create_publisher(PoseArray, f"{NS}/measurements/poses", 50)
        self.pub_ft = n.create_publisher(WrenchStamped, f"{NS}/measurements/base_wrench", 50)
        self.pub_act = n.create_publisher(ActuationCommand, "/soft_twin/actuation", 10)
        self.pub_cmd = n.create_publisher(JointState, "/soft_twin/joint_commands", 10)
        self.tip, self.joints, self.diag, self.tip_count = None, None, None, 0
        self.tips = []                                   # every estimated tool position received
        self.joint_log = []                              # every estimated joint-position dict received
        n.create_subscription(PoseWithCovarianceStamped, f"{NS}/estimate/tip_pose", self._on_tip, 10)
        n.create_subscription(JointState, f"{NS}/estimate/joint_states", self._on_joints, 10)
        self.backbones = {}                              # the last PoseArray of each backbone topic
        self.wrench = None
        n.create_subscription(WrenchStamped, f"{NS}/estimate/tip_wrench", self._on_wrench, 10)
        for topic, key in tuple((f"{NS}/estimate/backbones/{b}", b) for b in backbones) + ((f"{NS}/estimate/backbone",
                                                                                            "main"),):
            n.create_subscription(PoseArray, topic, lambda msg, key=key: self.backbones.__setitem__(key, msg), 10)
        n.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.reset = n.create_client(Trigger, f"{NS}/estimate/reset")
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:          # shutdown
            pass

    def _on_tip(self, msg):
        self.tips.append(matrix_from_pose(msg.pose.pose)[:3, 3])
        self.tip = msg
        self.tip_count += 1

    def _on_wrench(self, msg):
        self.wrench = msg

    def _on_joints(self, msg):
        self.joints = dict(zip(msg.name, msg.position))
        self.joint_log.append(self.joints)

    def _on_diag(self, msg):
        for s in msg.status:
            if s.name == "soft_twin_estimator":
                self.diag = {kv.key: kv.value for kv in s.values}

    @staticmethod
    def wait_until(pred, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            v = pred()
            if v:
                return v
            time.sleep(0.01)
        return pred()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def stop_estimator(proc):
    """SIGINT to the estimator's process (Ctrl-C), waited for; killed if it
    does not stop within 20 s."""
    interrupt(proc)
