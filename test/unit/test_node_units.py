"""The node's ROS-free parts: input validation, the twin's state machine,
parameter validation, robot lookup. (Message conversions need the ROS
message packages and are skipped without them.)"""
import math
from pathlib import Path

import numpy as np
import pytest

from soft_twin_core import twin as tw


from soft_twin_core import commands as cmd
from soft_twin.config import (PARAMETERS, ConfigError, config_from_values, load_robot,
                              resolve_robot_file, validate)
from soft_twin_core.engine import loads as ld
from soft_twin_core.errors import StaticsError
from soft_twin_core.reference import dynamics as dy
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference import loads as rl
from soft_twin_core.reference import statics as st
from soft_twin_core.robot.model import load_model
from soft_twin_core.solve import constrained as cs
from soft_twin_core.solve.constrained import MechanismSimulator
from rod_statics import mechanism, solve_statics

ROOT = Path(__file__).resolve().parents[2]
ROBOT = ROOT / "config" / "robots" / "tendon_arm.yaml"
NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]


@pytest.fixture(scope="module")
def model():
    return load_model(ROBOT)


# ------------------------------------------------------------------ inputs

def test_parse_actuation_named_keeps_the_others(model):
    u = cmd.parse_actuation(model, ["tendon_z_pos"], [0.5], [0.1, 0.2, 0.3, 0.4])
    assert u.tolist() == [0.1, 0.2, 0.5, 0.4]


def test_parse_actuation_positional_in_given_order(model):
    assert cmd.parse_actuation(model, [], [1, 2, 3, 4], np.zeros(4)).tolist() == [1, 2, 3, 4]
    order = ["tendon_z_neg", "tendon_z_pos", "tendon_y_neg", "tendon_y_pos"]
    assert cmd.parse_actuation(model, [], [1, 2, 3, 4], np.zeros(4), order).tolist() == [4, 3, 2, 1]


@pytest.mark.parametrize("names, values, reason", [
    (["tendon_y_pos"], [math.nan], "non_finite"),
    (["tendon_y_pos"], [math.inf], "non_finite"),
    (["tendon_y_pos", "tendon_z_pos"], [-math.inf, 1.0], "non_finite"),
    (["tendon_y_pos", "tendon_z_pos"], [1.0], "wrong_length"),
    (["tendon_y_pos"], [1.0, 2.0], "wrong_length"),
    ([], [1.0, 2.0, 3.0], "wrong_length"),
    ([], [], "wrong_length"),
    (["tendon_q"], [1.0], "unknown_name"),
    (["tendon_y_pos", "tendon_y_pos"], [1.0, 2.0], "duplicate_name"),
    (["tendon_y_neg"], [-0.1], "negative_tension"),
    ([], [0.1, 0.2, -1e-9, 0.0], "negative_tension"),
])
def test_parse_actuation_rejects(model, names, values, reason):
    current = np.array([0.1, 0.2, 0.3, 0.4])
    with pytest.raises(cmd.InputError) as exc:
        cmd.parse_actuation(model, names, values, current)
    assert exc.value.reason == reason
    assert current.tolist() == [0.1, 0.2, 0.3, 0.4]      # never partially applied


def test_parse_tip_wrench_frames():
    w, frame = cmd.parse_tip_wrench([1, 2, 3], [4, 5, 6], "base", "base", "tip")
    assert frame == "world" and w.tolist() == [1, 2, 3, 4, 5, 6]
    assert cmd.parse_tip_wrench([0, 0, 1], [0, 0, 0], "tip", "base", "tip")[1] == "body"
    for frame_id in ("", "map", "Base"):
        with pytest.raises(cmd.InputError) as exc:
            cmd.parse_tip_wrench([0, 0, 0], [0, 0, 0], frame_id, "base", "tip")
        assert exc.value.reason == "bad_frame"
    with pytest.raises(cmd.InputError) as exc:
        cmd.parse_tip_wrench([0, math.nan, 0], [0, 0, 0], "base", "base", "tip")
    assert exc.value.reason == "non_finite"


# ------------------------------------------------------------------ lost inputs

def test_sequence_gaps_one_publisher_is_exact():
    g = cmd.SequenceGaps()
    assert [g.add(n, publishers=1) for n in (5, 6, 7, 10, 11, 200)] == [0, 0, 0, 2, 0, 188]
    assert g.lost == 190 and g.supported
    # the publisher restarted (numbers start again): a new stream, nothing lost
    assert [g.add(n, publishers=1) for n in (1, 2, 4)] == [0, 0, 1]
    assert g.lost == 191


def test_sequence_gaps_several_publishers():
    g = cmd.SequenceGaps()
    # A publishes 1..100, B joins at 5000 (it published before matching): not a gap
    lost = [g.add(n, publishers=1) for n in range(1, 51)]
    lost += [g.add(5000, publishers=2)]
    for a, b in zip(range(51, 101), range(5001, 5051)):
        lost += [g.add(a, publishers=2), g.add(b, publishers=2)]
    assert sum(lost) == 0 and g.lost == 0
    # each loses some: counted per publisher
    for a, b in ((103, 5051), (104, 5060), (105, 5061)):
        g.add(a, publishers=2)
        g.add(b, publishers=2)
    assert g.lost == 2 + 8
    # B leaves: its stream is forgotten; A goes on
    assert g.add(106, publishers=1) == 0 and g.add(110, publishers=1) == 3


def test_sequence_gaps_without_numbers():
    g = cmd.SequenceGaps()
    for n in (None, cmd.SequenceGaps.UNSUPPORTED):
        assert g.add(n) == 0
    assert not g.supported and g.lost == 0


# ------------------------------------------------------------------ the twin (of a classic rod: a one-member mechanism)

def _settings(mode, **kw):
    return tw.TwinSettings(mode=mode, **kw)


def _twin(model, settings, d=None):
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.twin import Twin
    return Twin(from_robot_model(model, d), settings)


def _fail_steps(twin):
    """Make the twin's simulator fail every step (as a non-converging step does)."""
    def failing(*a, **k):
        raise cs.StepError("Newton did not converge in 8 iterations, in sub-steps either")
    twin._sim.step = failing


def test_quasi_static_twin_equals_core_statics(model):
    """The rod's statics (its own solver, an independent path) and the twin's
    equilibrium on the one-member mechanism agree: shape, support reaction
    and tip load."""
    twin = _twin(model, _settings("quasi_static"))
    rest = solve_statics(model)
    np.testing.assert_allclose(twin.state.q, rest.q, rtol=0, atol=1e-12)
    u = np.array([0.3, 0.0, 0.0, 0.2])
    twin.set_actuation(u)
    twin.set_tip_wrench([0.0, 0.0, -0.05, 0, 0, 0], "world")
    info = twin.step()
    assert info.converged and info.steps == 1
    ref = solve_statics(model, u, ld.Loads(point=(ld.tip_load(model, (0, 0, -0.05)),)), q_init=rest.q)
    snap = twin.outputs()
    np.testing.assert_allclose(twin.state.q, ref.q, rtol=0, atol=1e-10)
    _, P = kin.backbone(model, ref.q)
    np.testing.assert_allclose(snap.backbone, P, rtol=0, atol=1e-10)
    np.testing.assert_allclose(snap.base_wrench, ref.base_wrench_world, atol=1e-10)   # base at the origin
    # the tip wrench is the applied tip load, in tip axes
    R = snap.tip_pose[:3, :3]
    np.testing.assert_allclose(snap.tip_wrench[:3], R.T @ [0, 0, -0.05], atol=1e-12)
    np.testing.assert_allclose(snap.tip_wrench[3:], 0, atol=1e-12)
    # ... and the rod's internal wrench at its tip section
    tip_internal = st.internal_wrenches(model, ref.q, [model.total_length], u, ld.Loads(
        point=(ld.tip_load(model, (0, 0, -0.05)),)))[0]
    np.testing.assert_allclose(snap.tip_wrench, tip_internal, atol=1e-9)
    # nothing changed: no new solve
    assert twin.step().steps == 0


def test_base_wrench_moment_is_about_the_frame_origin(model):
    # a robot whose base sits away from the origin: m_O = m_base + p0 x f
    import yaml
    d = yaml.safe_load(ROBOT.read_text())
    d["base"] = {"position": [0.1, -0.2, 0.3], "rpy": [0.0, 0.0, 0.5]}
    from soft_twin_core.robot.model import model_from_dict
    m = model_from_dict(d)
    base_w = _twin(m, _settings("quasi_static"), d).outputs().base_wrench
    ref = solve_statics(m)
    # balance about the origin: the reaction cancels gravity's force and its moment about the origin
    sq, wq, sec = rl.gauss_points(m)
    weight = np.array([m.sections[i].M[0, 0] for i in sec])[:, None] * wq[:, None] * m.gravity
    p = kin.poses(m, ref.q, sq)[:, :3, 3]
    np.testing.assert_allclose(base_w[:3], -weight.sum(axis=0), atol=1e-10)
    np.testing.assert_allclose(base_w[3:], -np.cross(p, weight).sum(axis=0), atol=1e-10)


def test_dynamic_twin_steps_like_the_core_simulator(model):
    """The twin steps as the core's simulator with the same settings:
    states to round-off; its base reaction with inertia is the rod's
    dynamic reaction (the numpy chain's) at the step's acceleration."""
    twin = _twin(model, _settings("dynamic", dt=0.005))
    u = np.array([0.2, 0.0, 0.1, 0.0])
    twin.set_actuation(u)
    s = twin.settings
    sim = MechanismSimulator(mechanism(model), s.dt, s.theta, twin.state.q, twin.state.qdot, tol=s.tolerance,
                             max_iterations=max(s.max_iterations, 10), max_substep_levels=s.max_substep_levels)
    info = twin.step(3)
    for _ in range(3):                 # the twin steps one tick at a time, as the node does
        sim.step(u)
    assert info.converged and info.steps == 3
    np.testing.assert_allclose(twin.state.q, sim.q, rtol=0, atol=1e-12)
    assert twin.state.t == pytest.approx(0.015)
    np.testing.assert_allclose(twin.outputs().base_wrench, dy.base_reaction_dynamic(
        model, sim.q, sim.v, sim.a, u, ld.Loads()), atol=1e-9)


def test_failed_step_keeps_the_state_and_drops_the_input(model):
    twin = _twin(model, _settings("dynamic"))
    twin.step()
    q, t = twin.state.q.copy(), twin.state.t
    good_step = twin._sim.step
    _fail_steps(twin)
    twin.set_actuation([0.3, 0, 0, 0], stamp="new")
    info = twin.step()
    assert not info.converged and "state kept" in info.message
    np.testing.assert_array_equal(twin.state.q, q)
    assert twin.state.t == t
    # the published state reflects the inputs of the last good step, and the
    # input that failed is dropped: the next step runs with the good ones
    snap = twin.outputs()
    assert not np.any(snap.u) and snap.command_stamp is None
    assert info.dropped == ("actuation",) and "input dropped" in info.message
    assert not np.any(twin.u) and twin.command_stamp is None and not twin.command_pending
    twin._sim.step = good_step
    assert twin.step().converged and twin.state.t > t


def test_a_step_that_raises_is_a_failure_not_a_crash(model):
    twin = _twin(model, _settings("dynamic"))
    twin.step()
    q = twin.state.q.copy()

    def raising(*a, **k):
        raise np.linalg.LinAlgError("Array must not contain infs or NaNs")
    twin._sim.step = raising
    twin.set_tip_wrench([0, 0, -1e300, 0, 0, 0])
    info = twin.step(3)
    assert not info.converged and info.steps == 0 and "LinAlgError" in info.message
    assert info.dropped == ("wrench",) and not np.any(twin.tip_wrench)
    np.testing.assert_array_equal(twin.state.q, q)


def test_a_late_failure_drops_the_state_inputs_once(model):
    """Inputs that stepped well for a while, then fail: back to the inputs
    before them (once); failing with nothing left to drop, new inputs are
    kept (they are not to blame) and tried at every step."""
    twin = _twin(model, _settings("dynamic"))
    twin.set_actuation([0.1, 0, 0, 0], stamp="a")
    assert twin.step(2).converged
    twin.set_actuation([0.2, 0, 0, 0], stamp="b")
    assert twin.step(2).converged
    good_step = twin._sim.step
    _fail_steps(twin)
    info = twin.step()
    assert info.dropped == ("actuation",) and twin.u[0] == 0.1 and twin.command_stamp == "a"
    info = twin.step()                      # "a" fails too: nothing left to drop
    assert not info.converged and info.dropped == () and twin.command_stamp == "a"
    twin.set_actuation([0.05, 0, 0, 0], stamp="c")
    info = twin.step()
    assert info.dropped == () and twin.command_stamp == "c"       # kept, tried again
    twin._sim.step = good_step
    assert twin.step().converged and twin.outputs().command_stamp == "c"


def test_the_commands_inputs_are_assembled_once_and_follow_every_change(model):
    """A twin stepping held commands reuses their core Inputs; every way
    the commands change (actuation, wrench, a drop, a reset) gives new
    Inputs equal to a fresh assembly of the new commands."""
    twin = _twin(model, _settings("dynamic"))

    def fresh():
        return cs.assemble_inputs(twin.mech, twin.u, twin.efforts, twin.positions, None, twin.held_loads())

    def same(a, b):
        return (np.array_equal(a.u, b.u) and np.array_equal(a.loads.wrench, b.loads.wrench)
                and np.array_equal(a.loads.joint, b.loads.joint))
    twin.set_actuation([0.1, 0, 0, 0], stamp="a")
    held = twin.core_inputs()
    assert twin.step(2).converged and twin.core_inputs() is held and same(held, fresh())
    twin.set_actuation([0.2, 0, 0, 0], stamp="b")
    assert twin.core_inputs() is not held and same(twin.core_inputs(), fresh()) and twin.core_inputs().u[0] == 0.2
    twin.set_tip_wrench([0, 0, -0.5, 0, 0, 0])
    assert same(twin.core_inputs(), fresh()) and twin.core_inputs().loads.wrench.shape[0] == 1
    _fail_steps(twin)
    info = twin.step()
    assert set(info.dropped) == {"actuation", "wrench"}
    assert twin.core_inputs().u[0] == 0.1 and twin.core_inputs().loads.wrench.shape[0] == 0
    twin.reset(solve=False)
    assert not np.any(twin.core_inputs().u) and same(twin.core_inputs(), fresh())


def _unlimited(model_path=ROBOT):
    """The default robot's description with any declared actuator limits
    removed (the failure path must be reached, not the door)."""
    import yaml
    d = yaml.safe_load(Path(model_path).read_text())
    for a in d.get("actuators", []):
        a.pop("limit", None)
    return d


@pytest.mark.parametrize("kind, magnitude", [("actuation", 1e6), ("actuation", 1e100), ("actuation", 1e300),
                                             ("wrench", 1e6), ("wrench", 1e300)])
def test_huge_inputs_fail_within_a_step_period_and_are_dropped(kind, magnitude):
    """Huge but finite inputs (what the door lets through when the robot
    declares no limit): the step fails within one step period (5 ms; it was
    25-200 ms: 10 Newton iterations at up to 5 sub-step levels plus a dense
    fallback), the state is kept, the input is dropped and the next step
    runs on. The cost is the least of five tries (CPU noise on a shared
    machine only adds)."""
    from soft_twin_core.robot.model import model_from_dict
    d = _unlimited()
    model = model_from_dict(d)
    twin = _twin(model, _settings("dynamic", dt=0.005), d)
    twin.warm_up()
    twin.set_actuation([0.2, 0, 0, 0], stamp="good")
    assert twin.step(2).converged
    costs = []
    for _ in range(5):
        q, t = twin.state.q.copy(), twin.state.t
        if kind == "actuation":
            twin.set_actuation([magnitude, 0, 0, 0], stamp="huge")
        else:
            twin.set_tip_wrench([0, 0, -magnitude, 0, 0, 0])
        info = twin.step()
        assert not info.converged and info.dropped == (kind,), info
        costs.append(info.compute_time)
        np.testing.assert_array_equal(twin.state.q, q)
        assert twin.state.t == t and twin.command_stamp == "good" and not np.any(twin.tip_wrench)
        info = twin.step()                  # on with the last good inputs
        assert info.converged and twin.state.t > t
    assert min(costs) <= 0.005, costs


# ------------------------------------------------------------------ limits at the door

def test_actuator_limits_from_the_robot_file():
    from soft_twin_core.robot.model import model_from_dict
    d = _unlimited()
    d["actuators"][0]["limit"] = 40.0
    model = model_from_dict(d)
    assert model.actuators[0].limit == 40.0 and model.actuators[1].limit == math.inf
    assert cmd.parse_actuation(model, ["tendon_y_pos"], [40.0], np.zeros(4))[0] == 40.0
    for v in (40.000001, 1e6, 1e300):
        with pytest.raises(cmd.InputError) as exc:
            cmd.parse_actuation(model, ["tendon_y_pos"], [v], np.zeros(4))
        assert exc.value.reason == "over_limit" and "40 N" in str(exc.value)
    # no limit declared: any finite tension passes the door
    assert cmd.parse_actuation(model, ["tendon_y_neg"], [1e300], np.zeros(4))[1] == 1e300


def test_chamber_limits_bound_the_pressure_magnitude():
    import yaml
    from soft_twin_core.robot.model import model_from_dict
    d = yaml.safe_load((ROBOT.parent / "pneumatic_arm.yaml").read_text())
    d["actuators"][0]["limit"] = 1.0e5
    d["actuators"][0].pop("min", None)      # the shipped chambers are positive-only; this one takes suction
    model = model_from_dict(d)
    name = model.actuator_names[0]
    u0 = np.zeros(len(model.actuators))
    assert cmd.parse_actuation(model, [name], [-1.0e5], u0)[0] == -1.0e5
    for v in (1.5e5, -1.5e5):
        with pytest.raises(cmd.InputError) as exc:
            cmd.parse_actuation(model, [name], [v], u0)
        assert exc.value.reason == "over_limit" and "Pa" in str(exc.value)


def test_tip_wrench_limits():
    assert cmd.parse_tip_wrench([0, 0, 999.0], [0, 0, 0], "b", "b", "t", 1e3, 1e2)[1] == "world"
    for force, torque in (([0, 0, 1001.0], [0, 0, 0]), ([1e300, 1e300, 0], [0, 0, 0]),
                          ([0, 0, 0], [0, 60.0, 80.01])):
        with pytest.raises(cmd.InputError) as exc:
            cmd.parse_tip_wrench(force, torque, "b", "b", "t", 1e3, 1e2)
        assert exc.value.reason == "over_limit"


# ------------------------------------------------------------------ bounded messages

def test_messages_from_huge_inputs_are_bounded(model):
    """A command with 10,000 names made an 89,077-character log line: every
    message built from user input is cut (~200 characters a piece) and says
    how much was left out."""
    from soft_twin_core.text import clip, short_list
    cases = [
        (["x%d" % i for i in range(10000)], [0.1] * 10000, "unknown_name", "(9"),
        (["tendon_y_pos"] * 10000, [0.1] * 10000, "duplicate_name", "repeated"),
        ([], [0.1] * 10000, "wrong_length", "10000"),
        (["n" * 100000], [0.1], "unknown_name", "more characters"),
    ]
    for names, values, reason, hint in cases:
        with pytest.raises(cmd.InputError) as exc:
            cmd.parse_actuation(model, names, values, np.zeros(4))
        assert exc.value.reason == reason and hint in str(exc.value)
        assert len(str(exc.value)) <= 600, (reason, len(str(exc.value)))
    with pytest.raises(cmd.InputError) as exc:
        cmd.parse_tip_wrench([0, 0, 0], [0, 0, 0], "f" * 100000, "base", "tip")
    assert len(str(exc.value)) <= 400 and "more characters" in str(exc.value)
    assert short_list(range(10000)).endswith("more)") and len(short_list(range(10000))) < 260
    assert clip("a" * 1000) == "a" * 200 + "... (800 more characters)"
    assert clip("short") == "short" and short_list(["a", "b"]) == "['a', 'b']"
    with pytest.raises(ConfigError) as exc:
        validate("mode", "m" * 100000)
    assert len(str(exc.value)) <= 400


def test_failed_solve_keeps_the_state(model, monkeypatch):
    twin = _twin(model, _settings("quasi_static"))
    twin.step()
    q = twin.state.q.copy()

    def fail(*a, **k):
        raise StaticsError("no")
    monkeypatch.setattr(cs, "solve_equilibrium", fail)
    twin.set_actuation([1.0, 0, 0, 0], stamp="bad")
    info = twin.step()
    assert not info.converged and "state kept" in info.message
    np.testing.assert_array_equal(twin.state.q, q)
    # the failed input is dropped: the twin keeps the inputs of its state
    assert not np.any(twin.u) and twin.command_stamp is None
    assert not np.any(twin.outputs().u) and twin.outputs().command_stamp is None
    assert not twin.needs_solve


def test_reset_and_mode_switch(model):
    twin = _twin(model, _settings("dynamic"))
    twin.set_actuation([0.5, 0, 0, 0])
    twin.set_tip_wrench([0, 0, -0.01, 0, 0, 0])
    twin.step(5)
    twin.reset()
    assert twin.state.t == 0 and not np.any(twin.u) and not np.any(twin.tip_wrench)
    np.testing.assert_array_equal(twin.state.q, twin.rest_q)
    twin.change_settings(_settings("quasi_static"))
    twin.set_actuation([0.5, 0, 0, 0])
    assert twin.step().converged
    assert not np.any(twin.state.qdot)


def test_command_pending_until_a_step_or_solve_uses_it(model):
    for mode in ("dynamic", "quasi_static"):
        twin = _twin(model, _settings(mode))
        assert not twin.command_pending
        twin.set_actuation([0.1, 0, 0, 0], stamp=object())
        assert twin.command_pending
        twin.set_actuation([0.2, 0, 0, 0], stamp=object())   # supersedes the first
        assert twin.command_pending
        assert twin.step().converged
        assert not twin.command_pending
        twin.set_actuation([0.3, 0, 0, 0], stamp=object())
        twin.reset()
        assert not twin.command_pending


def test_queries_leave_the_twin_alone(model):
    """Statics and FK on the twin's query copy, the rod IK query: the twin's
    own state is untouched; IK's answer holds the target in the rod's own
    statics."""
    twin = _twin(model, _settings("quasi_static"))
    q = twin.state.q.copy()
    info, res = twin.query_copy().statics(np.array([0.4, 0, 0, 0]), np.zeros(6))
    assert info.converged and info.residual is not None
    msg, fk = twin.query_copy().forward_kinematics(strains=res.strains.ravel())
    np.testing.assert_allclose(fk.tip_pose, res.tip_pose, atol=1e-12)
    ik = twin.query_copy().inverse_kinematics(res.tip_pose, tolerance=1e-8)
    assert ik.reached, ik.status
    assert ik.position_error <= 1e-8
    # the target came from an actuation: IK through statics finds one that holds it
    assert ik.actuation_found and ik.names == tuple(model.actuator_names)
    eq = solve_statics(model, ik.values, q_init=ik.q)
    np.testing.assert_allclose(eq.tip_pose[:3, 3], res.tip_pose[:3, 3], atol=1e-7)
    np.testing.assert_array_equal(twin.state.q, q)
    with pytest.raises(ValueError, match="expected 36"):
        twin.query_copy().forward_kinematics(strains=[0.0] * 5)


# ------------------------------------------------------------------ parameters

def test_defaults_are_valid():
    cfg = config_from_values({})
    assert cfg.mode == "dynamic" and cfg.step_rate_hz == 200.0 and cfg.dt == 0.005
    assert set(PARAMETERS) == set(cfg.__dataclass_fields__)


@pytest.mark.parametrize("name, value", [
    ("mode", "kinematic"), ("mode", 3), ("step_rate_hz", 0), ("step_rate_hz", -5.0),
    ("step_rate_hz", math.nan), ("step_rate_hz", "fast"), ("step_rate_hz", True),
    ("step_rate_hz", 5000.0), ("backbone_points_per_section", 0), ("backbone_points_per_section", 2.5),
    ("base_frame", ""), ("tip_frame", "tip link"), ("integrator_theta", 0.3),
    ("integrator_tolerance", 0.0), ("publish_every_n_steps", 0), ("marker_rate_hz", -1.0),
    ("diagnostics_rate_hz", 0.0), ("sections_per_segment", -1), ("actuator_names", ["a", "a"]),
    ("max_catchup_steps", 0), ("wrench_rate_hz", 0.0), ("republish_rate_hz", 0.0),
    ("step_on_command", "yes"), ("step_on_command", 1),
])
def test_bad_parameter_values_are_rejected_with_a_reason(name, value):
    with pytest.raises(ConfigError, match=name):
        validate(name, value)


def test_integer_rates_are_accepted():
    assert validate("step_rate_hz", 100) == 100.0


def test_frames_must_differ():
    with pytest.raises(ConfigError, match="differ"):
        config_from_values({"base_frame": "a", "tip_frame": "a"})


def test_robot_lookup(tmp_path, monkeypatch):
    assert resolve_robot_file("") == ROBOT.resolve()
    assert resolve_robot_file("pneumatic_arm") == (ROBOT.parent / "pneumatic_arm.yaml").resolve()
    assert resolve_robot_file("config/robots/pneumatic_arm.yaml").name == "pneumatic_arm.yaml"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.yaml").write_text(ROBOT.read_text())
    assert resolve_robot_file("mine.yaml") == tmp_path / "mine.yaml"
    with pytest.raises(ConfigError, match="not found"):
        resolve_robot_file("nope.yaml")
    with pytest.raises(ConfigError, match="does not exist"):
        resolve_robot_file(str(tmp_path / "nope.yaml"))


def test_load_robot_inline_override_and_errors():
    cfg = config_from_values({"robot_description": ROBOT.read_text(), "sections_per_segment": 1})
    robot = load_robot(cfg)
    assert robot.model.n_sections == 3 and robot.source.startswith("inline")
    assert [max(g.cy, g.cz) for g in robot.mech.members[0].geometry] == pytest.approx([0.012, 0.010, 0.008])
    with pytest.raises(ConfigError, match="segments"):
        load_robot(config_from_values({"robot_description": "name: x\nsegments: []\n"}))
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_robot(config_from_values({"robot_description": "a: [1,"}))
    with pytest.raises(ConfigError, match="do not match"):
        load_robot(config_from_values({"actuator_names": ["tendon_y_pos"]}))
    cfg = config_from_values({"actuator_names": list(reversed(NAMES))})
    assert load_robot(cfg).model.actuator_names == tuple(NAMES)


# ------------------------------------------------------------------ conversions

def test_quaternions_match_scipy_everywhere():
    pytest.importorskip("geometry_msgs", reason="needs the ROS message packages")
    from scipy.spatial.transform import Rotation
    from soft_twin import conversions as cv
    R = Rotation.random(2000, random_state=3)
    q = cv.quaternions_from_matrices(R.as_matrix())
    ref = R.as_quat() * np.sign(R.as_quat()[:, 3:4])
    np.testing.assert_allclose(q, ref, atol=1e-14)
    for ang in (0.0, 1e-9, np.pi - 1e-9, np.pi):
        for axis in np.eye(3):
            M = Rotation.from_rotvec(ang * axis).as_matrix()
            back = Rotation.from_quat(cv.quaternions_from_matrices(M[None])[0]).as_matrix()
            np.testing.assert_allclose(back, M, atol=1e-14)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R[0].as_matrix(), [0.1, -0.2, 0.3]
    np.testing.assert_allclose(cv.matrix_from_pose(cv.pose_msg(T)), T, atol=1e-15)
    # the RViz cylinder axis (z) goes onto the pose's x axis
    Rc = Rotation.from_quat(cv.cylinder_orientation(T[None])[0]).as_matrix()
    np.testing.assert_allclose(Rc[:, 2], T[:3, 0], atol=1e-14)


def test_params_file_lists_every_parameter_with_its_default():
    import yaml
    values = yaml.safe_load((ROOT / "config" / "params.yaml").read_text())["soft_twin"]["ros__parameters"]
    for name, (default, _) in PARAMETERS.items():
        if default is None:          # actuator_names: unset by default (commented out in the file)
            assert name not in values
            assert f"# {name}:" in (ROOT / "config" / "params.yaml").read_text()
            continue
        assert name in values, name
        assert values[name] == default, (name, values[name], default)
    assert set(values) <= set(PARAMETERS)
    config_from_values(values)


def test_forward_kinematics_of_an_articulated_twin():
    """FK of a tree robot (issue 26): the strains of an equilibrium give
    back its tip pose (joints where they are); the current state; the
    equilibrium under an actuation equals the core's; bad strains are
    named; the twin is untouched."""
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.robot.model import ModelError, find_file
    from soft_twin_core.solve.constrained import solve_equilibrium
    from soft_twin_core.solve.outputs import q_from_section_strains, section_strains, state_outputs
    from soft_twin_core.twin import Twin
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    twin = Twin(mech, tw.TwinSettings(mode="quasi_static"))
    twin.set_joint_commands({"pan": 0.3, "tilt": -0.2}, {})
    twin.step()
    q_before = twin.state.q.copy()
    ref = solve_equilibrium(mech, {"tendon_y_pos": 2.0}, None, {"pan": 0.3, "tilt": -0.2})
    out = state_outputs(mech, ref.q, ref.lam, ref.inputs)
    # the strains of that equilibrium, the joints at the twin's (same commands): its tip pose
    msg, snap = twin.query_copy().forward_kinematics(section_strains(mech, ref.q).ravel())
    assert msg.startswith("ok") and np.abs(snap.tip_pose - out.frames["tool"]).max() < 1e-12
    msg, snap = twin.query_copy().forward_kinematics((), np.array([2.0, 0.0, 0.0, 0.0]))
    assert np.abs(snap.tip_pose - out.frames["tool"]).max() < 1e-9
    msg, snap = twin.query_copy().forward_kinematics()
    assert "current" in msg and np.abs(snap.tip_pose - twin.outputs().tip_pose).max() == 0.0
    with pytest.raises(ModelError, match="expected 24 values"):
        twin.query_copy().forward_kinematics(np.zeros(6))
    bad = section_strains(mech, ref.q)
    bad[1, 0] = 1.1                                            # axial: not free in this arm
    with pytest.raises(ModelError, match=r"section 1 .* mode\(s\) \[0\]"):
        q_from_section_strains(mech, bad, ref.q)
    with pytest.raises(ValueError, match="not both"):
        twin.query_copy().forward_kinematics(np.zeros(24), np.zeros(4))
    assert np.array_equal(twin.state.q, q_before)
    np.testing.assert_array_equal(q_from_section_strains(mech, section_strains(mech, ref.q), q_before), ref.q)


def test_a_tree_twin_checks_its_inputs_at_the_door_only():
    """Validate once (issue 26): the node's parse functions check a command;
    the twin assembles the core's Inputs without checking again, on every
    step and publish (make_inputs ran on each before). The assembled Inputs
    equal make_inputs' for the same valid commands."""
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.robot.model import find_file
    from soft_twin_core.solve import constrained as cs
    from soft_twin_core.twin import Twin
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    pl = [cs.FrameLoad("tool", np.array([0.1, 0.0, -0.2, 0.0, 0.01, 0.0]), "world")]
    a = cs.assemble_inputs(mech, np.array([1.0, 0, 0.5, 0]), {}, {"pan": 0.2}, {"pan": 0.1}, pl)
    b = cs.make_inputs(mech, np.array([1.0, 0, 0.5, 0]), None, {"pan": 0.2}, {"pan": 0.1, "tilt": 0.0},
                       point_loads=pl)
    for f in ("u", "effort", "q_cmd", "v_cmd", "gravity"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    for f in ("joint", "x", "wrench", "world"):
        np.testing.assert_array_equal(getattr(a.loads, f), getattr(b.loads, f))
    calls = []
    real = cs.make_inputs
    cs.make_inputs = lambda *a, **k: calls.append(1) or real(*a, **k)
    try:
        twin = Twin(mech, tw.TwinSettings(mode="dynamic", dt=0.005))
        twin.set_joint_commands({"pan": 0.3, "tilt": -0.2}, {})
        twin.set_actuation(np.array([0.0, 0.0, 1.0, 0.0]))
        n0 = len(calls)
        for _ in range(20):
            assert twin.step().converged
            twin.outputs()
        assert len(calls) == n0                    # none per step or publish
    finally:
        cs.make_inputs = real
    pan = mech.tree.idx_q[mech.tree.joint_index("pan")]
    assert 0.0 < twin.state.q[pan] < 0.3          # on its way (the shaped reference)


def test_a_tree_twin_drops_failed_inputs_as_the_rod_twin_does():
    """One input-drop policy (issue 26): the pan-tilt twin, like the rod's
    (test_a_late_failure_drops_the_state_inputs_once): a new input that
    fails is dropped; inputs that stepped well and then fail give way to
    the inputs before them, once; with nothing left to drop, new inputs are
    kept and tried at every step."""
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.robot.model import find_file
    from soft_twin_core.solve import constrained as cs
    from soft_twin_core.twin import Twin
    twin = Twin(load_mechanism(find_file("pan_tilt_arm", "robots")), _settings("dynamic"))
    twin.set_actuation(np.array([0.1, 0, 0, 0]), stamp="a")
    assert twin.step(2).converged
    twin.set_joint_commands({"pan": 0.1, "tilt": 0.0}, {}, stamp="b")
    assert twin.step(2).converged
    good_step = twin._sim.step

    def failing(*a, **k):
        raise cs.StepError("forced")
    twin._sim.step = failing
    info = twin.step()                      # "b" (the state's own inputs) fails: back to "a", once
    assert info.dropped == ("joint",) and twin.positions["pan"] == 0.0 and twin.command_stamp == "a"
    info = twin.step()                      # "a" fails too: nothing left to drop
    assert not info.converged and info.dropped == () and twin.command_stamp == "a"
    twin.set_actuation(np.array([0.05, 0, 0, 0]), stamp="c")
    info = twin.step()
    assert info.dropped == () and twin.command_stamp == "c" and twin.u[0] == 0.05   # kept, tried again
    twin._sim.step = good_step
    assert twin.step().converged and twin.outputs().u[0] == 0.05
    # a fresh input that fails at once is dropped (back to the good state's)
    twin._sim.step = failing
    twin.set_actuation(np.array([9.0, 0, 0, 0]), stamp="d")
    info = twin.step()
    assert info.dropped == ("actuation",) and twin.u[0] == 0.05 and twin.command_stamp == "c"


def test_forward_kinematics_of_a_closed_chain_says_whether_the_strains_close_it():
    """A closed chain (the planar parallel robot): the strains of one of its
    equilibria close it; other strains leave a gap, named in metres."""
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.robot.model import find_file
    from soft_twin_core.solve.constrained import solve_equilibrium
    from soft_twin_core.solve.outputs import section_strains
    from soft_twin_core.twin import Twin
    mech = load_mechanism(find_file("planar_parallel_robot", "robots"))
    twin = Twin(mech, tw.TwinSettings(mode="quasi_static"))
    twin.step()
    ref = solve_equilibrium(mech)
    msg, _ = twin.query_copy().forward_kinematics(section_strains(mech, twin.state.q).ravel())
    assert msg.endswith("the constraints hold"), msg
    bent = section_strains(mech, ref.q)
    bent[:3, 5] += 0.5                       # 0.5 rad/m more bending at the first sections of one leg only
    msg, _ = twin.query_copy().forward_kinematics(bent.ravel())
    assert "violated by up to" in msg, msg


def test_ik_from_a_far_off_state_is_tried_again_from_rest():
    """The tendon arm curled by 15.9 N and 18 N (its tip 0.28 m from the
    rest tip) asked for a target 40 mm above the rest tip, out of reach:
    the solve from the curled state ended 280 mm from the target; tried
    again from rest, the answer is the one from rest (32 mm away, the
    closest the arm gets), whatever the state it starts from."""
    from soft_twin_core import twin as tw
    from soft_twin_core.robot.mechanism import load_mechanism
    t = tw.Twin(load_mechanism("tendon_arm"), tw.TwinSettings(mode="quasi_static"))
    target = t.outputs().tip_pose[:3, 3] + [0.0, 0.0, 0.04]
    from_rest = t.inverse_kinematics(target, 1e-4)
    t.set_actuation(np.array([15.9, 0.0, 18.0, 0.0]))
    assert t.step().converged
    assert np.linalg.norm(t.outputs().tip_pose[:3, 3] - target) > 0.2
    from_curled = t.inverse_kinematics(target, 1e-4)
    assert not from_rest.reached and 0.02 < from_rest.position_error < 0.05
    assert from_curled.position_error == pytest.approx(from_rest.position_error, rel=1e-6)
    np.testing.assert_allclose(from_curled.values, from_rest.values, atol=1e-6)
