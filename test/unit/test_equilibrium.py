"""One equilibrium solver for every robot without constraint rows
(soft_twin_core.solve.equilibrium): a classic rod and a tree of soft members with
effort-controlled joints take the same compiled Newton, stability check,
continuation and tangent hint. Checked against the rod front end, the KKT
path of closed chains, a closed form (a torsion spring against an effort)
and the pendulum's stiffness k - m g l_c (an arm held upright by a spring)."""

import math

import numpy as np
import pytest
import yaml

from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import find_file, load_model
from soft_twin_core.solve import equilibrium as eq
from soft_twin_core.solve.constrained import _Equilibrium, _kkt_newton, make_inputs, solve_equilibrium
from rod_statics import solve_statics


def _pan_tilt():
    """The pan-tilt arm's file with both joints effort-controlled, with
    torsion springs of 2 N m/rad."""
    with open(find_file("pan_tilt_arm", "robots")) as f:
        d = yaml.safe_load(f)
    for b in d["bodies"][:2]:
        b["joint"].update(control="effort", stiffness=2.0)
    return d


def test_a_rod_as_a_mechanism_is_solved_as_the_rod():
    """The tendon arm loaded as a one-member mechanism: the same equilibrium
    as the rod front end, judged stable, its tangent a working hint."""
    rod = load_model("tendon_arm")
    mech = load_mechanism(find_file("tendon_arm", "robots"))
    u = {"tendon_y_pos": 2.0, "tendon_z_neg": 1.0}
    a = solve_statics(rod, u)
    b = solve_equilibrium(mech, u)
    assert b.lam.size == 0 and b.stable and b.min_stiffness_eigenvalue > 0
    assert np.abs(a.q - b.q).max() <= 1e-9 * np.abs(a.q).max()
    # the smallest eigenvalue is that of an independent finite-difference tangent of the residual
    pb = _Equilibrium(mech, b.inputs)
    h = 1e-7
    K_fd = np.column_stack([(pb.residual(b.q + h * e, np.zeros(0))[0] - pb.residual(b.q - h * e, np.zeros(0))[0])
                            / (2 * h) for e in np.eye(mech.tree.nv)])
    lo = np.linalg.eigvals(K_fd).real.min()
    assert abs(b.min_stiffness_eigenvalue - lo) <= 1e-5 * abs(lo)
    # a warm solve with the tangent as a hint: fewer tangents, the same answer
    u2 = {"tendon_y_pos": 2.05, "tendon_z_neg": 1.0}
    counts = []
    real = eq.Problem.tangent

    def counting(self, q):
        counts.append(1)
        return real(self, q)
    eq.Problem.tangent = counting
    try:
        cold = solve_equilibrium(mech, u2, q_init=b.q, check_stability=False)
        n_cold = len(counts)
        counts.clear()
        warm = solve_equilibrium(mech, u2, q_init=b.q, check_stability=False, tangent_hint=b.tangent)
    finally:
        eq.Problem.tangent = real
    assert np.abs(warm.q - cold.q).max() <= 1e-9 * np.abs(cold.q).max()
    assert warm.iterations >= 1 and (n_cold == 0 or len(counts) <= n_cold)


def test_an_effort_against_a_torsion_spring_turns_the_joint_by_effort_over_stiffness():
    """Gravity off, no tendon: an effort tau on the pan joint (spring k)
    turns everything distal rigidly by tau / k; the arm stays straight."""
    d = _pan_tilt()
    d["gravity"] = [0.0, 0.0, 0.0]
    mech = mechanism_from_dict(d)
    tree = mech.tree
    r = solve_equilibrium(mech, efforts={"pan": 0.3, "tilt": -0.1})
    qi = {j.name: tree.idx_q[i] for i, j in enumerate(tree.joints)}
    assert r.q[qi["pan"]] == pytest.approx(0.3 / 2.0, rel=1e-10)
    assert r.q[qi["tilt"]] == pytest.approx(-0.1 / 2.0, rel=1e-10)
    soft = np.ones(tree.nq, bool)
    soft[[qi["pan"], qi["tilt"]]] = False
    assert np.abs(r.q[soft] - tree.q0[soft]).max() < 1e-12
    assert r.joint_efforts["pan"] == pytest.approx(0.3)


def test_the_compiled_path_and_the_kkt_path_agree_under_gravity_and_efforts():
    """With gravity, tendons and efforts: the compiled solver and the KKT
    Newton of closed chains (run with no rows) give the same equilibrium."""
    mech = mechanism_from_dict(_pan_tilt())
    u, eff = {"tendon_y_pos": 1.5}, {"pan": 0.05, "tilt": 0.2}
    r = solve_equilibrium(mech, u, efforts=eff)
    pb = _Equilibrium(mech, make_inputs(mech, u, eff))
    q, lam, it, ok, R, phi, sc = _kkt_newton(pb, mech.tree.q0.copy(), np.zeros(0), 1e-12, 50)
    assert ok and r.stable
    assert np.abs(q - r.q).max() <= 1e-8 * np.abs(r.q).max()


def _upright(k_tilt):
    """The pan-tilt arm turned upright (tilt reference -pi/2: the arm along
    +z) with a stiff arm, held by a tilt spring k_tilt [N m/rad]; and m l_c,
    the mass moment about the tilt axis [kg m] from the file's numbers."""
    d = _pan_tilt()
    d["bodies"][1]["joint"].update(stiffness=k_tilt, reference=-math.pi / 2, limits=[-3.0, 3.0])
    arm = d["bodies"][2]
    for seg in arm["segments"]:
        seg["material"]["youngs_modulus"] = 2.0e9
    arm["actuators"] = []
    link = d["bodies"][1]
    ml = link["mass"] * link["com"][0]
    x0 = arm["joint"]["position"][0]
    s = 0.0
    for seg in arm["segments"]:
        m = seg["material"]["density"] * math.pi * seg["cross_section"]["radius"] ** 2 * seg["length"]
        ml += m * (x0 + s + seg["length"] / 2)
        s += seg["length"]
    return mechanism_from_dict(d), ml


@pytest.mark.parametrize("ratio", [2.0, 0.5])
def test_an_arm_held_upright_is_stable_while_the_spring_beats_its_weight(ratio):
    """An inverted pendulum: the upright equilibrium is stable iff
    k > m g l_c; the smallest stiffness eigenvalue is k - m g l_c (the arm
    is 1000 times stiffer than the spring: its own modes barely couple)."""
    _, ml = _upright(1.0)
    g = 9.81
    k = ratio * g * ml
    mech, _ = _upright(k)
    r = solve_equilibrium(mech)
    assert r.stable == (ratio > 1)
    assert r.min_stiffness_eigenvalue == pytest.approx(k - g * ml, rel=2e-3)
    tilt = mech.tree.idx_q[[j.name for j in mech.tree.joints].index("tilt")]
    assert r.q[tilt] == pytest.approx(-math.pi / 2, abs=1e-9)          # the upright equilibrium, flagged if unstable


def test_the_rod_and_the_mechanism_share_one_solver():
    """No second Newton loop: both front ends build equilibrium.Problem."""
    made = []
    real = eq.Problem.__init__

    def init(self, *a, **kw):
        made.append(1)
        real(self, *a, **kw)
    eq.Problem.__init__ = init
    try:
        solve_statics(load_model("tendon_arm"), {"tendon_y_pos": 1.0})
        n_rod = len(made)
        solve_equilibrium(load_mechanism(find_file("tendon_arm", "robots")), {"tendon_y_pos": 1.0})
    finally:
        eq.Problem.__init__ = real
    assert n_rod >= 1 and len(made) > n_rod


def test_a_mechanism_without_multipliers_steps_on_the_rod_integrator():
    """Dynamics: a mechanism without multipliers (the tendon arm) steps on
    the engine's compiled O(n) theta integrator; the pan-tilt arm with
    effort joints steps too, and its energy balance holds (a spring-held
    arm released from rest under gravity, theta = 1/2, no damping: kinetic
    + potential constant)."""
    from soft_twin_core.solve.constrained import MechanismSimulator
    mech = load_mechanism(find_file("tendon_arm", "robots"))
    b = MechanismSimulator(mech, 2e-3, 0.5, tol=1e-8, max_iterations=10)
    b.step({"tendon_y_pos": 2.0}, n=150)
    assert b.lam.size == 0 and b._theta_integrator is not None
    assert b.t == pytest.approx(0.3) and b.factorisations < 150
    d = _pan_tilt()
    for body in d["bodies"][:2]:
        body["joint"]["damping"] = 0.0
    for seg in d["bodies"][2]["segments"]:
        seg["material"]["viscosity"] = 0.0
    arm = mechanism_from_dict(d)
    sim = MechanismSimulator(arm, 1e-3, 0.5, tol=1e-12, max_iterations=40)
    sim.step(efforts={"pan": 0.02}, n=5)                      # a kick (the effort does work), then free
    e0 = sum(sim.energy())
    sim.step(n=300)
    T, V = sim.energy()
    assert T > 1e-4 * abs(e0)                                    # it moves
    assert abs(T + V - e0) <= 1e-5 * max(abs(e0), T)             # midpoint rule (implicit Euler: 6e-3)
