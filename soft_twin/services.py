"""The node's query services: forward kinematics, statics, inverse
kinematics and reset (``~/forward_kinematics``, ``~/statics_query``,
``~/inverse_kinematics``, ``~/reset``; the plan services are in
:mod:`soft_twin.plan_service`).

Each handler takes the node, the request and the response. It copies what it
needs from the twin under the node's lock (microseconds), checks the request
at the door (the same parse functions as the topics) and computes outside
the lock, on a copy of the twin: in the node's process for a robot without
multipliers (a classic rod: the compiled statics), in the query worker
process for a tree robot (its Python would hold the GIL against the
stepping clock). A request that cannot be answered gets
``success: false`` and a message naming the reason; the twin is never
changed by a query.
"""

import math
import time

import numpy as np

from soft_twin_core import lie
from soft_twin_core.errors import StaticsError
from soft_twin_core.planning.planner import PlanError
from soft_twin_core.robot.model import ModelError

from soft_twin import conversions as cv
from soft_twin_core import commands as cmd
from soft_twin_core.planning import ik as core_ik
from soft_twin.query_worker import QueryError
from soft_twin_core.text import clip


def copy_state(node):
    """(model, q, u, tip wrench, its frame, cfg, actuator order): what a query
    needs, copied under the node's lock."""
    with node._lock:
        t = node.twin
        return (node.robot.model, t.state.q.copy(), t.u.copy(), t.tip_wrench.copy(), t.tip_frame,
                node.cfg, node.cfg.actuator_names)


def _twin_copy(node):
    """The twin's quasi-static copy for a query, taken under the node's lock."""
    with node._lock:
        return node.twin.query_copy()


def _requested_actuation(req, model, u, order):
    """The request's actuation (names/values over the current ``u``), or None when it gives none."""
    if len(req.actuator_names) or len(req.actuator_values):
        return cmd.parse_actuation(model, req.actuator_names, req.actuator_values, u, order)
    return None


def forward_kinematics(node, req, resp):
    """The backbone and tip pose for given strains, for the equilibrium under
    a given actuation, or of the current state."""
    model, q, u, _, _, cfg, order = copy_state(node)
    try:
        actuation = _requested_actuation(req, model, u, order)
    except cmd.InputError as e:
        resp.success, resp.message = False, clip(f"actuation rejected ({e.reason}): {e}", 400)
        return resp
    try:
        message, res = _twin_copy(node).forward_kinematics(req.strains, actuation)
    except (ValueError, StaticsError) as e:
        resp.success, resp.message = False, clip(str(e), 400)
        return resp
    resp.success, resp.message = True, clip(message, 400)
    if resp.success:
        resp.backbone = cv.pose_array(res.backbone, node._header(cfg.base_frame))
        resp.strains = res.strains.ravel().tolist()
        resp.tip_pose = cv.pose_msg(res.tip_pose)
    return resp


def statics_query(node, req, resp):
    """The equilibrium under an actuation (default: the current one) and a
    tip wrench (base frame), from the current state; the twin untouched."""
    model, q, u, _, _, cfg, order = copy_state(node)
    try:
        actuation = _requested_actuation(req, model, u, order)
        actuation = u if actuation is None else actuation
        force, torque = cv.wrench_parts(req.tip_wrench)
        w, frame = cmd.parse_tip_wrench(force, torque, cfg.base_frame, cfg.base_frame, cfg.tip_frame,
                                       cfg.max_tip_force_n, cfg.max_tip_torque_nm)
    except cmd.InputError as e:
        resp.success, resp.message = False, clip(f"input rejected ({e.reason}): {e}", 400)
        return resp
    info, res = _twin_copy(node).statics(actuation, w, frame)       # joints at the twin's current commands
    resp.success, resp.message = info.converged, clip(info.message or "ok", 400)
    if info.converged:
        resp.backbone = cv.pose_array(res.backbone, node._header(cfg.base_frame))
        resp.strains = res.strains.ravel().tolist()
        resp.tip_pose = cv.pose_msg(res.tip_pose)
        resp.base_wrench = cv.wrench_msg(res.base_wrench)
        resp.iterations = int(info.iterations)
        if info.residual is not None:
            resp.residual = float(info.residual)
    return resp


def inverse_kinematics(node, req, resp, timing=False):
    """Actuation (and joint commands) reaching a tip target; ``timing``: log
    the handler's wall and thread CPU time (the benchmarks' hook)."""
    if not timing:
        return _inverse_kinematics(node, req, resp)
    w0, c0 = time.perf_counter(), time.thread_time()
    try:
        return _inverse_kinematics(node, req, resp)
    finally:
        node.get_logger().info(f"timing inverse_kinematics: wall {1e3 * (time.perf_counter() - w0):.2f} ms "
                               f"thread CPU {1e3 * (time.thread_time() - c0):.2f} ms")


def ik_query(node, target, tol):
    """The twin's IK (:meth:`soft_twin_core.twin.Twin.inverse_kinematics`)
    on a copy of its state: a tree robot's in the query worker process
    (hundreds of milliseconds of Python that would hold the GIL against the
    stepping clock), a robot without multipliers (a classic rod) on its
    compiled statics in this process (milliseconds)."""
    if node.robot.articulated:
        return node.query("inverse_kinematics", target, tol)
    return _twin_copy(node).inverse_kinematics(target, tol)


def _inverse_kinematics(node, req, resp):
    return ik_answer(node, req, resp)[0]


def ik_answer(node, req, resp):
    """Joint commands and actuator inputs putting the tip at the target pose,
    or position with ``position_only``: ``actuator_names``/``actuator_values``
    the position-controlled joints (rad or m) first, then the actuators (N
    or Pa); a robot without inputs answers with the shape that reaches the
    target (``actuation_found`` False). Returns (resp, the twin's IK result
    -- its configuration ``q`` included -- or None when there is none)."""
    tol = req.tolerance
    if not math.isfinite(tol) or tol < 0:
        resp.success, resp.message = False, f"tolerance must be >= 0 (0 = default 1e-6), got {tol}"
        return resp, None
    try:
        target = cv.matrix_from_pose(req.target)
    except ValueError as e:
        resp.success, resp.message = False, clip(f"target rejected: {e}", 400)
        return resp, None
    try:
        r = ik_query(node, target[:3, 3] if req.position_only else target, tol or 1e-6)
    except (PlanError, StaticsError, ModelError, ValueError, np.linalg.LinAlgError, QueryError) as e:
        resp.success, resp.message = False, clip(f"IK failed: {e}", 400)
        return resp, None
    resp.success = r.reached
    by = "joint commands and actuation" if node.twin.mech.joints_with("position") else "actuation"
    if not r.actuation_found:
        resp.message = ("converged: shape reaching the target (this robot has no actuators)" if r.reached else
                        f"IK did not reach the target: position error {r.position_error:.3g} m (a shape only: "
                        f"this robot has no actuators)")
    elif r.reached:
        resp.message = f"converged: reached by {by} (static equilibrium)"
    else:
        resp.message = (f"target not reached by {by} ({core_ik.IK_STATUS.get(r.status, r.status)}): the closest "
                        f"pose the inputs can hold, position error {r.position_error:.3g} m")
    resp.strains = r.strains.ravel().tolist()
    resp.actuation_found = bool(r.actuation_found)
    resp.actuator_names = list(r.names)
    resp.actuator_values = [float(v) for v in r.values]
    resp.achieved = cv.pose_msg(r.achieved_pose)
    resp.position_error = float(r.position_error)
    # position only: |log(R_achieved^T R_target)|, informative
    resp.orientation_error = (float(np.linalg.norm(lie.log_so3(r.achieved_pose[:3, :3].T @ target[:3, :3])))
                              if req.position_only else float(r.orientation_error))
    resp.iterations = int(r.iterations)
    return resp, r


def reset(node, req, resp):
    """The twin back to rest: no actuation, no tip load, t = 0, its schedule restarted."""
    with node._lock:
        node.twin.reset()
        node._anchor, node._steps_done = None, 0
        mode = node.cfg.mode
    resp.success = True
    resp.message = f"twin reset: no actuation, no tip load, {node.twin.rest_message}, t = 0"
    if mode == "quasi_static":
        node._solve_trigger.trigger()
    node.get_logger().info(resp.message)
    return resp


def pause(node, req, resp):
    """std_srvs/SetBool ``~/pause``: data true pauses the twin, false resumes it
    (:meth:`SoftTwinNode.set_paused`)."""
    was, t = node.set_paused(req.data)
    state = "paused" if req.data else "running"
    resp.success = True
    resp.message = f"twin {state} at t = {t:.4f} s" + (" (it already was)" if was == bool(req.data) else "")
    node.get_logger().info(resp.message)
    return resp


def single_step(node, req, resp):
    """std_srvs/Trigger ``~/step``: one step of the paused twin
    (:meth:`SoftTwinNode.single_step`); refused while it runs."""
    out = node.single_step()
    if out is None:
        resp.success = False
        resp.message = "the twin is running: pause it first (~/pause with data: true)"
        return resp
    info, t = out
    resp.success = bool(info.converged)
    resp.message = (f"stepped to t = {t:.4f} s" if info.converged else
                    f"step failed, the state kept at t = {t:.4f} s: {info.message}")
    return resp
