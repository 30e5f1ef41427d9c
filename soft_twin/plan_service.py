"""The node's ~/plan_path service: plan a tip path through statics
(:mod:`soft_twin_core.planner`) from the twin's current state and, on
request, execute it: one ActuationCommand per sample, stamped and published
at its planned time on the ``plan_output_topic`` (for the real robot), and
on the twin's own ``~/actuation`` so that the twin follows the same
commands through its ordinary input path."""

import threading
import time

import numpy as np
import yaml

from soft_twin_core import paths as pth
from soft_twin_core import planner as pl
from soft_twin_core.model import ModelError
from soft_twin_core.statics import StaticsError

from soft_twin import twin as tw
from soft_twin.text import clip

# the first command goes out this long after the answer is ready, so a
# client can be listening when it does (s)
START_DELAY_S = 0.2


def plan_request(model, q, u, loads, req):
    """(Plan, None) or (None, message) for a PlanPath request."""
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
        opts = pl.PlanOptions(position_weights=w, tolerance=req.tolerance or 1e-6, pretension=req.pretension,
                              max_rate=req.max_rate or None, loads=loads)
        u_start = np.maximum(u, pl.actuator_bounds(model, opts)[0]) if req.max_rate > 0 else None
        return pl.plan_path(model, path, opts, u_start=u_start, q_start=q), None
    except (pth.PathError, pl.PlanError, ModelError, ValueError, StaticsError, np.linalg.LinAlgError) as e:
        return None, clip(str(e), 400)


def fill_response(resp, plan):
    resp.actuator_names = list(plan.actuator_names)
    resp.times = (plan.times - plan.times[0]).tolist()
    resp.values = plan.u.ravel().tolist()
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


class PlanRunner:
    """Publishes a plan's commands at their times from a thread of its own;
    a new plan or :meth:`cancel` stops the running one."""

    def __init__(self, node, msg_type, own_topic="~/actuation"):
        self._node = node
        self._type = msg_type
        self._pubs = {}
        self._own = own_topic
        self._thread = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.published = 0
        self._progress = [0, 0]        # commands of the current/last execution: [published, planned]

    def _publisher(self, topic):
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = self._node.create_publisher(self._type, topic, 100)
        return pub

    def prepare(self, topic):
        """Make the output publisher now (subscribers can match before a plan
        runs). The publisher on the twin's own input exists only while a
        plan runs (an idle extra publisher there would blur the node's
        accounting of lost commands by sequence numbers)."""
        with self._lock:
            if self._resolved(topic) != self._resolved(self._own):
                self._publisher(topic)

    def _resolved(self, topic):
        try:
            return self._node.resolve_topic_name(topic)
        except Exception:      # older rclpy: compare as given
            return topic

    def start(self, names, times, values, topic, frame_id=""):
        """Start publishing now + START_DELAY_S; returns the start stamp
        (builtin_interfaces/Time): command k is stamped start + times[k]."""
        self.cancel()
        with self._lock:
            out = [self._publisher(topic)]
            if self._resolved(topic) != self._resolved(self._own):
                out.append(self._publisher(self._own))
            own = self._pubs.get(self._own)
            clock = self._node.get_clock()
            start_ns = clock.now().nanoseconds + int(START_DELAY_S * 1e9)
            t0 = time.monotonic() + START_DELAY_S
            self._stop = stop = threading.Event()
            self._progress = [0, len(times)]
            self._thread = threading.Thread(
                target=self._run, args=(stop, out, list(names), np.asarray(times, float),
                                        np.asarray(values, float), start_ns, t0, frame_id, own),
                name="plan_runner", daemon=True)
            self._thread.start()
        from builtin_interfaces.msg import Time
        return Time(sec=start_ns // 1_000_000_000, nanosec=start_ns % 1_000_000_000)

    def _run(self, stop, pubs, names, times, values, start_ns, t0, frame_id, own):
        try:
            self._publish_all(stop, pubs, names, times, values, start_ns, t0, frame_id)
        finally:
            if own is not None:
                with self._lock:
                    if self._pubs.get(self._own) is own and self._thread is threading.current_thread():
                        del self._pubs[self._own]
                        try:
                            self._node.destroy_publisher(own)
                        except Exception:      # the node is going away
                            pass

    def _publish_all(self, stop, pubs, names, times, values, start_ns, t0, frame_id):
        for k, t in enumerate(times):
            if stop.wait(max(0.0, t0 + t - time.monotonic())):
                return
            msg = self._type()
            ns = start_ns + int(round(t * 1e9))
            msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
            msg.header.frame_id = frame_id
            msg.names = names
            msg.values = [float(v) for v in values[k]]
            try:
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
        commands published, commands planned)."""
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


def handle(node, runner, req, resp):
    """The ~/plan_path callback body (node: the TwinNode)."""
    model, q, u, w, frame, cfg, _ = node._copy_state()
    try:
        loads = tw.make_loads(model, w, frame)
    except (ValueError, ModelError) as e:
        resp.success, resp.message = False, clip(f"tip load: {e}", 400)
        return resp
    if not model.actuators:
        resp.success, resp.message = False, "this robot has no actuators: there is nothing to plan"
        return resp
    plan, err = plan_request(model, q, u, loads, req)
    if plan is None:
        resp.success, resp.message = False, f"plan rejected: {err}"
        return resp
    fill_response(resp, plan)
    if req.execute:
        resp.start_stamp = runner.start(plan.actuator_names, resp.times, plan.u, cfg.plan_output_topic)
        resp.executing = True
        resp.message += f"; executing on {cfg.plan_output_topic} over {resp.times[-1]:.3g} s"
    node.get_logger().info(f"plan_path: {resp.message}")
    return resp
