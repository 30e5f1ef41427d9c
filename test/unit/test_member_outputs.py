"""Member outputs sampled inside the sections (points_per_section): on a
classic rod as a mechanism they equal the rod's own numpy functions, in
statics and in motion (poses, internal wrenches with tendons, gravity, a
distributed and a tip load; point velocities and accelerations); on a tree
the cut is continuous across section boundaries, and one sample per section
gives the section boundaries."""
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
