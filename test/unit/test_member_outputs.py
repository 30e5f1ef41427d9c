"""Member outputs sampled inside the sections (points_per_section): on a
classic rod as a mechanism they equal the rod's own numpy functions, in
statics and in motion (poses, internal wrenches with tendons, gravity, a
distributed and a tip load; point velocities and accelerations); on a tree
the cut is continuous across section boundaries, and one sample per section
gives the section boundaries."""
import math

import numpy as np
import pytest

from soft_twin_core.engine.loads import DistributedLoad, Loads, PointLoad
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.robot.model import load_model
from soft_twin_core.solve.constrained import make_inputs
from soft_twin_core.solve.outputs import cut_wrenches, run_passes, state_outputs

U = np.array([1.5, 0.0, 0.7, 0.0])         # N, tendons of the tendon arm
LOADS = Loads(point=(PointLoad(0.4, (0.05, -0.1, 0.2, 0.0, 0.01, 0.0), "world"),),
              distributed=(DistributedLoad((0.0, 0.3, -0.2, 0.0, 0.0, 0.0), "world", 0.13, 0.31),))


@pytest.fixture(scope="module")
def rod():
    return load_model("tendon_arm"), load_mechanism("tendon_arm")


def _state(model, seed):
    rng = np.random.default_rng(seed)
    q = model.q0 + 0.5 * rng.standard_normal(model.n_dof)
    return q, rng.standard_normal(model.n_dof), rng.standard_normal(model.n_dof)


def test_rod_samples_in_statics_equal_the_rods_own_functions(rod):
    from soft_twin_core.reference.statics import internal_wrenches
    model, mech = rod
    q, _, _ = _state(model, 1)
    inp = make_inputs(mech, U, loads=LOADS)
    (m,) = state_outputs(mech, q, np.zeros(0), inp, points_per_section=5).members
    s, P = kin.backbone(model, q, 5)
    assert np.allclose(m.s, s, atol=1e-15)
    assert np.abs(m.poses - P).max() < 1e-12
    W = internal_wrenches(model, q, s, U, LOADS)
    assert np.abs(m.internal_wrench - W).max() <= 1e-9 * np.abs(W).max()
    assert np.abs(W[1:-1:5]).max() > 0 and not np.allclose(W[1], W[2])     # interior values vary


def test_rod_samples_in_motion_equal_the_rods_own_functions(rod):
    from soft_twin_core.reference.dynamics import internal_wrenches_dynamic
    model, mech = rod
    q, v, a = _state(model, 2)
    inp = make_inputs(mech, U, loads=LOADS)
    (m,) = state_outputs(mech, q, np.zeros(0), inp, v, a, points_per_section=4).members
    s = kin.backbone_abscissae(model, 4)
    mot = kin.point_motion(model, q, v, a, s)
    assert np.abs(m.velocities - mot["v_world"]).max() <= 1e-10 * np.abs(mot["v_world"]).max()
    assert np.abs(m.accelerations - mot["a_world"]).max() <= 1e-10 * np.abs(mot["a_world"]).max()
    W = internal_wrenches_dynamic(model, q, v, a, s, U, LOADS)
    assert np.abs(m.internal_wrench - W).max() <= 1e-9 * np.abs(W).max()


def test_one_sample_per_section_gives_the_boundaries_and_the_cut_is_continuous():
    from soft_twin_core.solve.constrained import solve_equilibrium
    mech = load_mechanism("soft_gripper")
    eq = solve_equilibrium(mech, actuation={"close_0": 2.0}, positions={"wrist": 0.3},
                           loads=Loads(distributed=(DistributedLoad((0.4, 0.0, 0.0, 0, 0, 0), "world", 0.01, 0.05,
                                                                    "finger_0"),)))
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    fine = state_outputs(mech, eq.q, eq.lam, eq.inputs, points_per_section=3)
    for m1, m3 in zip(out.members, fine.members):
        assert len(m1.s) == len(m3.s[::3]) and np.allclose(m1.internal_wrench, m3.internal_wrench[::3], atol=1e-12)
        assert np.allclose(m1.poses, m3.poses[::3], atol=1e-15)
    # the cut at a section's end is the cut at the next section's start (no offset between them)
    from soft_twin_core.solve.constrained import concat_loads, constraint_loads
    ws = Workspace(mech.tree)
    loads = concat_loads(eq.inputs.loads, constraint_loads(mech, eq.lam))
    run_passes(mech, ws, eq.q, None, None, loads, eq.inputs.gravity)
    js = mech.tree.paths[0].joints
    L = mech.tree.paths[0].lengths
    for a, b, La in zip(js[:-1], js[1:], L[:-1]):
        end = cut_wrenches(ws, loads, a, [La], [ws.work.g_out[a]])
        start = cut_wrenches(ws, loads, b, [0.0], [ws.work.g_in[b]])
        assert np.abs(end - start).max() <= 1e-12 * max(np.abs(start).max(), 1e-300)


def test_the_largest_stress_counts_both_cross_sections_at_a_section_start():
    """max_von_mises against the beam formula sigma = M r / I: a rod of a
    thin proximal segment (r = 5 mm) and a thick distal one (r = 10 mm),
    bending moments given at its samples, the largest at the segments'
    joint: there the thin cross-section's stress counts, though the sample
    belongs to the thick section; without that cut the largest is elsewhere."""
    import math
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import model_from_dict
    from soft_twin_core.solve.outputs import max_von_mises
    seg = lambda r: {"length": 0.1, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": r},  # noqa
                     "material": {"youngs_modulus": 1e6, "density": 1000}, "free_modes": "bending_torsion"}
    d = {"gravity": [0, 0, 0], "segments": [seg(0.005), seg(0.010)]}
    mech = from_robot_model(model_from_dict(d), d)
    s = np.array([0.0, 0.05, 0.1, 0.15, 0.2])
    M = np.array([0.001, 0.002, 0.01, 0.002, 0.0])        # N m about y, largest at the joint s = 0.1
    W = np.zeros((5, 6))
    W[:, 4] = M
    smax, s_at = max_von_mises(mech, {"backbone": {"s": s, "internal_wrench": W}})
    I_thin = math.pi * 0.005 ** 4 / 4
    assert s_at == pytest.approx(0.1) and smax == pytest.approx(0.01 * 0.005 / I_thin, rel=1e-9)


def test_the_internal_force_steps_inside_a_section_are_the_weight_lumped_at_its_quadrature_points():
    """Issue 31: why the internal force of a member under gravity is a
    staircase inside each section. The engine integrates a section's mass
    by 2-point Gauss-Legendre quadrature, so its weight acts at the
    quadrature points (weights w_k = h/2, abscissae x_k = h (1 -+ 1/sqrt(3))/2
    in a section of length h). On a straight
    horizontal cantilever (stiff: 4e-7 of its length of sag) the shear force
    at a cut s is the weight of the quadrature points beyond it,
    ``rho A g sum_{x_k > s} w_k``: constant between points, a step of
    ``rho A g w_k`` at each. At the section boundaries it equals the
    continuum's ``rho A g (L - s)`` (the quadrature is exact for the
    constant line density), and so does the bending moment (quadratic in
    s: within the 2-point rule's exactness, degree 3); in between the force differs from the line by
    less than the largest step, which halves with the sections."""
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import model_from_dict
    from soft_twin_core.solve.constrained import solve_equilibrium
    L, r, rho, g = 0.2, 0.01, 1000.0, 9.81
    lam = rho * math.pi * r ** 2 * g                     # N/m: the line weight
    worst = []
    for n in (4, 8):
        d = {"gravity": [0, 0, -g], "segments": [{
            "length": L, "sections": n, "cross_section": {"shape": "solid_circle", "radius": r},
            "material": {"youngs_modulus": 1e12, "density": rho}}]}
        mech = from_robot_model(model_from_dict(d), d)
        eq = solve_equilibrium(mech)
        (m,) = state_outputs(mech, eq.q, eq.lam, eq.inputs, points_per_section=24).members
        assert np.abs(m.poses[:, 2, 3]).max() < 1e-6 * L                         # straight
        h = L / n
        xg, wg = np.polynomial.legendre.leggauss(2)
        xk = (np.arange(n)[:, None] * h + 0.5 * h * (xg + 1.0)).ravel()     # the quadrature points [m]
        wk = np.tile(0.5 * h * wg, n)
        lumped = np.array([lam * wk[xk > s].sum() for s in m.s])
        shear = -m.internal_wrench[:, 2]                 # the distal part's weight pulls the cut down
        assert np.abs(shear - lumped).max() <= 1e-6 * lam * L
        moment = np.array([lam * (wk * (xk - s))[xk > s].sum() for s in m.s])
        assert np.abs(np.abs(m.internal_wrench[:, 4]) - moment).max() <= 1e-6 * lam * L ** 2
        at = np.isclose(m.s / h, np.round(m.s / h), atol=1e-9)          # the section boundaries
        assert at.sum() == n + 1
        assert np.abs(shear[at] - lam * (L - m.s[at])).max() <= 1e-6 * lam * L
        assert np.abs(np.abs(m.internal_wrench[at, 4]) - lam * (L - m.s[at]) ** 2 / 2).max() <= 1e-6 * lam * L ** 2
        dev = np.abs(shear - lam * (L - m.s)).max()
        assert 0.1 * lam * wk.max() < dev <= lam * wk.max()
        worst.append(dev)
    assert worst[1] == pytest.approx(worst[0] / 2, rel=0.15)


def test_a_tendons_compression_and_moment_are_even_along_its_span_and_step_at_its_anchor():
    """Issue 31: the staircase inside sections is gravity's (its weight
    lumped at the quadrature points, the test above), not the tendons'. A
    straight tendon at offset d in the cross-section, tension T, anchored at
    s_a, loads the backbone (the tendon apart) as the continuum says on
    the whole bent arm: the distal part, pulled at the anchor by -T along
    the tendon, exerts on the proximal part the body-frame wrench [-T, 0,
    0] and moment d x [-T, 0, 0] at every cut before the anchor, and
    nothing beyond it: even to round-off inside and across every section,
    one step at the anchor (the tendon_arm: y tendon to the tip, z tendon
    to 0.30 m; zero gravity)."""
    from soft_twin_core.solve.constrained import solve_equilibrium
    mech = load_mechanism("tendon_arm")
    Ty, Tz, d = 5.0, 3.0, 0.007
    u = np.array([Ty if a.name == "tendon_y_pos" else Tz if a.name == "tendon_z_pos" else 0.0
                  for a in mech.actuators])
    eq = solve_equilibrium(mech, inputs=make_inputs(mech, u, None, None, None, Loads(gravity=False), []))
    (m,) = state_outputs(mech, eq.q, eq.lam, eq.inputs, points_per_section=8).members
    bend = m.poses[-1][:3, 0]
    assert abs(bend[1]) > 0.1 and abs(bend[2]) > 0.1, bend     # bent away from straight, both ways
    s, W = m.s, m.internal_wrench
    before, after = s < 0.30 - 1e-9, s > 0.30 + 1e-9
    y = np.cross([0, d, 0], [-Ty, 0, 0])
    z = np.cross([0, 0, d], [-Tz, 0, 0])
    expected = np.where(before[:, None], np.r_[-Ty - Tz, 0, 0, y + z], np.r_[-Ty, 0, 0, y])
    keep = before | after
    assert after[:-1].sum() > 8 and before.sum() > 16
    np.testing.assert_allclose(W[keep][:-1], expected[keep][:-1], atol=1e-9 * Ty)
