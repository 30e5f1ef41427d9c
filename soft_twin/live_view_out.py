"""The node's live 3D view in the browser (parameter ``live_view_port``:
0 off, else a viser server on http://127.0.0.1:<port>): the published
states drawn at up to ``RATE_HZ`` by :class:`soft_twin_core.live_view.LiveView`
(backbone tube with the section radii, base and tip frames, the tip load as
an arrow, the actuation values)."""

import time

import numpy as np

from soft_twin_core.scene import Snapshot, segment_ends, split_members

RATE_HZ = 20.0


def tip_force_world(model, snap):
    """Sum of the point forces [N] applied at the tip, world axes."""
    f = np.zeros(3)
    for pl in getattr(snap.loads, "point", ()):
        if abs(pl.s - model.total_length) < 1e-9:
            w = np.asarray(pl.wrench[:3], dtype=float)
            f += snap.tip_pose[:3, :3] @ w if pl.frame == "body" else w
    return f


def articulated_view_snapshot(mech, snap):
    """(scene.Snapshot, radii per member) of an articulated robot's state:
    its members through their section boundaries (radii from their
    cross-sections), its links' visual shapes (a bar from the parent link's
    frame for a link without one) and its rigid joints
    (:func:`soft_twin_core.mechanism_scene.snapshot`)."""
    from soft_twin_core.mechanism_scene import member_radii, snapshot
    members = {name: poses[:, :3, 3] for name, (poses, _) in snap.backbones.items()}
    return snapshot(mech, members, snap.frames, time=float(snap.t)), member_radii(mech)


def view_snapshot(model, snap, radii_per_section):
    """(scene.Snapshot, radii per member) of a twin state."""
    P = snap.backbone[:, :3, 3]
    members, links = split_members(P, snap.s, segment_ends(model))
    sec, _ = model.locate(np.minimum(snap.s, model.total_length))
    r = np.asarray(radii_per_section, dtype=float)[sec]
    radii, k = [], 0
    for m in members:
        radii.append(r[k:k + len(m)])
        k += len(m)
    return Snapshot(members, links, time=float(snap.t)), radii


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
            from soft_twin_core.live_view import LiveView
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
        model = robot.model
        if getattr(robot, "articulated", False):
            shot, radii = articulated_view_snapshot(robot.mechanism, snap)
            if not self._framed:              # the first state: frame the robot for every new page
                from soft_twin_core.scene import bounds
                view.frame(*bounds([shot], pad=0.3))
                self._framed = True
            view.show(shot, radii, base_pose=np.eye(4), tip_pose=snap.tip_pose,
                      actuation=dict(zip(model.actuator_names, np.asarray(snap.u, dtype=float).tolist())),
                      text=f"({snap.mode})",
                      joints=dict(zip(snap.joint_names, np.asarray(snap.joint_positions, dtype=float).tolist())))
            return
        shot, radii = view_snapshot(model, snap, robot.section_radii())
        view.show(shot, radii, base_pose=snap.backbone[0], tip_pose=snap.tip_pose,
                  tip_force=tip_force_world(model, snap),
                  actuation=dict(zip(model.actuator_names, np.asarray(snap.u, dtype=float).tolist())),
                  text=f"({snap.mode})")

    def close(self):
        if self._view is not None:
            self._view.close()
        self._view, self._port = None, 0
