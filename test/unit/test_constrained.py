"""Soft articulated robots: constraints, joint control, outputs (issue
"Soft articulated robots end to end").

References, each independent of the code under test:
* a planar Reissner-rod boundary-value problem solved by collocation
  (``continuum.solve_planar_rods``, scipy's solve_bvp) for the clamped-clamped
  beam and the parallel continuum robot;
* the four-bar's closed-form position analysis and its reduced one-dof
  Lagrange equation integrated by solve_ivp;
* Pinocchio's RNEA for the rigid arm with the soft member frozen;
* statics of a free body (reactions balance the loads) and beam theory
  (M c / I + N / A) for stresses;
* central differences for the Newton matrix.
"""

import copy

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.integrators import integrate_pass
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.reference.continuum import PlanarRod, solve_planar_rods
from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import ModelError, find_file
from soft_twin_core.solve.constrained import (FrameLoad, MechanismSimulator, _Equilibrium, make_inputs,
                                              solve_equilibrium)
from soft_twin_core.solve.outputs import state_outputs
from rod_statics import solve_statics

E, NU, RADIUS = 2.0e9, 0.3, 0.01
G_MOD = E / (2 * (1 + NU))
AREA, INERTIA = np.pi * RADIUS**2, np.pi * RADIUS**4 / 4


def _member(name, length, n, parent="base", joint=None, modes="all", shape=None):
    cs = shape or {"shape": "solid_circle", "radius": RADIUS}
    d = {"name": name, "type": "member", "parent": parent,
         "segments": [{"name": name, "length": length, "sections": n, "cross_section": cs,
                       "material": {"youngs_modulus": E, "poisson_ratio": NU, "density": 1000.0},
                       "free_modes": modes}]}
    if joint is not None:
        d["joint"] = joint
    return d


def _balance(points_wrenches):
    """Sum of world wrenches [f; m_about_point] at points, as force and moment about the origin."""
    f = np.zeros(3)
    m = np.zeros(3)
    for p, w in points_wrenches:
        f += w[:3]
        m += w[3:] + np.cross(p, w[:3])
    return f, m


# ----------------------------------------------------------------------------
# Fixed-fixed beam
# ----------------------------------------------------------------------------

def _fixed_fixed(n, L=1.0):
    return mechanism_from_dict({
        "name": "ff", "gravity": [0, 0, 0], "bodies": [_member("beam", L, n)],
        "frames": [{"name": "mid", "body": "beam", "s": L / 2}],
        "constraints": [{"name": "right", "type": "clamped", "frame": "beam_tip", "to": "world"}]})


@pytest.fixture(scope="module")
def ff_reference():
    L, F = 1.0, 100.0
    rods = [PlanarRod(E * AREA, G_MOD * AREA, E * INERTIA, L / 2, ("world", (0, 0, 0)), ("junction", 0, (0, 0, 0))),
            PlanarRod(E * AREA, G_MOD * AREA, E * INERTIA, L / 2, ("junction", 0, (0, 0, 0)), ("world", (L, 0, 0)))]
    return solve_planar_rods(rods, [(0.0, -F, 0.0)], [(L / 2, 0.0, 0.0)]), F


def test_fixed_fixed_beam_matches_continuum_at_second_order(ff_reference):
    ref, F = ff_reference
    z_ref = ref.junctions[0, 1]
    assert -0.02 < z_ref < -0.017          # mildly nonlinear: the membrane tension carries part of the load
    errs, reactions, zs = [], [], []
    for n in (8, 16, 32):
        mech = _fixed_fixed(n)
        eq = solve_equilibrium(mech, point_loads=[FrameLoad("mid", [0, 0, -F, 0, 0, 0])])
        out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
        p = out.frames["mid"][:3, 3]
        errs.append(abs(p[2] - z_ref))
        zs.append(p[2])
        assert abs(p[0] - 0.5) < 1e-9 and abs(p[1]) < 1e-12       # symmetric, planar
        reactions.append(eq.constraint_wrenches["right"])
        # the two end reactions balance the load (1e-9 of the load)
        base = out.joint_wrenches["beam_0"]
        f, m = _balance([(np.zeros(3), base), (out.frames["beam_tip"][:3, 3], eq.constraint_wrenches["right"]),
                         (p, np.array([0, 0, -F, 0, 0, 0]))])
        assert np.abs(f).max() < 1e-9 * F and np.abs(m).max() < 1e-9 * F
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(rates - 2.0) < 0.1), (errs, rates)
    assert errs[-1] < 3e-3 * abs(z_ref)
    # Richardson extrapolation of the last two: the continuum's limit, far closer than either
    z_lim = zs[-1] + (zs[-1] - zs[-2]) / 3
    assert abs(z_lim - z_ref) < 0.02 * errs[-1]
    # the right clamp's reaction: the continuum's end force (n_x, n_z) and moment
    n_end = ref.state(1, 0.5)[3:, 0]
    r = reactions[-1]
    assert abs(r[0] - n_end[0]) < 0.01 * n_end[0] and abs(r[2] - n_end[1]) < 1e-6 * F
    assert abs(r[4] - n_end[2]) < 0.01 * abs(n_end[2])


def test_fixed_fixed_example_file_sags_under_gravity():
    mech = load_mechanism(find_file("fixed_fixed_beam", "robots"))
    eq = solve_equilibrium(mech)
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    weight = 1000.0 * AREA * 1.0 * 9.81
    assert out.frames["mid"][2, 3] < 0
    # each clamp carries half the weight (symmetry), pulling up
    assert abs(eq.constraint_wrenches["right_clamp"][2] - weight / 2) < 1e-9 * weight
    assert abs(out.joint_wrenches["beam_0"][2] - weight / 2) < 1e-9 * weight


# ----------------------------------------------------------------------------
# Stresses
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("shape", ["solid_circle", "rectangle"])
def test_cantilever_root_stress_is_Mc_over_I_plus_N_over_A(shape):
    cs = ({"shape": "solid_circle", "radius": RADIUS} if shape == "solid_circle" else
          {"shape": "rectangle", "width": 0.02, "height": 0.012})
    mech = mechanism_from_dict({"name": "c", "gravity": [0, 0, 0],
                                "bodies": [_member("rod", 0.5, 6, shape=cs)]})
    F = np.array([-30.0, 8.0, -20.0])
    eq = solve_equilibrium(mech, point_loads=[FrameLoad("rod_tip", list(F) + [0, 0, 0])])
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    tip = out.frames["rod_tip"][:3, 3]
    assert np.linalg.norm(tip - [0.5, 0, 0]) > 1e-3          # visibly bent
    # root cut: the distal part pulls with F and the moment of F about the root (root axes = world)
    N = F[0]
    M = np.cross(tip, F)
    w = out.members[0].internal_wrench[0]
    assert np.abs(w - np.r_[F, M]).max() < 1e-9 * np.abs(np.r_[F, M]).max()
    if shape == "solid_circle":
        expect = abs(N) / AREA + np.hypot(M[1], M[2]) * RADIUS / INERTIA
    else:
        b, h = 0.02, 0.012
        I2, I3 = b * h**3 / 12, h * b**3 / 12
        expect = abs(N) / (b * h) + abs(M[1]) * (h / 2) / I2 + abs(M[2]) * (b / 2) / I3
    assert abs(out.members[0].normal_stress[0] - expect) < 1e-9 * expect
    # the tip cut carries exactly the load; its stress is the axial part only
    assert np.abs(out.members[0].internal_wrench[-1][3:]).max() < 1e-9


# ----------------------------------------------------------------------------
# The Newton matrix
# ----------------------------------------------------------------------------

def test_equilibrium_tangent_matches_central_differences():
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    inp = make_inputs(mech, actuation={"tendon_z_pos": 3.0, "tendon_y_neg": 1.0}, positions={"pan": 0.3},
                      point_loads=[FrameLoad("tool", [0.1, 0.2, -0.3, 0.01, 0.0, 0.02]),
                                   FrameLoad("tilt_link", [0.0, 0.5, 0.1, 0.0, 0.0, 0.0], "body")])
    pb = _Equilibrium(mech, inp)
    rng = np.random.default_rng(0)
    q = mech.tree.q0 + 0.2 * rng.standard_normal(mech.tree.nv)
    lam = rng.standard_normal(2)
    Kt = pb.tangent(q, lam)
    h = 1e-6
    fd = np.array([(pb.residual(q + h * e, lam)[0] - pb.residual(q - h * e, lam)[0]) / (2 * h)
                   for e in np.eye(len(q))]).T
    assert np.abs(Kt - fd).max() < 1e-7 * np.abs(Kt).max()
    _, _, G = pb.residual(q, lam)
    fdG = np.array([(pb.residual(q + h * e, lam)[1] - pb.residual(q - h * e, lam)[1]) / (2 * h)
                    for e in np.eye(len(q))]).T
    assert np.abs(G - fdG).max() < 1e-8


# ----------------------------------------------------------------------------
# Rigid four-bar: closed form and reduced equation of motion
# ----------------------------------------------------------------------------

A4, B4, C4, D4 = 0.10, 0.30, 0.25, 0.30      # crank, coupler, rocker, ground [m]
MASSES = (0.2, 0.5, 0.4)


def _atan2c(y, x):
    """atan2 that accepts complex arguments (complex-step derivatives)."""
    return 2 * np.arctan(y / (np.sqrt(x * x + y * y) + x))


def four_bar_angles(t2):
    """Closed-form position analysis: absolute coupler and rocker angles for
    the crank angle t2 (rotations about +y: a link at angle t points along
    (cos t, -sin t) in (x, z)); open branch."""
    ax, aw = A4 * np.cos(t2), A4 * np.sin(t2)
    dx, dw = D4 - ax, -aw
    L2 = dx * dx + dw * dw
    t3 = _atan2c(dw, dx) + np.arccos((B4 * B4 + L2 - C4 * C4) / (2 * B4 * np.sqrt(L2)))
    bx, bw = ax + B4 * np.cos(t3), aw + B4 * np.sin(t3)
    return t3, _atan2c(bw, bx - D4)


def _rod(m, length):
    return {"mass": m, "com": [length / 2, 0, 0], "inertia": [1e-6, m * length**2 / 12, m * length**2 / 12, 0, 0, 0]}


def four_bar(t2):
    t3, t4 = four_bar_angles(t2)
    return mechanism_from_dict({
        "name": "four_bar", "gravity": [0, 0, -9.81],
        "bodies": [
            {"name": "crank", "type": "link", **_rod(MASSES[0], A4),
             "joint": {"name": "crank", "type": "revolute", "axis": [0, 1, 0], "reference": float(t2),
                       "control": "passive"}},
            {"name": "coupler", "type": "link", "parent": "crank", **_rod(MASSES[1], B4),
             "joint": {"name": "knee", "type": "revolute", "axis": [0, 1, 0], "position": [A4, 0, 0],
                       "reference": float(t3 - t2), "control": "passive"}},
            {"name": "rocker", "type": "link", **_rod(MASSES[2], C4),
             "joint": {"name": "rocker", "type": "revolute", "axis": [0, 1, 0], "position": [D4, 0, 0],
                       "reference": float(t4), "control": "passive"}}],
        "frames": [{"name": "coupler_end", "body": "coupler", "position": [B4, 0, 0]},
                   {"name": "rocker_end", "body": "rocker", "position": [C4, 0, 0]}],
        "constraints": [{"name": "loop", "type": "pinned", "frame": "coupler_end", "to": "rocker_end"}]})


def reduced_four_bar(t20, t_end):
    """The crank angle over time from the one-dof Lagrange equation
    m(t2) t2'' + m'(t2) t2'^2 / 2 + V'(t2) = 0, with m and V from the closed
    form (complex-step derivatives)."""
    Is = [m * l * l / 12 for m, l in zip(MASSES, (A4, B4, C4))]

    def coms(t2):
        t3, t4 = four_bar_angles(t2)
        return ([(A4 / 2 * np.cos(t2), A4 / 2 * np.sin(t2)),
                 (A4 * np.cos(t2) + B4 / 2 * np.cos(t3), A4 * np.sin(t2) + B4 / 2 * np.sin(t3)),
                 (D4 + C4 / 2 * np.cos(t4), C4 / 2 * np.sin(t4))], (t2, t3, t4))

    def derivs(t2, h=1e-20):
        c, ang = coms(t2 + 1j * h)
        return [(x.imag / h, w.imag / h) for x, w in c], [a.imag / h for a in ang]

    def meff(t2):
        dc, da = derivs(t2)
        return sum(m * (x * x + w * w) + i * o * o for m, (x, w), i, o in zip(MASSES, dc, Is, da))

    def rhs(t, y):
        t2, om = y
        dc, _ = derivs(t2)
        dV = sum(-m * 9.81 * w for m, (x, w) in zip(MASSES, dc))     # z = -w
        e = 1e-6
        dm = (meff(t2 + e) - meff(t2 - e)) / (2 * e)
        return [om, -(0.5 * dm * om * om + dV) / meff(t2)]

    return solve_ivp(rhs, (0, t_end), [t20, 0.0], rtol=1e-12, atol=1e-12, dense_output=True)


def test_four_bar_follows_its_closed_form_and_reduced_dynamics():
    t20 = 1.0
    mech = four_bar(t20)
    ref = reduced_four_bar(t20, 1.0)
    errs = []
    for dt in (2e-3, 1e-3):
        sim = MechanismSimulator(mech, dt)
        n = round(1.0 / dt)
        worst_closure = 0.0
        for k in range(n):
            sim.step()
            t3, t4 = four_bar_angles(sim.q[0])
            worst_closure = max(worst_closure, abs(sim.q[0] + sim.q[1] - t3), abs(sim.q[2] - t4))
        assert worst_closure < 1e-9          # the closed form's coupler and rocker angles
        errs.append(abs(sim.q[0] - ref.sol(sim.t)[0]))
    assert errs[1] < 1e-4
    assert 3.0 < errs[0] / errs[1] < 5.0     # second order (implicit midpoint)


def test_four_bar_drift_stays_below_1e8_m_over_10_s():
    mech = four_bar(0.3)
    sim = MechanismSimulator(mech, 5e-3)
    e0 = sum(sim.energy())
    worst = 0.0
    for _ in range(200):
        sim.step(n=10)
        worst = max(worst, sim.constraint_error())
    assert sim.t == pytest.approx(10.0)
    assert worst < 1e-8
    # no damping: the energy stays within a small band (midpoint rule)
    assert abs(sum(sim.energy()) - e0) < 1e-3 * MASSES[1] * 9.81 * 0.1


# ----------------------------------------------------------------------------
# Motion-controlled rigid arm carrying a soft arm
# ----------------------------------------------------------------------------

def test_position_controlled_efforts_equal_inverse_dynamics():
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    tree = mech.tree
    sim = MechanismSimulator(mech, 2e-3)
    ws = Workspace(tree)
    iv = [tree.idx_v[tree.joint_index(n)] for n in ("pan", "tilt")]
    worst = 0.0
    for k in range(150):
        t1 = (k + 1) * sim.dt
        q0, v0 = sim.q.copy(), sim.v.copy()
        sim.step(actuation={"tendon_z_pos": 2.0}, positions={"pan": 0.8 * np.sin(3 * t1), "tilt": -0.3 * t1})
        th, h = sim.theta, sim.dt
        vt = v0 + th * h * sim.a                                 # the step's intermediate state
        qt = np.empty(tree.nq)
        integrate_pass(tree.kernel_arrays, q0, vt, th * h, qt)
        tau = alg.rnea(tree, ws, qt, vt, sim.a)                  # gravity, damping: the same terms
        eff = sim.joint_efforts()
        for name, i in zip(("pan", "tilt"), iv):
            worst = max(worst, abs(eff[name] - tau[i]) / max(1.0, abs(tau[i])))
        assert abs(sim.q[tree.idx_q[tree.joint_index("pan")]] - 0.8 * np.sin(3 * t1)) < 1e-12
    assert worst < 1e-9


@pytest.mark.parametrize("name", ["pan_tilt_arm", "soft_gripper"])
def test_position_controlled_joints_eliminated_step_as_the_kkt_step_holds_them(name):
    """A robot whose only multipliers are position-controlled (revolute or
    prismatic) joints steps through the compiled step with those joints
    eliminated (their velocity prescribed, their effort their residual
    row); the Python KKT step holds them by multipliers. From the same
    states they agree: configuration to 1e-8, efforts to 1e-6."""
    mech = load_mechanism(find_file(name, "robots"))
    sims = [MechanismSimulator(mech, 5e-3, 0.5, tol=1e-12) for _ in range(2)]
    assert sims[0]._use_compiled_step and not sims[0].contact
    sims[1]._use_compiled_step = False
    pos = [mech.tree.joints[i].name for i in mech.joints_with("position")]
    for k in range(100):
        inp = make_inputs(mech, {a.name: 1.0 for a in mech.actuators[:1]},
                          positions={p: 0.3 * np.sin(2 * np.pi * k * 5e-3) for p in pos})
        for sim in sims:
            sim.step(inputs=inp)
        a, b = sims
        assert np.abs(a.q - b.q).max() <= 1e-8 * max(np.abs(b.q).max(), 1.0), k
        np.testing.assert_allclose(a.lam, b.lam, rtol=1e-6, atol=1e-9)
        assert a.contacts is None
        b.q, b.v, b.a, b.lam = a.q.copy(), a.v.copy(), a.a.copy(), a.lam.copy()


def test_frozen_soft_arm_efforts_match_pinocchio():
    pin = pytest.importorskip("pinocchio")
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    tree = mech.tree
    rng = np.random.default_rng(3)
    q = tree.q0.copy()
    v = np.zeros(tree.nv)
    a = np.zeros(tree.nv)
    ip, it = tree.idx_v[tree.joint_index("pan")], tree.idx_v[tree.joint_index("tilt")]
    q[[ip, it]] = rng.uniform(-1, 1, 2)
    v[[ip, it]] = rng.uniform(-2, 2, 2)
    a[[ip, it]] = rng.uniform(-5, 5, 2)
    tau = alg.rnea(tree, Workspace(tree), q, v, a)        # soft modes at rest: the member is rigid here
    # Pinocchio: pan (RZ), tilt (RY at z 0.08) carrying the tilt link and the straight arm as rigid bodies
    model = pin.Model()
    model.gravity.linear = np.array([0, 0, -9.81])
    j1 = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "pan")
    model.appendBodyToJoint(j1, pin.Inertia(0.40, np.array([0, 0, 0.03]), np.diag([4e-4, 4e-4, 3e-4])),
                            pin.SE3.Identity())
    j2 = model.addJoint(j1, pin.JointModelRY(), pin.SE3(np.eye(3), np.array([0, 0, 0.08])), "tilt")
    model.appendBodyToJoint(j2, pin.Inertia(0.15, np.array([0.025, 0, 0]), np.diag([5e-5, 8e-5, 8e-5])),
                            pin.SE3.Identity())
    x0 = 0.05
    for r, length in ((0.012, 0.15), (0.009, 0.15)):
        A, I = np.pi * r**2, np.pi * r**4 / 4
        m = 1100.0 * A * length
        Ic = np.diag([1100.0 * 2 * I * length, 1100.0 * I * length + m * length**2 / 12,
                      1100.0 * I * length + m * length**2 / 12])
        model.appendBodyToJoint(j2, pin.Inertia(m, np.array([x0 + length / 2, 0, 0]), Ic), pin.SE3.Identity())
        x0 += length
    data = model.createData()
    ref = pin.rnea(model, data, q[[ip, it]], v[[ip, it]], a[[ip, it]])
    damping = 0.05 * v[[ip, it]]
    assert np.abs(tau[[ip, it]] - (ref + damping)).max() < 1e-9 * max(1.0, np.abs(ref).max())


# ----------------------------------------------------------------------------
# Planar parallel continuum robot
# ----------------------------------------------------------------------------

def _parallel(n, L=0.4, half=0.05):
    pitch = -np.pi / 2           # rods along world +z
    return mechanism_from_dict({
        "name": "parallel", "gravity": [0, 0, 0],
        "bodies": [
            _member("rod1", L, n, joint={"type": "fixed", "position": [-half, 0, 0], "rpy": [0, pitch, 0]}),
            {"name": "platform", "type": "link", "parent": "rod1", "mass": 0.0,
             "joint": {"type": "fixed", "position": [0, 0, -half], "rpy": [0, -pitch, 0]}},
            _member("rod2", L, n, joint={"type": "fixed", "position": [half, 0, 0], "rpy": [0, pitch, 0]})],
        "frames": [{"name": "rod2_mount", "body": "platform", "position": [half, 0, 0], "rpy": [0, pitch, 0]}],
        "constraints": [{"name": "rod2_to_platform", "type": "clamped", "frame": "rod2_tip",
                         "to": "rod2_mount"}]})


def test_parallel_continuum_robot_matches_continuum_and_balances():
    L, half = 0.4, 0.05
    load = np.array([40.0, 0.0, -20.0, 0.0, 3.0, 0.0])     # world [f; m] on the platform centre
    rods = [PlanarRod(E * AREA, G_MOD * AREA, E * INERTIA, L, ("world", (-half, 0, -np.pi / 2)),
                      ("junction", 0, (-half, 0, -np.pi / 2))),
            PlanarRod(E * AREA, G_MOD * AREA, E * INERTIA, L, ("world", (half, 0, -np.pi / 2)),
                      ("junction", 0, (half, 0, -np.pi / 2)))]
    ref = solve_planar_rods(rods, [(load[0], load[2], load[4])], [(0.0, L, 0.0)])
    x_ref, z_ref, th_ref = ref.junctions[0]
    assert abs(x_ref) > 5e-3 and abs(th_ref) > 1e-3      # the platform visibly moves and turns
    errs = []
    for n in (4, 8, 16):
        mech = _parallel(n)
        eq = solve_equilibrium(mech, point_loads=[FrameLoad("platform", load)])
        out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
        g = out.frames["platform"]
        th = np.arctan2(g[0, 2], g[0, 0])        # rotation about +y
        errs.append(max(abs(g[0, 3] - x_ref), abs(g[2, 3] - z_ref), abs(th - th_ref) * L))
        # the rods' base reactions balance the platform load
        f, m = _balance([(np.array([-half, 0, 0]), out.joint_wrenches["rod1_0"]),
                         (np.array([half, 0, 0]), out.joint_wrenches["rod2_0"]), (g[:3, 3], load)])
        assert np.abs(f).max() < 1e-9 * 20 and np.abs(m).max() < 1e-9 * 20
    assert errs[-1] < 1e-3 * L
    assert errs[0] / errs[1] > 3.0 and errs[1] / errs[2] > 3.0      # second-order convergence


# ----------------------------------------------------------------------------
# Robot files: errors name the field
# ----------------------------------------------------------------------------

BAD = [
    (lambda d: d["bodies"][1].update(parent="nowhere"), "bodies[1] (tilt_link).parent"),
    (lambda d: d["bodies"][0]["joint"].update(type="hinge"), "bodies[0] (pan_link).joint.type"),
    (lambda d: d["bodies"][0]["joint"].update(limits=[1.0, -1.0]), "bodies[0] (pan_link).joint.limits"),
    (lambda d: d["bodies"][0].update(inertia=[1, 1, 5, 0, 0, 0]), "bodies[0] (pan_link).inertia"),
    (lambda d: d["bodies"][2]["segments"][0].update(length=-0.1), "bodies[2] (arm).segments[0].length"),
    (lambda d: d["bodies"][0].update(segments=[]), "bodies[0] (pan_link).segments"),
    (lambda d: d.update(constraints=[{"type": "clamped", "frame": "nope"}]), "constraints[0].frame"),
    (lambda d: d.update(constraints=[{"type": "weld", "frame": "tool"}]), "constraints[0].type"),
    (lambda d: d["frames"][0].update(body="ghost"), "frames[0].body"),
    (lambda d: d["bodies"][0]["joint"].update(control="torque"), "bodies[0] (pan_link).joint.control"),
]


@pytest.mark.parametrize("corrupt,field", BAD, ids=[f for _, f in BAD])
def test_tree_file_errors_name_the_field(corrupt, field):
    import yaml
    with open(find_file("pan_tilt_arm", "robots")) as fh:
        d = yaml.safe_load(fh)
    d = copy.deepcopy(d)
    corrupt(d)
    with pytest.raises(ModelError) as e:
        mechanism_from_dict(d)
    assert field in str(e.value)


def test_joint_commands_are_checked():
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    with pytest.raises(ValueError, match="unknown joint 'elbow'"):
        make_inputs(mech, positions={"elbow": 0.1})
    with pytest.raises(ValueError, match="outside the joint limits"):
        make_inputs(mech, positions={"tilt": 2.0})
    with pytest.raises(ValueError, match="not finite"):
        make_inputs(mech, positions={"pan": float("nan")})
    with pytest.raises(ValueError, match="not effort-controlled"):
        make_inputs(mech, efforts={"pan": 1.0})


# ----------------------------------------------------------------------------
# Moving bases; example robots
# ----------------------------------------------------------------------------

def _arm_on(motion):
    return mechanism_from_dict({"name": "b", "gravity": [0, 0, -9.81], "base": {"motion": motion},
                                "bodies": [_member("arm", 0.3, 3, modes="bending_torsion")]})


def test_floating_base_falls_freely_without_deforming():
    mech = _arm_on("floating")
    sim = MechanismSimulator(mech, 5e-3)
    sim.step(n=100)
    t = sim.t
    p = state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a).frames["base"][:3, 3]
    # uniform gravity: every point falls alike (the midpoint rule is exact for constant acceleration)
    assert abs(p[2] + 0.5 * 9.81 * t * t) < 1e-9 and abs(p[0]) < 1e-12
    soft = [mech.tree.idx_q[i] for i in mech.tree.soft_joints]
    assert np.abs(sim.q[soft[0]:] - mech.tree.q0[soft[0]:]).max() < 1e-9
    with pytest.raises(ValueError, match="the base is floating"):
        solve_equilibrium(mech)


def test_a_free_flying_soft_arm_keeps_its_energy_elastic_part_included():
    """A soft arm on a floating base, bent and let go in zero gravity
    without damping: the simulator's elastic energy is the reference
    potential (:func:`reference.multibody.potential_energy`, the soft
    joints' strains beside the free joint's quaternion: it was left at 0
    when nq != nv), and kinetic plus elastic energy holds to the midpoint
    rule's order (the free arm's bending modes are fast: the error falls
    more than 4x as dt halves from 0.2 ms, to under 1 % at 0.1 ms), while
    the elastic part trades more than half of itself for motion."""
    from soft_twin_core.reference.multibody import potential_energy
    mech = mechanism_from_dict({"name": "b", "gravity": [0, 0, 0], "base": {"motion": "floating"},
                                "bodies": [_member("arm", 0.3, 3, modes="bending_torsion")]})
    q = mech.tree.q0.copy()
    soft = [mech.tree.idx_q[i] for i in mech.tree.soft_joints]
    q[soft[0]:] += 2.0 * (np.arange(len(q) - soft[0]) % 3 == 1)        # bent: 2 rad/m about y
    errors = []
    for dt in (2e-4, 1e-4):
        sim = MechanismSimulator(mech, dt, 0.5, q=q, tol=1e-12, max_iterations=40)
        T0, V0 = sim.energy()
        assert T0 == 0.0 and V0 == pytest.approx(potential_energy(mech.tree, q), rel=1e-12)
        worst, least = 0.0, V0
        for _ in range(10):
            sim.step(n=int(round(0.005 / dt)))
            T, V = sim.energy()
            assert V == pytest.approx(potential_energy(mech.tree, sim.q), rel=1e-12)
            worst, least = max(worst, abs(T + V - V0) / V0), min(least, V)
        assert least < 0.5 * V0
        errors.append(worst)
    assert errors[1] < 0.01 and errors[0] > 4 * errors[1], errors


def test_prescribed_base_follows_its_trajectory_and_reports_its_reaction():
    mech = _arm_on("prescribed")
    assert [c.name for c in mech.constraints] == ["base"]
    sim = MechanismSimulator(mech, 2e-3)
    for k in range(1, 201):
        t = k * sim.dt
        target = np.eye(4)
        target[0, 3] = 0.05 * np.sin(2 * np.pi * t)
        sim.step(targets=[target])
        assert sim.constraint_error([target]) < 1e-10
    # held still at a static equilibrium, the base constraint's wrench is the fixed base's reaction
    fixed = _arm_on("fixed")
    eq = solve_equilibrium(fixed)
    reaction = state_outputs(fixed, eq.q, eq.lam, eq.inputs).joint_wrenches["arm_0"]
    held = MechanismSimulator(mech, 2e-3, q=np.r_[0, 0, 0, 0, 0, 0, 1, eq.q])
    held.step(n=5)
    assert np.abs(held.v).max() < 1e-9
    w = held.constraint_wrenches()["base"]
    assert np.abs(w - reaction).max() < 1e-9 * np.abs(reaction).max()
    assert reaction[2] == pytest.approx(1000.0 * AREA * 0.3 * 9.81, rel=1e-12)


def test_gripper_closes_symmetrically_and_turns_with_its_wrist():
    mech = load_mechanism(find_file("soft_gripper", "robots"))
    eq = solve_equilibrium(mech, actuation={f"close_{k}": 2.0 for k in range(3)}, positions={"wrist": 0.5})
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    tips = np.array([out.frames[f"finger_{k}_tip"][:3, 3] for k in range(3)])
    r = np.hypot(tips[:, 0], tips[:, 1])
    assert np.ptp(r) < 1e-9 and r[0] < 0.03 - 5e-3          # all three close by the same amount
    ang = np.arctan2(tips[:, 1], tips[:, 0])
    assert abs(np.angle(np.exp(1j * (ang[0] - 0.5)))) < 1e-6    # finger 0 turned with the wrist
    assert np.ptp(tips[:, 2]) < 1e-9
    # the fingers' tendons are internal: the wrist's torque is zero (no gravity moment about z)
    assert abs(eq.joint_efforts["wrist"]) < 1e-9


def test_parallel_robot_example_balances_its_loads():
    mech = load_mechanism(find_file("planar_parallel_robot", "robots"))
    load = np.array([2.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    eq = solve_equilibrium(mech, point_loads=[FrameLoad("platform", load)])
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    weight = sum(out.members[k].s[-1] for k in range(2)) * 6450.0 * np.pi * 0.002**2 + 0.05
    f, m = _balance([(np.array([-0.05, 0, 0]), out.joint_wrenches["rod1_0"]),
                     (np.array([0.05, 0, 0]), out.joint_wrenches["rod2_0"]),
                     (out.frames["platform"][:3, 3], load)])
    # the weight of rods and platform is the rest
    assert abs(f[0]) < 1e-9 and abs(f[2] - weight * 9.81) < 1e-6
    assert out.frames["platform"][0, 3] > 5e-3


def test_member_point_velocities_and_accelerations_match_the_jacobians():
    mech = load_mechanism(find_file("pan_tilt_arm", "robots"))
    tree = mech.tree
    sim = MechanismSimulator(mech, 2e-3)
    for k in range(40):
        sim.step(actuation={"tendon_y_pos": 1.5}, positions={"pan": 0.01 * k, "tilt": -0.005 * k})
    out = state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a)
    mo = out.members[0]
    ws = Workspace(tree)
    js = list(tree.paths[0].joints)
    for k, (j, x) in enumerate([(j, 0.0) for j in js] + [(js[-1], tree.joints[js[-1]].section.length)]):
        g, J = alg.point_jacobian(tree, ws, sim.q, j, x, frame="world")
        Jd = alg.point_jacobian_dot(tree, ws, sim.q, sim.v, j, x, frame="world")
        assert np.abs(g - mo.poses[k]).max() < 1e-12
        np.testing.assert_allclose(mo.velocities[k], (J @ sim.v)[:3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(mo.accelerations[k], (J @ sim.a + Jd @ sim.v)[:3], rtol=0, atol=1e-10)
    assert np.abs(mo.velocities).max() > 1e-3
    still = state_outputs(mech, sim.q, sim.lam, sim.inputs)
    assert not np.any(still.members[0].velocities) and not np.any(still.members[0].accelerations)


@pytest.mark.parametrize("name", ["soft_gripper", "pan_tilt_arm", "fixed_fixed_beam", "planar_parallel_robot"])
def test_examples_step_from_rest_in_few_iterations(name):
    """At a static equilibrium (forces all zero for the hanging gripper) a
    step converges at once: the criteria have an absolute floor."""
    mech = load_mechanism(find_file(name, "robots"))
    eq = solve_equilibrium(mech)
    sim = MechanismSimulator(mech, 5e-3, q=eq.q)
    sim.step(n=3)
    assert sim.iterations <= 3
    assert np.abs(sim.v).max() < 1e-6


def test_point_moment_tendons_on_the_mechanism_path():
    """A classic rod with a point-moment tendon (and a distributed one), run
    as a one-member mechanism: the follower moment is an input of every
    mechanism path (the statics, the dynamics' accelerations, the node's
    twin), equal to the rod's own statics and equations of motion (found
    missing: the mechanism's inputs dropped point-moment tendons)."""
    from soft_twin_core.engine import loads as ld
    from soft_twin_core.reference import dynamics as dy
    from soft_twin_core.reference import kinematics as kin
    from soft_twin_core.reference import loads as rl
    from soft_twin_core.reference import statics as st
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
    from soft_twin_core.solve import constrained as cs
    from soft_twin_core.twin import Twin, TwinSettings
    d = benchmark_cantilever_dict(4, "all")
    d["actuators"] = [{"name": "p", "offset": [0.005, 0.003], "model": "point_moment", "end": 0.35},
                      {"name": "a", "offset": [-0.004, 0.002]}]
    m = model_from_dict(d)
    mech = from_robot_model(m)
    u = np.array([6.0, 2.0])
    ref = solve_statics(m, u).q
    assert np.abs(ref - solve_statics(m, [0.0, 2.0]).q).max() > 0.1          # the point moment matters
    assert np.allclose(cs.solve_equilibrium(mech, u).q, ref, atol=1e-10)
    rng = np.random.default_rng(4)
    q, v = m.q0 + 0.2 * rng.standard_normal(m.n_dof), rng.standard_normal(m.n_dof)
    a_ref = dy.forward_dynamics(m, q, v, u)                  # the numpy chain's equations of motion
    sim = cs.MechanismSimulator(mech, 1e-3, 0.5, q=q)
    sim.v = v
    a = sim.start_multipliers(cs.make_inputs(mech, u)).a
    assert np.allclose(a, a_ref, rtol=1e-9, atol=1e-9 * np.abs(a_ref).max())
    # independent of the engine: the numpy chain's residual (follower moment and tendon by quadrature)
    R = st.residual(m, ref, u, ld.Loads())
    assert np.abs(R).max() < 1e-8 * np.abs(m.K_q @ (ref - m.q0)).max()
    twin = Twin(mech, TwinSettings(mode="quasi_static"))
    twin.set_actuation(u)
    twin.step()
    assert np.allclose(twin.state.q, ref, atol=1e-8)
    # the support's reaction: the tendons are internal (their motors on the support), so it balances the
    # weight alone, force and moment about the origin by quadrature (found wrong: the mechanism's outputs
    # took the follower moment for an external load, 0.03 N m off here)
    sq, wq, sec = rl.gauss_points(m)
    weight = np.array([m.sections[i].M[0, 0] for i in sec])[:, None] * wq[:, None] * m.gravity
    p = kin.poses(m, ref, sq)[:, :3, 3]
    eq = cs.solve_equilibrium(mech, u)
    for got in (twin.outputs().base_wrench, state_outputs(mech, eq.q, eq.lam, eq.inputs).base_wrench):
        np.testing.assert_allclose(got[:3], -weight.sum(axis=0), atol=1e-10)
        np.testing.assert_allclose(got[3:], -np.cross(p, weight).sum(axis=0), atol=1e-10)


def test_a_step_without_inputs_takes_the_defaults_each_time():
    """step() with no inputs reuses its default inputs (checked once), and a
    step with actuation in between does not leak into the next plain step():
    the states equal those of steps given make_inputs(mech) each time."""
    mech = load_mechanism(find_file("tendon_arm", "robots"))
    a, b = MechanismSimulator(mech, 2e-3, 0.5), MechanismSimulator(mech, 2e-3, 0.5)
    pull = {mech.actuators[0].name: 2.0}
    a.step(n=3)
    first = a.inputs
    a.step(actuation=pull, n=3)
    a.step(n=3)
    assert a.inputs is first and not np.any(a.inputs.u)
    b.step(inputs=make_inputs(mech), n=3)
    b.step(inputs=make_inputs(mech, pull), n=3)
    b.step(inputs=make_inputs(mech), n=3)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v)
