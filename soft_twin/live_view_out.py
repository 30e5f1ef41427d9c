"""The node's live 3D view in the browser (parameter ``live_view_port``:
0 off, else a viser server on http://127.0.0.1:<port>): the published
states drawn at up to ``RATE_HZ`` by :class:`soft_twin_core.viz.live_view.LiveView`
(a tube per member with its sections' radii, links and joints, base and
tip frames, the tip load as an arrow, the actuation values and joint
positions with their units).

The page drives the twin too (issue 31): a slider per actuator and per
position- or effort-controlled joint (:func:`page_controls`) publishes
on the node's own ``~/actuation`` and ``~/joint_commands`` topics, so a
value from the page is validated, counted and recorded as any command;
pause, step and reset call what the ``~/pause``, ``~/step`` and
``~/reset`` services call; the time-scale slider sets the ``time_scale``
parameter (validated as any parameter change)."""

import math
import threading
import time

import numpy as np

RATE_HZ = 30.0
DEFAULT_TENSION_N = 20.0         # slider range of a tendon without a declared limit
DEFAULT_PRESSURE_PA = 50e3       # ... of a chamber without one
DEFAULT_EFFORT = {"revolute": 1.0, "prismatic": 10.0}      # [N m], [N]: effort-controlled joints, +-
DEFAULT_TRAVEL = {"revolute": math.pi, "prismatic": 0.1}   # [rad], [m]: position-controlled joints without limits
PUSH_STIFFNESS_N_PER_M = 10.0    # the page's push: a spring from the pushed point to the dragged gizmo
GIZMO_MODES = ("solve IK", "push a point (spring)")
PICK_RADIUS_M = 0.03             # a click picks the robot's point nearest its ray, if within this [m]
PLAN_SPEED_M_S = 0.05            # the page's "plan a line here": the tip moves at 5 cm/s (at least 1 s)


def page_controls(mech, u=None, positions=None, efforts=None):
    """The page's sliders (:class:`soft_twin_core.viz.live_view.Control`) of
    a robot: an actuator's admissible range (``lower``, ``upper``; where the
    robot file declares no bound, 0 to 20 N of tension or +-50 kPa of
    pressure), a position-controlled joint's limits (else +-pi rad or
    +-0.1 m), an effort-controlled joint's +-1 N m or +-10 N; each at its
    current value (``u``, ``positions``, ``efforts``)."""
    from soft_twin_core.engine.joint_kinds import PRISMATIC
    from soft_twin_core.viz.live_view import Control
    out = []
    for k, act in enumerate(mech.actuators):
        tendon = act.kind == "tendon"
        big = DEFAULT_TENSION_N if tendon else DEFAULT_PRESSURE_PA
        lo = act.lower if math.isfinite(act.lower) else (0.0 if tendon else -big)
        hi = act.upper if math.isfinite(act.upper) else big
        value = float(u[k]) if u is not None else 0.0
        out.append(Control("actuation", act.name, lo, hi, _step(lo, hi), "N" if tendon else "Pa", value))
    tree = mech.tree
    for i in mech.rigid_joints:
        j, mode = tree.joints[i], mech.control[i]
        kind = "prismatic" if j.kind == PRISMATIC else "revolute"
        if mode == "position":
            lo, hi = j.limits if j.limits is not None else (-DEFAULT_TRAVEL[kind], DEFAULT_TRAVEL[kind])
            unit, value = ("m" if kind == "prismatic" else "rad"), (positions or {}).get(j.name, j.q_ref)
        elif mode == "effort":
            lo, hi = -DEFAULT_EFFORT[kind], DEFAULT_EFFORT[kind]
            unit, value = ("N" if kind == "prismatic" else "N m"), (efforts or {}).get(j.name, 0.0)
        else:
            continue
        out.append(Control(f"joint {mode}", j.name, float(lo), float(hi), _step(lo, hi), unit, float(value)))
    return out


def _step(lo, hi):
    """A slider step: a round number near a five-hundredth of the range."""
    x = (hi - lo) / 500.0
    return float(10.0 ** math.floor(math.log10(x))) if x > 0 else 1.0


def point_position(snap, name):
    """World position [m] of a frame or ``<member>@<s>`` point of a
    twin's Snapshot (a member point between its backbone samples: linear)."""
    if name in snap.frames:
        return np.asarray(snap.frames[name], dtype=float)[:3, 3]
    member, s = name.rsplit("@", 1)
    poses, ss = snap.backbones[member]
    P = np.asarray(poses, dtype=float)[:, :3, 3]
    return np.array([np.interp(float(s), ss, P[:, k]) for k in range(3)])


def nearest_point_to_ray(snap, mech, origin, direction):
    """(name, position, distance from the ray [m]) of the robot's point
    nearest a ray (a click): its members' backbone samples, named
    ``<member>@<s>`` (s to the micrometre), and its links' frames;
    (None, None, inf) for a robot with neither."""
    d = np.asarray(direction, dtype=float)
    d = d / max(np.linalg.norm(d), 1e-300)
    names, points = [], []
    for m in mech.members:
        if m.name in snap.backbones:
            poses, ss = snap.backbones[m.name]
            names += [f"{m.name}@{s:.6f}" for s in ss]
            points += [T[:3, 3] for T in np.asarray(poses, dtype=float)]
    for link in mech.links:
        if link.name in snap.frames:
            names.append(link.name)
            points.append(np.asarray(snap.frames[link.name], dtype=float)[:3, 3])
    if not names:
        return None, None, np.inf
    v = np.asarray(points) - np.asarray(origin, dtype=float)
    along = np.maximum(v @ d, 0.0)
    miss = np.linalg.norm(v - along[:, None] * d, axis=1)
    k = int(np.argmin(miss))
    return names[k], points[k], float(miss[k])


def actuator_routes(mech, snap):
    """[(kind, polyline (K, 3) [m])] of each actuator: its path through the
    member's cross-sections, ``p(s) + R(s) d(s)`` at the member's backbone
    samples from its ``start`` to its ``end`` (d: the robot file's offset,
    routing included: :meth:`Actuator.offset_at`)."""
    tree, out = mech.tree, []
    for k, act in enumerate(mech.actuators):
        pi = tree.actuator_paths[k] if tree.actuator_paths else tree.actuator_path
        member = next((m for m in mech.members if m.path == pi), None)
        if member is None or member.name not in snap.backbones:
            continue
        poses, s = snap.backbones[member.name]
        poses, s = np.asarray(poses, dtype=float), np.asarray(s, dtype=float)
        on = (s >= act.start - 1e-9) & (s <= act.end + 1e-9)
        if on.sum() < 2:
            continue
        d, _ = act.offset_at(s[on])
        out.append((act.kind, np.einsum("kij,kj->ki", poses[on, :3, :3], d) + poses[on, :3, 3]))
    return out


def articulated_view_snapshot(mech, snap):
    """(scene.Snapshot, radii per member) of a robot's state: its members
    through their backbone points (radii from their cross-sections), its
    links' visual shapes (a bar from the parent link's frame for a link
    without one) and its rigid joints
    (:func:`soft_twin_core.viz.scene.snapshot`)."""
    from soft_twin_core.viz.scene import member_radii, snapshot
    members = {name: poses[:, :3, 3] for name, (poses, _) in snap.backbones.items()}
    return (snapshot(mech, members, snap.frames, time=float(snap.t)),
            member_radii(mech, {name: len(P) for name, P in members.items()}))


# the page's "colour by" menu: label -> the values per member at its backbone points, from a state
COLOURINGS = {
    "none": None,
    "peak normal stress [MPa]": lambda snap: {m.name: 1e-6 * np.asarray(m.normal_stress, dtype=float)
                                              for m in snap._loads.members},
    "bending moment [N m]": lambda snap: {n: np.hypot(w[:, 4], w[:, 5]) for n, w in snap.internal_wrenches.items()},
    "axial force [N]": lambda snap: {n: w[:, 0] for n, w in snap.internal_wrenches.items()},
    "torsion [N m]": lambda snap: {n: w[:, 3] for n, w in snap.internal_wrenches.items()},
}


def member_values(snap, members, label):
    """(label, [values per member in ``members`` order]) of the colouring
    ``label`` (:data:`COLOURINGS`) of a state, or None ("none")."""
    make = COLOURINGS[label]
    if make is None:
        return None
    by_name = make(snap)
    return label, [np.nan_to_num(np.asarray(by_name[m], dtype=float)) for m in members]


def contact_arrows(snap):
    """(positions, forces) of a state's contacts, or None."""
    st = snap.contacts
    if st is None or not len(st):
        return None
    return np.asarray(st.p, dtype=float), np.asarray(st.force, dtype=float)


def units_of(mech):
    """{actuator or joint name: unit} for the page's panel."""
    from soft_twin_core.engine.joint_kinds import PRISMATIC
    out = {a.name: ("N" if a.kind == "tendon" else "Pa") for a in mech.actuators}
    tree = mech.tree
    out.update({tree.joints[i].name: "m" if tree.joints[i].kind == PRISMATIC else "rad" for i in mech.rigid_joints})
    return out


class LiveViewOutput:
    def __init__(self, node):
        self._node = node
        self._view, self._port = None, 0
        self._last = -np.inf
        self._framed = False
        self._controls_of = None         # the robot the page's controls were made for
        self.colour_by = "none"           # the page's "colour by" choice (COLOURINGS)
        self.trail = True
        self.routes = False               # the page's "actuators' routes" box
        self.frames = False               # the page's "frames" box
        self._latest = None               # the last state given to publish: redrawn on a change of the page's view
        self._ik = threading.Condition()  # the target's IK: the latest target waiting, a worker thread solving it
        self._ik_target, self._ik_answer, self._ik_thread, self._closed = None, None, None, False
        self.gizmo_mode = GIZMO_MODES[0]
        self._push_at = None              # push mode, while dragged: where the gizmo is [m]
        self._push_point = None           # push mode: the point picked on the page (None: the tip)
        self._target_at = None            # where the gizmo was last dragged to [m] (the plan's end)
        self._plan_thread = None          # the page's plan, solved off the page's thread
        self._pubs = None                # (actuation, joint command) publishers to the node's own inputs

    def follow(self, port):
        """Serve on ``port`` (0: stop)."""
        if port == self._port:
            return
        self.close()
        if port:
            from soft_twin_core.viz.live_view import LiveView
            try:
                self._view = LiveView(port=port, title=self._node.get_name())
            except OSError as e:
                self._node.get_logger().error(f"live_view_port: cannot serve on port {port}: {e}")
                return
            self._port = port
            self._framed = False
            self._controls_of = None
            self._node.get_logger().info(f"live 3D view: {self._view.url} (a browser without a GPU: "
                                         f"{self._view.url.rstrip('/')}/?fixedDpr=0.5)")

    def publish(self, snap, robot, force=False):
        """Draw a published state (at most RATE_HZ a second; ``force``: now,
        e.g. the page's state line after a pause)."""
        view = self._view
        now = time.monotonic()
        self._latest = (snap, robot)
        if view is None or (now - self._last < 1.0 / RATE_HZ and not force):
            return
        self._last = now
        if self._controls_of is not robot:
            self._make_controls(robot)
        shot, radii = articulated_view_snapshot(robot.mech, snap)
        if not self._framed:              # the first state: frame the robot for every new page
            from soft_twin_core.viz.scene import bounds
            view.frame(*bounds([shot], pad=0.3))
            self._framed = True
        tip_force = snap.tip_pose[:3, :3] @ np.asarray(snap.tip_wrench[:3], dtype=float)      # tip axes -> base
        if self._push_at is not None:      # the spring follows the pushed point
            self._push()
        values = None
        if self.colour_by != "none" and snap.state is not None:
            values = member_values(snap, [m.name for m in robot.mech.members], self.colour_by)
        view.show(shot, radii, base_pose=np.eye(4), tip_pose=snap.tip_pose, values=values, trail=self.trail,
                  contacts=contact_arrows(snap),
                  tip_force=tip_force if np.any(tip_force) else None,
                  actuation=dict(zip(robot.mech.actuator_names, np.asarray(snap.u, dtype=float).tolist())),
                  text=f"({snap.mode}{', paused' if self._node.paused else ''})",
                  joints=dict(zip(snap.joint_names, np.asarray(snap.joint_positions, dtype=float).tolist())),
                  units=units_of(robot.mech), paused=self._node.paused, point_forces=snap.point_loads,
                  routes=actuator_routes(robot.mech, snap) if self.routes else None,
                  frames=snap.frames if self.frames else None)

    def _make_controls(self, robot):
        """The page's sliders for ``robot`` and the run controls."""
        node = self._node
        if self._pubs is None:
            from sensor_msgs.msg import JointState
            from soft_twin.msg import ActuationCommand, PointWrench
            from geometry_msgs.msg import WrenchStamped
            self._pubs = (node.create_publisher(ActuationCommand, "~/actuation", 10),
                          node.create_publisher(JointState, "~/joint_commands", 10)
                          if robot.mech.joint_names else None,
                          node.create_publisher(WrenchStamped, "~/tip_wrench_command", 10),
                          node.create_publisher(PointWrench, "~/point_wrench_command", 10))
        twin = node.twin
        controls = page_controls(robot.mech, twin.u, twin.positions, twin.efforts)
        self._view.set_controls(controls, self._send, on_pause=node.set_paused, on_step=node.single_step,
                                on_reset=self._reset, on_time_scale=self._time_scale,
                                time_scale=node.cfg.time_scale)
        self._view.set_view_options(list(COLOURINGS), self._set_colour, self._set_trail, self.trail,
                                    on_routes=self._set_flag("routes"), routes=self.routes,
                                    on_frames=self._set_flag("frames"), frames=self.frames)
        self._view.set_target(twin.outputs().tip_pose[:3, 3], self._on_target, self._apply_ik, GIZMO_MODES,
                              self._set_gizmo_mode, on_plan=self._plan_to_target)
        self._view.set_pick(self._on_pick)
        self._controls_of = robot

    def _set_gizmo_mode(self, mode):
        """What dragging the gizmo does; the gizmo back on the tip."""
        self.gizmo_mode = mode
        self._push_point = None
        if self._latest is not None and self._view is not None:
            p = self._latest[0].tip_pose[:3, 3]
            self._view.move_target(p)
            self._view.say_target(f"drag the gizmo (at [{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}] m): " + (
                "a spring of %g N/m from the tip pulls it there (a dead load, base axes), until you let go; "
                "click a member or a link to push that point instead" % PUSH_STIFFNESS_N_PER_M
                if mode != GIZMO_MODES[0] else "inverse kinematics to its position"))

    def _on_pick(self, origin, direction):
        """A click on the robot (push mode): the point nearest the click's
        ray among the members' backbone points (``<member>@<s>``) and the
        links' frames becomes the pushed point; the gizmo moves onto it."""
        latest = self._latest
        if latest is None or self.gizmo_mode == GIZMO_MODES[0]:
            return
        name, p, miss = nearest_point_to_ray(latest[0], latest[1].mech, origin, direction)
        if name is None or miss > PICK_RADIUS_M:          # a click beside the robot
            return
        self._push_point = name
        self._view.move_target(p)
        self._view.say_target(f"picked `{name}` at [{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}] m: drag the gizmo, a "
                              f"spring of {PUSH_STIFFNESS_N_PER_M:g} N/m pulls that point (a dead load, base axes)")

    def _on_target(self, position, phase="update"):
        """The page's gizmo moved. Solving IK: for the latest position (a
        drag sends many; the worker takes the newest when it is free).
        Pushing: the spring's force on the tip while dragged, none (and the
        gizmo back on the tip) once let go."""
        if self.gizmo_mode != GIZMO_MODES[0]:
            if phase == "end":
                self._push_at = None
                self._send_push(np.zeros(3))
                if self._latest is not None:
                    self._view.move_target(self._pushed_position(self._latest[0]))
            else:
                self._push_at = np.asarray(position, dtype=float)
                self._push()
            return
        self._target_at = np.asarray(position, dtype=float)
        with self._ik:
            self._ik_target = np.asarray(position, dtype=float)
            if self._ik_thread is None:
                self._ik_thread = threading.Thread(target=self._ik_loop, name="live_view_ik", daemon=True)
                self._ik_thread.start()
            self._ik.notify()

    def _ik_loop(self):
        while True:
            with self._ik:
                while self._ik_target is None and not self._closed:
                    self._ik.wait()
                if self._closed:
                    return
                target, self._ik_target = self._ik_target, None
            try:
                self._solve_ik(target)
            except Exception as e:          # the page says so; the node goes on
                if self._view is not None:
                    self._view.show_ik(target, None, f"IK failed: {type(e).__name__}: {e}")

    def _pushed_position(self, snap):
        """Where the pushed point (the tip unless one was picked) is [m]."""
        return snap.tip_pose[:3, 3] if self._push_point is None else point_position(snap, self._push_point)

    def _push(self):
        """The spring's force PUSH_STIFFNESS_N_PER_M (gizmo - point) on the
        pushed point now (at most the node's max_tip_force_n), sent as a tip
        wrench command or, for a picked point, a point wrench command (base
        axes: a dead load), said in the panel."""
        at, latest = self._push_at, self._latest
        if at is None or latest is None:
            return
        f = PUSH_STIFFNESS_N_PER_M * (at - self._pushed_position(latest[0]))
        cap = 0.99 * self._node.cfg.max_tip_force_n
        n = float(np.linalg.norm(f))
        if n > cap:
            f *= cap / n
        self._send_push(f)
        what = "the tip" if self._push_point is None else f"`{self._push_point}`"
        self._view.say_target(f"pushing {what} with [{f[0]:.3f}, {f[1]:.3f}, {f[2]:.3f}] N "
                              f"({np.linalg.norm(f):.3f} N)")

    def _send_push(self, force):
        if self._push_point is None:
            self._send_wrench(force)
            return
        from soft_twin.msg import PointWrench
        node = self._node
        msg = PointWrench(header=node._header(node.cfg.base_frame), point=self._push_point)
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = map(float, force)
        self._pubs[3].publish(msg)

    def _send_wrench(self, force):
        from geometry_msgs.msg import WrenchStamped
        node = self._node
        msg = WrenchStamped(header=node._header(node.cfg.base_frame))
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = map(float, force)
        self._pubs[2].publish(msg)

    def _solve_ik(self, target):
        """The node's own IK (what ``~/inverse_kinematics`` answers, position
        only, to 0.1 mm) for the target; the answer shown and kept for "apply"."""
        from geometry_msgs.msg import Pose
        from soft_twin import services
        from soft_twin.srv import InverseKinematics
        from soft_twin_core.viz.live_view import shown_value
        from soft_twin_core.viz.scene import skeleton        # here: the view's modules load with the page
        req = InverseKinematics.Request(position_only=True, tolerance=1e-4)
        req.target = Pose()
        req.target.position.x, req.target.position.y, req.target.position.z = map(float, target)
        req.target.orientation.w = 1.0
        r, result = services.ik_answer(self._node, req, InverseKinematics.Response())
        ghost = None if result is None else skeleton(self._node.robot.mech, result.q)
        units = units_of(self._node.robot.mech)
        inputs = ", ".join(f"{n} = {shown_value(v)} {units.get(n, '')}".rstrip()
                           for n, v in zip(r.actuator_names, r.actuator_values))
        p = r.achieved.position
        achieved = np.array([p.x, p.y, p.z]) if r.actuation_found else None
        self._ik_answer = r if r.actuation_found else None
        view = self._view
        if view is not None:
            reach = "" if achieved is None else f"; the tip reaches [{achieved[0]:.4f}, {achieved[1]:.4f}, " \
                                                 f"{achieved[2]:.4f}] m, {1e3 * r.position_error:.2f} mm from the target"
            view.show_ik(target, achieved, f"{r.message}" + (f"; {inputs}" if inputs else "") + reach
                         + ("" if ghost is None else " (its shape: the violet ghost)"), ghost)

    def _apply_ik(self):
        """The last IK answer's inputs sent as the sliders send theirs."""
        r = self._ik_answer
        if r is None:
            return
        if self._view is not None:
            self._view.show_ghost(None)             # (the twin goes there now)
        from sensor_msgs.msg import JointState
        from soft_twin.msg import ActuationCommand
        node = self._node
        joints = set(node.robot.mech.joint_names)
        header = node._header(node.cfg.base_frame)
        pairs = list(zip(r.actuator_names, map(float, r.actuator_values)))
        act = [(n, v) for n, v in pairs if n not in joints]
        pos = [(n, v) for n, v in pairs if n in joints]
        if act:
            self._pubs[0].publish(ActuationCommand(header=header, names=[n for n, _ in act], values=[v for _, v in act]))
        if pos and self._pubs[1] is not None:
            self._pubs[1].publish(JointState(header=header, name=[n for n, _ in pos], position=[v for _, v in pos]))

    def _plan_to_target(self):
        """The page's "plan a line here": the node's own ~/plan_path (the
        twin's planner, executed on the twin's inputs as a client's plan is)
        for a straight line from the tip to where the gizmo was dragged, at
        PLAN_SPEED_M_S; the planned tip path drawn as the ghost, the answer
        said in the panel. Solved in a thread of its own (a tree robot's
        plan takes a second)."""
        if self._target_at is None or self._latest is None:
            self._view.say_target("drag the gizmo to where the tip should go first")
            return
        if self._plan_thread is not None and self._plan_thread.is_alive():
            return
        start, end = self._latest[0].tip_pose[:3, 3].copy(), self._target_at.copy()
        self._plan_thread = threading.Thread(target=self._plan_line, args=(start, end), name="live_view_plan",
                                             daemon=True)
        self._plan_thread.start()

    def _plan_line(self, start, end):
        import yaml
        from soft_twin.srv import PlanPath
        duration = max(1.0, float(np.linalg.norm(end - start)) / PLAN_SPEED_M_S)
        req = PlanPath.Request(path_yaml=yaml.safe_dump({
            "type": "line", "start": start.tolist(), "end": end.tolist(), "duration": duration,
            "sample_period": 0.1}), execute=True)
        try:
            r = self._node._srv_plan_path(req, PlanPath.Response())
        except Exception as e:                 # the page says so; the node goes on
            r = PlanPath.Response(success=False, message=f"plan failed: {type(e).__name__}: {e}")
        view = self._view
        if view is None:
            return
        tips = np.asarray(r.predicted_tip, dtype=float).reshape(-1, 3)
        if len(tips):
            e = tips[-1]
            view.show_ghost([tips] + self._shape_reaching(e))
            view.say_target(f"{r.message}; the planned tip path and the shape it ends in (violet) end at "
                            f"[{e[0]:.4f}, {e[1]:.4f}, {e[2]:.4f}] m")
        else:
            view.show_ghost(None)
            view.say_target(r.message)

    def _shape_reaching(self, tip):
        """Polylines of the robot's shape with its tip at ``tip`` (a plan's
        end, which its inputs reach): the twin's IK of that point
        (:func:`services.ik_query`), [] when it fails."""
        from soft_twin import services
        from soft_twin_core.viz.scene import skeleton        # here: the view's modules load with the page
        try:
            return skeleton(self._node.robot.mech, services.ik_query(self._node, tip, 1e-4).q)
        except Exception:                   # (the path alone is drawn)
            return []

    def _set_colour(self, label):
        self.colour_by = label
        self._redraw()

    def _set_trail(self, on):
        self.trail = bool(on)
        self._redraw()

    def _set_flag(self, name):
        """A page box's callback: the attribute ``name`` set, the state drawn again."""
        def set_it(on):
            setattr(self, name, bool(on))
            self._redraw()
        return set_it

    def _redraw(self):
        """The last state drawn again (a paused twin publishes none)."""
        if self._latest is not None:
            with self._node._publish_lock:
                self.publish(*self._latest, force=True)

    def _send(self, control, value):
        """A slider's value, published on the node's own input topic."""
        node = self._node
        header = node._header(node.cfg.base_frame)
        if control.kind == "actuation":
            from soft_twin.msg import ActuationCommand
            self._pubs[0].publish(ActuationCommand(header=header, names=[control.name], values=[value]))
        elif self._pubs[1] is not None:
            from sensor_msgs.msg import JointState
            msg = JointState(header=header, name=[control.name])
            if control.kind == "joint position":
                msg.position = [value]
            else:
                msg.effort = [value]
            self._pubs[1].publish(msg)

    def _reset(self):
        from std_srvs.srv import Trigger
        from soft_twin import services
        services.reset(self._node, Trigger.Request(), Trigger.Response())

    def _time_scale(self, value):
        from rclpy.parameter import Parameter
        result = self._node.set_parameters([Parameter("time_scale", value=float(value))])[0]
        if not result.successful:
            self._node.get_logger().warn(f"time scale from the page refused: {result.reason}")

    def close(self):
        with self._ik:
            self._closed = True
            self._ik.notify()
            thread = self._ik_thread
        if thread is not None:
            thread.join(5.0)
        with self._ik:
            self._ik_thread, self._ik_target, self._ik_answer, self._closed = None, None, None, False
        if self._view is not None:
            self._view.close()
        self._view, self._port = None, 0
