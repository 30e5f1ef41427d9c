"""Friction in statics (issue 27): Coulomb's law smoothed over a stick
length, against the contacts' displacements from where they stick
(:func:`soft_twin_core.engine.contact.stick_friction`,
:class:`soft_twin_core.solve.contact.StickPoints`), checked against its
definition and finite differences, and against linear beam theory on a
cantilever whose tip is pressed on a plane and pushed sideways: it sticks
under mu N, slides beyond it, and when the push is taken off it rests where
friction holds it (hysteresis), in the core and in a quasi-static twin."""

import math

import numpy as np
import pytest

from soft_twin_core.engine.algorithms import forward_kinematics
from soft_twin_core.engine.contact import STICK_TIME, Obstacle, stick_friction
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import mechanism_from_dict, tip_frame
from soft_twin_core.solve import constrained as cs
from soft_twin_core.solve.contact import MemberContact
from soft_twin_core.twin import Twin, TwinSettings

L, R, E = 0.3, 0.005, 2e8          # m, m, Pa: EI = 0.098 N m^2, a tip stiffness 3 EI / L^3 = 10.9 N/m
EI = E * math.pi * R ** 4 / 4
GAP, MU, P = 0.005, 0.5, 0.2       # m below the rod, Coulomb's mu, N pressing the tip down


def _rod():
    return mechanism_from_dict({"name": "rod", "gravity": [0, 0, 0], "bodies": [{
        "name": "rod", "type": "member", "segments": [{
            "length": L, "sections": 8, "cross_section": {"shape": "solid_circle", "radius": R},
            "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000},
            "free_modes": "bending_torsion"}]}]})


def _floor(mu=MU):
    return Obstacle("floor", "plane", np.array([0, 0, -(R + GAP)]), np.array([0, 0, 1.0]), friction=mu)


def test_stick_friction_is_coulombs_law_smoothed_over_the_stick_length():
    """``F = -mu fn tanh(|d| / l_s) d / |d|``: at ``|d| = l_s atanh(t)`` its
    size is t mu fn, against d; mu fn at large d; its derivative equals
    central differences (1e-7 relative), also at d = 0 (mu fn / l_s I:
    the stick's stiffness)."""
    v_s = 1e-4
    ls = v_s * STICK_TIME
    fn = np.array([2.0, 2.0, 2.0, 2.0])
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = np.array([0.1, 0.5, 0.9, 0.999])
    d = dirs * (ls * np.arctanh(t))[:, None]
    F, dF = stick_friction(fn, d, MU, v_s)
    assert np.allclose(np.linalg.norm(F, axis=1), t * MU * fn, rtol=1e-12)
    assert np.allclose(F / np.linalg.norm(F, axis=1, keepdims=True), -dirs, atol=1e-12)
    for c in range(4):
        h = 1e-6 * ls
        fd = np.column_stack([(stick_friction(fn[:1], d[c] + h * e, MU, v_s)[0][0]
                               - stick_friction(fn[:1], d[c] - h * e, MU, v_s)[0][0]) / (2 * h) for e in np.eye(3)])
        assert np.allclose(dF[c], fd, rtol=1e-7, atol=1e-7 * MU * fn[0] / ls)
    F0, dF0 = stick_friction(fn[:1], np.zeros((1, 3)), MU, v_s)
    assert np.all(F0 == 0) and np.allclose(dF0[0], -MU * fn[0] / ls * np.eye(3), rtol=1e-12)
    big = stick_friction(fn[:1], np.array([[1.0, 0, 0]]), MU, v_s)[0]
    assert big[0, 0] == pytest.approx(-MU * fn[0], rel=1e-12)


def _tip_y(mech, ws, q):
    return forward_kinematics(mech.tree, ws, q)[1][-1][1, 3]


def test_a_rod_pressed_on_a_plane_sticks_slides_and_rests_where_friction_holds_it():
    """The cantilever's tip pressed on a plane (a contact at arc length a,
    normal force N) and pushed sideways by T, each equilibrium from the one
    before (its stick points, :meth:`MemberContact.stuck_after`):

    - T = 0.04 N < mu N: it sticks, the tip moved 0.07 mm (less than 0.2 mm,
      where without friction it would move T L^3 / 3 EI = 3.7 mm);
    - T = 0.2 N > mu N: it slides, the friction mu N (0.1 %), and the tip
      is where linear beam theory puts it under T at L and mu N back at a,
      ``(T L^3 / 3 - mu N a^2 (3 L - a) / 6) / EI`` (1 %);
    - T taken off: the rod springs back until the friction holds it,
      ``mu N a^2 (3 L - a) / (6 EI)`` from the middle (1 %), 6.6 mm, not
      at 0 as without friction;
    - T = 0.04 N again: friction turns, the point moves only to take up
      its stick (at most 6 stick lengths, 0.6 mm);
    - T = -0.2 N: it slides to the other side, the mirror image."""
    mech = _rod()
    ws = Workspace(mech.tree)
    floor = _floor()
    mc = MemberContact(mech, (floor,))
    tip = tip_frame(mech)
    stick, q, seen = mc.stick_points(ws, mech.tree.q0), None, {}
    ls = floor.stiction_velocity * STICK_TIME
    for step, T in enumerate((0.0, 0.04, 0.2, 0.0, 0.04, -0.2, 0.0)):
        eq = cs.solve_equilibrium(mech, point_loads=[cs.FrameLoad(tip, np.array([0, T, -P, 0, 0, 0]), "world")],
                                  obstacles=(floor,), stick=stick, q_init=q)
        st = eq.contacts
        assert len(st) == 1
        q, stick = eq.q, mc.stuck_after(ws, eq.q, stick, st)
        N = st.force[0, 2]
        a = mc.points.s[st.point[0]]
        friction = np.linalg.norm(st.force[0, :2])
        held = MU * N * a ** 2 * (3 * L - a) / (6 * EI)
        y = _tip_y(mech, ws, q)
        seen[step] = y
        if step == 0:
            assert y == 0.0 and friction == 0.0       # touched down in this solve: sticks from the next
        elif step == 1:
            assert 0 < y < 2e-4 and friction == pytest.approx(T, rel=0.05)
        elif step in (2, 5):
            assert friction == pytest.approx(MU * N, rel=1e-3)
            assert y == pytest.approx(np.sign(T) * (abs(T) * L ** 3 / 3 / EI - held), rel=0.01)
        elif step in (3, 6):
            assert friction == pytest.approx(MU * N, rel=1e-3)
            assert y == pytest.approx(np.sign(seen[step - 1]) * held, rel=0.01)
        else:
            assert 0 < y - seen[3] < 6 * ls and friction < MU * N


def test_a_quasi_static_twin_remembers_where_friction_holds_its_arm():
    """The twin keeps its stick points from solve to solve: pushed past mu N
    and let go, its tip rests where friction holds it (as the core above);
    on a frictionless plane it goes back to the middle; a reset forgets."""
    mech = _rod()
    rests = {}
    for mu in (MU, 0.0):
        tw = Twin(mech, TwinSettings(mode="quasi_static"), obstacles=(_floor(mu),))
        for T in (0.0, 0.2, 0.0):
            tw.set_tip_wrench(np.array([0, T, -P, 0, 0, 0]), "world")
            assert tw.step().converged
        rests[mu] = tw.outputs().tip_pose[1, 3]
        if mu:
            tw.reset()
            tw.set_tip_wrench(np.array([0, 0, -P, 0, 0, 0]), "world")
            assert tw.step().converged and abs(tw.outputs().tip_pose[1, 3]) < 1e-9
    assert 6.4e-3 < rests[MU] < 6.7e-3 and abs(rests[0.0]) < 1e-9


def test_the_statics_tangent_with_friction_is_the_residuals_derivative():
    """Newton's matrix of statics with friction (sliding and sticking
    contacts: :meth:`MemberContact.add_stiffness`' ``dFf_dd`` and
    ``dFf_dp``) against central differences of the residual, on the plane
    (whose normal does not turn: the law's derivative is exact there)."""
    mech = _rod()
    ws = Workspace(mech.tree)
    floor = _floor()
    mc = MemberContact(mech, (floor,))
    tip = tip_frame(mech)
    stick, q = mc.stick_points(ws, mech.tree.q0), None
    for T in (0.0, 0.2, 0.1):
        loads = [cs.FrameLoad(tip, np.array([0, T, -P, 0, 0, 0]), "world")]
        eq = cs.solve_equilibrium(mech, point_loads=loads, obstacles=(floor,), stick=stick, q_init=q)
        q = eq.q
        pb = cs._Equilibrium(mech, eq.inputs, None, (floor,), stick)
        K = pb.tangent(q, eq.lam)
        h = 1e-7
        fd = np.column_stack([(pb.residual(q + h * e, eq.lam)[0] - pb.residual(q - h * e, eq.lam)[0]) / (2 * h)
                              for e in np.eye(len(q))])
        assert np.abs(K - fd).max() < 1e-5 * np.abs(fd).max(), (T, np.abs(K - fd).max(), np.abs(fd).max())
        stick = mc.stuck_after(ws, q, stick, eq.contacts)


def test_a_scenarios_statics_holds_with_friction_from_increment_to_increment(tmp_path):
    """The CLI's statics (:func:`files.scenario.run_statics`) with the tip
    load applied in increments (``load_steps``): the tip touches down in
    the second of four (fraction 1/2: frictionless in that increment, it
    lands where the half load puts it without friction), then sticks there
    while the load grows to its full value (mu N holds it); in one
    increment, the same scenario is frictionless (the whole lateral load
    bends the rod), as the plane without friction is in four."""
    import yaml
    from soft_twin_core.files.scenario import load_scenario, run_statics
    T = 0.04
    robot = {"name": "rod", "gravity": [0, 0, 0], "bodies": [{
        "name": "rod", "type": "member", "segments": [{
            "length": L, "sections": 8, "cross_section": {"shape": "solid_circle", "radius": R},
            "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000},
            "free_modes": "bending_torsion"}]}]}
    (tmp_path / "rod.yaml").write_text(yaml.safe_dump(robot))
    tips = {}
    for mu, steps in ((MU, 4), (MU, 1), (0.0, 4)):
        sc = {"robot": "rod.yaml", "gravity": False, "load_steps": steps,
              "loads": [{"frame": "rod_tip", "force": [0, T, -P], "axes": "world"}],
              "obstacles": [{"name": "floor", "type": "plane", "point": [0, 0, -(R + GAP)], "normal": [0, 0, 1],
                             "friction": mu}]}
        (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
        tips[mu, steps] = run_statics(load_scenario(str(tmp_path / "sc.yaml")))["tip_position"][1]
    free = T * L ** 3 / (3 * EI)                       # 3.7 mm: the whole lateral load on the free rod
    assert tips[MU, 1] == pytest.approx(tips[0.0, 4], rel=1e-6) and tips[0.0, 4] == pytest.approx(free, rel=0.03)
    assert tips[MU, 4] == pytest.approx(free / 2, rel=0.05)        # held where it landed, at half the load
