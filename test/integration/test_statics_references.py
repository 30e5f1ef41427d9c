"""PCS statics against independent continuum references (issue 5): the
elliptic-integral elastica and the 3D Cosserat boundary value problem of
soft_twin_core.reference.continuum (which shares no code with the PCS solver)."""

import numpy as np

from soft_twin_core.engine import loads as ld
from soft_twin_core.reference.continuum import elastica_cantilever_tip, solve_cosserat_statics
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator
from rod_statics import mechanism, solve_statics


def inextensible_rod(n):
    """EI = 1 N m^2, L = 1 m; only bending free: the exact inextensible,
    unshearable limit of the elastica."""
    return model_from_dict({"gravity": [0, 0, 0], "segments": [{
        "length": 1.0, "sections": n, "free_modes": "bending",
        "cross_section": {"shape": "explicit", "area": 1.0, "I2": 1.0, "I3": 1.0, "J": 2.0},
        "material": {"youngs_modulus": 1.0, "shear_modulus": 0.5, "density": 1.0}}]})


def elastica_errors(n, alphas=range(1, 11)):
    m = inextensible_rod(n)
    q, errs = None, []
    for a in alphas:                          # P L^2 / EI = a, continuation in the load
        r = solve_statics(m, loads=ld.Loads(point=(ld.tip_load(m, (0, 0, -a)),), gravity=False),
                             q_init=q)
        q = r.q
        x, d = elastica_cantilever_tip(a)
        p = r.tip_pose[:3, 3]
        errs.append(np.hypot(p[0] - x, -p[2] - d))
    return np.array(errs)


def test_elastica_tip_within_half_percent_at_8_sections_and_converging():
    """Bisshopp-Drucker elastica, PL^2/EI = 1..10: at 8 sections the tip is
    within 0.5 % of L (measured: 0.30 % at PL^2/EI = 10); the error falls 4x
    per doubling of the sections (second order)."""
    e4, e8, e16 = elastica_errors(4), elastica_errors(8), elastica_errors(16)
    assert e8.max() < 0.005
    assert np.all(e4 > e8) and np.all(e8 > e16)
    assert np.all((e8 / e16 > 3.5) & (e8 / e16 < 4.5))


def test_pcs_converges_to_3d_continuum_with_torsion():
    """Benchmark rod (all six strain modes) under gravity, a dead tip force and
    a dead tip moment out of every principal plane (bending in 3D with
    torsion): PCS tip pose converges to the BVP at second order."""
    m1 = model_from_dict(benchmark_cantilever_dict(1))
    sec = m1.sections[0]
    f_tip, m_tip = np.array([0.05, 0.1, -0.05]), np.array([0.004, 0.002, -0.003])
    ref = solve_cosserat_statics(sec.K, 0.5, tip_force_world=f_tip, tip_moment_world=m_tip,
                                 distributed_force_world=sec.M[0, 0] * m1.gravity)
    H_ref = ref.tip_pose()
    errs = []
    for n in (4, 8, 16):
        m = model_from_dict(benchmark_cantilever_dict(n))
        r = solve_statics(m, loads=ld.Loads(point=(ld.tip_load(m, f_tip, m_tip),)))
        assert np.abs(r.strains[:, 3]).max() > 0.1          # torsion really is involved
        errs.append(np.linalg.norm(r.tip_pose[:3, 3] - H_ref[:3, 3]))
        R_err = np.linalg.norm(r.tip_pose[:3, :3] - H_ref[:3, :3])
        assert R_err < 20 * errs[-1] / 0.5 + 1e-9
    assert errs[0] > errs[1] > errs[2]
    assert 3.0 < errs[1] / errs[2] < 5.0
    assert errs[2] < 2e-3 * 0.5
    # both base reactions balance the same loads
    r = solve_statics(model_from_dict(benchmark_cantilever_dict(16)),
                         loads=ld.Loads(point=(ld.tip_load(m, f_tip, m_tip),)))
    assert np.allclose(r.base_wrench_world[:3], ref.base_wrench_world[:3], rtol=1e-9, atol=1e-12)


def test_pre_curved_rod_under_follower_load_matches_continuum():
    """A pre-curved, pre-twisted member (constant f0) under a follower tip
    wrench: PCS approaches the BVP at second order (measured tip errors
    8.3e-3, 2.1e-3, 5.3e-4 m for 2, 4, 8 sections)."""
    f0 = [1.0, 0.0, 0.0, 0.8, 1.5, -0.5]
    W = np.array([0.0, 0.02, -0.01, 0.001, 0.0, 0.002])
    errs = []
    for n in (2, 4, 8):
        d = benchmark_cantilever_dict(n)
        d["gravity"] = [0, 0, 0]
        d["segments"][0]["reference_strain"] = f0
        m = model_from_dict(d)
        r = solve_statics(m, loads=ld.Loads(point=(ld.tip_load(m, W[:3], W[3:], frame="body"),),
                                               gravity=False))
        ref = solve_cosserat_statics(m.sections[0].K, 0.5, f0=f0, tip_wrench_body=W)
        errs.append(np.linalg.norm(r.tip_pose[:3, 3] - ref.tip_pose()[:3, 3]))
    assert 3.5 < errs[0] / errs[1] < 4.5 and 3.5 < errs[1] / errs[2] < 4.5
    assert errs[2] < 1e-3


def test_cayley_map_model_converges_to_the_same_continuum():
    """With kinematic_map: cayley each section is a Cayley arc (not a
    constant-strain helix); statics and dynamics run on the numpy path and
    the tip still converges to the continuum solution as sections are added."""
    m1 = model_from_dict(benchmark_cantilever_dict(1))
    sec = m1.sections[0]
    ref = solve_cosserat_statics(sec.K, 0.5, distributed_force_world=sec.M[0, 0] * m1.gravity)
    errs = []
    for n in (4, 8, 16):
        d = benchmark_cantilever_dict(n)
        d["kinematic_map"] = "cayley"
        r = solve_statics(model_from_dict(d))
        errs.append(np.linalg.norm(r.tip_pose[:3, 3] - ref.tip_pose()[:3, 3]))
    assert errs[0] > errs[1] > errs[2] and errs[2] < 0.012 * 0.5
    d = benchmark_cantilever_dict(2, "bending_torsion")
    d["kinematic_map"] = "cayley"
    sim = MechanismSimulator(mechanism(model_from_dict(d)), 1e-3)
    sim.step(n=20)                                  # raises StepError if a step fails
    assert np.all(np.isfinite(sim.q))
