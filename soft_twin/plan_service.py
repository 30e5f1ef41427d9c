"""The node's ~/plan_path service: plan a tip path through statics
(:mod:`soft_twin_core.planning.planner`, :meth:`soft_twin_core.twin.Twin.plan`) from the twin's current state
and, on request, execute it: one ActuationCommand per sample, stamped and
published at its planned time on the ``plan_output_topic`` (for the real
robot), and on the twin's own ``~/actuation`` so that the twin follows the
same commands through its ordinary input path; an articulated robot's
position-controlled joints likewise get one JointState per sample on the
``plan_joint_output_topic`` and on the twin's ``~/joint_commands``."""

from dataclasses import dataclass
import threading
import time

import numpy as np
import yaml

from soft_twin_core.errors import StaticsError
from soft_twin_core.planning import paths as pth
from soft_twin_core.planning import planner as pl
from soft_twin_core.robot.model import ModelError

from soft_twin import services
from soft_twin.query_worker import QueryError
from soft_twin_core.text import clip

# the first command goes out this long after the answer is ready, so a
# client can be listening when it does (s)
START_DELAY_S = 0.2


_PLAN_ERRORS = (pth.PathError, pl.PlanError, ModelError, ValueError, StaticsError, np.linalg.LinAlgError,
                QueryError)


def plan_request(req, plan):
    """(a plan, None) or (None, message) for a PlanPath request: the path
    parsed and the numbers checked at the door, then ``plan(path,
    position_weights=, tolerance=, pretension=, max_rate=)`` (the twin's
    planner, :meth:`soft_twin_core.twin.Twin.plan`)."""
    try:
        d = yaml.safe_load(req.path_yaml) if req.path_yaml.strip() else None
    except yaml.YAMLError as e:
        return None, f"path_yaml: invalid YAML: {clip(str(e), 200)}"
    try:
        path = pth.path_from_dict(d, "path")
        w = tuple(req.position_weights) if len(req.position_weights) else (1.0, 1.0, 1.0)
        for name in ("tolerance", "pretension", "max_rate"):
            v = getattr(req, name)
            if not np.isfinite(v) or v < 0:
                return None, f"{name}: expected a finite number >= 0, got {v}"
        return plan(path, position_weights=w, tolerance=req.tolerance or 1e-6, pretension=req.pretension,
                    max_rate=req.max_rate or None), None
    except _PLAN_ERRORS as e:
        return None, clip(str(e), 400)


def plan_columns(plan):
    """(names, values (N, k)): the plan's joint commands first, then the
    actuator inputs."""
    return tuple(plan.joint_names) + tuple(plan.actuator_names), np.hstack([plan.joints, plan.u])


def fill_response(resp, plan):
    names, values = plan_columns(plan)
    resp.actuator_names = list(names)
    resp.times = (plan.times - plan.times[0]).tolist()
    resp.values = values.ravel().tolist()
    resp.predicted_tip = plan.tip.ravel().tolist()
    resp.errors = plan.weighted_error.tolist()
    resp.reached = [bool(r) for r in plan.reached]
    resp.unreachable = int((~plan.reached).sum())
    s = plan.summary()
    resp.success = resp.unreachable == 0
    resp.message = (f"planned {s['samples']} samples, all reached (max error {s['max_error_m']:.3g} m)"
                    if resp.success else
                    f"planned {s['samples']} samples: {resp.unreachable} not reachable {s['statuses']}, "
                    f"the plan follows the closest reachable points")


@dataclass
class Channel:
    """One stream of a plan's execution: ``values`` (N, len(names)) as
    ``msg_type`` (ActuationCommand or sensor_msgs/JointState positions) on
    ``topic`` (for the real robot) and on the twin's own input ``own``."""
    msg_type: type
    names: tuple
    values: np.ndarray
    topic: str
    own: str


def _message(msg_type, names, values, ns, frame_id):
    msg = msg_type()
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    msg.header.frame_id = frame_id
    vals = [float(v) for v in values]
    if hasattr(msg, "position"):              # sensor_msgs/JointState
        msg.name, msg.position = list(names), vals
    else:                                     # soft_twin/ActuationCommand
        msg.names, msg.values = list(names), vals
    return msg


class PlanRunner:
    """Publishes a plan's commands at their times from a thread of its own;
    a new plan or :meth:`cancel` stops the running one."""

    def __init__(self, node):
        self._node = node
        self._pubs = {}
        self._thread = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.published = 0
        self._progress = [0, 0]        # samples of the current/last execution: [published, planned]

    def _publisher(self, msg_type, topic):
        key = (msg_type, self._resolved(topic))
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self._node.create_publisher(msg_type, topic, 100)
        return pub

    def prepare(self, msg_type, topic, own):
        """Make the output publisher now (subscribers can match before a plan
        runs). The publisher on the twin's own input exists only while a
        plan runs (an idle extra publisher there would blur the node's
        accounting of lost commands by sequence numbers)."""
        with self._lock:
            if self._resolved(topic) != self._resolved(own):
                self._publisher(msg_type, topic)

    def _resolved(self, topic):
        try:
            return self._node.resolve_topic_name(topic)
        except Exception:      # older rclpy: compare as given
            return topic

    def start(self, channels, times, frame_id=""):
        """Start publishing now + START_DELAY_S; returns the start stamp
        (builtin_interfaces/Time): sample k of every channel is stamped start
        + times[k]."""
        self.cancel()
        with self._lock:
            streams, own = [], []
            for ch in channels:
                pubs = [self._publisher(ch.msg_type, ch.topic)]
                if self._resolved(ch.topic) != self._resolved(ch.own):
                    pubs.append(self._publisher(ch.msg_type, ch.own))
                    own.append(((ch.msg_type, self._resolved(ch.own)), pubs[-1]))
                streams.append((ch.msg_type, tuple(ch.names), np.asarray(ch.values, float), pubs))
            clock = self._node.get_clock()
            start_ns = clock.now().nanoseconds + int(START_DELAY_S * 1e9)
            t0 = time.monotonic() + START_DELAY_S
            self._stop = stop = threading.Event()
            self._progress = [0, len(times)]
            self._thread = threading.Thread(
                target=self._run, args=(stop, streams, np.asarray(times, float), start_ns, t0, frame_id, own),
                name="plan_runner", daemon=True)
            self._thread.start()
        from builtin_interfaces.msg import Time
        return Time(sec=start_ns // 1_000_000_000, nanosec=start_ns % 1_000_000_000)

    def _run(self, stop, streams, times, start_ns, t0, frame_id, own):
        try:
            self._publish_all(stop, streams, times, start_ns, t0, frame_id)
        finally:
            with self._lock:
                for key, pub in own:
                    if self._pubs.get(key) is pub and self._thread is threading.current_thread():
                        del self._pubs[key]
                        try:
                            self._node.destroy_publisher(pub)
                        except Exception:      # the node is going away
                            pass

    def _publish_all(self, stop, streams, times, start_ns, t0, frame_id):
        for k, t in enumerate(times):
            if stop.wait(max(0.0, t0 + t - time.monotonic())):
                return
            ns = start_ns + int(round(t * 1e9))
            try:
                for msg_type, names, values, pubs in streams:
                    msg = _message(msg_type, names, values[k], ns, frame_id)
                    for p in pubs:
                        p.publish(msg)
            except Exception:     # the node is shutting down
                return
            self.published += 1
            self._progress[0] += 1

    def running(self):
        return self._thread is not None and self._thread.is_alive()

    def cancel(self):
        """Stop the running execution (if any) and wait for its thread: no
        command of it goes out after this returns. Returns (was running,
        samples published, samples planned)."""
        with self._lock:
            was = self._thread is not None and self._thread.is_alive() and not self._stop.is_set()
            self._stop.set()
            th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(timeout=2.0)
        return was, self._progress[0], self._progress[1]


def handle_cancel(node, runner, resp):
    """The ~/cancel_plan callback body (std_srvs/Trigger): success True when
    an execution was running and is now stopped (its remaining commands are
    never published; the twin and the robot keep the last command sent),
    False when none was running."""
    was, done, total = runner.cancel()
    if was:
        resp.success = True
        resp.message = (f"plan execution cancelled after {done} of {total} commands; the last command "
                        f"sent stays applied")
    else:
        resp.success = False
        resp.message = "no plan is executing" + (f" (the last one published {done} of {total} commands)"
                                                 if total else "")
    node.get_logger().info(f"cancel_plan: {resp.message}")
    return resp


def channels(plan, cfg, actuation_type, joint_type):
    """The execution's streams: the actuator inputs (ActuationCommand on
    ``plan_output_topic`` and ``~/actuation``) and, for an articulated
    robot, the joint position commands (JointState on
    ``plan_joint_output_topic`` and ``~/joint_commands``)."""
    out = []
    joints = tuple(plan.joint_names)
    if joints:
        out.append(Channel(joint_type, joints, plan.joints, cfg.plan_joint_output_topic, "~/joint_commands"))
    if len(plan.actuator_names):
        out.append(Channel(actuation_type, tuple(plan.actuator_names), plan.u, cfg.plan_output_topic,
                           "~/actuation"))
    return out


def handle(node, runner, req, resp, actuation_type, joint_type):
    """The ~/plan_path callback body (node: the TwinNode)."""
    cfg = node.cfg
    # the twin's planner on a copy of its state (services.ik_query: a tree robot in the query worker process)
    if node.robot.articulated:
        plan, err = plan_request(req, lambda path, **options: node.query("plan", path, **options))
    else:
        twin = services._twin_copy(node)
        plan, err = plan_request(req, twin.plan)
    if plan is None:
        resp.success, resp.message = False, f"plan rejected: {err}"
        return resp
    fill_response(resp, plan)
    if req.execute:
        chans = channels(plan, cfg, actuation_type, joint_type)
        resp.start_stamp = runner.start(chans, resp.times)
        resp.executing = True
        resp.message += f"; executing on {', '.join(c.topic for c in chans)} over {resp.times[-1]:.3g} s"
    node.get_logger().info(f"plan_path: {resp.message}")
    return resp
