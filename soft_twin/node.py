"""The soft_twin ROS 2 node: a real-time digital twin of a soft robot.

Thin by design: everything it computes comes from ``soft_twin_core``
(through the one twin of every robot file,
:class:`soft_twin_core.twin.Twin`; the checks at the
door: :mod:`soft_twin_core.twin`); the node wires parameters, topics,
services and threads, owns the clock and the state, and never blocks the
stepping clock. Its collaborators: :mod:`soft_twin.inputs` (message batches
to checked inputs), :mod:`soft_twin.schedule` (which steps are due),
:mod:`soft_twin.diagnostics`, :mod:`soft_twin.markers`,
:mod:`soft_twin.services` and :mod:`soft_twin.plan_service`.

Threads: the stepping clock (:class:`soft_twin.stepper.Stepper`, a thread of
its own, not an rclpy timer: each timer tick cost the Python executor a
wake-up of ~2.5 ms under the GIL) advances the twin every step period
(dynamic mode) or re-publishes it (quasi-static mode) and publishes its state.
The executor (:class:`soft_twin.executor.TwinExecutor`, a
``MultiThreadedExecutor`` with rclpy 7.1's dispatch bug worked around) runs
the callbacks in groups:

* ``step``     (mutually exclusive): the quasi-static solve trigger (a new
  input solves at once).
* ``inputs``   (mutually exclusive): the actuation and tip-wrench
  subscriptions; each callback takes everything queued on its topic (one
  executor dispatch per message could not keep up with a 1 kHz stream while
  services ran), validates, counts and folds it outside the lock and
  applies the result in microseconds; inputs lost before the node took them
  are counted from the publishers' sequence numbers (dynamic mode with
  ``step_on_command``: an input arriving at most at the step rate also takes
  the next step itself, at once; any input callback that finds the step
  clock a period late takes the steps due).
* ``services`` (reentrant): FK, IK, statics query, reset. They copy what they
  need from the twin under the lock and compute outside it.
* ``diagnostics`` (mutually exclusive): the /diagnostics timer.

One lock guards the twin and its schedule; it is held for one step (or
solve) and for the microseconds an input or a service needs, never while a
service computes. A second lock keeps the published states in step order.

Topics, services and parameters: see README.md ("Interfaces").
"""

import math
import os
import sys
import threading
import time
import traceback

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, WrenchStamped
from sensor_msgs.msg import JointState
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.exceptions import InvalidHandle, ParameterNotDeclaredException, ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Float64MultiArray, Header, MultiArrayDimension
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from soft_twin.msg import ActuationCommand, Contacts, Obstacle, PointWrench, Strains
from soft_twin.stepper import Stepper
from soft_twin.srv import ForwardKinematics, InverseKinematics, StaticsQuery

from soft_twin import conversions as cv
from soft_twin import diagnostics, inputs, markers, schedule, services
from soft_twin import live_view_out, recorder, tf_out
from soft_twin_core import commands as cmd
from soft_twin_core._blas import blas_on_one_thread
from soft_twin_core import twin as tw
from soft_twin.executor import TwinExecutor
from soft_twin.shutdown import StopSignals, spin_until_stopped, tear_down
from soft_twin.config import (PARAMETERS, ConfigError, coerced, config_from_values, load_robot,
                              unknown_parameters_message)
from soft_twin_core.text import clip

NODE_NAME = "soft_twin"
# benchmark hook: SOFT_TWIN_SERVICE_TIMING=1 logs the IK service body's wall and thread CPU time
_SERVICE_TIMING = bool(os.environ.get("SOFT_TWIN_SERVICE_TIMING"))
ACTUATION_QUEUE = 100       # subscription depths (keep last)
WRENCH_QUEUE = 10
JOINT_QUEUE = 100
OBSTACLE_QUEUE = 100
class StartupInterrupted(Exception):
    """The start-up was abandoned on request (a stop signal, see main)."""


class UnknownParameterError(ParameterNotDeclaredException):
    """A parameter this node does not have (named, with the nearest of its
    own); the parameter services answer with this message as the reason."""

    def __init__(self, names):
        Exception.__init__(self, unknown_parameters_message(names))


class SoftTwinNode(Node):
    """The digital twin node (see the module docstring)."""

    def __init__(self, node_name=NODE_NAME, stop_requested=None, **kwargs):
        """``stop_requested``: a callable asked between the start-up's steps
        (robot, rest shape, kernel warm-up); True abandons the start-up
        (the node is destroyed, :class:`StartupInterrupted` raised)."""
        self._stop_requested = stop_requested or (lambda: False)
        super().__init__(node_name, **kwargs)
        # --- parameters: declare, validate, load the robot ------------------
        # Dynamic typing, so that a wrong type gets config's reason, not rclpy's;
        # an integer for a float parameter is taken as that float (the
        # parameter keeps its type: at start here, on change in _coerce_parameters)
        overrides = getattr(self, "_parameter_overrides", {})
        for name, (default, description) in PARAMETERS.items():
            value = default
            if name in overrides:
                value = coerced(name, overrides[name].value)
            self.declare_parameter(name, value, ParameterDescriptor(
                name=name, description=description, dynamic_typing=True), ignore_override=True)
        self._values = {name: self._declared_value(name) for name in PARAMETERS}
        try:
            # a misspelt -p name:=value (or params-file entry) would silently change nothing
            unknown = sorted(n for n in overrides if n not in self._parameters
                             and not n.startswith("qos_overrides."))
            if unknown:
                raise ConfigError(unknown_parameters_message(unknown))
            self.cfg = config_from_values(self._values)
            self.robot = load_robot(self.cfg)
        except ConfigError:
            self.destroy_node()
            raise                   # the caller reports it (main: exit status 2)
        self._lock = threading.Lock()            # the twin, its schedule and the statistics
        self._publish_lock = threading.Lock()    # state publications, in step order
        self._wrench_lock = threading.Lock()     # one wrench computation at a time
        self._stats_lock = threading.Lock()      # internal error counts (taken without the others)
        self._staged = None
        self._command_received = None     # newest applied command: (header, stamp [ns], taken [ns])
        self._command_gaps = cmd.SequenceGaps()    # commands lost upstream, from sequence numbers
        self._wrench_gaps = cmd.SequenceGaps()
        self._point_wrench_gaps = cmd.SequenceGaps()
        self._base_pose_gaps = cmd.SequenceGaps()
        self._joint_gaps = cmd.SequenceGaps()
        self._last_input_time = -math.inf
        self._reported_internal_errors = 0
        self.stats = diagnostics.Stats()
        self._markers = markers.Markers()
        self.get_logger().info(f"robot {self.robot.model.name!r} from {self.robot.source}: "
                               f"{self._describe_robot(self.robot)}")
        for w in self.robot.warnings:            # implausible values: a likely unit slip (issue 25)
            self.get_logger().warning(w)
        self._startup_point()
        self.twin = self._make_twin(self.robot, self._settings(self.cfg))
        self.get_logger().info(f"mode {self.cfg.mode}; {self.twin.rest_message}")
        self._startup_point()
        self._query_worker = self._make_query_worker(self.robot)     # articulated IK and plans (issue 25)
        self.get_logger().info("warming up the compiled kernels (about a second from numba's disk cache, "
                               "which `make setup` fills; about a minute compiling when there is none) ...")
        took = self.twin.warm_up()
        self.get_logger().info(f"warm-up done in {took:.1f} s")
        self._startup_point()

        # --- callback groups -------------------------------------------------
        self._step_group = MutuallyExclusiveCallbackGroup()
        self._input_group = MutuallyExclusiveCallbackGroup()
        self._service_group = ReentrantCallbackGroup()
        self._diag_group = MutuallyExclusiveCallbackGroup()

        # --- publishers ------------------------------------------------------
        state_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                               history=HistoryPolicy.KEEP_LAST)
        self._pub_backbone = self.create_publisher(PoseArray, "~/backbone", state_qos)
        self._pub_tip = self.create_publisher(PoseStamped, "~/tip_pose", state_qos)
        self._pub_tip_wrench = self.create_publisher(WrenchStamped, "~/tip_wrench", state_qos)
        self._pub_base_wrench = self.create_publisher(WrenchStamped, "~/base_wrench", state_qos)
        self._pub_strains = self.create_publisher(Strains, "~/strains", state_qos)
        self._pub_markers = self.create_publisher(MarkerArray, "~/markers", 1)
        self._pub_contacts = self.create_publisher(Contacts, "~/contacts", state_qos)       # issue 27
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._make_articulated_interfaces(state_qos)

        # --- subscriptions (keep last: under overload the oldest inputs go, and
        # are counted from the sequence numbers); each callback takes the
        # message the executor handed it plus everything else queued by then
        on_actuation, on_wrench = self._guarded(self._on_actuation), self._guarded(self._on_tip_wrench)
        self._actuation_sub = self.create_subscription(
            ActuationCommand, "~/actuation", lambda msg, info: on_actuation(msg, info), ACTUATION_QUEUE,
            callback_group=self._input_group)
        self._wrench_sub = self.create_subscription(
            WrenchStamped, "~/tip_wrench_command", lambda msg, info: on_wrench(msg, info), WRENCH_QUEUE,
            callback_group=self._input_group)
        on_point = self._guarded(self._on_point_wrench)       # issue 31: a load on any point
        self._point_wrench_sub = self.create_subscription(
            PointWrench, "~/point_wrench_command", lambda msg, info: on_point(msg, info), WRENCH_QUEUE,
            callback_group=self._input_group)
        on_base = self._guarded(self._on_base_pose)           # a prescribed base, carried (issue 29)
        self._base_pose_sub = self.create_subscription(
            PoseStamped, "~/base_pose_command", lambda msg, info: on_base(msg, info), WRENCH_QUEUE,
            callback_group=self._input_group)
        on_obstacle = self._guarded(self._on_obstacle)
        self._obstacle_sub = self.create_subscription(
            Obstacle, "~/obstacles", lambda msg, info: on_obstacle(msg, info), OBSTACLE_QUEUE,
            callback_group=self._input_group)

        # --- services --------------------------------------------------------
        self.create_service(ForwardKinematics, "~/forward_kinematics", self._guarded(self._srv_fk),
                            callback_group=self._service_group)
        self.create_service(InverseKinematics, "~/inverse_kinematics", self._guarded(self._srv_ik),
                            callback_group=self._service_group)
        self.create_service(StaticsQuery, "~/statics_query", self._guarded(self._srv_statics),
                            callback_group=self._service_group)
        self.create_service(Trigger, "~/reset", self._guarded(self._srv_reset), callback_group=self._service_group)
        # issue 31: pause, single step (slow motion: the time_scale parameter)
        self._paused = False
        self.create_service(SetBool, "~/pause", self._guarded(self._srv_pause), callback_group=self._service_group)
        self.create_service(Trigger, "~/step", self._guarded(self._srv_step), callback_group=self._service_group)
        # --- issue 13: tip path planning and timed execution (soft_twin.plan_service)
        from soft_twin import plan_service
        from soft_twin.srv import PlanPath
        self._plan_runner = plan_service.PlanRunner(self)
        self._plan_runner.prepare(ActuationCommand, self.cfg.plan_output_topic, "~/actuation")
        if self.robot.mech.joint_names:
            self._plan_runner.prepare(JointState, self.cfg.plan_joint_output_topic, "~/joint_commands")
        self.create_service(PlanPath, "~/plan_path", self._guarded(self._srv_plan_path),
                            callback_group=self._service_group)
        self.create_service(Trigger, "~/cancel_plan", self._guarded(self._srv_cancel_plan),
                            callback_group=self._service_group)

        # --- seeing the twin (issue 12): /tf frames, MCAP recording ----------
        self._tf = tf_out.TfOutput(self)
        self._recorder = recorder.Recorder(self, [
            self._pub_backbone, self._pub_tip, self._pub_tip_wrench, self._pub_base_wrench,
            self._pub_strains, self._pub_markers, self._pub_contacts, self._pub_diag, self._tf.publisher]
            + self._articulated_publishers(), self._publish_lock)
        self._recorder.follow(self.cfg.record_file)
        self._live_view = live_view_out.LiveViewOutput(self)
        self._live_view.follow(self.cfg.live_view_port)

        # --- timers (steady clock: the twin runs on wall time) ---------------
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._solve_trigger = self.create_guard_condition(self._guarded(self._on_solve_trigger),
                                                          callback_group=self._step_group)
        self._stepper = None
        self._make_stepper()
        self._diag_timer = self.create_timer(1.0 / self.cfg.diagnostics_rate_hz,
                                             self._guarded(self._publish_diagnostics),
                                             callback_group=self._diag_group, clock=self._steady)
        self.add_pre_set_parameters_callback(self._coerce_parameters)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self.get_logger().info(
            f"twin running: {self.cfg.mode}"
            + (f" at {self.cfg.step_rate_hz:g} Hz (dt = {1e3 * self.cfg.dt:g} ms)" if self.cfg.mode == "dynamic"
               else "") + f"; frames {self.cfg.base_frame!r} -> {self.cfg.tip_frame!r}")

    @property
    def executor(self):
        return Node.executor.fget(self)

    @executor.setter
    def executor(self, new_executor):
        """Added to an executor: the stepping clock starts (as an rclpy timer
        would fire once the node is spun; a node made but never spun, e.g.
        in a test taking its steps by hand, does not step by itself)."""
        Node.executor.fset(self, new_executor)
        if new_executor is not None and getattr(self, "_stepper", None) is not None:
            self._stepper.start()

    # ------------------------------------------------------------------------
    # the robot: joints, members, constraints (a classic rod: one member, no joints)
    # ------------------------------------------------------------------------
    @staticmethod
    def _describe_robot(robot):
        m = robot.mech
        return (f"joints {list(m.joint_names)}, soft members {[x.name for x in m.members]} "
                f"({len(m.tree.soft_joints)} sections), constraints {[c.name for c in m.constraints]}, "
                f"{m.tree.nv} dof, actuators {list(m.actuator_names)}")

    @staticmethod
    def _make_twin(robot, settings):
        return tw.Twin(robot.mech, settings, robot.obstacles)

    @staticmethod
    def _make_query_worker(robot):
        """An articulated robot's IK and plans run in a worker process
        (:mod:`soft_twin.query_worker`): their Python would hold the GIL
        against the stepping clock. None for rod robots (their queries are
        compiled kernels, milliseconds)."""
        if not robot.articulated:
            return None
        from soft_twin.query_worker import QueryWorker
        return QueryWorker(robot.description)

    def query(self, method, *args, **kwargs):
        """An articulated twin's query ``method`` (inverse_kinematics, plan)
        on a copy of its state, in the worker process."""
        with self._lock:
            state, worker = self.twin.query_state(), self._query_worker
        return worker.run(method, state, *args, **kwargs)

    def _make_articulated_interfaces(self, qos):
        """Joint states out and joint commands in, one backbone per soft
        member, one wrench topic per constraint and per rigid joint
        (``_pub_constraints`` keys: constraint names, ("joint", name)):
        every robot's (a classic rod: no joints, one member)."""
        self._pub_members, self._pub_constraints = {}, {}
        mech = self.robot.mech
        self._pub_joints = self.create_publisher(JointState, "~/joint_states", qos)
        self._pub_internal = {}
        for m in mech.members:
            self._pub_members[m.name] = self.create_publisher(PoseArray, f"~/backbones/{_topic_name(m.name)}", qos)
            self._pub_internal[m.name] = self.create_publisher(
                Float64MultiArray, f"~/internal_wrenches/{_topic_name(m.name)}", qos)
        for c in mech.constraints:
            self._pub_constraints[c.name] = self.create_publisher(
                WrenchStamped, f"~/constraint_wrenches/{_topic_name(c.name)}", qos)
        for name in mech.joint_names:
            self._pub_constraints[("joint", name)] = self.create_publisher(
                WrenchStamped, f"~/joint_wrenches/{_topic_name(name)}", qos)
        on_joints = self._guarded(self._on_joint_command)
        self._sub_joints = self.create_subscription(
            JointState, "~/joint_commands", lambda msg, info: on_joints(msg, info), JOINT_QUEUE,
            callback_group=self._input_group)

    def _articulated_publishers(self):
        """Every publisher of the joint, member and wrench topics (recorded too; issue 12)."""
        return ([self._pub_joints] + list(self._pub_members.values()) + list(self._pub_internal.values())
                + list(self._pub_constraints.values()))

    def _on_joint_command(self, msg, info=None):
        """Every queued JointState command in order: validated
        (:func:`articulated.parse_joint_command`) and folded outside the twin
        lock, counted, and the result applied once (a command naming some
        joints keeps the others'). As for the actuation: the commands lost
        upstream are counted from the sequence numbers, and those applied
        but replaced before a step used them as superseded."""
        batch = self._take_queued(self._sub_joints, (msg, info), JOINT_QUEUE)
        publishers = self._sub_joints.get_publisher_count()
        lost = sum(self._joint_gaps.add(inputs.sequence_number(inf), publishers) for _, inf in batch)
        with self._lock:
            twin = self.twin
            start = (twin.positions, twin.efforts)
        fold = inputs.fold_joint_commands(twin.mech, batch, *start)
        with self._lock:
            twin = self.twin
            if (twin.positions, twin.efforts) != start:
                # reset, a plan or another batch meanwhile: fold again onto the new commands
                fold = inputs.fold_joint_commands(twin.mech, batch, twin.positions, twin.efforts)
            pos, eff, newest, n_applied, errors = fold
            s = self.stats
            s.input_batches.append(len(batch))
            s.totals["joint_commands_received"] += len(batch)
            s.totals["joint_commands_lost"] += lost
            s.lost += lost
            for e in errors:
                s.reject("joint", e)
            if newest is not None:
                s.totals["joint_commands_applied"] += n_applied
                s.totals["joint_commands_superseded"] += n_applied - 1 + int(twin.joint_command_pending)
                twin.set_joint_commands(pos, eff, stamp=newest.header)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("joint command", errors), throttle_duration_sec=1.0)
        if newest is not None:
            self._react_to_input(batch)

    def _publish_articulated(self, snap, header):
        if self.listened(self._pub_joints):
            js = JointState(header=header, name=list(snap.joint_names))
            js.position = snap.joint_positions.tolist()
            js.velocity = snap.joint_velocities.tolist()
            js.effort = snap.joint_efforts.tolist()
            self._pub_joints.publish(js)
        for name, pub in self._pub_members.items():
            if self.listened(pub):
                pub.publish(cv.pose_array(snap.backbones[name][0], header))
        for name, pub in self._pub_internal.items():
            if self.listened(pub):
                w = np.asarray(snap.internal_wrenches[name], dtype=float)
                msg = Float64MultiArray(data=w.ravel().tolist())
                msg.layout.dim = [MultiArrayDimension(label="section_boundary", size=len(w), stride=w.size),
                                  MultiArrayDimension(label="N_V2_V3_T_M2_M3", size=6, stride=6)]
                pub.publish(msg)

    # ------------------------------------------------------------------------
    # configuration
    # ------------------------------------------------------------------------
    def _startup_point(self):
        """Between two steps of the start-up: abandon it if a stop was asked."""
        if self._stop_requested():
            self.destroy_node()
            raise StartupInterrupted("stop requested during the start-up")

    def _guarded(self, callback):
        """The callback, made unable to take the node down: an unexpected
        exception (a bug, not a bad input: those are handled where they
        arise) is logged with its traceback and counted in the diagnostics
        (internal_errors_total); a service gets success=False."""
        def run(*args):
            try:
                return callback(*args)
            except Exception as e:
                if not self.context.ok():
                    # shutting down (Ctrl-C shuts the context down from the signal
                    # handler while a step may still be publishing): not an error
                    return None
                with self._stats_lock:
                    self.stats.totals["internal_errors"] += 1
                    self.stats.last_internal_error = clip(f"{callback.__name__}: {type(e).__name__}: {e}", 400)
                self.get_logger().error(f"internal error in {callback.__name__}: {type(e).__name__}: "
                                        f"{clip(e, 400)}\n" + clip(traceback.format_exc(), 4000),
                                        throttle_duration_sec=1.0)
                if len(args) == 2 and hasattr(args[1], "success"):      # a service response
                    args[1].success = False
                    args[1].message = clip(f"internal error: {type(e).__name__}: {e}", 400)
                    return args[1]
                return None
        run.__name__ = callback.__name__
        return run

    def _declared_value(self, name):
        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:
            return None

    @staticmethod
    def _settings(cfg):
        return tw.TwinSettings(mode=cfg.mode, dt=cfg.dt, theta=cfg.integrator_theta,
                               tolerance=cfg.integrator_tolerance,
                               points_per_section=cfg.backbone_points_per_section)

    def _make_stepper(self):
        """The stepping clock (:class:`soft_twin.stepper.Stepper`, a thread,
        not an rclpy timer: see its module) at the step period (dynamic) or
        the re-publish period (quasi-static), its schedule restarted."""
        cfg = self.cfg
        period = cfg.wall_dt if cfg.mode == "dynamic" else 1.0 / cfg.republish_rate_hz
        with self._lock:
            self._anchor = None        # wall time of twin step 0 (dynamic schedule)
            self._steps_done = 0
            self._unpublished = 0
            self._last_wrench_time = -math.inf
            self._last_marker_time = -math.inf
        if self._stepper is None:
            self._stepper = Stepper(self._guarded(self._on_step_tick), period)
        else:
            self._stepper.set_period(period)

    def _coerce_parameters(self, params):
        """Before rclpy looks at a change: an integer for one of our float
        parameters becomes that float (the parameter keeps its type), and a
        name the node does not have is refused with a reason naming it
        (rclpy's own says "undeclared parameter(s): []"), and counted."""
        unknown = [p.name for p in params if not self.has_parameter(p.name)]
        if unknown:
            self._count_parameter_rejection(unknown_parameters_message(unknown))
            raise UnknownParameterError(unknown)
        return [Parameter(p.name, value=coerced(p.name, p.value)) if p.name in PARAMETERS else p
                for p in params]

    def _count_parameter_rejection(self, reason):
        reason = clip(reason, 400)
        with self._stats_lock:
            self.stats.totals["rejected_parameter_changes"] += 1
            self.stats.last_parameter_rejection = reason
        self.get_logger().warn(f"parameter change rejected: {reason}")

    def _on_set_parameters(self, params):
        """Validate a parameter change as a whole; reject with a reason (the
        running twin is untouched, the refusal counted) or stage it for
        _after_set_parameters."""
        values = dict(self._values)
        try:
            for p in params:
                if p.name not in PARAMETERS:
                    continue            # e.g. use_sim_time: not ours
                if p.type_ == Parameter.Type.NOT_SET:
                    raise ConfigError(f"{p.name}: cannot be unset (it is a parameter of this node)")
                values[p.name] = p.value
            cfg = config_from_values(values)
            robot = load_robot(cfg) if (cfg.robot_key != self.cfg.robot_key
                                        or cfg.actuator_names != self.cfg.actuator_names) else None
            twin = None
            if robot is not None and cfg.robot_key != self.cfg.robot_key:
                twin = self._make_twin(robot, self._settings(cfg))   # solves the rest shape: fails here, not later
        except ConfigError as e:
            reason = clip(e, 400)
            self._count_parameter_rejection(reason)
            return SetParametersResult(successful=False, reason=reason)
        except Exception as e:  # a robot the core cannot handle: reject, keep running
            reason = clip(f"{type(e).__name__}: {e}", 400)
            self._count_parameter_rejection(reason)
            return SetParametersResult(successful=False, reason=reason)
        self._staged = (values, cfg, robot, twin)
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params):
        if self._staged is None:
            return
        values, cfg, robot, twin = self._staged
        self._staged = None
        old = self.cfg
        with self._lock:
            self._values, self.cfg = values, cfg
            if robot is not None:
                self.robot = robot
            if twin is not None:
                self.twin = twin
                old_worker, self._query_worker = self._query_worker, self._make_query_worker(robot)
                if old_worker is not None:
                    old_worker.close()
            else:
                self.twin.change_settings(self._settings(cfg))
        if twin is not None:
            self.get_logger().info(f"new robot {robot.model.name!r} from {robot.source}: state reset")
        if (cfg.mode, cfg.step_rate_hz, cfg.republish_rate_hz, cfg.time_scale) != (
                old.mode, old.step_rate_hz, old.republish_rate_hz, old.time_scale):
            self._make_stepper()
        if cfg.diagnostics_rate_hz != old.diagnostics_rate_hz:
            self._diag_timer.timer_period_ns = int(1e9 / cfg.diagnostics_rate_hz)
        if cfg.mode == "quasi_static":
            self._solve_trigger.trigger()
        if cfg.record_file != old.record_file or any(p.name == "record_file" for p in params):
            self._recorder.follow(cfg.record_file)     # issue 12: a new recording ('' stops)
        self._live_view.follow(cfg.live_view_port)     # issue 12: browser view on/off
        self.get_logger().info("parameters applied: " + ", ".join(f"{p.name}={clip(repr(p.value), 100)}"
                                                                  for p in params))

    # ------------------------------------------------------------------------
    # inputs
    # ------------------------------------------------------------------------
    def _take_queued(self, sub, first, limit):
        """The message the executor took (with its info) plus the others
        waiting in the subscription's queue, oldest first, at most ``limit``
        in all (more stay queued for the next callback). One executor
        dispatch per message costs ~1 ms of Python and far more while a
        service computes (GIL): at 1 kHz the queue overflowed; draining it
        here makes that cost per batch."""
        batch = [first]
        try:
            with sub.handle:
                while len(batch) < limit:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is None:
                        break
                    batch.append(taken)
        except InvalidHandle:      # destroyed under us: shutting down
            pass
        self._recorder.received(sub, batch)            # issue 12: recording of the inputs
        return batch

    def _on_actuation(self, msg, info=None):
        """Every queued command in order: counted, validated and folded into
        the actuation (a partial command keeps the other actuators); the
        result is applied once, stamped with the newest valid command. The
        commands applied but not the newest of their batch, or replaced
        before a step used them, are counted as superseded. The folding runs
        outside the twin lock (it holds the lock for microseconds, so a step
        never waits for a batch)."""
        batch = self._take_queued(self._actuation_sub, (msg, info), ACTUATION_QUEUE)
        publishers = self._actuation_sub.get_publisher_count()
        taken_ns = self.get_clock().now().nanoseconds
        lost = sum(self._command_gaps.add(inputs.sequence_number(inf), publishers) for _, inf in batch)
        with self._lock:
            twin, cfg = self.twin, self.cfg
            u0 = twin.u
        fold = inputs.fold_commands(twin.model, batch, u0, cfg.actuator_names)
        with self._lock:
            twin = self.twin
            if twin.u is not u0 or self.cfg is not cfg:
                # reset or reconfigured meanwhile: fold again onto the new actuation
                fold = inputs.fold_commands(twin.model, batch, twin.u, self.cfg.actuator_names)
            u, newest, n_applied, errors = fold
            s = self.stats
            s.input_batches.append(len(batch))
            s.totals["commands_received"] += len(batch)
            s.totals["commands_lost"] += lost
            s.lost += lost
            for e in errors:
                s.reject("actuation", e)
            if newest is not None:
                s.totals["commands_applied"] += n_applied
                s.totals["commands_superseded"] += n_applied - 1 + int(twin.command_pending)
                twin.set_actuation(u, stamp=newest.header)
                stamp_ns = newest.header.stamp.sec * 1_000_000_000 + newest.header.stamp.nanosec
                # latency from the command's stamp (a zero stamp: from its arrival here)
                self._command_received = (newest.header, stamp_ns if stamp_ns > 0 else taken_ns, taken_ns)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("actuation command", errors), throttle_duration_sec=1.0)
        if newest is not None:
            self._react_to_input(batch)

    def _on_tip_wrench(self, msg, info=None):
        """Every queued wrench in order, counted and validated (outside the
        twin lock); the newest valid one is applied (a wrench replaces the
        one before)."""
        batch = self._take_queued(self._wrench_sub, (msg, info), WRENCH_QUEUE)
        publishers = self._wrench_sub.get_publisher_count()
        lost = sum(self._wrench_gaps.add(inputs.sequence_number(inf), publishers) for _, inf in batch)
        cfg = self.cfg
        newest, errors = inputs.parse_wrenches(batch, cfg)
        with self._lock:
            if self.cfg is not cfg:     # reconfigured meanwhile (frames)
                newest, errors = inputs.parse_wrenches(batch, self.cfg)
            s = self.stats
            s.totals["wrenches_received"] += len(batch)
            s.totals["wrenches_applied"] += len(batch) - len(errors)
            s.totals["wrenches_lost"] += lost
            s.lost += lost
            for e in errors:
                s.reject("wrench", e)
            if newest is not None:
                self.twin.set_tip_wrench(*newest)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("tip wrench", errors), throttle_duration_sec=1.0)
        if newest is not None:
            self._react_to_input(batch)

    def _on_base_pose(self, msg, info=None):
        """Every queued geometry_msgs/PoseStamped in order, counted and
        validated (:func:`inputs.parse_base_poses`); the newest valid one is
        where the prescribed base goes at the next step."""
        batch = self._take_queued(self._base_pose_sub, (msg, info), WRENCH_QUEUE)
        publishers = self._base_pose_sub.get_publisher_count()
        lost = sum(self._base_pose_gaps.add(inputs.sequence_number(inf), publishers) for _, inf in batch)
        with self._lock:
            newest, errors = inputs.parse_base_poses(batch, self.cfg, self.twin.mech)
            s = self.stats
            s.totals["base_poses_received"] += len(batch)
            s.totals["base_poses_applied"] += len(batch) - len(errors)
            s.totals["base_poses_lost"] += lost
            s.lost += lost
            for e in errors:
                s.reject("base_pose", e)
            if newest is not None:
                self.twin.set_base_pose(newest)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("base pose", errors), throttle_duration_sec=1.0)
        if newest is not None:
            self._react_to_input(batch)

    def _on_point_wrench(self, msg, info=None):
        """Every queued soft_twin/PointWrench in order, counted with the
        tip wrenches and validated (:func:`inputs.parse_point_wrenches`);
        each valid one replaces the load on its point (zeros remove it)."""
        batch = self._take_queued(self._point_wrench_sub, (msg, info), WRENCH_QUEUE)
        publishers = self._point_wrench_sub.get_publisher_count()
        lost = sum(self._point_wrench_gaps.add(inputs.sequence_number(inf), publishers) for _, inf in batch)
        with self._lock:
            valid, errors = inputs.parse_point_wrenches(batch, self.cfg, self.twin.mech)
            s = self.stats
            s.totals["wrenches_received"] += len(batch)
            s.totals["wrenches_applied"] += len(valid)
            s.totals["wrenches_lost"] += lost
            s.lost += lost
            for e in errors:
                s.reject("wrench", e)
            for point, w, axes in valid:
                self.twin.set_point_wrench(point, w, axes)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("point wrench", errors), throttle_duration_sec=1.0)
        if valid:
            self._react_to_input(batch)

    def _on_obstacle(self, msg, info=None):
        """Every queued soft_twin/Obstacle in order: checked and applied
        (:func:`inputs.fold_obstacles`) to the twin's obstacles, counted; a
        move is taken over the next step (:meth:`Twin.set_obstacles`)."""
        batch = self._take_queued(self._obstacle_sub, (msg, info), OBSTACLE_QUEUE)
        with self._lock:
            twin = self.twin
            obstacles, n_applied, errors = inputs.fold_obstacles(batch, twin.obstacles)
            s = self.stats
            s.totals["obstacle_updates_received"] += len(batch)
            s.totals["obstacle_updates_applied"] += n_applied
            for e in errors:
                s.reject("obstacle", e)
            if n_applied:
                twin.set_obstacles(obstacles)
        if errors:
            self.get_logger().warn(inputs.rejection_warning("obstacle", errors), throttle_duration_sec=1.0)
        if n_applied:
            self._react_to_input(batch)

    def _react_to_input(self, batch):
        """Quasi-static: have the step group solve at once. Dynamic with
        step_on_command: take the next step right here (it saves the executor
        hand-over to the step group, ~0.5 ms and more under load) - for inputs
        arriving at most at the step rate (one input taken, at least dt after
        the one before, by arrival time); a faster stream is sampled by the
        stepping clock, which keeps this callback light for the next inputs.
        Either way, a stepping clock more than a period late (the GIL held by a
        service, a busy CPU) is caught up here rather than dropping steps."""
        info = batch[-1][1]
        arrival = info.get("received_timestamp", 0) if isinstance(info, dict) else 0
        arrival = 1e-9 * arrival if arrival else time.time()
        sparse = len(batch) == 1 and arrival - self._last_input_time >= self.cfg.wall_dt
        self._last_input_time = arrival
        if self.cfg.mode == "quasi_static":
            self._solve_trigger.trigger()
        elif sparse and self._early_step_allowed():
            self._step_dynamic(early=True)
        elif self._clock_late():
            # the stepping clock missed a tick (GIL, CPU): catch up here, unless a step is under way
            self._step_dynamic(wait=False)

    def _clock_late(self):
        """Dynamic mode: is the next step more than a period past its tick?
        (A hint read without the lock, like _early_step_allowed.)"""
        cfg = self.cfg
        return cfg.mode == "dynamic" and schedule.clock_late(time.monotonic(), self._anchor, cfg.wall_dt,
                                                              self._steps_done)

    # ------------------------------------------------------------------------
    # stepping
    # ------------------------------------------------------------------------
    def _on_step_tick(self):
        if self.cfg.mode == "dynamic":
            self._step_dynamic()
        else:
            self._update_quasi_static(republish=True)

    def _on_solve_trigger(self):
        """A new input in quasi-static mode: solve at once."""
        if self.cfg.mode == "quasi_static":
            self._update_quasi_static(republish=False)

    def _early_step_allowed(self):
        """Dynamic mode, step_on_command: may the next step start now? Only
        while twin time does not already lead wall time (it never leads by
        more than one step, so the step rate is kept). A hint read without
        the lock; _step_dynamic decides under it."""
        cfg = self.cfg
        return (cfg.mode == "dynamic" and cfg.step_on_command
                and schedule.may_step_early(time.monotonic(), self._anchor, cfg.wall_dt, self._steps_done))

    def _step_dynamic(self, early=False, wait=True):
        """The steps due by the wall clock: twin step k is due at anchor + k dt.
        ``early`` (a new input arrived, step_on_command): step k may start
        now if step k - 1 is due, so twin time never leads by more than one
        step. Called by the stepping clock and, for early or late steps, by the
        input callbacks: the lock serialises them, the publish lock keeps the
        published states in order. ``wait=False``: return at once if the
        lock is busy (a step under way takes what is due)."""
        cfg = self.cfg
        if not self._lock.acquire(blocking=wait):
            return
        try:
            now = time.monotonic()
            if self._paused:
                return
            if self._anchor is None:
                self._anchor = now - cfg.wall_dt
            due = schedule.steps_due(now, self._anchor, cfg.wall_dt, self._steps_done, early)
            if due <= 0:
                return
            due, dropped = schedule.catch_up(due, cfg.max_catchup_steps)
            self.stats.totals["dropped_steps"] += dropped
            self._steps_done += dropped
            twin, robot = self.twin, self.robot
            info = twin.step(due)
            # a failed step (its input dropped) is taken again at the next tick, as a catch-up step
            self._steps_done += due if info.converged else info.steps
            self._record(info, twin.settings.dt * info.steps)
            self._unpublished += due          # failed steps too: the last good state keeps coming
            if self._unpublished < cfg.publish_every_n_steps:
                return
            self._unpublished = 0
            snap = twin.outputs()
            self._publish_lock.acquire()      # before the twin lock is released: states go out in order
        finally:
            self._lock.release()
        header = self._publish_taken(snap, robot)
        if now - self._last_wrench_time >= 1.0 / cfg.wrench_rate_hz - 0.5 * cfg.dt:
            self._publish_wrenches(snap, robot, header, now)

    def _update_quasi_static(self, republish):
        with self._lock:
            twin, robot = self.twin, self.robot
            if not twin.needs_solve and not republish:
                return
            if self._paused:             # the state shown stays: republished, new inputs wait for ~/step
                if not republish:
                    return
            else:
                solved = twin.needs_solve
                info = twin.step()
                if solved:
                    self._record(info, 0.0)
            snap = twin.outputs()
            self._publish_lock.acquire()
        header = self._publish_taken(snap, robot)
        self._publish_wrenches(snap, robot, header, time.monotonic())

    def set_paused(self, paused):
        """Pause (True) or resume the twin: paused, the dynamic twin takes
        no step and a quasi-static one solves no new input (the inputs
        still arrive, are counted and wait), until :meth:`single_step` or
        the resume; resumed, the schedule restarts from now (no catch-up
        of the pause). Returns (paused before, twin time [s])."""
        with self._lock:
            was, self._paused = self._paused, bool(paused)
            if was and not self._paused:
                self._anchor, self._steps_done = None, 0
            t, mode = self.twin.state.t, self.cfg.mode
            snap, robot = self.twin.outputs(), self.robot
        if not paused and mode == "quasi_static":
            self._solve_trigger.trigger()
        with self._publish_lock:
            self._live_view.publish(snap, robot, force=True)      # the page's state line says so
        return was, t

    def single_step(self):
        """While paused: one step of dt (dynamic) or the solve of the inputs
        waiting (quasi-static), published. Returns its UpdateInfo and the
        twin time after it, or None when the twin is not paused."""
        with self._lock:
            if not self._paused:
                return None
            twin, robot = self.twin, self.robot
            dynamic = self.cfg.mode == "dynamic"
            info = twin.step(1)
            self._record(info, twin.settings.dt * info.steps if dynamic else 0.0)
            snap, t = twin.outputs(), twin.state.t
            self._publish_lock.acquire()
        header = self._publish_taken(snap, robot)
        self._publish_wrenches(snap, robot, header, time.monotonic())
        return info, t

    @property
    def paused(self):
        return self._paused

    def _publish_taken(self, snap, robot):
        """Publish a state whose publish lock the caller took while holding
        the twin lock (so that states go out in step order), and release
        it; returns the header."""
        try:
            return self._publish(snap, robot)
        finally:
            self._publish_lock.release()

    def _record(self, info, sim_dt):
        """Statistics of one step call or solve (under the lock)."""
        dropped = self.stats.record(info, sim_dt)
        if "actuation" in dropped:
            self._command_received = None
        if not info.converged:
            self.get_logger().error(info.message, throttle_duration_sec=1.0)

    # ------------------------------------------------------------------------
    # outputs
    # ------------------------------------------------------------------------
    def create_publisher(self, *args, **kwargs):
        """rclpy's, without its default QoS-event handlers (two per publisher:
        a warning on an incompatible subscriber's QoS or type; that
        subscriber's own node warns too). Each is a waitable the Python
        executor visits on every wake-up: the node's 20 of them were a third
        of a wake-up's ~2.5 ms under the GIL (py-spy), paid twice per service
        request. The subscriptions keep theirs (a user's publisher that cannot
        reach the twin is reported here)."""
        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def _header(self, frame):
        return Header(stamp=self.get_clock().now().to_msg(), frame_id=frame)

    def listened(self, pub):
        """Someone takes ``pub``'s messages: a subscriber, or the recording.
        A state topic nobody takes is not built: the backbone's PoseArray
        alone cost ~1 ms of Python per state under the GIL (py-spy), time a
        service computing in the node waited for."""
        return pub.get_subscription_count() > 0 or self._recorder.recording

    def _publish(self, snap, robot):
        """The state topics someone takes (backbone first: it is what latency is measured
        on); returns their common header."""
        t0 = time.perf_counter()
        cfg = self.cfg
        stamp = self.get_clock().now()
        header = Header(stamp=stamp.to_msg(), frame_id=cfg.base_frame)
        if self.listened(self._pub_backbone):
            self._pub_backbone.publish(cv.pose_array(snap.backbone, header))
        if self.listened(self._pub_tip):
            self._pub_tip.publish(PoseStamped(header=header, pose=cv.pose_msg(snap.tip_pose)))
        if self.listened(self._pub_strains):
            strains = Strains(header=header, n_sections=len(snap.strains))
            strains.strains = snap.strains.ravel().tolist()
            strains.strain_rates = snap.strain_rates.ravel().tolist()
            if snap.command_stamp is not None:
                strains.last_command = snap.command_stamp
            self._pub_strains.publish(strains)
        self._publish_articulated(snap, header)
        if self.listened(self._pub_contacts):
            self._pub_contacts.publish(cv.contacts_msg(robot.mech, snap.contacts, snap.obstacles, header))
        self._last_articulated = snap
        self._tf.publish(snap, robot, header)          # issue 12: /tf
        self._live_view.publish(snap, robot)           # issue 12: browser view (throttled)
        received = self._command_received
        if received is not None and received[0] is snap.command_stamp:
            # the first publication of a state with this command: latency from the
            # command's stamp to this state's stamp (queueing in the node included)
            self._command_received = None
            self.stats.command_latencies.append(1e-9 * (stamp.nanoseconds - received[1]))
            self.stats.node_latencies.append(1e-9 * (stamp.nanoseconds - received[2]))
        now = time.monotonic()
        if (cfg.marker_rate_hz > 0 and now - self._last_marker_time >= 1.0 / cfg.marker_rate_hz
                and self.listened(self._pub_markers)):
            self._last_marker_time = now
            self._pub_markers.publish(self._markers(snap, robot, header))
        self.stats.publish_times.append(time.perf_counter() - t0)
        self.stats.publishes += 1
        return header

    def _publish_wrenches(self, snap, robot, header, now):
        """Tip and base wrenches of a published state (same stamp), computed
        outside the locks, only when someone listens (a subscriber or the
        recording: every documented topic is recorded), by one thread at a
        time (another thread already at it: skipped)."""
        if not (self.listened(self._pub_tip_wrench) or self.listened(self._pub_base_wrench)
                or any(self.listened(p) for p in self._pub_constraints.values())):
            return
        if not self._wrench_lock.acquire(blocking=False):
            return
        try:
            self._last_wrench_time = now
            tip, base = snap.tip_wrench, snap.base_wrench
            for key, pub in self._pub_constraints.items():
                w = snap.joint_wrenches[key[1]] if isinstance(key, tuple) else snap.constraint_wrenches[key]
                pub.publish(WrenchStamped(header=header, wrench=cv.wrench_msg(w)))
            self._pub_tip_wrench.publish(WrenchStamped(header=Header(stamp=header.stamp,
                                                                     frame_id=self.cfg.tip_frame),
                                                       wrench=cv.wrench_msg(tip)))
            self._pub_base_wrench.publish(WrenchStamped(header=header, wrench=cv.wrench_msg(base)))
        finally:
            self._wrench_lock.release()

    def _publish_diagnostics(self):
        """The /diagnostics status of the period since the last one (:mod:`soft_twin.diagnostics`)."""
        now = time.monotonic()
        with self._lock:
            s, cfg, twin = self.stats, self.cfg, self.twin
            gaps = {"actuation": self._command_gaps, "wrench": self._wrench_gaps, "joint": self._joint_gaps}
            values, rate = diagnostics.values(s, cfg, twin, gaps, now, self._paused)
            values.update(diagnostics.joint_values(s, gaps, getattr(self, "_last_articulated", None)))
            new_error = s.totals["internal_errors"] > self._reported_internal_errors
            level, message = diagnostics.level(s, cfg, rate, new_error, self._paused)
            if new_error and message.startswith("internal error"):
                self._reported_internal_errors = s.totals["internal_errors"]
            s.reset_window(now)
        self._pub_diag.publish(diagnostics.diagnostic_array(self._header(cfg.base_frame), f"{self.get_name()}: twin",
                                                            twin.model.name, level, message, values))

    # ------------------------------------------------------------------------
    # services
    # ------------------------------------------------------------------------
    # the handlers: soft_twin.services
    def _srv_fk(self, req, resp):
        return services.forward_kinematics(self, req, resp)

    def _srv_statics(self, req, resp):
        return services.statics_query(self, req, resp)

    def _srv_ik(self, req, resp):
        return services.inverse_kinematics(self, req, resp, _SERVICE_TIMING)

    def _srv_plan_path(self, req, resp):
        from soft_twin import plan_service
        return plan_service.handle(self, self._plan_runner, req, resp, ActuationCommand, JointState)

    def _srv_cancel_plan(self, req, resp):
        from soft_twin import plan_service
        return plan_service.handle_cancel(self, self._plan_runner, resp)

    def _srv_reset(self, req, resp):
        return services.reset(self, req, resp)

    def _srv_pause(self, req, resp):
        return services.pause(self, req, resp)

    def _srv_step(self, req, resp):
        return services.single_step(self, req, resp)

    # --- the plan execution stops, the MCAP recording closes with the node ----
    def destroy_node(self):
        if getattr(self, "_stepper", None) is not None:
            self._stepper.close()
        runner = getattr(self, "_plan_runner", None)
        if runner is not None:
            runner.cancel()
        recorder_ = getattr(self, "_recorder", None)
        if recorder_ is not None:
            recorder_.close()
        if getattr(self, "_live_view", None) is not None:
            self._live_view.close()
        if getattr(self, "_query_worker", None) is not None:
            self._query_worker.close()
        return super().destroy_node()


def _topic_name(name):
    """A ROS topic token for a user-given name (letters, digits, underscores)."""
    import re
    t = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return t if t and not t[0].isdigit() else f"_{t}"


def main(args=None):
    """Console entry point ``soft_twin_node`` (``--ros-args`` passed through).
    Exit status 0 after SIGINT or SIGTERM (at any time), 2 for an invalid
    configuration (a bad or unknown parameter, a robot that cannot load)."""
    # hand the GIL to the stepping thread within ~1 ms of a service computing
    sys.setswitchinterval(0.001)
    blas_on_one_thread()      # no spinning BLAS thread beside the controller (small matrices)
    stop = StopSignals(NODE_NAME)
    stop.install()
    logger = rclpy.logging.get_logger(NODE_NAME)
    node = executor = None
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        try:
            node = SoftTwinNode(stop_requested=stop.requested)
        except ConfigError as e:
            logger.fatal(f"invalid configuration: {clip(e, 2000)}")
            return 2
        logger = node.get_logger()
        stop.add_last_act(node._recorder.close_now)
        executor = TwinExecutor(num_threads=5)
        executor.add_node(node)
        spin_until_stopped(executor, stop)
    except StartupInterrupted:
        pass
    finally:
        twin = getattr(node, "twin", None)
        tear_down(stop, logger, executor, node,
                  f" (twin time {twin.state.t:.3f} s, {node.stats.totals['steps']} steps)"
                  if twin is not None and executor is not None else " during start-up")
    if stop.received is not None:
        logger.info("stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
