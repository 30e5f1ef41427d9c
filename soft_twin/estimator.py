"""soft_twin_estimator: a ROS 2 node that tracks the real robot from its
sensors with the core's extended Kalman filter
(:class:`soft_twin_core.estimation.StrainEKF`), next to the open-loop twin
(``soft_twin.node``), which it leaves untouched.

    python -m soft_twin.estimator --ros-args -p robot_description_file:=tracked_arm \\
        -p sensors_file:=sensors.yaml -p rate_hz:=100.0 -p wrench:=payload

Parameters: ``robot_description_file`` (path or example name),
``sensors_file`` (YAML, :func:`soft_twin_core.sensors.load_sensors`),
``rate_hz`` (filter rate, default 100), ``wrench`` (none, payload, force,
wrench), ``actuation_topic`` (default ``/soft_twin/actuation``: the twin's
commands are the filter's inputs), ``frame_id`` (default ``base_link``),
``joint_command_topic`` (tree robots, default ``/soft_twin/joint_commands``),
``record_file`` (an MCAP file, ROS 2 bag format, that records every
message the node receives -- measurements and commands -- for
``soft-twin-sim calibrate --data FILE.mcap``; closed when the node stops;
``recorded_inputs`` in the diagnostics counts them), ``max_reading_age_s``
(default 1.0: a reading stamped further from the node's clock is rejected).

A tree robot file (soft articulated robot, e.g. ``pan_tilt_arm``) runs the
tree filter instead, with joint-state measurements: see
:mod:`soft_twin.tree_estimator` for its topics.

Subscriptions (the pose of each sensor frame in the base frame):
``~/measurements/poses`` (geometry_msgs/PoseArray: one pose per pose
sensor of the sensors file, in its order), ``~/measurements/pose``
(geometry_msgs/PoseStamped, ``header.frame_id`` = the sensor's name),
``~/measurements/position`` (geometry_msgs/PointStamped, ``frame_id`` = a
marker's name), and the actuation topic (soft_twin/ActuationCommand).
Malformed readings (NaN, an unknown sensor name, a PoseArray of the wrong
length) are rejected and counted; so are readings with a stamp too old, in
the future, or older than the sensor's last one (a zero stamp: taken at
arrival); the filter gates outliers. Every topic's messages are counted as
received and lost (sequence gaps); readings of one sensor arriving within
one filter step are merged into one (:mod:`soft_twin.readings`).

Publications: ``~/estimate/tip_pose`` (geometry_msgs/PoseWithCovarianceStamped:
the tip position covariance in the position block, m^2; the rotation block
is left 0), ``~/estimate/backbone`` (PoseArray), ``~/estimate/tip_wrench``
(WrenchStamped, world axes: the estimated external tip load) and the
filter's health on ``/diagnostics`` (name ``soft_twin_estimator``). Service
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
from std_srvs.srv import Trigger

from soft_twin.msg import ActuationCommand
from soft_twin import conversions as cv
from soft_twin.readings import STAMP_REJECTIONS, InputLedger, accept_reading
from soft_twin.shutdown import StopSignals, spin_until_stopped, tear_down
from soft_twin_core import estimation as es
from soft_twin_core import sensors as sn
from soft_twin_core.model import load_model

NODE_NAME = "soft_twin_estimator"
_REJECTION_KINDS = ("non_finite", "malformed", "wrong_length", "unknown_sensor", "actuation") + STAMP_REJECTIONS
_WRENCH = {"none": None, "payload": "payload", "force": "force", "wrench": "wrench"}


class EstimatorNode(Node):

    def __init__(self, node_name=NODE_NAME, **kwargs):
        super().__init__(node_name, **kwargs)
        p = {
            "robot_description_file": ("tendon_arm", "robot file or example name"),
            "sensors_file": ("", "YAML list of the sensors (soft_twin_core.sensors.load_sensors)"),
            "rate_hz": (100.0, "filter rate [Hz]"),
            "wrench": ("none", "estimated tip load: none, payload, force or wrench"),
            "actuation_topic": ("/soft_twin/actuation", "the twin's actuation commands (the inputs)"),
            "frame_id": ("base_link", "frame of the published estimates"),
            "joint_command_topic": ("/soft_twin/joint_commands", "the twin's joint commands (tree robots)"),
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
        # --- recording of the inputs (MCAP, for soft-twin-sim calibrate --data FILE.mcap) ---
        from soft_twin import recorder
        self._recorder = recorder.Recorder(self, [])     # started at the end (nothing is received before)
        # --- soft articulated robots (tree robot files): soft_twin.tree_estimator ---
        self.tree = None
        mech = _tree_robot(get("robot_description_file"))
        if mech is not None:
            from soft_twin import tree_estimator
            self.tree = tree_estimator.TreeEstimation(self, mech, get("sensors_file"), rate, get("frame_id"),
                                                      get("actuation_topic"), get("joint_command_topic"))
            self.model = mech
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.create_service(Trigger, "~/estimate/reset", self._on_reset)
            self.create_timer(1.0 / rate, self.tree.on_timer)
            self.create_timer(0.2, self._publish_diagnostics)
            self._start_recording(get("record_file"))
            return
        self.model = load_model(get("robot_description_file"))
        self.sensors = sn.load_sensors(get("sensors_file"), self.model)
        self.pose_sensors = [s for s in self.sensors if isinstance(s, sn.PoseSensor)]
        self.frame_id = get("frame_id")
        self.ekf = es.StrainEKF(self.model, self.sensors, 1.0 / rate, wrench=_WRENCH[get("wrench")])
        self.rejections = dict.fromkeys(_REJECTION_KINDS, 0)
        self.last_rejection = ""
        self.pub_tip = self.create_publisher(PoseWithCovarianceStamped, "~/estimate/tip_pose", 10)
        self.pub_backbone = self.create_publisher(PoseArray, "~/estimate/backbone", 10)
        self.pub_wrench = self.create_publisher(WrenchStamped, "~/estimate/tip_wrench", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PoseArray, "~/measurements/poses", self._on_poses, 50)
        self.create_subscription(PoseStamped, "~/measurements/pose", self._on_pose, 50)
        self.create_subscription(PointStamped, "~/measurements/position", self._on_position, 50)
        self.create_subscription(ActuationCommand, get("actuation_topic"), self._on_actuation, 50)
        self.create_service(Trigger, "~/estimate/reset", self._on_reset)
        self.create_timer(1.0 / rate, self._on_timer)
        self.create_timer(0.2, self._publish_diagnostics)
        self._start_recording(get("record_file"))

    def _start_recording(self, path):
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
        if not isinstance(s, sn.PoseSensor):
            self._reject("unknown_sensor", f"pose: unknown pose sensor {msg.header.frame_id!r}; "
                         f"configured: {[x.name for x in self.pose_sensors]}")
            return
        self._accept(s, lambda: cv.matrix_from_pose(msg.pose), msg.header.stamp)

    def _on_position(self, msg):
        s = self.ekf.by_name.get(msg.header.frame_id)
        if not isinstance(s, sn.PositionMarker):
            self._reject("unknown_sensor", f"position: unknown marker {msg.header.frame_id!r}")
            return
        self._accept(s, lambda: np.array([msg.point.x, msg.point.y, msg.point.z]), msg.header.stamp)

    def _on_actuation(self, msg):
        names = list(self.model.actuator_names)
        u = self.ekf.u.copy()
        if len(msg.names) != len(msg.values):
            self._reject("actuation", f"actuation: {len(msg.names)} names but {len(msg.values)} values")
            return
        for n, v in zip(msg.names, msg.values):
            if n not in names or not math.isfinite(v) or (v < 0 and self.model.actuators[names.index(n)].kind
                                                           == "tendon"):
                self._reject("actuation", f"actuation: bad entry {n!r} = {v!r}")
                return
            u[names.index(n)] = v
        self.ekf.u = u

    def _on_reset(self, req, resp):
        self.ledger.reset()
        if self.tree is not None:
            self.tree.reset()
            resp.success, resp.message = True, "estimate reset to the initial state"
            return resp
        self.ekf.reset()
        self.rejections = dict.fromkeys(_REJECTION_KINDS, 0)
        self.last_rejection = ""
        resp.success = True
        resp.message = "estimate reset to the initial state"
        return resp

    # ----------------------------------------------------------------- filter
    def _on_timer(self):
        self.ekf.predict()
        self.ekf.update(self.ledger.take())
        stamp = self.get_clock().now().to_msg()
        T = self.ekf.tip_pose()
        msg = PoseWithCovarianceStamped()
        msg.header.stamp, msg.header.frame_id = stamp, self.frame_id
        msg.pose.pose = cv.pose_msg(T)
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.ekf.tip_position_cov()
        msg.pose.covariance = [float(x) for x in cov.ravel()]
        self.pub_tip.publish(msg)
        _, P = self.ekf.backbone(4)
        self.pub_backbone.publish(cv.pose_array(P, _header(stamp, self.frame_id)))
        w = WrenchStamped()
        w.header = _header(stamp, self.frame_id)
        w.wrench = cv.wrench_msg(self.ekf.wrench())
        self.pub_wrench.publish(w)

    def _publish_diagnostics(self):
        if self.tree is not None:
            h = self.tree.ekf.health
            st = DiagnosticStatus(name="soft_twin_estimator", hardware_id=self.model.name)
            st.level = DiagnosticStatus.OK if h.integrator_failures == 0 else DiagnosticStatus.WARN
            st.message = "tracking" if h.accepted else "no measurement yet"
            values = {**self.tree.diagnostics(), **self.ledger.diagnostics(),
                      "recorded_inputs": self.recorded_inputs()}
            st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
            arr = DiagnosticArray()
            arr.header.stamp = self.get_clock().now().to_msg()
            arr.status = [st]
            self.pub_diag.publish(arr)
            return
        h = self.ekf.health
        st = DiagnosticStatus(name="soft_twin_estimator", hardware_id=self.model.name)
        ok = h.integrator_failures == 0
        st.level = DiagnosticStatus.OK if ok else DiagnosticStatus.WARN
        st.message = "tracking" if h.accepted else "no measurement yet"
        mass, mass_std = self.ekf.payload_mass_kg()
        values = {"predictions": h.predictions, "measurements_accepted": h.accepted, "measurements_gated": h.gated,
                  "measurements_dropped": h.dropped,
                  "measurements_rejected": h.rejected + sum(self.rejections.values()),
                  **{f"rejected_{k}": n for k, n in self.rejections.items()}, "last_rejection": self.last_rejection,
                  "mean_nis_per_dof": f"{h.mean_nis_per_dof:.3f}", "integrator_failures": h.integrator_failures,
                  "tip_position_std_m": f"{float(np.sqrt(np.trace(self.ekf.tip_position_cov()))):.6g}",
                  "payload_mass_kg": f"{mass:.6g}", "payload_mass_std_kg": f"{mass_std:.6g}",
                  **self.ledger.diagnostics(), "recorded_inputs": self.recorded_inputs()}
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diag.publish(arr)


def _tree_robot(name):
    """The Mechanism of a tree robot file (``bodies``), else None (a classic robot)."""
    from soft_twin_core.mechanism import is_tree_file, load_mechanism
    from soft_twin_core.model import ModelError, find_file, read_yaml_file, robot_mapping
    path = find_file(name, "robots")
    d = robot_mapping(read_yaml_file(path, ModelError, "robot file"), f"robot file {path}")
    return load_mechanism(path) if is_tree_file(d) else None


def _header(stamp, frame):
    from std_msgs.msg import Header
    return Header(stamp=stamp, frame_id=frame)


def main(args=None):
    """Entry point (``python -m soft_twin.estimator --ros-args ...``). Exit
    status 0 after SIGINT or SIGTERM (at any time: :mod:`soft_twin.shutdown`),
    2 for a robot, sensors file or parameter that does not load."""
    stop = StopSignals(NODE_NAME)
    stop.install()
    logger = rclpy.logging.get_logger(NODE_NAME)
    node = executor = None
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = EstimatorNode()        # a signal during it: the start-up ends, then the node stops
        logger = node.get_logger()
        stop.add_last_act(node._recorder.close_now)
        logger.info(f"estimator running: robot {getattr(node.model, 'name', '?')!r}, "
                    f"{'tree filter' if node.tree is not None else 'strain EKF'} at "
                    f"{node.get_parameter('rate_hz').value:g} Hz")
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
