"""A client of a running soft_twin node, for tests, the demo and benchmarks.

:class:`NodeProcess` starts the node in a second Python process (and stops
it with SIGINT, as Ctrl-C would); :class:`TwinClient` talks to it from this
process with its own rclpy context, spinning in a background thread. Nothing
here sleeps a fixed time waiting for ROS: it waits for the condition it needs
(a matched subscription, a service, a message) up to a timeout.

    with NodeProcess(["-p", "mode:=quasi_static"]) as proc, TwinClient() as c:
        c.wait_ready(timeout=60)
        stamp = c.send_actuation(["tendon_y_pos"], [0.5])
        c.wait_until(lambda: c.applied(stamp), timeout=5)
"""

from collections import deque
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from soft_twin.msg import ActuationCommand, PointWrench, Strains
from soft_twin.srv import ForwardKinematics, InverseKinematics, PlanPath, StaticsQuery

REPO_ROOT = Path(__file__).resolve().parents[1]


def stamp_key(stamp):
    """A hashable key (sec, nanosec) of a builtin_interfaces/Time."""
    return (int(stamp.sec), int(stamp.nanosec))


def interrupt(proc, timeout=20.0):
    """Stop a child process as Ctrl-C would: SIGINT, then wait up to
    ``timeout`` s; killed if it has not stopped by then. Returns its exit
    code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


class NodeProcess:
    """The node in a child process: ``python -m soft_twin.node --ros-args ...``.

    ros_args: extra arguments after ``--ros-args`` (e.g. ``["-p", "mode:=dynamic"]``);
    node_name: remaps the node name (topics and services follow: ``/<name>/...``);
    module: the node's module (``soft_twin.estimator`` for the estimator).
    Run from the repository root when this module is in a checkout (the
    node then runs from the sources), else from the current directory. Output goes to ``log_path`` (default: a pipe
    read by :meth:`output`)."""

    def __init__(self, ros_args=(), node_name="soft_twin", log_path=None, cwd=None, env=None, module="soft_twin.node"):
        self.node_name = node_name
        args = [sys.executable, "-m", module, "--ros-args", "-r", f"__node:={node_name}", *ros_args]
        self.log_path = log_path
        cwd = cwd or (REPO_ROOT if (REPO_ROOT / "package.xml").is_file() else None)
        self._log = open(log_path, "w") if log_path else subprocess.PIPE
        self.proc = subprocess.Popen(args, cwd=cwd, env=env or os.environ.copy(), stdout=self._log,
                                     stderr=subprocess.STDOUT, text=True)
        self._out = None

    def alive(self):
        return self.proc.poll() is None

    def stop(self, timeout=20.0):
        """SIGINT, then wait; returns the exit code (kills after the timeout)."""
        interrupt(self.proc, timeout)
        if self._out is None and self._log is subprocess.PIPE:
            self._out = self.proc.stdout.read()
            self.proc.stdout.close()
        if self._log not in (None, subprocess.PIPE):
            self._log.close()
        return self.proc.returncode

    def output(self):
        """The node's log (after :meth:`stop`)."""
        if self._out is not None:
            return self._out
        return Path(self.log_path).read_text() if self.log_path else ""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


class TwinClient:
    """Subscribes to a twin's outputs, publishes its inputs, calls its services.

    Latest messages: ``backbone``, ``tip_pose``, ``strains``, ``tip_wrench``,
    ``base_wrench`` (None until received; an articulated robot's
    ``joint_states`` too when asked for in ``topics``), counts in ``counts``,
    ``diagnostics()`` as a dict. ``history`` keeps (receive time
    (time.monotonic), message) of the last ``keep`` backbones, strains and
    diagnostics dicts, for latency and rate measurements."""

    TOPICS = ("backbone", "tip_pose", "strains", "tip_wrench", "base_wrench")

    def __init__(self, node_name="soft_twin", client_name="soft_twin_client", keep=2000, topics=TOPICS):
        self.ns = f"/{node_name}"
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(client_name, context=self.context)
        self._topics = tuple(topics)
        self._cond = threading.Condition()
        self.backbone = self.tip_pose = self.strains = self.tip_wrench = self.base_wrench = None
        self.joint_states = None
        self._diag = None
        self.counts = dict(backbone=0, tip_pose=0, strains=0, tip_wrench=0, base_wrench=0, diagnostics=0,
                           joint_states=0)
        self.history = dict(backbone=deque(maxlen=keep), strains=deque(maxlen=keep),
                            diagnostics=deque(maxlen=keep), joint_states=deque(maxlen=keep))
        n = self.node
        types = dict(backbone=PoseArray, tip_pose=PoseStamped, strains=Strains, tip_wrench=WrenchStamped,
                     base_wrench=WrenchStamped, joint_states=JointState)
        for name in topics:
            n.create_subscription(types[name], f"{self.ns}/{name}", self._store(name), 50)
        n.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.pub_actuation = n.create_publisher(ActuationCommand, f"{self.ns}/actuation", 10)
        self.pub_wrench = n.create_publisher(WrenchStamped, f"{self.ns}/tip_wrench_command", 10)
        self.pub_point_wrench = n.create_publisher(PointWrench, f"{self.ns}/point_wrench_command", 10)
        self.pub_joints = n.create_publisher(JointState, f"{self.ns}/joint_commands", 10)
        self.clients = {
            "forward_kinematics": n.create_client(ForwardKinematics, f"{self.ns}/forward_kinematics"),
            "inverse_kinematics": n.create_client(InverseKinematics, f"{self.ns}/inverse_kinematics"),
            "statics_query": n.create_client(StaticsQuery, f"{self.ns}/statics_query"),
            "reset": n.create_client(Trigger, f"{self.ns}/reset"),
            "plan_path": n.create_client(PlanPath, f"{self.ns}/plan_path"),
            "cancel_plan": n.create_client(Trigger, f"{self.ns}/cancel_plan"),
            "pause": n.create_client(SetBool, f"{self.ns}/pause"),
            "step": n.create_client(Trigger, f"{self.ns}/step"),
        }
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    # --- plumbing ------------------------------------------------------------
    def _spin(self):
        try:
            self.executor.spin()
        except Exception:   # context shut down under us: we are closing
            pass

    def _store(self, name):
        def cb(msg):
            now = time.monotonic()
            with self._cond:
                setattr(self, name, msg)
                self.counts[name] += 1
                if name in self.history:
                    self.history[name].append((now, msg))
                self._cond.notify_all()
        return cb

    def _on_diag(self, msg):
        for status in msg.status:
            if status.name == f"{self.ns[1:]}: twin":
                with self._cond:
                    self._diag = (status, {kv.key: kv.value for kv in status.values})
                    self.counts["diagnostics"] += 1
                    self.history["diagnostics"].append((time.monotonic(), self._diag[1]))
                    self._cond.notify_all()

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- waiting -------------------------------------------------------------
    def wait_until(self, predicate, timeout):
        """Wait until predicate() is true (re-checked on every message); returns it."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                ok = predicate()
                if ok:
                    return ok
                left = end - time.monotonic()
                if left <= 0:
                    return ok
                self._cond.wait(min(left, 0.05))

    # The state topics every twin publishes on each step: wait_ready waits for the
    # first message of each one subscribed, so that a caller can read them at once.
    STATE_TOPICS = ("backbone", "tip_pose", "strains")

    def wait_ready(self, timeout=60.0):
        """Services up, inputs matched, a first message on every subscribed state
        topic (backbone, tip pose, strains) arrived; TimeoutError otherwise."""
        end = time.monotonic() + timeout
        for c in self.clients.values():
            if not c.wait_for_service(timeout_sec=max(0.1, end - time.monotonic())):
                raise TimeoutError(f"service {c.srv_name} not available after {timeout} s")
        ok = self.wait_until(lambda: (self.pub_actuation.get_subscription_count() > 0
                                      and self.pub_wrench.get_subscription_count() > 0
                                      and all(self.counts[t] > 0 for t in self.STATE_TOPICS
                                              if t in self._topics)),
                             max(0.1, end - time.monotonic()))
        if not ok:
            raise TimeoutError(f"twin {self.ns} not publishing/subscribed after {timeout} s")

    def wait_diagnostics(self, predicate=lambda d: True, timeout=10.0):
        """The next diagnostics dict satisfying predicate (None on timeout)."""
        start = self.counts["diagnostics"]
        got = self.wait_until(lambda: self.counts["diagnostics"] > start and predicate(self._diag[1]), timeout)
        return dict(self._diag[1]) if got else None

    def diagnostics(self):
        """The latest diagnostics key-values (dict), plus 'level' and 'message'."""
        with self._cond:
            if self._diag is None:
                return None
            status, values = self._diag
            return dict(values, level=int.from_bytes(status.level, "little")
                        if isinstance(status.level, bytes) else int(status.level), message=status.message)

    # --- inputs --------------------------------------------------------------
    def now(self):
        return self.node.get_clock().now().to_msg()

    def send_actuation(self, names, values, frame_id=""):
        """Publish an ActuationCommand; returns its header stamp (unique per call)."""
        msg = ActuationCommand()
        msg.header.stamp = self.now()
        msg.header.frame_id = frame_id
        msg.names = list(names)
        msg.values = [float(v) for v in values]
        self.pub_actuation.publish(msg)
        return msg.header.stamp

    def _send_wrench(self, pub, msg, force, torque, frame_id):
        """Stamp ``msg`` (a WrenchStamped or PointWrench), fill its wrench, publish it; returns its stamp."""
        msg.header.stamp = self.now()
        msg.header.frame_id = frame_id
        (msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z) = [float(v) for v in force]
        (msg.wrench.torque.x, msg.wrench.torque.y, msg.wrench.torque.z) = [float(v) for v in torque]
        pub.publish(msg)
        return msg.header.stamp

    def send_tip_wrench(self, force, torque, frame_id):
        return self._send_wrench(self.pub_wrench, WrenchStamped(), force, torque, frame_id)

    def send_point_wrench(self, point, force, torque, frame_id):
        """Publish a wrench on ``point`` (a frame or ``<member>@<s>``); returns its stamp."""
        return self._send_wrench(self.pub_point_wrench, PointWrench(point=str(point)), force, torque, frame_id)

    def send_joint_command(self, names, positions=(), efforts=()):
        """Publish a JointState command (articulated robots); returns its stamp."""
        msg = JointState()
        msg.header.stamp = self.now()
        msg.name = list(names)
        msg.position = [float(v) for v in positions]
        msg.effort = [float(v) for v in efforts]
        self.pub_joints.publish(msg)
        return msg.header.stamp

    def subscribe(self, msg_type, topic, depth=50):
        """Keep every message of another topic: returns the list they go into."""
        box = []

        def cb(msg):
            with self._cond:
                box.append(msg)
                self._cond.notify_all()
        self.node.create_subscription(msg_type, topic, cb, depth)
        return box

    def applied(self, stamp):
        """The latest Strains message if it reflects the command stamped ``stamp``."""
        s = self.strains
        return s if s is not None and stamp_key(s.last_command.stamp) == stamp_key(stamp) else None

    def state_after(self, stamp):
        """(backbone, strains) of the first state reflecting command ``stamp``
        (matched by the shared header stamp), or None."""
        with self._cond:
            for _, s in self.history["strains"]:
                if stamp_key(s.last_command.stamp) == stamp_key(stamp):
                    for _, b in self.history["backbone"]:
                        if stamp_key(b.header.stamp) == stamp_key(s.header.stamp):
                            return b, s
        return None

    def arrival(self, topic, msg):
        """When (time.monotonic) a message of ``history[topic]`` arrived, or None."""
        with self._cond:
            return next((t for t, m in self.history[topic] if m is msg), None)

    # --- services ------------------------------------------------------------
    def call(self, service, request, timeout=30.0):
        """Call a service ('forward_kinematics', ...); TimeoutError if no answer."""
        fut = self.clients[service].call_async(request)
        done = threading.Event()
        fut.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            self.clients[service].remove_pending_request(fut)
            raise TimeoutError(f"{service}: no response within {timeout} s")
        return fut.result()


def start_twin(node_name, ros_args, log_path, topics=TwinClient.TOPICS, timeout=120.0, ready=None):
    """(NodeProcess, TwinClient) of a node started in a second process and
    ready (services up, inputs matched, states arriving; ``ready(client)``:
    a further condition); AssertionError with the node's output otherwise."""
    proc = NodeProcess(ros_args, node_name=node_name, log_path=log_path)
    client = TwinClient(node_name, client_name=f"{node_name}_test_client", topics=topics)
    try:
        client.wait_ready(timeout)
        if ready is not None and not client.wait_until(lambda: ready(client), 20.0):
            raise TimeoutError("not ready")
    except Exception:
        client.close()
        proc.stop()
        raise AssertionError(f"node did not come up:\n{proc.output()[-3000:]}")
    return proc, client


def stop_twin(proc, client):
    """Close the client, stop the node (SIGINT) and check it exited cleanly."""
    client.close()
    rc = proc.stop()
    out = proc.output()
    assert rc == 0 and "Traceback" not in out, f"exit code {rc}\n{out[-3000:]}"
