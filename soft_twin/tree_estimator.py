"""The estimator node's side for soft articulated robots (a tree robot
file, e.g. ``pan_tilt_arm``): :class:`soft_twin_core.tree_estimation.TreeEKF`
with the sensors of :mod:`soft_twin_core.tree_sensors`, on the
``soft_twin_estimator`` node (:mod:`soft_twin.estimator` hands over to
:class:`TreeEstimation` when ``robot_description_file`` is a tree file).

Subscriptions (next to the classic ones): ``~/measurements/joint_states``
(sensor_msgs/JointState: the positions of the joints of the sensors file's
``joint_state`` sensors; a sensor takes a reading when the message names
all its joints), ``~/measurements/pose`` (PoseStamped, ``frame_id`` = a
pose sensor's name), ``~/measurements/poses`` (PoseArray, one pose per
pose sensor in file order), ``~/measurements/position`` (PointStamped, a
marker's name), ``~/measurements/base_wrench`` (geometry_msgs/WrenchStamped:
the reading of the sensors file's ``base_wrench`` sensor, the support's
wrench on the robot in world axes about the base origin), the actuation
topic and ``joint_command_topic`` (default
``/soft_twin/joint_commands``: the twin's joint commands, positions of
position-controlled joints and efforts of effort-controlled ones).

Rejected and counted (``rejected_<kind>`` in the diagnostics): a JointState
naming a joint the robot does not have (``unknown_joint``), with a
different number of names and positions (``wrong_length``), with a NaN
position of a measured joint (``non_finite``); poses as in the classic
node.

Publications: ``~/estimate/tip_pose`` (PoseWithCovarianceStamped of the
tip frame, ``soft_twin_core.mechanism.tip_frame``: position covariance,
m^2), ``~/estimate/joint_states`` (JointState: positions and velocities
of the rigid joints), ``~/estimate/backbone/<member>`` (PoseArray per soft
member), the filter's health on ``/diagnostics``.
"""

import math

import numpy as np
from geometry_msgs.msg import PointStamped, PoseArray, PoseStamped, PoseWithCovarianceStamped, WrenchStamped
from sensor_msgs.msg import JointState

from soft_twin import conversions as cv
from soft_twin_core.commands import parse_joint_command
from soft_twin_core.mechanism import tip_frame
from soft_twin.msg import ActuationCommand
from soft_twin.readings import STAMP_REJECTIONS, accept_reading
from soft_twin_core.commands import InputError
from soft_twin_core import tree_estimation as te
from soft_twin_core import tree_sensors as ts

REJECTION_KINDS = ("non_finite", "malformed", "wrong_length", "unknown_sensor", "unknown_joint", "actuation",
                   "joint_command") + STAMP_REJECTIONS


class TreeEstimation:
    """Subscriptions, filter and publications of the estimator node for a tree robot."""

    def __init__(self, node, mech, sensors_file, rate, frame_id, actuation_topic, joint_command_topic):
        self.node, self.mech, self.frame_id = node, mech, frame_id
        self.sensors = ts.load_tree_sensors(sensors_file, mech)
        self.pose_sensors = [s for s in self.sensors if isinstance(s, ts.FramePoseSensor) and not s.position_only]
        self.joint_sensors = [s for s in self.sensors if isinstance(s, ts.JointStateSensor)]
        self.wrench_sensors = [s for s in self.sensors if isinstance(s, ts.BaseWrenchSensor)]
        self.ekf = te.TreeEKF(mech, self.sensors, 1.0 / rate)
        self.tip = tip_frame(mech)
        self.rejections = dict.fromkeys(REJECTION_KINDS, 0)
        self.last_rejection = ""
        self.cmd_pos, self.cmd_eff = {}, {}
        n = node
        self.pub_tip = n.create_publisher(PoseWithCovarianceStamped, "~/estimate/tip_pose", 10)
        self.pub_joints = n.create_publisher(JointState, "~/estimate/joint_states", 10)
        self.pub_backbones = {m.name: n.create_publisher(PoseArray, f"~/estimate/backbone/{m.name}", 10)
                              for m in mech.members}
        n.create_subscription(JointState, "~/measurements/joint_states", self.on_joint_states, 50)
        n.create_subscription(PoseArray, "~/measurements/poses", self.on_poses, 50)
        n.create_subscription(PoseStamped, "~/measurements/pose", self.on_pose, 50)
        n.create_subscription(PointStamped, "~/measurements/position", self.on_position, 50)
        n.create_subscription(WrenchStamped, "~/measurements/base_wrench", self.on_base_wrench, 50)
        n.create_subscription(ActuationCommand, actuation_topic, self.on_actuation, 50)
        n.create_subscription(JointState, joint_command_topic, self.on_joint_command, 50)

    # ------------------------------------------------------------------ inputs
    def reject(self, kind, reason):
        self.rejections[kind] += 1
        self.last_rejection = reason
        self.node.get_logger().warn(f"measurement rejected: {reason}", throttle_duration_sec=1.0)

    def accept(self, sensor, reading, stamp):
        """Validate ``reading()`` for the sensor and its stamp (the node's ledger,
        :mod:`soft_twin.readings`); an accepted one waits for the next filter step."""
        accept_reading(self.node.ledger, self.reject, sensor.name, lambda: ts.measurement_vector(sensor, reading()),
                       stamp, self.node.get_clock().now().nanoseconds)

    def on_joint_states(self, msg):
        names, pos = list(msg.name), list(msg.position)
        if len(names) != len(pos):
            self.reject("wrong_length", f"joint_states: {len(names)} names but {len(pos)} positions")
            return
        unknown = [x for x in names if x not in self.mech.joint_names]
        if unknown:
            self.reject("unknown_joint", f"joint_states: unknown joint(s) {unknown}; this robot has "
                                         f"{list(self.mech.joint_names)}")
            return
        value = dict(zip(names, pos))
        for s in self.joint_sensors:
            if all(j in value for j in s.joints):
                self.accept(s, lambda s=s: np.array([value[j] for j in s.joints], dtype=float), msg.header.stamp)

    def on_poses(self, msg):
        if len(msg.poses) != len(self.pose_sensors):
            self.reject("wrong_length", f"poses: expected {len(self.pose_sensors)} poses (one per pose sensor "
                                        f"{[s.name for s in self.pose_sensors]}), got {len(msg.poses)}")
            return
        for s, pose in zip(self.pose_sensors, msg.poses):
            self.accept(s, lambda pose=pose: cv.matrix_from_pose(pose), msg.header.stamp)

    def on_pose(self, msg):
        s = self.ekf.by_name.get(msg.header.frame_id)
        if not (isinstance(s, ts.FramePoseSensor) and not s.position_only):
            self.reject("unknown_sensor", f"pose: unknown pose sensor {msg.header.frame_id!r}; "
                                          f"configured: {[x.name for x in self.pose_sensors]}")
            return
        self.accept(s, lambda: cv.matrix_from_pose(msg.pose), msg.header.stamp)

    def on_position(self, msg):
        s = self.ekf.by_name.get(msg.header.frame_id)
        if not (isinstance(s, ts.FramePoseSensor) and s.position_only):
            self.reject("unknown_sensor", f"position: unknown marker {msg.header.frame_id!r}")
            return
        self.accept(s, lambda: np.array([msg.point.x, msg.point.y, msg.point.z]), msg.header.stamp)

    def on_base_wrench(self, msg):
        if not self.wrench_sensors:
            self.reject("unknown_sensor", "base_wrench: no base_wrench sensor in the sensors file")
            return
        f, t = msg.wrench.force, msg.wrench.torque
        self.accept(self.wrench_sensors[0], lambda: np.array([f.x, f.y, f.z, t.x, t.y, t.z], dtype=float),
                    msg.header.stamp)

    def on_actuation(self, msg):
        names = list(self.mech.actuator_names)
        u = self.ekf.u.copy()
        if len(msg.names) != len(msg.values):
            self.reject("actuation", f"actuation: {len(msg.names)} names but {len(msg.values)} values")
            return
        for n, v in zip(msg.names, msg.values):
            if n not in names or not math.isfinite(v):
                self.reject("actuation", f"actuation: bad entry {n!r} = {v!r}")
                return
            u[names.index(n)] = v
        self.ekf.u = u

    def on_joint_command(self, msg):
        try:
            pos, eff = parse_joint_command(self.mech, msg.name, msg.position, msg.velocity, msg.effort,
                                           self.cmd_pos, self.cmd_eff)
            self.ekf.set_inputs(positions=pos or None, efforts=eff or None)
        except (InputError, ValueError) as e:
            self.reject("joint_command", f"joint command: {e}")
            return
        self.cmd_pos, self.cmd_eff = pos, eff

    def reset(self):
        self.ekf.reset()
        self.cmd_pos, self.cmd_eff = {}, {}
        self.rejections = dict.fromkeys(REJECTION_KINDS, 0)
        self.last_rejection = ""

    # ----------------------------------------------------------------- filter
    def on_timer(self):
        self.ekf.predict()
        self.ekf.update(self.node.ledger.take())
        stamp = self.node.get_clock().now().to_msg()
        msg = PoseWithCovarianceStamped()
        msg.header.stamp, msg.header.frame_id = stamp, self.frame_id
        msg.pose.pose = cv.pose_msg(self.ekf.frame_pose(self.tip))
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.ekf.frame_position_cov(self.tip)
        msg.pose.covariance = [float(x) for x in cov.ravel()]
        self.pub_tip.publish(msg)
        js = JointState()
        js.header.stamp, js.header.frame_id = stamp, self.frame_id
        tree = self.mech.tree
        idx = [tree.idx_v[i] for i in self.mech.rigid_joints]
        js.name = list(self.mech.joint_names)
        js.position = [float(self.ekf.q[k]) for k in idx]
        js.velocity = [float(self.ekf.v[k]) for k in idx]
        self.pub_joints.publish(js)
        for name, pub in self.pub_backbones.items():
            arr = cv.pose_array(self.ekf.member_backbone(name))
            arr.header.stamp, arr.header.frame_id = stamp, self.frame_id
            pub.publish(arr)

    def diagnostics(self):
        """{key: value} of the filter's health for /diagnostics."""
        h = self.ekf.health
        jp = self.ekf.joint_positions()
        return {"predictions": h.predictions, "measurements_accepted": h.accepted, "measurements_gated": h.gated,
                "measurements_dropped": h.dropped,
                "measurements_rejected": h.rejected + sum(self.rejections.values()),
                **{f"rejected_{k}": n for k, n in self.rejections.items()}, "last_rejection": self.last_rejection,
                "mean_nis_per_dof": f"{h.mean_nis_per_dof:.3f}", "integrator_failures": h.integrator_failures,
                "tip_frame": self.tip,
                "tip_position_std_m": f"{float(np.sqrt(np.trace(self.ekf.frame_position_cov(self.tip)))):.6g}",
                **{f"joint_{n}_std": f"{s:.6g}" for n, (_, s) in jp.items()}}
