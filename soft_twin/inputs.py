"""The node's inputs, message batch to checked values (pure: no rclpy).

Each subscription callback of :mod:`soft_twin.node` takes every message
queued on its topic and folds the batch here, outside the twin lock: the
door's parse functions (:func:`soft_twin_core.commands.parse_actuation`,
:func:`soft_twin_core.commands.parse_tip_wrench`,
:func:`soft_twin_core.commands.parse_joint_command`) validate each message once;
the valid ones are applied in order (a partial command keeps the other
actuators or joints), the invalid ones come back as
:class:`soft_twin_core.commands.InputError` for the counters. Nothing downstream checks
them again.
"""

from soft_twin import conversions as cv
from soft_twin_core import commands as cmd
from soft_twin_core.text import clip


def sequence_number(info):
    """The publisher's sequence number of a message (None when the
    middleware gives none)."""
    return info.get("publication_sequence_number") if isinstance(info, dict) else None


def fold_commands(model, batch, u, order):
    """(actuation after the valid ActuationCommands of ``batch`` [(msg,
    info)] in order, the newest valid one, how many were valid, the
    InputErrors of the others); ``u`` the actuation before, ``order`` the
    configured actuator order of unnamed commands."""
    newest, n_applied, errors = None, 0, []
    for m, _ in batch:
        try:
            u = cmd.parse_actuation(model, m.names, m.values, u, order)
        except cmd.InputError as e:
            errors.append(e)
        else:
            newest, n_applied = m, n_applied + 1
    return u, newest, n_applied, errors


def fold_joint_commands(mech, batch, pos, eff):
    """(positions, efforts after the valid JointState commands of ``batch``
    in order, the newest valid one, how many were valid, the InputErrors of
    the others)."""
    newest, n_applied, errors = None, 0, []
    for m, _ in batch:
        try:
            pos, eff = cmd.parse_joint_command(mech, m.name, m.position, m.velocity, m.effort, pos, eff)
        except cmd.InputError as e:
            errors.append(e)
        else:
            newest, n_applied = m, n_applied + 1
    return pos, eff, newest, n_applied, errors


def parse_wrenches(batch, cfg):
    """(the newest valid (wrench, core frame) of a batch of WrenchStamped
    tip-wrench commands, or None; the InputErrors of the invalid ones)."""
    newest, errors = None, []
    for m, _ in batch:
        force, torque = cv.wrench_parts(m.wrench)
        try:
            newest = cmd.parse_tip_wrench(force, torque, m.header.frame_id, cfg.base_frame, cfg.tip_frame,
                                         cfg.max_tip_force_n, cfg.max_tip_torque_nm)
        except cmd.InputError as e:
            errors.append(e)
    return newest, errors


def parse_base_poses(batch, cfg, mech):
    """(the newest valid base pose (4x4) of a batch of PoseStamped
    commands, or None; the InputErrors of the invalid ones)
    (:func:`soft_twin_core.commands.parse_base_pose`)."""
    newest, errors = None, []
    for m, _ in batch:
        try:
            newest = base_pose_of(m, mech, cfg.base_frame)
        except cmd.InputError as e:
            errors.append(e)
    return newest, errors


def base_pose_of(msg, mech, base_frame):
    """The 4x4 of a PoseStamped base pose command, checked
    (:func:`soft_twin_core.commands.parse_base_pose`; a zero quaternion:
    "non_finite"); InputError naming why not."""
    try:
        T = cv.matrix_from_pose(msg.pose)
    except ValueError as e:
        raise cmd.InputError("non_finite", f"base pose: {e}") from None
    return cmd.parse_base_pose(mech, T, msg.header.frame_id, base_frame)


def parse_point_wrenches(batch, cfg, mech):
    """(the valid (point, wrench, core axes) of a batch of soft_twin/PointWrench
    commands, in order; the InputErrors of the others)
    (:func:`soft_twin_core.commands.parse_point_wrench`)."""
    valid, errors = [], []
    for m, _ in batch:
        force, torque = cv.wrench_parts(m.wrench)
        try:
            valid.append(cmd.parse_point_wrench(mech, m.point, force, torque, m.header.frame_id, cfg.base_frame,
                                                cfg.max_tip_force_n, cfg.max_tip_torque_nm))
        except cmd.InputError as e:
            errors.append(e)
    return valid, errors


def fold_obstacles(batch, obstacles):
    """(the obstacles after the valid soft_twin/Obstacle messages of
    ``batch`` in order, how many were valid, the InputErrors of the others);
    ``obstacles`` the tuple before. ADD checks the shape and law as a robot
    file's entry (:func:`soft_twin_core.robot.obstacles.obstacle_at`), MOVE
    and REMOVE need an obstacle of that name."""
    n_applied, errors = 0, []
    for m, _ in batch:
        try:
            obstacles = cv.obstacles_after(m, obstacles)
        except cmd.InputError as e:
            errors.append(e)
        else:
            n_applied += 1
    return obstacles, n_applied, errors


def rejection_warning(kind, errors):
    """The log line for a batch's rejected inputs (the newest reason, and how many more)."""
    e = errors[-1]
    return (f"{kind} rejected ({e.reason}): {clip(e, 400)}"
            + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""))
