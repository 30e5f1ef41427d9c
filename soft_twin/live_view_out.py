"""The node's live 3D view in the browser (parameter ``live_view_port``:
0 off, else a viser server on http://127.0.0.1:<port>): the published
states drawn at up to ``RATE_HZ`` by :class:`soft_twin_core.viz.live_view.LiveView`
(a tube per member with its sections' radii, links and joints, base and
tip frames, the tip load as an arrow, the actuation values and joint
positions)."""

import time

import numpy as np

RATE_HZ = 20.0


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


class LiveViewOutput:
    def __init__(self, node):
        self._node = node
        self._view, self._port = None, 0
        self._last = -np.inf
        self._framed = False

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
            self._node.get_logger().info(f"live 3D view: {self._view.url}")

    def publish(self, snap, robot):
        view = self._view
        now = time.monotonic()
        if view is None or now - self._last < 1.0 / RATE_HZ:
            return
        self._last = now
        shot, radii = articulated_view_snapshot(robot.mech, snap)
        if not self._framed:              # the first state: frame the robot for every new page
            from soft_twin_core.viz.scene import bounds
            view.frame(*bounds([shot], pad=0.3))
            self._framed = True
        tip_force = snap.tip_pose[:3, :3] @ np.asarray(snap.tip_wrench[:3], dtype=float)      # tip axes -> base
        view.show(shot, radii, base_pose=np.eye(4), tip_pose=snap.tip_pose,
                  tip_force=tip_force if np.any(tip_force) else None,
                  actuation=dict(zip(robot.mech.actuator_names, np.asarray(snap.u, dtype=float).tolist())),
                  text=f"({snap.mode})",
                  joints=dict(zip(snap.joint_names, np.asarray(snap.joint_positions, dtype=float).tolist())))

    def close(self):
        if self._view is not None:
            self._view.close()
        self._view, self._port = None, 0
