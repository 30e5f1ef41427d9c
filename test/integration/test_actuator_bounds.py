"""Actuator bounds (issue 25, item 10 and item 9's last paragraph).

A robot file's actuator takes an optional ``min``/``max`` on top of its
``limit`` (|u| <= limit; a tendon's range is [0, limit]); one core rule,
:func:`soft_twin_core.robot.model.check_actuator_input`, is used by the node, the
offline runners (rod and tree), and the bounds of IK, the planner and
calibration. The shipped pneumatic arm's chambers are positive-only
(``min: 0``): before, a 1 cm move asked for tens of kPa of suction.
"""

import copy
import math

import numpy as np
import pytest
import yaml

from soft_twin_core.planning import planner as pl
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import ModelError, check_actuator_input, find_file, model_from_dict
from rod_statics import solve_statics

PNEUMATIC = find_file("pneumatic_arm", "robots")
PAN_TILT = find_file("pan_tilt_arm", "robots")


def _pneumatic_dict():
    return yaml.safe_load(open(PNEUMATIC).read())


def _with_suction(d):
    """The pneumatic arm as shipped before: chambers take any pressure."""
    d = copy.deepcopy(d)
    for a in d["actuators"]:
        a.pop("min", None)
        a.pop("max", None)
    return d


# ------------------------------------------------------------------ the schema and the one rule

def test_min_max_and_limit_shorthand_give_the_range():
    d = _pneumatic_dict()
    d = _with_suction(d)
    d["actuators"][0] = {**d["actuators"][0], "limit": 6.0e4}
    d["actuators"][1] = {**d["actuators"][1], "min": 0.0, "max": 5.0e4}
    d["actuators"][2] = {**d["actuators"][2], "limit": 6.0e4, "min": -1.0e4}
    d["actuators"][4] = _pneumatic_dict()["actuators"][4]   # as shipped
    m = model_from_dict(d)
    a = m.actuators
    assert (a[0].lower, a[0].upper) == (-6.0e4, 6.0e4)  # limit alone: |p| <= limit
    assert (a[1].lower, a[1].upper) == (0.0, 5.0e4)
    assert (a[2].lower, a[2].upper) == (-1.0e4, 6.0e4)  # limit and min intersect
    assert (a[3].lower, a[3].upper) == (-math.inf, math.inf)
    assert (a[4].lower, a[4].upper) == (0.0, 1.0e5)    # the shipped file: [0, 100 kPa]
    d["actuators"][4]["limit"] = 5.0e4                 # limit and max: the tighter wins (a study varies limit)
    d["actuators"][5] = {**d["actuators"][5], "limit": 5.0e4, "max": 9.0e4, "min": -9.0e4}
    a = model_from_dict(d).actuators
    assert (a[4].lower, a[4].upper) == (0.0, 5.0e4) and (a[5].lower, a[5].upper) == (-5.0e4, 5.0e4)
    t = yaml.safe_load(open(find_file("tendon_arm", "robots")).read())
    t["actuators"][0]["limit"] = 20.0
    t["actuators"][1]["max"] = 7.0
    t["actuators"][2]["min"] = 0.5                     # a minimum tension (pretension)
    mt = model_from_dict(t)
    assert [(x.lower, x.upper) for x in mt.actuators[:4]] == [(0.0, 20.0), (0.0, 7.0), (0.5, math.inf),
                                                              (0.0, math.inf)]


@pytest.mark.parametrize("patch,words", [
    ({"type": "tendon", "min": -1.0}, ["actuators[0].min", "-1", "can only pull"]),
    ({"min": 5.0e4, "max": 1.0e4}, ["actuators[0]", "empty input range", "50000", "10000"]),
    ({"limit": 6.0e4, "min": 7.0e4}, ["actuators[0]", "empty input range", "70000", "60000"]),
    ({"min": "zero"}, ["actuators[0].min"]),
])
def test_bad_bounds_name_the_field_the_value_and_the_limit(patch, words):
    d = _with_suction(_pneumatic_dict())
    d["actuators"][0].update(patch)
    if patch.get("type") == "tendon":
        d["actuators"][0].pop("area")
    with pytest.raises(ModelError) as exc:
        model_from_dict(d)
    for w in words:
        assert w in str(exc.value)


def test_check_actuator_input_reasons():
    d = _with_suction(_pneumatic_dict())
    d["actuators"][0].update(limit=6.0e4, min=0.0)
    d["actuators"][1].update(max=5.0e4)
    t = yaml.safe_load(open(find_file("tendon_arm", "robots")).read())
    t["actuators"][0]["limit"] = 10.0
    m, mt = model_from_dict(d), model_from_dict(t)
    c0, c1, c2 = m.actuators[:3]
    assert check_actuator_input(c0, 6.0e4) is None and check_actuator_input(c0, 0.0) is None
    assert check_actuator_input(c0, 9.0e4)[0] == "over_limit"
    assert "90000 Pa" in check_actuator_input(c0, 9.0e4)[1] and "60000 Pa" in check_actuator_input(c0, 9.0e4)[1]
    assert check_actuator_input(c0, -1.0)[0] == "under_limit"          # min: 0
    assert "min 0 Pa" in check_actuator_input(c0, -1.0)[1]
    assert check_actuator_input(c1, 5.0e4 + 1)[0] == "over_limit"      # max
    assert check_actuator_input(c2, -1e300) is None                    # no bound declared
    assert check_actuator_input(c2, math.nan)[0] == "non_finite"
    tendon = mt.actuators[0]
    assert check_actuator_input(tendon, -0.1)[0] == "negative_tension"
    assert check_actuator_input(tendon, 10.5)[0] == "over_limit"
    assert check_actuator_input(tendon, 10.0) is None


def test_the_node_uses_the_same_rule():
    from soft_twin_core import commands as cmd
    d = _with_suction(_pneumatic_dict())
    d["actuators"][0].update(limit=6.0e4, min=0.0)
    d["actuators"][1].update(max=5.0e4)
    m = model_from_dict(d)
    u0 = np.zeros(len(m.actuators))
    assert "under_limit" in cmd.REJECT_REASONS
    for k in (0, 1, 2):
        a = m.actuators[k]
        for v in (-7.0e4, -1.0, 0.0, 3.0e4, 5.0e4, 5.5e4, 6.0e4, 6.5e4, 1e300):
            expected = check_actuator_input(a, v)
            if expected is None:
                assert cmd.parse_actuation(m, [a.name], [v], u0)[k] == v
            else:
                with pytest.raises(cmd.InputError) as exc:
                    cmd.parse_actuation(m, [a.name], [v], u0)
                assert (exc.value.reason, str(exc.value)) == expected
    # the shipped pneumatic arm: suction is refused at the door
    with pytest.raises(cmd.InputError) as exc:
        cmd.parse_actuation(model_from_dict(_pneumatic_dict()), ["chamber_2"], [-29477.0], u0)
    assert exc.value.reason == "under_limit" and "-29477" in str(exc.value)


def test_the_articulated_node_uses_the_core_joint_rule():
    from soft_twin_core import commands as cmd
    from soft_twin_core.robot.mechanism import check_joint_position, load_mechanism
    mech = load_mechanism(PAN_TILT)
    tilt = next(j for j in mech.tree.joints if j.name == "tilt")
    for v in (-2.0, -1.5, 0.3, 1.5, 1.6):
        bad = check_joint_position(tilt, v)
        assert (bad is None) == (-1.5 <= v <= 1.5)
        if bad is None:
            assert cmd.parse_joint_command(mech, ["tilt"], [v], [], [], {}, {})[0]["tilt"] == v
        else:
            with pytest.raises(cmd.InputError) as exc:
                cmd.parse_joint_command(mech, ["tilt"], [v], [], [], {}, {})
            assert (exc.value.reason, str(exc.value)) == bad


# ------------------------------------------------------------------ offline runners (CLI: exit 2)

def _cli(args, capsys):
    from soft_twin_core import cli
    code = cli.main(args)
    return code, capsys.readouterr().err


def test_rod_scenario_over_the_limit_exits_2_naming_field_value_and_bound(tmp_path, capsys):
    d = _pneumatic_dict()
    d["actuators"][0]["limit"] = 60000
    d["actuators"][0].pop("max", None)
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(d))
    sc = tmp_path / "over.yaml"
    sc.write_text(yaml.safe_dump({"robot": "robot.yaml", "actuation": {"chamber_1": 90000}}))
    code, err = _cli(["statics", str(sc)], capsys)
    assert code == 2, err
    assert "scenario.actuation.chamber_1" in err and "90000" in err and "60000" in err and "over_limit" in err
    assert "Traceback" not in err
    # a profile too (checked at its points), and suction on the positive-only chambers
    sc.write_text(yaml.safe_dump({"robot": "robot.yaml",
                                  "actuation_profile": {"chamber_2": [[0, 0], [0.1, -5000]]}}))
    code, err = _cli(["dynamics", str(sc), "--duration", "0.01"], capsys)
    assert code == 2 and "scenario.actuation_profile.chamber_2" in err and "-5000" in err and "min 0" in err
    # within the bounds it runs
    sc.write_text(yaml.safe_dump({"robot": "robot.yaml", "actuation": {"chamber_1": 60000}}))
    code, err = _cli(["statics", str(sc), "--output", str(tmp_path / "out.json")], capsys)
    assert code == 0, err


def test_tree_scenario_over_the_limit_exits_2(tmp_path, capsys):
    d = yaml.safe_load(open(PAN_TILT).read())
    acts = None
    for b in d["bodies"]:
        for a in b.get("actuators", []) or []:
            if a["name"] == "tendon_z_pos":
                a["limit"] = 5.0
                acts = a
    assert acts is not None
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(d))
    sc = tmp_path / "over.yaml"
    for body, words in (({"actuation": {"tendon_z_pos": 8.0}}, ["scenario.actuation.tendon_z_pos", "8", "5 N"]),
                        ({"actuation_profile": {"tendon_z_pos": [[0, 0], [1, 6]]}},
                         ["scenario.actuation_profile.tendon_z_pos", "6", "5 N"]),
                        ({"joint_trajectories": {"tilt": [[0, 0], [1, 2.0]]}},
                         ["scenario.joint_trajectories.tilt", "2", "joint limits"])):
        sc.write_text(yaml.safe_dump({"robot": "robot.yaml", **body}))
        code, err = _cli(["statics", str(sc)], capsys)
        assert code == 2, (body, err)
        for w in words:
            assert w in err, (w, err)
    sc.write_text(yaml.safe_dump({"robot": "robot.yaml", "actuation": {"tendon_z_pos": 5.0}}))
    code, err = _cli(["statics", str(sc), "--output", str(tmp_path / "out.json")], capsys)
    assert code == 0, err


# ------------------------------------------------------------------ IK and planners respect the bounds

def _rest(m):
    return solve_statics(m, np.zeros(len(m.actuators)))


def test_pneumatic_ik_stays_positive_and_reports_unreachable():
    """The 1 cm sideways move of the issue: the old (suction) answer, the
    bounded answer, and an independent bounded optimiser agreeing that it
    is out of reach with positive pressures."""
    from scipy.optimize import least_squares
    old = model_from_dict(_with_suction(_pneumatic_dict()))
    new = model_from_dict(_pneumatic_dict())
    r0 = _rest(new)
    tgt = r0.tip_pose.copy()
    tgt[:3, 3] += [0.01, 0.0, 0.0]
    opts = pl.PlanOptions(tolerance=1e-5, orientation_weight=0.0)
    a = pl.TipSolver(from_robot_model(old), opts).solve(tgt, np.zeros(6), r0.q)
    assert a.reached and a.x.min() < -1e4                 # the old answer: tens of kPa of suction
    b = pl.TipSolver(from_robot_model(new), opts).solve(tgt, np.zeros(6), r0.q)
    assert np.all(b.x >= 0.0) and not b.reached and b.status == "at_limit"
    # independent check: forward statics at the answer, and scipy's bounded least squares
    p = solve_statics(new, b.x).tip_pose[:3, 3]
    assert abs(np.linalg.norm(p - tgt[:3, 3]) - b.position_error) < 1e-9

    def f(x):
        return (solve_statics(new, x * 1e4).tip_pose[:3, 3] - tgt[:3, 3]) * 1e3

    ref = least_squares(f, np.full(6, 2.0), bounds=(0.0, 10.0), diff_step=1e-4, xtol=1e-10, ftol=1e-12)
    best = np.linalg.norm(ref.fun) / 1e3
    assert best > 5e-4                                  # truly out of reach (0.73 mm short)
    assert b.position_error <= best * (1 + 1e-3)


def test_pneumatic_ik_reaches_a_target_reachable_with_positive_pressures():
    new = model_from_dict(_pneumatic_dict())
    old = model_from_dict(_with_suction(_pneumatic_dict()))
    u_true = np.array([2.0e4, 0.0, 0.0, 3.0e4, 0.0, 0.0])
    tgt = solve_statics(new, u_true).tip_pose
    r0 = _rest(new)
    opts = pl.PlanOptions(tolerance=1e-7, orientation_weight=0.0)
    a = pl.TipSolver(from_robot_model(old), opts).solve(tgt, np.zeros(6), r0.q)
    assert a.reached and a.x.min() < -100.0             # unbounded: the least-norm answer sucks
    b = pl.TipSolver(from_robot_model(new), opts).solve(tgt, np.zeros(6), r0.q)
    assert b.reached and np.all(b.x >= 0.0)
    # independent forward statics from rest (not the solver's warm start)
    p = solve_statics(new, b.x).tip_pose[:3, 3]
    assert np.linalg.norm(p - tgt[:3, 3]) < 1e-6


def test_planned_path_respects_min_and_max():
    from soft_twin_core.planning.paths import TipPath
    d = _pneumatic_dict()
    for a in d["actuators"]:
        a["max"] = 4.0e4
    m = model_from_dict(d)
    p0 = _rest(m).tip_pose[:3, 3] - m.base_pose[:3, 3]
    p0 = m.base_pose[:3, :3].T @ p0
    # base frame: down the arm is the base's +x; sideways the base's y
    path = TipPath(np.array([0.0, 0.5, 1.0, 1.5]),
                   p0 + np.array([[0, 0, 0], [0.003, 0.004, 0], [0.0, 0.008, 0], [0.0, 0.0, 0.008]]))
    plan = pl.plan_path(from_robot_model(m), path, pl.PlanOptions(tolerance=1e-6, orientation_weight=0.0))
    assert plan.lower.tolist() == [0.0] * 6 and plan.upper.tolist() == [4.0e4] * 6
    assert np.all(plan.u >= 0.0) and np.all(plan.u <= 4.0e4)
    assert pl.check_plan(plan) == []
    # sideways at the rest height needs suction (or more than max): flagged, not faked
    assert plan.reached[0] and not plan.reached[1:].any()
    assert set(plan.status[1:]) == {"at_limit"} and plan.u[1].max() == 4.0e4
    old = pl.plan_path(from_robot_model(model_from_dict(_with_suction(_pneumatic_dict()))), path,
                       pl.PlanOptions(tolerance=1e-6, orientation_weight=0.0))
    assert old.u.min() < 0.0                            # the same path asked for suction before


def test_articulated_planner_bounds_come_from_the_robot_file():
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    d = yaml.safe_load(open(PAN_TILT).read())
    for b in d["bodies"]:
        for a in b.get("actuators", []) or []:
            a["max"] = 1.0
            if a["name"] == "tendon_y_neg":
                a["min"] = 0.25
    mech = mechanism_from_dict(d)
    solver = pl.TipSolver(mech, pl.PlanOptions())
    nj = solver.n_j
    assert solver.upper[nj:].tolist() == [1.0] * 4
    assert solver.lower[nj:].tolist() == [0.0, 0.25, 0.0, 0.0]
    # a target that asks 4 N of one tendon: the answer stays within [min, max]
    u_true = np.array([4.0, 0.0, 0.0, 0.0])
    x_true = np.concatenate([np.zeros(nj), u_true])
    eq = solver.statics.solve(x_true, None)
    tgt = eq.pose[:3, 3]
    x0 = np.clip(np.zeros(nj + 4), solver.lower, solver.upper)
    x_ref = np.concatenate([x0[:nj], solver.lower[nj:]])
    x = solver.solve(tgt, x0, None, x_ref=x_ref).x
    assert np.all(x >= solver.lower) and np.all(x <= solver.upper)


# ------------------------------------------------------------------ calibration

def test_calibration_refuses_recorded_inputs_outside_the_bounds(tmp_path):
    from soft_twin_core.estimation import calibration as cal
    from soft_twin_core.estimation import sensors as sn
    d = _pneumatic_dict()
    m = model_from_dict(d)
    sensors = [sn.marker("tip", 1e-4, s=m.total_length)]
    inputs = np.array([[1e4, 0, 0, 0, 0, 0], [0, 2e4, 0, 0, 0, 0], [0, 0, -3e4, 0, 0, 0.0]])
    with pytest.raises(cal.CalibrationError) as exc:
        cal.record_static_sweep(m, sensors, inputs, np.random.default_rng(0))
    assert "row 3" in str(exc.value) and "chamber_3" in str(exc.value) and "under_limit" in str(exc.value)
    rec = cal.Recording(inputs, {"tip": np.zeros((3, 3))})
    with pytest.raises(cal.CalibrationError) as exc:
        cal.Problem(d, sensors, rec, ["youngs_modulus:lower"])
    assert "row 3" in str(exc.value) and "-30000" in str(exc.value) and "min 0 Pa" in str(exc.value)


def test_workspace_ranges_respect_min_and_max():
    from soft_twin_core.planning import reach as wm
    d = _pneumatic_dict()
    for a in d["actuators"]:
        a["max"] = 5.0e4
    m = model_from_dict(d)
    opts = wm.parse_workspace_options({"samples": 4}, "workspace")
    idx, lo, hi = wm.actuation_ranges(m, opts)          # no limit: the range comes from min/max
    assert lo.tolist() == [0.0] * 6 and hi.tolist() == [5.0e4] * 6
    opts = wm.parse_workspace_options({"samples": 4, "limits": {"chamber_1": [-1.0e4, 5.0e4]}}, "workspace")
    with pytest.raises(ValueError) as exc:
        wm.actuation_ranges(m, opts)
    assert "workspace.limits.chamber_1" in str(exc.value) and "-10000" in str(exc.value)


@pytest.mark.ros
def test_node_rejects_suction_and_its_ik_stays_positive():
    """The node with the shipped pneumatic arm: a negative pressure is
    refused and counted (under_limit); its IK service answers the issue's
    1 cm sideways move with pressures >= 0 and says it is out of reach."""
    rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from geometry_msgs.msg import Pose
    from rclpy.parameter import Parameter
    from soft_twin.msg import ActuationCommand
    from soft_twin.node import SoftTwinNode
    from soft_twin.srv import InverseKinematics
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = SoftTwinNode(context=ctx, parameter_overrides=[
            Parameter("robot_description_file", value="pneumatic_arm.yaml")])
        try:
            msg = ActuationCommand(names=["chamber_2"], values=[-29477.0])
            msg.header.stamp.sec = 1
            node._on_actuation(msg, None)
            assert node.stats.rejected_by_reason["under_limit"] == 1 and not np.any(node.twin.u)
            m = node.robot.model
            p = m.base_pose[:3, :3].T @ (_rest(m).tip_pose[:3, 3] - m.base_pose[:3, 3])
            req = InverseKinematics.Request(position_only=True, tolerance=1e-6)
            req.target = Pose()
            req.target.position.x, req.target.position.y, req.target.position.z = float(p[0]), float(p[1]) + 0.01, \
                float(p[2])
            req.target.orientation.w = 1.0
            resp = node._srv_ik(req, InverseKinematics.Response())
            assert resp.actuation_found and len(resp.actuator_values) == 6
            assert min(resp.actuator_values) >= 0.0 and max(resp.actuator_values) <= 1.0e5
            assert not resp.success and "bound" in resp.message
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
