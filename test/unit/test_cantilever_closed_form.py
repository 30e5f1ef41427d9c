"""The seeds' part C closed form (soft_twin_core.solve.cantilever:
Grazioso, Di Gironimo and Siciliano, RoboSoft 2018): F(a) against its
definition expm(a ad(f0)^T) (the slide's lower-left block lacks a minus
sign), the strain field against the linearised equilibrium it solves,
the Magnus backbone against the exponential and its order, the exact
statics for pure moments (PCS engine and the continuum BVP), and the
error for a tip force growing as the cube of the load."""

import numpy as np
import pytest
from scipy.linalg import expm

from soft_twin_core.errors import ModelError
from soft_twin_core.lie import ad, exp_se3
from soft_twin_core.reference.continuum import solve_cosserat_statics
from soft_twin_core.robot.mechanism import from_robot_model, tip_frame
from soft_twin_core.robot.model import model_from_dict
from soft_twin_core.solve.cantilever import (backbone_poses, closed_form_strain, member_closed_form,
                                              wrench_transport)
from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs

RNG = np.random.default_rng(3)
L = 0.3


def _arm(sections=10, radius=0.01, f0=None):
    seg = {"name": "s", "length": L, "sections": sections,
           "cross_section": {"shape": "solid_circle", "radius": radius},
           "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1000.0}}
    if f0 is not None:
        seg["reference_strain"] = list(f0)
    d = {"name": "arm", "gravity": [0, 0, 0], "segments": [seg]}
    return from_robot_model(model_from_dict(d), d)


def test_F_is_the_solution_map_of_the_linearised_equilibrium():
    """F(a) = expm(a ad(f0)^T) for random (pre-curved) reference strains,
    F(0) = I; the strain field's wrench K f solves sigma' = ad(f0)^T sigma
    (central differences) and meets the tip condition K f(L) = g."""
    for _ in range(5):
        f0 = RNG.normal(size=6)
        for a in (0.0, 0.37, 2.1):
            np.testing.assert_allclose(wrench_transport(a, f0), expm(a * ad(f0).T), atol=1e-13)
        np.testing.assert_allclose(wrench_transport(0.37, f0) @ np.linalg.inv(wrench_transport(2.1, f0)),
                                   wrench_transport(0.37 - 2.1, f0), atol=1e-12)
    f0 = np.array([1.0, 0.1, -0.2, 0.5, 2.0, -1.0])
    A = RNG.normal(size=(6, 6))
    K = A @ A.T + 6 * np.eye(6)                   # any SPD stiffness, coupled
    g = RNG.normal(size=6)
    s = np.linspace(0.01, L - 0.01, 7)
    h = 1e-5
    sig = closed_form_strain(s, K, f0, L, g) @ K.T
    dsig = (closed_form_strain(s + h, K, f0, L, g) - closed_form_strain(s - h, K, f0, L, g)) @ K.T / (2 * h)
    np.testing.assert_allclose(dsig, sig @ ad(f0), atol=1e-7 * np.abs(sig).max())   # rows: (ad^T sigma)^T
    np.testing.assert_allclose(K @ closed_form_strain([L], K, f0, L, g)[0], g, atol=1e-12)


def test_the_magnus_backbone_is_exact_for_constant_strain_and_of_fourth_order():
    xi0 = RNG.normal(size=6)
    H = backbone_poses(lambda s: np.tile(xi0, (len(s), 1)), L, points=5, steps=4)
    np.testing.assert_allclose(H[-1], exp_se3(L * xi0), atol=1e-13)
    slope = RNG.normal(size=6) * 5

    def strain(s):
        return xi0 + np.outer(s, slope) + np.outer(np.sin(7 * s), slope[::-1])
    ref = backbone_poses(strain, L, points=2, steps=512)[-1]
    err = [np.abs(backbone_poses(strain, L, points=2, steps=n)[-1] - ref).max() for n in (4, 8, 16)]
    rates = np.log2(np.array(err[:-1]) / err[1:])
    assert np.all((rates > 3.8) & (rates < 4.3)), rates


@pytest.mark.parametrize("moment", [[0.5, 0, 0], [0, 0.8, 0], [0, 0, -1.2], [0, 0.3, 0.4]])
def test_a_pure_moment_is_exact(moment):
    """A tip moment (in units of EI/L) about the torsion axis, either
    bending axis or, for the round section, any axis of its cross-section
    plane: a constant strain that solves the nonlinear statics too. The
    closed form's tip pose matches the engine's statics (follower moment)
    to 1e-10 and the continuum BVP's to its tolerance."""
    mech = _arm()
    sec = mech.tree.joints[mech.members[0].joints[0]].section
    g = np.r_[0, 0, 0, np.array(moment) * sec.K[4, 4] / L]
    cf = member_closed_form(mech, g)
    eq = solve_equilibrium(mech, point_loads=[FrameLoad(tip_frame(mech), g, "body")], tol=1e-13)
    tip = state_outputs(mech, eq.q, eq.lam, eq.inputs).frames[tip_frame(mech)]
    np.testing.assert_allclose(cf.tip, tip, atol=1e-10 * L)
    np.testing.assert_allclose(cf.strain, np.tile(cf.strain[0], (len(cf.s), 1)), atol=1e-14)
    bvp = solve_cosserat_statics(sec.K, L, tip_wrench_body=g)
    np.testing.assert_allclose(cf.tip, bvp.tip_pose(), atol=1e-8 * L)


def test_a_pre_curved_arm_under_a_moment_and_a_tip_force_error_growing_as_the_cube_of_the_load():
    """A pre-curved arm (f0 with curvature) keeps the exactness for a moment
    about its curvature axis. For a dead transverse tip force on a straight
    arm the closed form is the linear beam's moment carried on the exact
    kinematics: its tip error against the continuum BVP falls as the cube
    of the load (the deflection's first nonlinear term; halving the load
    divides it by 8 within 5 %), and stays under 1 % of the deflection up
    to F L^2 / EI = 0.3."""
    f0 = [1, 0, 0, 0, 2.0, 0]
    mech = _arm(f0=f0)
    sec = mech.tree.joints[mech.members[0].joints[0]].section
    g = np.r_[0, 0, 0, 0, 0.7 * sec.K[4, 4] / L, 0]
    bvp = solve_cosserat_statics(sec.K, L, f0=f0, tip_wrench_body=g)
    np.testing.assert_allclose(member_closed_form(mech, g).tip, bvp.tip_pose(), atol=1e-8 * L)

    mech = _arm()
    sec = mech.tree.joints[mech.members[0].joints[0]].section
    EI = sec.K[4, 4]
    errors = {}
    for w in (0.3, 0.15, 0.075):
        F = np.array([0, 0, -w * EI / L ** 2])
        bvp = solve_cosserat_statics(sec.K, L, tip_force_world=F)
        tip = bvp.tip_pose()[:3, 3]
        err = np.linalg.norm(member_closed_form(mech, np.r_[F, 0, 0, 0]).tip[:3, 3] - tip)
        errors[w] = err
        assert err < 0.01 * np.linalg.norm(tip - [L, 0, 0])
    assert errors[0.3] / errors[0.15] == pytest.approx(8, rel=0.05)
    assert errors[0.15] / errors[0.075] == pytest.approx(8, rel=0.05)


def test_bad_input_names_the_member_or_the_wrench():
    mech = _arm()
    with pytest.raises(ValueError, match="tip_wrench"):
        member_closed_form(mech, [0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="tip_wrench"):
        member_closed_form(mech, [0, 0, 1])
    with pytest.raises(ModelError, match="'nope'"):
        member_closed_form(mech, np.zeros(6), member="nope")
    seg = {"length": 0.1, "sections": 2, "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1e3}}
    d = {"name": "tapered", "segments": [dict(seg, name="a", cross_section={"shape": "solid_circle", "radius": 0.01}),
                                         dict(seg, name="b", cross_section={"shape": "solid_circle", "radius": 0.02})]}
    with pytest.raises(ModelError, match="'backbone'.*uniform.*K differ"):
        member_closed_form(from_robot_model(model_from_dict(d), d), np.zeros(6))
