"""The twin's frames on ``/tf`` (tf2_msgs/TFMessage): with the published
states, at most ``tf_rate_hz`` (default 50 Hz), every named frame of the
robot, the cross-section frames at every soft member's section boundaries,
and the tip, each as a child of ``base_frame`` (the robot description's
world frame), stamped like the state topics.

Frame ids: ``<prefix><frame>`` (links, member tips, user frames; a classic
rod's ``tip``), ``<prefix><member>_<i>`` (i = 0 at the member's base, i =
n_sections at its end; a classic rod's member is ``backbone``) and
``tip_frame`` (the tip pose topic's frame, so ``lookup_transform(base_frame,
tip_frame)`` gives exactly ``~/tip_pose``). The prefix is the ``tf_prefix``
parameter, by default the node's name and a slash
(``soft_twin/backbone_3``), so several twins share one /tf.

tf2_msgs comes from a ROS installation or, in the pinned venv, from the
set-up's build of interfaces/tf2_msgs (the ROS wheels on PyPI have none).
"""

import time

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from soft_twin.conversions import quaternions_from_matrices

# tf2_ros's TransformBroadcaster profile
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                    history=HistoryPolicy.KEEP_LAST)


def frame_prefix(tf_prefix, node_name):
    return tf_prefix if tf_prefix else f"{node_name}/"


def articulated_frames(snap, prefix, tip_frame):
    """(child frame id, pose) of a state: every named frame of the robot
    (links, member tips, user frames) as ``<prefix><name>``, every member's
    section boundaries as ``<prefix><member>_<i>`` (i = 0 at its base), and
    the tip as ``tip_frame``."""
    out = [(f"{prefix}{name}", g) for name, g in snap.frames.items()]
    k = snap.points_per_section
    for member, (poses, _) in snap.backbones.items():
        out += [(f"{prefix}{member}_{i}", g) for i, g in enumerate(poses[::k])]
    out.append((tip_frame, snap.tip_pose))
    return out


def tf_message(named_poses, header):
    """TFMessage of [(child, 4x4)] with the parent ``header.frame_id`` and its stamp."""
    T = np.array([p for _, p in named_poses], dtype=float)
    quats = quaternions_from_matrices(T[:, :3, :3]).tolist()
    msg = TFMessage()
    for (child, _), p, q in zip(named_poses, T[:, :3, 3].tolist(), quats):
        t = TransformStamped()
        t.header = header
        t.child_frame_id = child
        tr, ro = t.transform.translation, t.transform.rotation
        tr.x, tr.y, tr.z = p
        ro.x, ro.y, ro.z, ro.w = q
        msg.transforms.append(t)
    return msg


class TfOutput:
    """Publishes the frames of the published states on /tf at ``tf_rate_hz``."""

    def __init__(self, node):
        self._node = node
        self.publisher = node.create_publisher(TFMessage, "/tf", TF_QOS)
        self._last = -float("inf")

    def publish(self, snap, robot, header):
        """Broadcast the frames of a published state, at most ``tf_rate_hz``
        (a state is taken when 1/rate has passed since the last, less half a
        step: a 50 Hz rate takes every 4th state at 200 Hz)."""
        cfg = self._node.cfg
        now = time.monotonic()
        if cfg.tf_rate_hz <= 0 or now - self._last < 1.0 / cfg.tf_rate_hz - 0.5 * cfg.dt:
            return
        if not self._node.listened(self.publisher):       # no TF listener and no recording: nothing to build
            return
        self._last = now
        prefix = frame_prefix(cfg.tf_prefix, self._node.get_name())
        self.publisher.publish(tf_message(articulated_frames(snap, prefix, cfg.tip_frame), header))
