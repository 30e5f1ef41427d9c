"""Loads on any point of a robot (issue 31: the page's push on a picked
point; a script's hung weight or force gauge): a soft member's points
``<member>@<s>`` as frames, the twin's point wrenches (against the
cantilever's closed form), and the checks at the door."""

import math

import numpy as np
import pytest

from soft_twin_core import commands as cmd
from soft_twin_core.engine.algorithms import point_poses
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.twin import Twin, TwinSettings

E, R, L = 5.0e6, 0.005, 0.2
EI = E * math.pi * R ** 4 / 4


def _cantilever(sections=16, gravity=(0.0, 0.0, 0.0)):
    """A straight soft member along x from the base, bending only, no gravity."""
    return mechanism_from_dict({
        "name": "cantilever", "gravity": list(gravity),
        "bodies": [{"name": "arm", "type": "member", "parent": "base",
                    "segments": [{"name": "s", "length": L, "sections": sections,
                                  "cross_section": {"shape": "solid_circle", "radius": R},
                                  "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000.0},
                                  "free_modes": "bending"}]}]})


def test_a_members_points_are_frames_named_by_arc_length():
    """``arm@0.05`` is the point 50 mm along the member (the straight
    member: at x = 0.05 m), ``arm@0`` its base and ``arm@0.2`` its end
    (the ``arm_tip`` frame); a point past the end, a member not there and
    an arc length that is not a number are refused, naming what is
    wrong."""
    mech = _cantilever()
    refs = [mech.frame(n) for n in ("arm@0.05", "arm@0", "arm@0.2", "arm@0.1234")]
    P = point_poses(mech.tree, Workspace(mech.tree), mech.tree.q0, [r.joint for r in refs], [r.x for r in refs])
    np.testing.assert_allclose(P[:, :3, 3], [[0.05, 0, 0], [0, 0, 0], [0.2, 0, 0], [0.1234, 0, 0]], atol=1e-12)
    tip = mech.frame("arm_tip")
    assert (refs[2].joint, refs[2].x) == (tip.joint, pytest.approx(tip.x))
    for name, words in (("arm@0.25", "[0, 0.2] m"), ("leg@0.1", "no member named 'leg'"),
                        ("arm@half", "number of metres"), ("nowhere", "'<member>@<s>'")):
        with pytest.raises(KeyError) as e:
            mech.frame(name)
        assert words in str(e.value), str(e.value)


@pytest.mark.parametrize("a", [0.1, 0.0625])
def test_a_point_force_on_a_member_bends_it_as_the_cantilevers_closed_form(a):
    """A small transverse force P at s = a (a dead load, 1e-4 of the tip
    deflection the length) on a quasi-static twin: the deflection at a is
    ``P a^3 / (3 EI)`` and at the tip ``P a^2 (3 L - a) / (6 EI)``
    (Euler-Bernoulli) within 0.5 % (32 sections; PCS's piecewise
    constant curvature is 1 % off at a = 5 sections of 16); the snapshot lists the load
    where the point is. A follower load (the point's axes) bends it the
    same at this size; zeros remove the load, a reset every point load."""
    mech = _cantilever(32)
    P = 3 * EI * 2e-5 / 0.1 ** 3
    twin = Twin(mech, TwinSettings(mode="quasi_static"))
    twin.set_point_wrench(f"arm@{a}", [0.0, 0.0, -P, 0.0, 0.0, 0.0])
    assert twin.step().converged
    snap = twin.outputs()
    poses, s = snap.backbones["arm"]
    z = np.interp(a, s, poses[:, 2, 3])
    assert -z == pytest.approx(P * a ** 3 / (3 * EI), rel=0.005)
    assert -snap.tip_pose[2, 3] == pytest.approx(P * a ** 2 * (3 * L - a) / (6 * EI), rel=0.005)
    (name, at, force), = snap.point_loads
    assert name == f"arm@{a}" and at == pytest.approx([a, 0.0, z], abs=1e-8)      # (x: a less 2e-9) and force == pytest.approx([0, 0, -P])
    tip = snap.tip_pose[2, 3]
    twin.set_point_wrench(f"arm@{a}", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    twin.set_point_wrench(f"arm@{a}", [0.0, 0.0, -P, 0.0, 0.0, 0.0], "body")
    assert twin.step().converged
    assert twin.outputs().tip_pose[2, 3] == pytest.approx(tip, rel=1e-3)
    twin.set_point_wrench(f"arm@{a}", np.zeros(6))
    assert twin.step().converged and abs(twin.outputs().tip_pose[2, 3]) < 1e-12
    assert not twin.outputs().point_loads
    twin.set_point_wrench("arm@0.1", [0.0, 0.0, -P, 0.0, 0.0, 0.0])
    twin.reset()
    assert twin.point_wrenches == {} and abs(twin.outputs().tip_pose[2, 3]) < 1e-12


def test_point_wrench_commands_are_checked_at_the_door():
    """:func:`commands.parse_point_wrench`: a frame or a member point, in
    the base axes (dead) or the point's own (follower); an unknown point
    ("bad_point"), another frame_id ("bad_frame"), a non-finite or too
    large wrench are refused with their reason."""
    mech = _cantilever()
    assert cmd.parse_point_wrench(mech, "arm@0.1", [0, 0, -1], [0, 0, 0], "base_link", "base_link")[2] == "world"
    p, w, axes = cmd.parse_point_wrench(mech, "arm_tip", [1, 0, 0], [0, 0, 0.1], "arm_tip", "base_link")
    assert (p, axes) == ("arm_tip", "body") and w.tolist() == [1, 0, 0, 0, 0, 0.1]
    for args, reason in ((("arm@0.3", [0, 0, 1], [0, 0, 0], "base_link"), "bad_point"),
                         (("arm@0.1", [0, 0, 1], [0, 0, 0], "world"), "bad_frame"),
                         (("arm@0.1", [0, float("nan"), 1], [0, 0, 0], "base_link"), "non_finite"),
                         (("arm@0.1", [0, 0, 2e3], [0, 0, 0], "base_link"), "over_limit")):
        with pytest.raises(cmd.InputError) as e:
            cmd.parse_point_wrench(mech, *args, "base_link", max_force=1e3)
        assert e.value.reason == reason and reason in cmd.REJECT_REASONS
