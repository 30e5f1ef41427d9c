"""The node's collaborators without a node: the step schedule's arithmetic,
the folding of input batches (real message objects), the statistics and the
diagnostics level, the markers of both kinds of robot."""
from types import SimpleNamespace

import numpy as np
import pytest

from soft_twin import schedule
from soft_twin_core import twin as tw

msgs = pytest.importorskip("soft_twin.msg", reason="needs the ROS message packages: the venv of `make setup`")


# ------------------------------------------------------------------ schedule

def test_steps_due_at_the_tick_and_early():
    # anchor 0, dt 10 ms: at 25 ms two steps are due (rounding), early allows the third
    assert schedule.steps_due(0.025, 0.0, 0.01, 0) == 2
    assert schedule.steps_due(0.025, 0.0, 0.01, 2) == 0
    assert schedule.steps_due(0.025, 0.0, 0.01, 2, early=True) == 1
    assert schedule.steps_due(0.025, 0.0, 0.01, 3, early=True) == 0     # never more than one step ahead


def test_clock_late_and_early_step_need_an_anchor():
    assert not schedule.clock_late(5.0, None, 0.01, 0)
    assert not schedule.may_step_early(5.0, None, 0.01, 0)
    assert schedule.clock_late(0.0301, 0.0, 0.01, 1)          # 3.01 periods in, 1 done: > 2 late
    assert not schedule.clock_late(0.0299, 0.0, 0.01, 1)
    assert schedule.may_step_early(0.0101, 0.0, 0.01, 1) and not schedule.may_step_early(0.0101, 0.0, 0.01, 2)


def test_catch_up_drops_the_backlog_beyond_the_bound():
    assert schedule.catch_up(3, 5) == (3, 0)
    assert schedule.catch_up(12, 5) == (5, 7)


# ------------------------------------------------------------------ inputs

@pytest.fixture(scope="module")
def model():
    from soft_twin_core.robot.model import load_model
    return load_model("tendon_arm")


def _cmd(names, values, sec=0):
    m = msgs.ActuationCommand(names=names, values=values)
    m.header.stamp.sec = sec
    return m, {"publication_sequence_number": sec}


def test_fold_commands_applies_the_valid_in_order_and_returns_the_errors(model):
    from soft_twin import inputs
    batch = [_cmd(["tendon_y_pos"], [1.0], 1), _cmd(["nope"], [2.0], 2), _cmd(["tendon_z_pos"], [3.0], 3),
             _cmd(["tendon_y_pos"], [float("nan")], 4)]
    u, newest, n, errors = inputs.fold_commands(model, batch, np.zeros(4), None)
    assert u.tolist() == [1.0, 0.0, 3.0, 0.0]                 # partial commands keep the others
    assert newest is batch[2][0] and n == 2
    assert [e.reason for e in errors] == ["unknown_name", "non_finite"]
    assert inputs.sequence_number(batch[1][1]) == 2 and inputs.sequence_number(None) is None
    assert "(and 1 more)" in inputs.rejection_warning("actuation command", errors)


def test_fold_joint_commands_on_a_tree_robot():
    from sensor_msgs.msg import JointState
    from soft_twin import inputs
    from soft_twin_core.robot.mechanism import load_mechanism
    mech = load_mechanism("pan_tilt_arm")
    good = JointState(name=["pan"], position=[0.2])
    bad = JointState(name=["elbow_that_is_not"], position=[0.1])
    pos, eff, newest, n, errors = inputs.fold_joint_commands(mech, [(good, None), (bad, None)], {}, {})
    assert pos["pan"] == pytest.approx(0.2) and newest is good and n == 1
    assert len(errors) == 1 and errors[0].reason == "unknown_name"


def test_parse_wrenches_keeps_the_newest_valid():
    from geometry_msgs.msg import WrenchStamped
    from soft_twin import inputs
    cfg = SimpleNamespace(base_frame="base", tip_frame="tip", max_tip_force_n=10.0, max_tip_torque_nm=1.0)
    a = WrenchStamped()
    a.header.frame_id = "base"
    a.wrench.force.z = -1.0
    b = WrenchStamped()
    b.header.frame_id = "base"
    b.wrench.force.z = -50.0                    # over max_tip_force_n
    newest, errors = inputs.parse_wrenches([(a, None), (b, None)], cfg)
    assert newest[0][2] == -1.0 and len(errors) == 1 and errors[0].reason == "over_limit"


# ------------------------------------------------------------------ diagnostics

def test_stats_record_takes_a_dropped_input_back_and_the_level_says_so():
    from diagnostic_msgs.msg import DiagnosticStatus
    from soft_twin import diagnostics
    s = diagnostics.Stats()
    s.totals["commands_applied"] = 3
    s.totals["joint_commands_applied"] = 1
    assert s.record(tw.UpdateInfo(steps=2, iterations=3), 0.02) == ()
    failed = tw.UpdateInfo(steps=0, iterations=9, converged=False, message="Newton failed",
                           dropped=("actuation", "joint"))
    assert s.record(failed, 0.0) == ("actuation", "joint")
    assert s.totals["commands_applied"] == 2 and s.totals["joint_commands_applied"] == 0
    assert s.rejected_by_reason["solver_failed"] == 2 and s.totals["steps"] == 2
    # every other input a twin drops (Twin._drop) is taken back too, and counted as rejected
    s.totals.update(wrenches_applied=1, obstacle_updates_applied=1, base_poses_applied=1)
    others = ("wrench", "obstacles", "base_pose")
    assert s.record(tw.UpdateInfo(converged=False, message="Newton failed", dropped=others), 0.0) == others
    assert s.totals["wrenches_applied"] == s.totals["obstacle_updates_applied"] == s.totals["base_poses_applied"] == 0
    assert s.totals["rejected_wrench"] == s.totals["rejected_obstacle"] == s.totals["rejected_base_pose"] == 1
    assert s.rejected_by_reason["solver_failed"] == 5
    cfg = SimpleNamespace(mode="dynamic", step_rate_hz=100.0, time_scale=1.0)
    assert diagnostics.level(s, cfg, 100.0, False)[0] == DiagnosticStatus.ERROR     # failing now
    s.record(tw.UpdateInfo(steps=1), 0.01)
    level, message = diagnostics.level(s, cfg, 100.0, False)
    assert level == DiagnosticStatus.WARN and "failed" in message                    # failed in this period
    s.reset_window(0.0)
    assert diagnostics.level(s, cfg, 100.0, False) == (DiagnosticStatus.OK, "ok")
    s.steps = 10
    assert "behind real time" in diagnostics.level(s, cfg, 50.0, False)[1]
    # slow motion (time_scale 0.5): 50 steps/s is the target; paused: no steps is no lag
    slow = SimpleNamespace(mode="dynamic", step_rate_hz=100.0, time_scale=0.5)
    assert diagnostics.level(s, slow, 50.0, False) == (DiagnosticStatus.OK, "ok")
    assert "of 50 steps/s (time_scale 0.5)" in diagnostics.level(s, slow, 40.0, False)[1]
    assert diagnostics.level(s, cfg, 0.0, False, paused=True) == (DiagnosticStatus.OK, "paused (~/pause, ~/step)")


def test_time_scale_is_validated_and_sets_the_wall_period():
    from soft_twin.config import ConfigError, config_from_values
    cfg = config_from_values({"time_scale": 0.25, "step_rate_hz": 200.0})
    assert cfg.dt == pytest.approx(0.005) and cfg.wall_dt == pytest.approx(0.02)
    assert config_from_values({}).time_scale == 1.0
    for bad in (0.0, -1.0, 11.0, float("nan"), "fast"):
        with pytest.raises(ConfigError, match="time_scale"):
            config_from_values({"time_scale": bad})


def test_the_pages_sliders_carry_each_input_its_range_and_unit():
    """One slider per actuator and per position- or effort-controlled joint
    (none for a passive one): the robot file's bounds where it declares
    them, else the documented defaults; units N, Pa, rad, m."""
    from soft_twin.live_view_out import page_controls, units_of
    from soft_twin_core.robot.mechanism import load_mechanism
    arm = load_mechanism("tendon_arm")
    c = page_controls(arm, np.array([0.0, 0.0, 3.0, 0.0]))
    assert [x.label for x in c] == ["tendon_y_pos [N]", "tendon_y_neg [N]", "tendon_z_pos [N]", "tendon_z_neg [N]"]
    assert all((x.kind, x.lo, x.hi) == ("actuation", 0.0, 20.0) for x in c) and c[2].value == 3.0
    pneu = load_mechanism("pneumatic_arm")
    for x, act in zip(page_controls(pneu), pneu.actuators):
        assert (x.unit, x.lo, x.hi) == ("Pa", act.lower, act.upper) and np.isfinite([x.lo, x.hi]).all()
        assert 0 < x.step <= (x.hi - x.lo) / 100
    pan = load_mechanism("pan_tilt_arm")
    joints = {x.name: x for x in page_controls(pan) if x.kind.startswith("joint")}
    tree = pan.tree
    modes = {tree.joints[i].name: pan.control[i] for i in pan.rigid_joints}
    assert set(joints) == {n for n, m in modes.items() if m in ("position", "effort")} and joints
    assert (joints["pan"].lo, joints["pan"].hi, joints["pan"].unit) == (-3.0, 3.0, "rad")
    assert units_of(pan)["pan"] == "rad" and units_of(pneu)[pneu.actuators[0].name] == "Pa"


# ------------------------------------------------------------------ markers

def test_markers_of_a_rod_and_fewer_samples_delete_the_rest(model):
    """A classic rod's tube: one cylinder per backbone interval, as long as
    the straight rod (1.05 overlap), the tip sphere at the tip; fewer
    samples delete the surplus cylinders."""
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker
    from soft_twin import markers
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.twin import Twin
    from soft_twin_core.twin import TwinSettings
    mech = from_robot_model(model)
    robot = SimpleNamespace(mech=mech)
    mk = markers.Markers()
    snap = Twin(mech, TwinSettings(mode="quasi_static", points_per_section=4)).outputs()
    out = mk(snap, robot, Header())
    tubes = [m for m in out.markers if m.ns == "tube"]
    assert len(tubes) == len(snap.s) - 1 == 4 * model.n_sections and all(m.action == Marker.ADD for m in tubes)
    L = sum(m.scale.z for m in tubes) / 1.05
    # the rest shape sags under gravity: the polyline is a little shorter than the arm
    assert L == pytest.approx(model.total_length, rel=2e-3)
    tip = [m for m in out.markers if m.ns == "tip"][0]
    assert tip.pose.position.x == pytest.approx(snap.tip_pose[0, 3])
    snap2 = Twin(mech, TwinSettings(mode="quasi_static", points_per_section=2)).outputs()
    out2 = mk(snap2, robot, Header())
    deleted = [m.id for m in out2.markers if m.action == Marker.DELETE]
    assert deleted == list(range(len(snap2.s) - 1, len(snap.s) - 1))


# ------------------------------------------------------------------ parameters

def test_parameter_coercion_and_the_unknown_name_hint():
    from soft_twin.config import PARAMETERS, coerced, unknown_parameters_message
    assert coerced("step_rate_hz", 200) == 200.0 and isinstance(coerced("step_rate_hz", 200), float)
    assert coerced("step_rate_hz", True) is True              # a bool is not a number here
    assert coerced("not_ours", 3) == 3
    text = unknown_parameters_message(["step_rate"])
    assert "'step_rate' -> 'step_rate_hz'?" in text and all(p in text for p in PARAMETERS)


def test_the_pages_actuator_routes_run_through_the_cross_sections_at_their_offsets():
    """The page draws each actuator along its route: at every backbone
    sample from its start to its end, the point ``p(s) + R(s) d(s)`` lies
    |d| from the backbone, square to its tangent (the tendon arm's four
    straight tendons on a curled arm, one of them made helical, 5 turns a
    metre; the pneumatic arm's chambers), and a view given routes and
    frames draws them (and takes them away when they are off)."""
    import yaml
    from soft_twin.live_view_out import actuator_routes
    from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
    from soft_twin_core.robot.model import find_file, model_from_dict
    from soft_twin_core.twin import Twin, TwinSettings
    from soft_twin_core.viz.live_view import LiveView
    d = yaml.safe_load(open(find_file("tendon_arm", "robots")).read())
    d["actuators"][0].update(routing="helical", radius=0.008, turns_per_meter=5.0)
    d["actuators"][0].pop("offset", None)
    helical = from_robot_model(model_from_dict(d), d)
    assert helical.actuators[0].routing == "helical"
    for robot, u in (("tendon_arm", [0.0, 0.0, 3.0, 0.0]), (helical, [1.0, 0.0, 0.0, 0.0]), ("pneumatic_arm", None)):
        mech = load_mechanism(robot) if isinstance(robot, str) else robot
        twin = Twin(mech, TwinSettings(mode="quasi_static"))
        if u is not None:
            twin.set_actuation(u)
            assert twin.step().converged
        snap = twin.outputs()
        routes = actuator_routes(mech, snap)
        assert [k for k, _ in routes] == [a.kind for a in mech.actuators]
        for (kind, P), act in zip(routes, mech.actuators):
            poses, s = (np.asarray(x) for x in snap.backbones[mech.members[0].name])
            on = (s >= act.start - 1e-9) & (s <= act.end + 1e-9)
            d, _ = act.offset_at(s[on])
            arm = P - poses[on, :3, 3]
            np.testing.assert_allclose(np.linalg.norm(arm, axis=1), np.linalg.norm(d, axis=1), rtol=1e-12)
            np.testing.assert_allclose(np.einsum("ki,ki->k", arm, poses[on, :3, 0]), 0.0, atol=1e-12)
    view = LiveView(port=0)
    try:
        from soft_twin.live_view_out import articulated_view_snapshot
        shot, radii = articulated_view_snapshot(mech, snap)
        view.show(shot, radii, routes=routes, frames=snap.frames)
        kinds = {k for k, _ in routes}
        assert ("/twin/chambers" in view._sent) == ("chamber" in kinds)
        assert all(f"/twin/frames/{n}" in view._sent for n in snap.frames)
        view.show(shot, radii)
        assert not any(n.startswith(("/twin/frames/", "/twin/tendons", "/twin/chambers")) for n in view._sent)
    finally:
        view.close()


def test_a_slider_the_page_moves_is_not_pulled_back_before_the_twin_takes_its_value(monkeypatch):
    """The page drags a slider to 16 N: its command goes out, and while the
    twin still holds its older value (the command on its way) the view does
    not write that value back onto the slider (it did: on a loaded machine
    a drag ended at 0 N). FOLLOW_HOLD_S after the page's last input the
    slider shows the twin's value again (a rejected command shows), and a
    command from a topic moves it at once."""
    from soft_twin_core.viz import live_view as lv
    clock = [100.0]
    monkeypatch.setattr(lv, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    view = lv.LiveView(port=0)
    try:
        sent = []
        view.set_controls([lv.Control("actuation", "t", 0.0, 20.0, 0.1, "N")], lambda c, v: sent.append(v))
        h, _ = view._sliders[("actuation", "t")]
        view._follow("actuation", {"t": 0.0})
        h.value = 16.0                           # the page's drag: viser takes the value, then calls back
        for callback in h._impl.update_cb:
            callback(SimpleNamespace(client=object(), target=h))
        assert sent == [16.0] and view.control_events == 1
        clock[0] += 0.5
        view._follow("actuation", {"t": 0.0})    # the twin has not applied it yet
        assert h.value == 16.0
        clock[0] += lv.FOLLOW_HOLD_S
        view._follow("actuation", {"t": 0.0})    # still not applied (say, rejected): the twin's value
        assert h.value == 0.0
        view._follow("actuation", {"t": 5.0})    # a command from a topic
        assert h.value == 5.0
    finally:
        view.close()
