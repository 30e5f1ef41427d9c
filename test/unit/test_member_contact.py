"""Members touching one another (issue 27, member-member contact): the
capsules along a member (``contact.between`` in a robot file,
robot.obstacles.member_capsules), carried by its sections' frames, which
the other members' contact points touch through the engine's contact law,
as they touch a link's collision shape.

Reference: two parallel cantilevers, one pushed by a tip force towards
the other across a gap; linear beam theory (tip compliance ``c = L^3 /
(3 EI)``) gives the contact force ``P = (F - g / c) / 2`` at the tips
(both tips then deflect by ``(F - P) c`` and ``P c``, the gap closed)."""

import numpy as np
import pytest

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.contact import obstacle_arrays, posable, pose_obstacles
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import ModelError
from soft_twin_core.solve.constrained import FrameLoad, MechanismSimulator, solve_equilibrium
from soft_twin_core.solve.contact import MemberContact

L, R, E, D = 0.2, 0.002, 1e7, 0.006      # length, radius, modulus, centre distance: a 2 mm gap [m, Pa]


def _member(name, y, n, viscosity=0.0):
    return {"name": name, "type": "member", "joint": {"name": name + "_root", "type": "fixed", "position": [0, y, 0]},
            "segments": [{"length": L, "sections": n, "cross_section": {"shape": "solid_circle", "radius": R},
                          "material": {"youngs_modulus": E, "density": 1000.0, "viscosity": viscosity},
                          "free_modes": "bending"}]}


def pair(n, spacing, viscosity=0.0, **between):
    return mechanism_from_dict({"name": "pair", "gravity": [0, 0, 0],
                                "bodies": [_member("a", 0.0, n, viscosity), _member("b", D, n, viscosity)],
                                "contact": {"spacing": spacing, "between": {"members": ["a", "b"], **between}}})


def _beam_theory():
    c = L ** 3 / (3 * E * np.pi * R ** 4 / 4)
    g = D - 2 * R
    F = 4 * g / c                     # free, a's tip would move 4 gaps
    return c, F, (F - g / c) / 2


def _tips(mech, q):
    """(a's, b's) tip deflections [m] along y."""
    refs = [mech.frame(f) for f in ("a_tip", "b_tip")]
    g = alg.point_poses(mech.tree, Workspace(mech.tree), q, [r.joint for r in refs], [r.x for r in refs])
    return g[0][1, 3], g[1][1, 3] - D


def test_the_capsules_and_who_touches_them():
    """Two half-capsules per section of the second member, carried by its
    sections' frames, touched by the first member's points only (each pair
    of members once): the capsules lie on the straight member's axis."""
    mech = pair(4, 0.01)
    caps = mech.shapes
    assert len(caps) == 8 and all(c.kind == "capsule" and c.touches == ("a",) and c.radius == R for c in caps)
    mc = MemberContact(mech)
    a = np.array([m == "a" for m in mc.points.member])
    assert mc.allowed[a].all() and not mc.allowed[~a].any()
    # posed at the reference configuration: end to end along b's axis, y = D
    ws = Workspace(mech.tree)
    passes.forward_pass(ws.m, ws.w, mech.tree.q0, ws.zeros_v, ws.zeros_v, 0)
    posed = posable(obstacle_arrays(caps))
    pose_obstacles(ws.w, obstacle_arrays(caps), posed)
    ends = np.sort(np.concatenate([posed.a[:, 0], posed.b[:, 0]]))
    h = L / 4
    expected = np.sort(np.concatenate([[k * h, (k + 0.5) * h, (k + 0.5) * h, (k + 1) * h] for k in range(4)]))
    assert np.allclose(posed.a[:, 1:], [D, 0]) and np.allclose(posed.b[:, 1:], [D, 0])
    assert np.allclose(ends, expected, atol=1e-12)


@pytest.mark.parametrize("n,spacing,tol", [(8, 0.005, 0.02), (32, 0.001, 0.005)])
def test_a_cantilever_pushed_onto_another_shares_the_load_as_beam_theory_says(n, spacing, tol):
    """Statics (the active set found by the solver): the pushed tip stops
    at (F - P) c, the other tip moves P c (the contact force P), the error
    shrinking with the contact resolution (2 % at 5 mm spacing, 0.5 % at
    1 mm), the deflections small (2.5 % of the length: linear theory)."""
    c, F, P = _beam_theory()
    mech = pair(n, spacing)
    eq = solve_equilibrium(mech, point_loads=[FrameLoad("a_tip", [0, F, 0, 0, 0, 0], "world")])
    ya, yb = _tips(mech, eq.q)
    assert ya == pytest.approx((F - P) * c, rel=tol) and yb == pytest.approx(P * c, rel=tol)
    assert eq.contacts is not None and len(eq.contacts)
    total = sum(f[1] for f in eq.contacts.force)               # on a's points, from b's capsules: -y
    assert -total == pytest.approx(P, rel=2 * tol)


def test_without_the_declaration_they_pass_through_each_other():
    c, F, P = _beam_theory()
    mech = mechanism_from_dict({"name": "pair", "gravity": [0, 0, 0],
                                "bodies": [_member("a", 0.0, 8), _member("b", D, 8)]})
    eq = solve_equilibrium(mech, point_loads=[FrameLoad("a_tip", [0, F, 0, 0, 0, 0], "world")])
    ya, yb = _tips(mech, eq.q)
    assert ya == pytest.approx(F * c, rel=0.01) and abs(yb) < 1e-12


def test_in_dynamics_the_pushed_pair_moves_together():
    """The compiled step with the members' capsules: pushed by the force, a
    touches b and both swing on together, their tips the gap apart (pressed
    in by less than the law's smoothing depth, a tenth of the radius: 55 um
    here), never through each other."""
    c, F, P = _beam_theory()
    mech = pair(8, 0.005, viscosity=2e3)
    sim = MechanismSimulator(mech, 2e-3)
    assert sim._use_compiled_step and sim.contact
    gaps = []
    for _ in range(40):
        sim.step(point_loads=[FrameLoad("a_tip", [0, F, 0, 0, 0, 0], "world")], n=10)
        ya, yb = _tips(mech, sim.q)
        gaps.append(D - 2 * R - (ya - yb))
    gaps = np.array(gaps)
    assert gaps.min() > -0.1 * R              # never through: pressed in less than the law's smoothing depth
    touching = gaps < 0.01 * (D - 2 * R)
    assert touching[-10:].all()


@pytest.mark.parametrize("between,field", [
    ({"members": ["a"]}, "members"), ({"members": ["a", "c"]}, "members"), ({"members": ["a", "a"]}, "members"),
    ({"members": ["a", "b"], "friction": -1}, "friction"), ({"members": ["a", "b"], "colour": 1}, "colour"),
    ({"members": ["a"], "self": "yes"}, "self"), ({"members": ["a"], "self": True, "exclusion": -1}, "exclusion")])
def test_bad_between_settings_are_refused_naming_the_field(between, field):
    with pytest.raises(ModelError, match=f"robot.contact.between.*{field}"):
        mechanism_from_dict({"name": "pair", "bodies": [_member("a", 0.0, 2), _member("b", D, 2)],
                             "contact": {"between": between}})


def test_a_classic_rod_has_no_member_to_touch():
    """The classic schema's one member ("backbone"): ``between`` refused, naming the field."""
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file
    d = read_yaml_file(find_file("tendon_arm", "robots"), what="robot file")
    d["contact"] = {"between": {"members": ["backbone", "other"]}}
    with pytest.raises(ModelError, match="robot.contact.between.members"):
        from_robot_model(model_from_dict(d), d)


def test_a_classic_rod_touches_itself_through_the_same_capsules():
    """The classic schema's one member, "backbone", with ``self: true``:
    the same capsules as a tree's member (two per section, on its own
    points), its points near a capsule (within the arc window) left out,
    those far along it in."""
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file
    d = read_yaml_file(find_file("tendon_arm", "robots"), what="robot file")
    d["contact"] = {"between": {"members": ["backbone"], "self": True}}
    mech = from_robot_model(model_from_dict(d), d)
    n = len(mech.members[0].joints)
    assert len(mech.shapes) == 2 * n and all(c.touches == ("backbone",) for c in mech.shapes)
    mc = MemberContact(mech)
    first = mech.shapes[0]                   # the base half of the first section
    lo, hi = first.skips[1:]
    near = (mc.points.s >= lo) & (mc.points.s <= hi)
    assert near.any() and not mc.allowed[near, 0].any() and mc.allowed[~near, 0].all()


def _coil(self_contact):
    """A 0.3 m arm (radius 3 mm) clamped at the origin; with ``self``, it
    touches itself beyond the default exclusion (four radii of arc)."""
    d = {"name": "coil", "gravity": [0, 0, 0], "bodies": [{"name": "arm", "type": "member", "segments": [{
        "length": 0.3, "sections": 24, "cross_section": {"shape": "solid_circle", "radius": 0.003},
        "material": {"youngs_modulus": 1e6, "density": 1000.0}, "free_modes": "bending"}]}],
        "contact": {"spacing": 0.003}}
    if self_contact:
        d["contact"]["between"] = {"members": ["arm"], "self": True}
    return mechanism_from_dict(d)


def _nearest_far_apart(mech, q, arc=0.025):
    """The least distance [m] from a contact point to the backbone more than
    ``arc`` [m] away along it (four radii and a capsule's length)."""
    from soft_twin_core.solve.contact import mechanism_contact_points
    path = mech.tree.paths[0]
    s = np.linspace(0, path.length, 301)
    sp = mechanism_contact_points(mech).s
    ws = Workspace(mech.tree)
    P = alg.point_poses(mech.tree, ws, q, *path.locate(s))[:, :3, 3]
    Q = alg.point_poses(mech.tree, ws, q, *path.locate(sp))[:, :3, 3]
    D = np.linalg.norm(Q[:, None] - P[None], axis=2)
    return D[np.abs(sp[:, None] - s[None]) > arc].min()


def test_an_arm_coiled_by_a_tip_moment_rests_on_itself():
    """A tip moment 1.15 times the one that bends the arm into one full
    circle (M = 2 pi EI / L): without self-contact the tip passes through
    the arm's base (0.4 mm apart); with it, its contact points keep the
    diameter (6 mm, to the penalty's 25 um) from every part of the arm
    farther than four radii and a capsule along it, the contacts found by
    the solver."""
    EI = 1e6 * np.pi * 0.003 ** 4 / 4
    load = [FrameLoad("arm_tip", [0, 0, 0, 0, 0, 1.15 * 2 * np.pi * EI / 0.3], "world")]
    free = _coil(False)
    assert _nearest_far_apart(free, solve_equilibrium(free, point_loads=load).q) < 0.001
    mech = _coil(True)
    assert len(mech.shapes) == 48 and all(c.touches == ("arm",) and c.skips[0] == "arm" for c in mech.shapes)
    eq = solve_equilibrium(mech, point_loads=load)
    assert eq.contacts is not None and len(eq.contacts)
    assert _nearest_far_apart(mech, eq.q) > 0.006 - 1e-4
    # a capsule's own neighbours (within four radii of arc) never touch it: straight, nothing touches
    assert solve_equilibrium(mech).contacts is None or not len(solve_equilibrium(mech).contacts)
