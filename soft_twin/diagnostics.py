"""The node's statistics and its /diagnostics status.

:class:`Stats` counts over one diagnostics period (rates, step and publish
times, latencies) and since start (``totals``); the node updates it under its
lock. :func:`values` turns a period into the status's key/values (units in
the key names), :func:`level` picks the status's level and message (the
first that applies: solver failing, failed steps, internal error, behind
real time, lost inputs, unstable equilibrium, rejected inputs, ok).
"""

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue


from soft_twin_core import commands as cmd
from soft_twin_core.text import clip


class Stats:
    """Counters over one diagnostics period and since start."""

    def __init__(self):
        self.reset_window(time.monotonic())
        self.totals = dict(steps=0, solver_failures=0, dropped_steps=0, commands_received=0,
                           commands_applied=0, commands_superseded=0, commands_lost=0,
                           wrenches_received=0, wrenches_applied=0, wrenches_lost=0,
                           rejected_actuation=0, rejected_wrench=0, internal_errors=0,
                           rejected_parameter_changes=0, joint_commands_received=0,
                           joint_commands_applied=0, joint_commands_superseded=0, joint_commands_lost=0,
                           rejected_joint=0, obstacle_updates_received=0, obstacle_updates_applied=0,
                           rejected_obstacle=0, base_poses_received=0, base_poses_applied=0, base_poses_lost=0,
                           rejected_base_pose=0)
        self.last_internal_error = ""
        self.rejected_by_reason = {r: 0 for r in cmd.REJECT_REASONS}
        self.last_rejection = ""
        self.last_parameter_rejection = ""
        self.last_solver_message = ""
        self.consecutive_failures = 0
        self.unstable = False

    def reset_window(self, now):
        self.window_start = now
        self.steps = 0
        self.ticks = 0
        self.sim_time = 0.0
        self.compute_times = []
        self.iterations = []
        self.publish_times = []
        self.command_latencies = []       # [s], command header.stamp -> first state with it
        self.node_latencies = []          # [s], command taken by the node -> first state with it
        self.input_batches = []           # commands taken per actuation callback
        self.rejected = 0
        self.lost = 0                     # inputs lost before the node took them
        self.failures = 0                 # failed steps or solves
        self.publishes = 0                # states published

    def reject(self, kind, err):
        self.totals[f"rejected_{kind}"] += 1
        self.rejected_by_reason[err.reason] += 1
        self.rejected += 1
        self.last_rejection = clip(f"{kind} ({err.reason}): {err}", 400)

    def record(self, info, sim_dt):
        """One step call or solve (``info``: :class:`soft_twin_core.twin.UpdateInfo`,
        ``sim_dt`` [s] of twin time it advanced). A failed one's dropped
        inputs are taken back from the applied counts and counted as
        rejected (reason solver_failed); returns their kinds."""
        self.ticks += 1
        self.steps += info.steps
        self.totals["steps"] += info.steps
        self.sim_time += sim_dt
        self.compute_times.append(info.compute_time)
        self.iterations.append(info.iterations)
        self.unstable = not info.stable
        if info.converged:
            self.consecutive_failures = 0
            if info.message:
                self.last_solver_message = info.message
            return ()
        self.consecutive_failures += 1
        self.failures += 1
        self.totals["solver_failures"] += 1
        self.last_solver_message = info.message
        applied = {"actuation": "commands_applied", "joint": "joint_commands_applied", "wrench": "wrenches_applied",
                   "obstacles": "obstacle_updates_applied", "base_pose": "base_poses_applied"}
        rejected = {"obstacles": "obstacle"}
        for kind in info.dropped:
            self.totals[applied[kind]] -= 1
            self.reject(rejected.get(kind, kind), cmd.InputError("solver_failed", info.message))
        return tuple(info.dropped)


def _lost(total, gaps):
    return str(total) if gaps.supported else "n/a"


def values(s, cfg, twin, gaps, now, paused=False):
    """(key/values of the period ending at monotonic time ``now`` [s], the
    step rate [Hz]); ``gaps``: the SequenceGaps of the actuation, wrench and
    joint topics; ``paused``: the twin is paused (``~/pause``)."""
    wall = max(now - s.window_start, 1e-9)
    ct = np.array(s.compute_times) if s.compute_times else np.zeros(1)
    its = np.array(s.iterations) if s.iterations else np.zeros(1)
    pt = np.array(s.publish_times) if s.publish_times else np.zeros(1)
    cl = np.array(s.command_latencies) if s.command_latencies else np.full(1, np.nan)
    nl = np.array(s.node_latencies) if s.node_latencies else np.full(1, np.nan)
    rate = s.steps / wall
    t = s.totals
    out = {
        "mode": cfg.mode,
        "robot": (f"{twin.mech.name} ({len(twin.mech.joint_names)} joints, {len(twin.mech.tree.soft_joints)} "
                  f"sections, {twin.mech.tree.nv} dof)"),
        "twin_time_s": f"{twin.state.t:.4f}",
        "contacts_active": str(len(twin.contacts) if twin.contacts is not None else 0),     # with obstacles
        "paused": "true" if paused else "false",
        "time_scale": f"{cfg.time_scale:g}",          # twin s per wall s (slow motion < 1)
        "step_rate_target_hz": (f"{cfg.step_rate_hz * cfg.time_scale:.3f}" if cfg.mode == "dynamic" and not paused
                                else "paused" if paused else "on input"),
        "step_rate_hz": f"{rate:.3f}",
        "publish_rate_hz": f"{s.publishes / wall:.3f}",
        "real_time_factor": f"{s.sim_time / wall:.4f}" if cfg.mode == "dynamic" else "n/a",
        "step_time_mean_ms": f"{1e3 * ct.mean():.4f}",
        "step_time_max_ms": f"{1e3 * ct.max():.4f}",
        "publish_time_mean_ms": f"{1e3 * pt.mean():.4f}",
        "command_to_publish_mean_ms": f"{1e3 * cl.mean():.4f}",
        "command_to_publish_max_ms": f"{1e3 * cl.max():.4f}",
        "command_in_node_mean_ms": f"{1e3 * nl.mean():.4f}",
        "solver_iterations_mean": f"{its.mean():.2f}",
        "solver_iterations_max": str(int(its.max())),
        "solver_failures_total": str(t["solver_failures"]),
        "solver_consecutive_failures": str(s.consecutive_failures),
        "solver_last_message": clip(s.last_solver_message, 400),
        "steps_total": str(t["steps"]),
        "dropped_steps_total": str(t["dropped_steps"]),
        "commands_received_total": str(t["commands_received"]),
        "commands_applied_total": str(t["commands_applied"]),
        "commands_superseded_total": str(t["commands_superseded"]),
        "commands_lost_total": _lost(t["commands_lost"], gaps["actuation"]),
        "command_queue_max": str(max(s.input_batches, default=0)),
        "wrenches_received_total": str(t["wrenches_received"]),
        "wrenches_applied_total": str(t["wrenches_applied"]),
        "wrenches_lost_total": _lost(t["wrenches_lost"], gaps["wrench"]),
        "rejected_inputs_total": str(t["rejected_actuation"] + t["rejected_wrench"] + t["rejected_joint"]
                                     + t["rejected_obstacle"] + t["rejected_base_pose"]),
        "rejected_actuation_total": str(t["rejected_actuation"]),
        "rejected_wrench_total": str(t["rejected_wrench"]),
        "obstacle_updates_received_total": str(t["obstacle_updates_received"]),      # ~/obstacles (issue 27)
        "obstacle_updates_applied_total": str(t["obstacle_updates_applied"]),
        "rejected_obstacle_total": str(t["rejected_obstacle"]),
        "base_poses_received_total": str(t["base_poses_received"]),          # ~/base_pose_command (issue 29)
        "base_poses_applied_total": str(t["base_poses_applied"]),
        "base_poses_lost_total": str(t["base_poses_lost"]),
        "rejected_base_pose_total": str(t["rejected_base_pose"]),
        "obstacles": str(len(twin.obstacles)),
        **{f"rejected_{r}_total": str(n) for r, n in s.rejected_by_reason.items()},
        "last_rejection": s.last_rejection,
        "rejected_parameter_changes_total": str(t["rejected_parameter_changes"]),
        "last_parameter_rejection": s.last_parameter_rejection,
        "internal_errors_total": str(t["internal_errors"]),
        "last_internal_error": s.last_internal_error,
    }
    return out, rate


def joint_values(s, gaps, snap):
    """Joint command counters and the members' peak stresses [Pa] of the
    last published state ``snap`` (None: none yet)."""
    t = s.totals
    out = {"joint_commands_received_total": str(t["joint_commands_received"]),
           "joint_commands_applied_total": str(t["joint_commands_applied"]),
           "joint_commands_superseded_total": str(t["joint_commands_superseded"]),
           "joint_commands_lost_total": _lost(t["joint_commands_lost"], gaps["joint"]),
           "rejected_joint_total": str(t["rejected_joint"])}
    if snap is not None:
        for name, (normal, shear) in snap.stresses.items():
            out[f"peak_normal_stress_{name}_pa"] = f"{normal:.6g}"
            out[f"peak_shear_stress_{name}_pa"] = f"{shear:.6g}"
    return out


def level(s, cfg, rate, new_internal_error, paused=False):
    """(DiagnosticStatus level, message) of a period: the first that applies
    (see the module); ``new_internal_error``: an internal error not reported yet."""
    last = clip(s.last_solver_message, 400)
    if s.consecutive_failures:
        return DiagnosticStatus.ERROR, f"solver failing, state kept: {last}"
    if s.failures:
        return DiagnosticStatus.WARN, (f"{s.failures} step(s) or solve(s) failed, the state kept and the input "
                                       f"dropped: {last}")
    if new_internal_error:
        return DiagnosticStatus.ERROR, f"internal error: {s.last_internal_error}"
    target = cfg.step_rate_hz * cfg.time_scale
    if cfg.mode == "dynamic" and s.steps and not paused and rate < 0.95 * target:
        return DiagnosticStatus.WARN, (f"behind real time: {rate:.1f} of {target:g} steps/s"
                                       + (f" (time_scale {cfg.time_scale:g})" if cfg.time_scale != 1 else ""))
    if s.lost:
        return DiagnosticStatus.WARN, f"{s.lost} input(s) lost before the node took them (queue overflow or transport)"
    if s.unstable:
        return DiagnosticStatus.WARN, "only an unstable equilibrium was found"
    if s.rejected:
        return DiagnosticStatus.WARN, f"{s.rejected} input(s) rejected: {s.last_rejection}"
    return DiagnosticStatus.OK, "paused (~/pause, ~/step)" if paused else "ok"


def diagnostic_array(header, name, hardware_id, lvl, message, kv):
    """The /diagnostics message of one status."""
    status = DiagnosticStatus(level=lvl, name=name, message=message, hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=v) for k, v in kv.items()])
    return DiagnosticArray(header=header, status=[status])
