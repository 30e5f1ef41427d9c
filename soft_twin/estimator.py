"""soft_twin_estimator: a ROS 2 node that tracks the real robot from its
sensors with the core's extended Kalman filter
(:class:`soft_twin_core.estimation.ekf.EKF`), next to the open-loop twin
(``soft_twin.node``), which it leaves untouched. One node for every robot
file: a classic rod, a tree of members, a soft articulated arm.

    python -m soft_twin.estimator --ros-args -p robot_description_file:=tracked_arm \\
        -p sensors_file:=sensors.yaml -p rate_hz:=100.0 -p wrench:=payload

Parameters: ``robot_description_file`` (path or example name),
``sensors_file`` (YAML, :func:`soft_twin_core.estimation.sensors.load_sensors`),
``rate_hz`` (filter rate, default 100), ``wrench`` (the estimated load at
the tip frame: none, payload, force, wrench), ``actuation_topic`` (default
``/soft_twin/actuation``: the twin's commands are the filter's inputs),
``joint_command_topic`` (default ``/soft_twin/joint_commands``: positions
of position-controlled joints and efforts of effort-controlled ones),
``frame_id`` (default ``base_link``), ``record_file`` (an MCAP file, ROS 2
bag format, that records every message the node receives -- measurements
and commands -- for ``soft-twin-sim calibrate --data FILE.mcap``; closed
when the node stops; ``recorded_inputs`` in the diagnostics counts them),
``max_reading_age_s`` (default 1.0: a reading stamped further from the
node's clock is rejected).

Subscriptions: ``~/measurements/poses`` (geometry_msgs/PoseArray: one pose
per pose sensor of the sensors file, in its order), ``~/measurements/pose``
(geometry_msgs/PoseStamped, ``header.frame_id`` = the sensor's name),
``~/measurements/position`` (geometry_msgs/PointStamped, ``frame_id`` = a
marker's name), ``~/measurements/joint_states`` (sensor_msgs/JointState:
the positions of the joints of the ``joint_state`` sensors; a sensor takes
a reading when the message names all its joints),
``~/measurements/base_wrench`` (geometry_msgs/WrenchStamped: the
``base_wrench`` sensor's reading, the support's wrench on the robot in
world axes about the base origin), the actuation topic
(soft_twin/ActuationCommand) and the joint command topic
(sensor_msgs/JointState). Poses are those of the sensor frames in the base
frame. Malformed readings (NaN, an unknown sensor or joint name, a
message of the wrong length) are rejected and counted
(``rejected_<kind>`` in the diagnostics); so are readings with a stamp too
old, in the future, or older than the sensor's last one (a zero stamp:
taken at arrival); the filter gates outliers. Every topic's messages are
counted as received and lost (sequence gaps); readings of one sensor
arriving within one filter step are merged into one
(:mod:`soft_twin.readings`).

Publications: ``~/estimate/tip_pose`` (geometry_msgs/PoseWithCovarianceStamped
of the tip frame, :func:`soft_twin_core.robot.mechanism.tip_frame`: the position
covariance in the position block, m^2; the rotation block is left 0),
``~/estimate/backbone`` (PoseArray of the main member, as the twin's
``~/backbone``), ``~/estimate/backbones/<member>`` (one per soft member),
``~/estimate/joint_states`` (JointState: positions and velocities of the
rigid joints), ``~/estimate/tip_wrench`` (WrenchStamped, world axes: the
estimated external tip load, zero with ``wrench:=none``) and the filter's
health on ``/diagnostics`` (name ``soft_twin_estimator``). Service
``~/estimate/reset`` (std_srvs/Trigger).
"""

import math
import sys

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PoseArray, PoseStamped, PoseWithCovarianceStamped, WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from soft_twin.msg import ActuationCommand
from soft_twin import conversions as cv
from soft_twin.inputs import base_pose_of
from soft_twin.readings import STAMP_REJECTIONS, InputLedger, accept_reading
from soft_twin.shutdown import StopSignals, spin_until_stopped, tear_down
from soft_twin_core._blas import blas_on_one_thread
from soft_twin_core.commands import InputError, parse_joint_command
from soft_twin_core.estimation import ekf as es
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.solve.outputs import main_member

NODE_NAME = "soft_twin_estimator"
REJECTION_KINDS = ("non_finite", "malformed", "wrong_length", "unknown_sensor", "unknown_joint", "actuation",
                   "joint_command", "base_pose") + STAMP_REJECTIONS
_WRENCH = {"none": None, "payload": "payload", "force": "force", "wrench": "wrench"}


class EstimatorNode(Node):

    def __init__(self, node_name=NODE_NAME, **kwargs):
        super().__init__(node_name, **kwargs)
        p = {
            "robot_description_file": ("tendon_arm", "robot file or example name"),
            "sensors_file": ("", "YAML list of the sensors (soft_twin_core.estimation.sensors.load_sensors)"),
            "rate_hz": (100.0, "filter rate [Hz]"),
            "wrench": ("none", "estimated tip load: none, payload, force or wrench"),
            "force_directions": ("", "with wrench force: the world directions of the force, 'x,y,z' or "
                                     "'x,y,z;x,y,z' ('': all three axes)"),
            "actuation_topic": ("/soft_twin/actuation", "the twin's actuation commands (the inputs)"),
            "frame_id": ("base_link", "frame of the published estimates"),
            "joint_command_topic": ("/soft_twin/joint_commands", "the twin's joint commands"),
            "base_pose_topic": ("/soft_twin/base_pose_command", "where a prescribed base is carried "
                                                                "(geometry_msgs/PoseStamped in frame_id)"),
            "record_file": ("", "MCAP file recording every measurement and command received ('' : none)"),
            "max_reading_age_s": (1.0, "readings stamped further than this from the node's clock are rejected [s]"),
        }
        for name, (value, doc) in p.items():
            self.declare_parameter(name, value, ParameterDescriptor(description=doc))
        get = lambda n: self.get_parameter(n).value  # noqa: E731
        if get("wrench") not in _WRENCH:
            raise ValueError(f"wrench: expected one of {list(_WRENCH)}, got {get('wrench')!r}")
        if not get("sensors_file"):
            raise ValueError("sensors_file: required (a YAML list of the sensors)")
        rate = float(get("rate_hz"))
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate_hz: expected a positive rate, got {rate!r}")
        max_age = float(get("max_reading_age_s"))
        if not (math.isfinite(max_age) and max_age > 0):
            raise ValueError(f"max_reading_age_s: expected a positive age in s, got {max_age!r}")
        self.ledger = InputLedger(max_age)        # every input topic and reading counted (soft_twin.readings)
        from soft_twin import recorder
        self._recorder = recorder.Recorder(self, [])     # started at the end (nothing is received before)
        # --- the robot, its sensors and the filter ---
        self.mech = mech = load_mechanism(get("robot_description_file"))
        self.sensors = sn.load_sensors(get("sensors_file"), mech)
        options = {}
        if get("force_directions"):
            options["force_directions"] = es.parse_directions(get("force_directions"), "force_directions")
        self.ekf = es.EKF(mech, self.sensors, 1.0 / rate, wrench=_WRENCH[get("wrench")], **options)
        self.frame_id = get("frame_id")
        self.pose_sensors = [s for s in self.sensors if isinstance(s, sn.PoseSensor) and not s.position_only]
        self.joint_sensors = [s for s in self.sensors if isinstance(s, sn.JointStateSensor)]
        self.wrench_sensors = [s for s in self.sensors if isinstance(s, sn.BaseWrenchSensor)]
        self.main = getattr(main_member(mech, self.ekf.tip), "name", None)
        self.rejections = dict.fromkeys(REJECTION_KINDS, 0)
        self.last_rejection = ""
        self.cmd_pos, self.cmd_eff = {}, {}
        self._base_pose = None             # the newest base pose received, for the next filter step
        # --- publications ---
        self.pub_tip = self.create_publisher(PoseWithCovarianceStamped, "~/estimate/tip_pose", 10)
        self.pub_backbone = self.create_publisher(PoseArray, "~/estimate/backbone", 10)
        self.pub_backbones = {m.name: self.create_publisher(PoseArray, f"~/estimate/backbones/{m.name}", 10)
                              for m in mech.members}
        self.pub_joints = self.create_publisher(JointState, "~/estimate/joint_states", 10)
        self.pub_wrench = self.create_publisher(WrenchStamped, "~/estimate/tip_wrench", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # --- subscriptions ---
        self.create_subscription(PoseArray, "~/measurements/poses", self._on_poses, 50)
        self.create_subscription(PoseStamped, "~/measurements/pose", self._on_pose, 50)
        self.create_subscription(PointStamped, "~/measurements/position", self._on_position, 50)
        self.create_subscription(JointState, "~/measurements/joint_states", self._on_joint_states, 50)
        self.create_subscription(WrenchStamped, "~/measurements/base_wrench", self._on_base_wrench, 50)
        self.create_subscription(ActuationCommand, get("actuation_topic"), self._on_actuation, 50)
        self.create_subscription(JointState, get("joint_command_topic"), self._on_joint_command, 50)
        self.create_subscription(PoseStamped, get("base_pose_topic"), self._on_base_pose, 50)
        self.create_service(Trigger, "~/estimate/reset", self._on_reset)
        self.create_timer(1.0 / rate, self._on_timer)
        self.create_timer(0.2, self._publish_diagnostics)
        path = get("record_file")
        if path and not self._recorder.follow(path):
            raise ValueError(f"record_file: cannot record to {path!r}")

    def create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
        """Every subscription's messages are counted (received, lost: the
        ledger) and recorded (``record_file``) before they are handled."""
        holder = []

        def recorded(msg, info):
            if holder:
                sub = holder[0]
                self.ledger.message(sub.topic_name, info, sub.get_publisher_count())
                rec = getattr(self, "_recorder", None)
                if rec is not None:
                    rec.received(sub, [(msg, info)])
            return callback(msg)
        sub = super().create_subscription(msg_type, topic, recorded, qos_profile, **kwargs)
        holder.append(sub)
        return sub

    def recorded_inputs(self):
        """Messages written to the current recording (0 when not recording)."""
        rec = getattr(self._recorder, "_recording", None)
        return sum(rec.counts.values()) if rec is not None else 0

    def destroy_node(self):
        """The recording closes with the node (``record_file``)."""
        rec = getattr(self, "_recorder", None)
        if rec is not None:
            rec.close()
        return super().destroy_node()

    # ------------------------------------------------------------------ inputs
    def _reject(self, kind, reason):
        self.rejections[kind] += 1
        self.last_rejection = reason
        self.get_logger().warn(f"measurement rejected: {reason}", throttle_duration_sec=1.0)

    def _accept(self, sensor, reading, stamp):
        """Validate ``reading()`` (a message converted to an array) for the
        sensor and its stamp; an accepted one waits for the next filter step."""
        accept_reading(self.ledger, self._reject, sensor.name, lambda: sn.measurement_vector(sensor, reading()),
                       stamp, self.get_clock().now().nanoseconds)

    def _on_poses(self, msg):
        if len(msg.poses) != len(self.pose_sensors):
            self._reject("wrong_length", f"poses: expected {len(self.pose_sensors)} poses (one per pose sensor "
                         f"{[s.name for s in self.pose_sensors]}), got {len(msg.poses)}")
            return
        for s, pose in zip(self.pose_sensors, msg.poses):
            self._accept(s, lambda pose=pose: cv.matrix_from_pose(pose), msg.header.stamp)

    def _on_pose(self, msg):
        s = self.ekf.by_name.get(msg.header.frame_id)
        if not (isinstance(s, sn.PoseSensor) and not s.position_only):
            self._reject("unknown_sensor", f"pose: unknown pose sensor {msg.header.frame_id!r}; "
                         f"configured: {[x.name for x in self.pose_sensors]}")
            return
        self._accept(s, lambda: cv.matrix_from_pose(msg.pose), msg.header.stamp)

    def _on_position(self, msg):
        s = self.ekf.by_name.get(msg.header.frame_id)
        if not (isinstance(s, sn.PoseSensor) and s.position_only):
            self._reject("unknown_sensor", f"position: unknown marker {msg.header.frame_id!r}")
            return
        self._accept(s, lambda: np.array([msg.point.x, msg.point.y, msg.point.z]), msg.header.stamp)

    def _on_joint_states(self, msg):
        names, pos = list(msg.name), list(msg.position)
        if len(names) != len(pos):
            self._reject("wrong_length", f"joint_states: {len(names)} names but {len(pos)} positions")
            return
        unknown = [x for x in names if x not in self.mech.joint_names]
        if unknown:
            self._reject("unknown_joint", f"joint_states: unknown joint(s) {unknown}; this robot has "
                                          f"{list(self.mech.joint_names)}")
            return
        value = dict(zip(names, pos))
        for s in self.joint_sensors:
            if all(j in value for j in s.joints):
                self._accept(s, lambda s=s: np.array([value[j] for j in s.joints], dtype=float), msg.header.stamp)

    def _on_base_wrench(self, msg):
        if not self.wrench_sensors:
            self._reject("unknown_sensor", "base_wrench: no base_wrench sensor in the sensors file")
            return
        f, t = msg.wrench.force, msg.wrench.torque
        self._accept(self.wrench_sensors[0], lambda: np.array([f.x, f.y, f.z, t.x, t.y, t.z], dtype=float),
                     msg.header.stamp)

    def _on_actuation(self, msg):
        names = list(self.mech.actuator_names)
        u = self.ekf.u.copy()
        if len(msg.names) != len(msg.values):
            self._reject("actuation", f"actuation: {len(msg.names)} names but {len(msg.values)} values")
            return
        for n, v in zip(msg.names, msg.values):
            if n not in names or not math.isfinite(v) or (v < 0 and self.mech.actuators[names.index(n)].kind
                                                           == "tendon"):
                self._reject("actuation", f"actuation: bad entry {n!r} = {v!r}")
                return
            u[names.index(n)] = v
        self.ekf.u = u

    def _on_joint_command(self, msg):
        try:
            pos, eff = parse_joint_command(self.mech, msg.name, msg.position, msg.velocity, msg.effort,
                                           self.cmd_pos, self.cmd_eff)
            self.ekf.set_inputs(positions=pos or None, efforts=eff or None)
        except (InputError, ValueError) as e:
            self._reject("joint_command", f"joint command: {e}")
            return
        self.cmd_pos, self.cmd_eff = pos, eff

    def _on_base_pose(self, msg):
        """A prescribed base's pose (checked as the twin checks it:
        :func:`soft_twin_core.commands.parse_base_pose`); the newest one is
        where the filter steps carry the base (poses arriving faster than
        the filter: the intermediate ones are passed over, so that a step's
        base velocity is the one over the step; slower: the base rests at
        the newest one between them)."""
        try:
            self._base_pose = base_pose_of(msg, self.mech, self.frame_id)
        except InputError as e:
            self._reject("base_pose", str(e))

    def _on_reset(self, req, resp):
        self.ledger.reset()
        self.ekf.reset()
        self.cmd_pos, self.cmd_eff = {}, {}
        self._base_pose = None
        self.rejections = dict.fromkeys(REJECTION_KINDS, 0)
        self.last_rejection = ""
        resp.success, resp.message = True, "estimate reset to the initial state"
        return resp

    # ----------------------------------------------------------------- filter
    def _on_timer(self):
        ekf = self.ekf
        ekf.predict(base_pose=self._base_pose)    # the newest pose again: the base rests there
        ekf.update(self.ledger.take())
        header = _header(self.get_clock().now().to_msg(), self.frame_id)
        msg = PoseWithCovarianceStamped(header=header)
        msg.pose.pose = cv.pose_msg(ekf.tip_pose())
        cov = np.zeros((6, 6))
        cov[:3, :3] = ekf.tip_position_cov()
        msg.pose.covariance = [float(x) for x in cov.ravel()]
        self.pub_tip.publish(msg)
        for name, pub in self.pub_backbones.items():
            arr = cv.pose_array(ekf.member_backbone(name), header)
            pub.publish(arr)
            if name == self.main:
                self.pub_backbone.publish(arr)
        if self.mech.rigid_joints:
            idx = [self.mech.tree.idx_v[i] for i in self.mech.rigid_joints]
            js = JointState(header=header, name=list(self.mech.joint_names))
            js.position = [float(ekf.q[k]) for k in idx]
            js.velocity = [float(ekf.v[k]) for k in idx]
            self.pub_joints.publish(js)
        w = WrenchStamped(header=header)
        w.wrench = cv.wrench_msg(ekf.wrench())
        self.pub_wrench.publish(w)

    def diagnostics(self):
        """{key: value} of the filter's health for /diagnostics."""
        h, ekf = self.ekf.health, self.ekf
        values = {"predictions": h.predictions, "measurements_accepted": h.accepted, "measurements_gated": h.gated,
                  "measurements_dropped": h.dropped,
                  "measurements_rejected": h.rejected + sum(self.rejections.values()),
                  **{f"rejected_{k}": n for k, n in self.rejections.items()}, "last_rejection": self.last_rejection,
                  "mean_nis_per_dof": f"{h.mean_nis_per_dof:.3f}", "integrator_failures": h.integrator_failures,
                  "tip_frame": ekf.tip,
                  "tip_position_std_m": f"{float(np.sqrt(np.trace(ekf.tip_position_cov()))):.6g}",
                  **{f"joint_{n}_std": f"{s:.6g}" for n, (_, s) in ekf.joint_positions().items()}}
        if ekf.k:
            mass, mass_std = ekf.payload_mass_kg()
            values.update(payload_mass_kg=f"{mass:.6g}", payload_mass_std_kg=f"{mass_std:.6g}")
        return values

    def _publish_diagnostics(self):
        h = self.ekf.health
        st = DiagnosticStatus(name=NODE_NAME, hardware_id=self.mech.name)
        st.level = DiagnosticStatus.OK if h.integrator_failures == 0 else DiagnosticStatus.WARN
        st.message = "tracking" if h.accepted else "no measurement yet"
        values = {**self.diagnostics(), **self.ledger.diagnostics(), "recorded_inputs": self.recorded_inputs()}
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diag.publish(arr)


def _header(stamp, frame):
    from std_msgs.msg import Header
    return Header(stamp=stamp, frame_id=frame)


def main(args=None):
    """Entry point (``python -m soft_twin.estimator --ros-args ...``). Exit
    status 0 after SIGINT or SIGTERM (at any time: :mod:`soft_twin.shutdown`),
    2 for a robot, sensors file or parameter that does not load."""
    blas_on_one_thread()      # no spinning BLAS thread beside the controller (small matrices)
    stop = StopSignals(NODE_NAME)
    stop.install()
    logger = rclpy.logging.get_logger(NODE_NAME)
    node = executor = None
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = EstimatorNode()        # a signal during it: the start-up ends, then the node stops
        logger = node.get_logger()
        stop.add_last_act(node._recorder.close_now)
        logger.info(f"estimator running: robot {node.mech.name!r}, {node.ekf.nr} coordinates, "
                    f"{len(node.sensors)} sensors, at {node.get_parameter('rate_hz').value:g} Hz")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spin_until_stopped(executor, stop)
    except (ValueError, OSError) as e:
        print(f"soft_twin_estimator: {e}", file=sys.stderr)
        return 2
    finally:
        tear_down(stop, logger, executor, node)
    if stop.received is not None:
        logger.info("stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
