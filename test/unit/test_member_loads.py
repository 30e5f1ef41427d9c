"""Loads at an arc length of any soft member, point and distributed (the
classic rod's loads, for every robot): a point load at a member's end is the
load on the frame there; the support balances a distributed load exactly
(global equilibrium of the deformed robot); a load names its member, or
takes the first; bad loads are refused naming the field."""
import numpy as np
import pytest

from soft_twin_core.engine.loads import DistributedLoad, Loads, PointLoad
from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.solve.constrained import FrameLoad, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs


@pytest.fixture(scope="module")
def gripper():
    return load_mechanism("soft_gripper")


def test_a_point_load_at_a_members_end_is_the_load_on_its_tip_frame(gripper):
    w = (0.0, 0.05, -0.1, 0.0, 0.001, 0.0)
    on_member = solve_equilibrium(gripper, actuation={"close_1": 1.0},
                                  loads=Loads(point=(PointLoad(0.08, w, "world", "finger_1"),)))
    on_frame = solve_equilibrium(gripper, actuation={"close_1": 1.0},
                                 point_loads=[FrameLoad("finger_1_tip", np.array(w), "world")])
    assert np.abs(on_member.q - on_frame.q).max() < 1e-10
    untouched = solve_equilibrium(gripper, actuation={"close_1": 1.0})
    js = gripper.tree.paths[1].joints
    moved = [np.abs(on_member.q - untouched.q)[gripper.tree.idx_q[j]] for j in js]
    assert max(moved) > 1e-3                                   # the load bent finger_1 ...
    other = gripper.tree.paths[0].joints                       # ... and not finger_0
    assert max(abs(on_member.q[gripper.tree.idx_q[j]] - untouched.q[gripper.tree.idx_q[j]]) for j in other) < 1e-9


def test_the_support_balances_a_distributed_load_on_the_deformed_rod():
    """Gravity off: the support's reaction is minus the resultant of a
    uniform world force w over [a, b] (its moment about the base: the
    integral of p(s) x w over the deformed span, by a 4001-point rule on the
    backbone's exact kinematics)."""
    from soft_twin_core.reference import kinematics as kin
    from soft_twin_core.robot.model import load_model
    model = load_model("tendon_arm")
    mech = load_mechanism("tendon_arm")
    a, b, w = 0.05, 0.15, np.array([0.0, 2.0, -1.0])
    loads = Loads(distributed=(DistributedLoad(tuple(w) + (0.0, 0.0, 0.0), "world", a, b),), gravity=False)
    eq = solve_equilibrium(mech, actuation={"tendon_z_pos": 1.5}, loads=loads)
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    root = out.joint_wrenches[mech.tree.joints[0].name]
    assert np.allclose(root[:3], -w * (b - a), atol=1e-12)
    s = np.linspace(a, b, 4001)
    P = kin.poses(model, eq.q, s)[:, :3, 3]                  # the rod's numpy kinematics
    p_int = np.trapezoid(P, s, axis=0)
    assert np.allclose(root[3:], -np.cross(p_int, w), atol=1e-7)
    assert np.abs(root[3:]).max() > 1e-3                       # a moment worth checking


def test_a_load_without_member_is_on_the_first(gripper):
    w = (0.0, 0.0, -0.1, 0.0, 0.0, 0.0)
    named = make_inputs(gripper, loads=Loads(point=(PointLoad(0.04, w, "world", "finger_0"),)))
    first = make_inputs(gripper, loads=Loads(point=(PointLoad(0.04, w),)))
    assert named.loads.joint.tolist() == first.loads.joint.tolist()
    assert np.allclose(named.loads.x, first.loads.x)


@pytest.mark.parametrize("load, field", [
    (PointLoad(0.04, (0, 0, -1, 0, 0, 0), "world", "thumb"), "loads.point[0].member: 'thumb'"),
    (PointLoad(0.09, (0, 0, -1, 0, 0, 0), "world", "finger_2"), "loads.point[0].s: must lie in [0, 0.08]"),
    (PointLoad(0.04, (0, 0, np.nan, 0, 0, 0)), "loads.point[0].wrench"),
    (PointLoad(0.04, (0, 0, -1, 0, 0, 0), "tool"), "loads.point[0].frame"),
    (DistributedLoad((0, 0, -1, 0, 0, 0), "world", 0.05, 0.02, "finger_1"), "loads.distributed[0]: need 0 <= start"),
])
def test_bad_member_loads_are_refused_naming_the_field(gripper, load, field):
    kind = "point" if isinstance(load, PointLoad) else "distributed"
    with pytest.raises(ValueError, match=None) as e:
        make_inputs(gripper, loads=Loads(**{kind: (load,)}))
    assert field in str(e.value)
