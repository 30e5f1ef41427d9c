"""Constrained statics (issue 25, item 8): an unloaded closed chain whose
constraint is not met at the reference solves (its residual scale was 1e-300
and the merit function overflowed), and an equilibrium is judged stable or
unstable by the reduced tangent stiffness on the constraints' allowed
motions.

References: the closed form of a uniformly stretched bar; a central finite
difference of the residual kernel (the reduced stiffness); Euler's buckling
load of a clamped-pinned column, 20.19 EI/L^2 ((4.4934/L)^2 EI); the
shipped planar parallel robot below and past its critical load."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.solve import constrained as cs
from soft_twin_core.solve.equilibrium import constraint_null_space, reduced_stiffness

ROOT = Path(__file__).resolve().parents[2]
E, R_BAR = 2.0e6, 0.01


def _bar(tip_x, sections=4):
    """A 0.4 m bar along x, no gravity, its tip clamped to the world at x = tip_x."""
    return mechanism_from_dict({
        "name": "stretched", "gravity": [0, 0, 0],
        "bodies": [{"name": "bar", "type": "member", "segments": [{
            "name": "bar", "length": 0.4, "sections": sections,
            "cross_section": {"shape": "solid_circle", "radius": R_BAR},
            "material": {"youngs_modulus": E, "poisson_ratio": 0.5, "density": 1000.0}, "free_modes": "all"}]}],
        "constraints": [{"name": "clamp", "type": "clamped", "frame": "bar_tip", "to": "world",
                         "target": {"position": [tip_x, 0.0, 0.0], "rpy": [0.0, 0.0, 0.0]}}]})


def test_unloaded_closed_chain_with_a_gap_solves_to_the_closed_form():
    """No load at all, the clamp 1 mm beyond the bar's tip: every section
    stretched by 0.401/0.4 (PCS is exact for a uniform axial strain), the
    clamp pulling the tip with EA * 0.001 / 0.4 along +x, stable."""
    mech = _bar(0.401)
    eq = cs.solve_equilibrium(mech)
    tree = mech.tree
    for i in tree.soft_joints:
        strain = eq.q[tree.idx_q[i]:tree.idx_q[i] + 6]
        np.testing.assert_allclose(strain, [1.0025, 0, 0, 0, 0, 0], rtol=0, atol=1e-12)
    EA = E * np.pi * R_BAR ** 2
    np.testing.assert_allclose(eq.constraint_wrenches["clamp"], [EA * 0.001 / 0.4, 0, 0, 0, 0, 0],
                               rtol=1e-9, atol=1e-12)
    assert eq.stable and eq.min_stiffness_eigenvalue > 0
    # and compressed by 1 mm: the same force, pushing
    eq = cs.solve_equilibrium(_bar(0.399))
    assert eq.constraint_wrenches["clamp"][0] == pytest.approx(-EA * 0.001 / 0.4, rel=1e-9)


def _column(P, sections=16):
    """A 0.4 m column along x, clamped at its base, its tip held on the x axis
    (a line constraint: free to slide along x and to turn), under an axial
    compressive force P [N] at the tip; no gravity."""
    mech = mechanism_from_dict({
        "name": "column", "gravity": [0, 0, 0],
        "bodies": [{"name": "col", "type": "member", "segments": [{
            "name": "col", "length": 0.4, "sections": sections,
            "cross_section": {"shape": "solid_circle", "radius": 0.002},
            "material": {"youngs_modulus": 6.0e10, "poisson_ratio": 0.33, "density": 6450.0},
            "free_modes": "all"}]}],
        "constraints": [{"name": "roller", "type": "line", "frame": "col_tip", "to": "world",
                         "target": {"position": [0.4, 0.0, 0.0], "rpy": [0, 0, 0]}, "direction": [1, 0, 0]}]})
    return mech, [cs.FrameLoad("col_tip", np.array([-P, 0, 0, 0, 0, 0]), "world")]


def _solve(mech, loads):
    return cs.solve_equilibrium(mech, point_loads=loads)


def _critical(make, lo, hi, n=40):
    """The load where the equilibrium found turns unstable (bisection)."""
    for _ in range(n):
        mid = 0.5 * (lo + hi)
        if _solve(*make(mid)).stable:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def test_euler_buckling_load_of_a_clamped_pinned_column():
    """The load at which the straight column's reduced stiffness loses
    positive definiteness is Euler's 20.19 EI/L^2, to the PCS discretisation
    error (O(1/n^2): within 1 % at 16 sections, closer at 32); below it the
    column is stable, past it the straight equilibrium (still found, by
    symmetry) is flagged unstable."""
    EI = 6.0e10 * np.pi * 0.002 ** 4 / 4
    euler = (4.493409457909064 / 0.4) ** 2 * EI
    errs = []
    for n in (16, 32):
        pc = _critical(lambda P: _column(P, n), 0.5 * euler, 1.5 * euler, n=30)
        errs.append(abs(pc / euler - 1))
    print(f"\nclamped-pinned column: critical load / Euler - 1 = {errs[0]:.2e} (16 sections), "
          f"{errs[1]:.2e} (32)")
    assert errs[0] < 1e-2 and errs[1] < errs[0] / 2.5        # converging (8.0e-3, then 2.6e-3)
    below, past = _solve(*_column(0.9 * euler)), _solve(*_column(1.2 * euler))
    assert below.stable and below.min_stiffness_eigenvalue > 0
    assert not past.stable and past.min_stiffness_eigenvalue < 0
    # past the critical load the straight shape is what was returned: flagged, not hidden
    tree = _column(1.2 * euler)[0].tree
    assert np.abs(past.q - tree.q0).max() < 1e-3


def _platform_load(P):
    mech = load_mechanism("planar_parallel_robot")
    return mech, [cs.FrameLoad("platform", np.array([0, 0, -P, 0, 0, 0]), "world")]


@pytest.fixture(scope="module")
def parallel_critical():
    """The planar parallel robot's critical downward platform load [N], gravity
    included (its rods are clamped-clamped columns joined by the platform)."""
    return _critical(_platform_load, 1.0, 2000.0, n=30)


def test_reduced_stiffness_is_the_finite_difference_of_the_residual(parallel_critical):
    """Z^T Kt Z (the analytic tangent, constraint forces' geometric stiffness
    included) equals Z^T dR/dq by central differences of the residual kernel
    at fixed multipliers, on the allowed motions Z, near the critical load."""
    mech, loads = _platform_load(0.8 * parallel_critical)
    eq = cs.solve_equilibrium(mech, point_loads=loads)
    pb = cs._Equilibrium(mech, eq.inputs)
    _, _, G = pb.residual(eq.q, eq.lam)
    Z = constraint_null_space(G)
    assert Z.shape[1] == mech.tree.nv - np.linalg.matrix_rank(G)
    np.testing.assert_allclose(G @ Z, 0, atol=1e-9 * np.abs(G).max())
    H = reduced_stiffness(pb.tangent(eq.q, eq.lam), Z)
    h = 1e-6
    fd = np.empty_like(H)
    for j in range(Z.shape[1]):
        rp = pb.residual(eq.q + h * Z[:, j], eq.lam)[0]
        rm = pb.residual(eq.q - h * Z[:, j], eq.lam)[0]
        fd[:, j] = Z.T @ (rp - rm) / (2 * h)
    np.testing.assert_allclose(H, fd, rtol=0, atol=1e-6 * np.abs(H).max())
    # the smallest eigenvalue reported is that of the finite-difference matrix
    ev = np.linalg.eigvalsh(0.5 * (fd + fd.T)).min()
    assert eq.min_stiffness_eigenvalue == pytest.approx(ev, rel=1e-4, abs=1e-6 * np.abs(H).max())


def test_parallel_robot_past_its_critical_load_is_flagged(parallel_critical):
    """Half the critical load: stable; four times: the planar equilibrium
    returned, flagged unstable (it used to come back with no flag)."""
    print(f"\nplanar parallel robot: critical downward platform load {parallel_critical:.2f} N")
    half = cs.solve_equilibrium(*_platform_load(0.5 * parallel_critical)[:1],
                                point_loads=_platform_load(0.5 * parallel_critical)[1])
    four = cs.solve_equilibrium(*_platform_load(4.0 * parallel_critical)[:1],
                                point_loads=_platform_load(4.0 * parallel_critical)[1])
    assert half.stable and half.min_stiffness_eigenvalue > 0
    assert not four.stable and four.min_stiffness_eigenvalue < 0


def test_statics_command_warns_of_an_unstable_equilibrium(tmp_path, parallel_critical):
    """The CLI: exit 0, "stable": false in the JSON and a warning on stderr
    saying what it means physically."""
    sc = tmp_path / "crushed.yaml"
    sc.write_text(yaml.safe_dump({
        "robot": str(ROOT / "config/robots/planar_parallel_robot.yaml"), "gravity": True,
        "loads": [{"frame": "platform", "force": [0.0, 0.0, -4.0 * parallel_critical], "axes": "world"}]}))
    p = subprocess.run([sys.executable, "-m", "soft_twin_core.cli", "statics", str(sc)], capture_output=True,
                       text=True, cwd=ROOT, timeout=300)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["stable"] is False and out["min_stiffness_eigenvalue"] < 0
    assert "unstable equilibrium" in p.stderr and "buckles" in p.stderr, p.stderr


def _prescribed_bar_file(folder, clamp_tip):
    """A 0.4 m steel-like rod (the planar parallel robot's) on a prescribed base, its tip clamped to the world
    where it lies at rest (optional); a scenario driving the base 4.2 m
    diagonally in 0.1 s: (robot path, scenario path)."""
    robot = {"name": "driven", "gravity": [0, 0, 0], "base": {"position": [0, 0, 0], "motion": "prescribed"},
             "bodies": [{"name": "bar", "type": "member", "segments": [{
                 "name": "bar", "length": 0.4, "sections": 4, "cross_section": {"shape": "solid_circle", "radius": 0.002},
                 "material": {"youngs_modulus": 6.0e10, "poisson_ratio": 0.33, "density": 6450.0, "viscosity": 1.0e7},
                 "free_modes": "all"}]}]}
    if clamp_tip:
        robot["constraints"] = [{"name": "wall", "type": "clamped", "frame": "bar_tip", "to": "world"}]
    (folder / "driven.yaml").write_text(yaml.safe_dump(robot))
    (folder / "drive.yaml").write_text(yaml.safe_dump({
        "robot": "driven.yaml", "base_trajectory": [[0.0, 0, 0, 0, 0, 0, 0], [0.1, 3.0, 3.0, 0, 0, 0, 0]]}))
    return folder / "driven.yaml", folder / "drive.yaml"


def test_statics_of_a_bar_between_a_carried_base_and_a_wall_is_hookes():
    """The bar clamped to the wall at its tip, its prescribed base pulled
    back 0.1 mm along its axis and turned 0.01 rad about it: a bar in
    uniform tension and torsion, whose clamp reactions are the closed forms
    E A delta / L and G J theta / L (exact for PCS: uniform strains), equal
    and opposite at the wall. The other components vanish."""
    import tempfile
    from soft_twin_core.lie import exp_so3
    from soft_twin_core.robot.mechanism import base_targets
    with tempfile.TemporaryDirectory() as d:
        robot, _ = _prescribed_bar_file(Path(d), clamp_tip=True)
        mech = load_mechanism(str(robot))
    delta, theta, L, r, E, nu = 1e-4, 0.01, 0.4, 0.002, 6.0e10, 0.33
    A, J, G = math.pi * r ** 2, math.pi * r ** 4 / 2, E / (2 * (1 + nu))
    T = np.eye(4)
    T[:3, :3] = exp_so3([theta, 0, 0])
    T[0, 3] = -delta
    eq = cs.solve_equilibrium(mech, targets=base_targets(mech, T))
    base, wall = eq.constraint_wrenches["base"], eq.constraint_wrenches["wall"]
    expected = np.array([-E * A * delta / L, 0, 0, G * J * theta / L, 0, 0])     # held against the bar
    assert np.allclose(base, expected, rtol=1e-7, atol=1e-7 * np.abs(expected).max())
    assert np.allclose(wall[[0, 3]], -expected[[0, 3]], rtol=1e-7)


def test_a_base_driven_against_a_clamp_fails_in_physical_terms(tmp_path):
    """A prescribed base driven metres in a tenth of a second against a rod
    clamped to the wall: the run stops, and the error says how far the base
    was asked to go (in all, in the step), the stress reached as a multiple
    of the material's modulus, the constraint error, and what it means."""
    from soft_twin_core.files.scenario import load_scenario, run_dynamics
    _, scenario = _prescribed_bar_file(tmp_path, clamp_tip=True)
    out = run_dynamics(load_scenario(str(scenario)), 0.1, 0.005)
    err = out.get("error", "")
    print(f"\n{err}")
    assert "failed" in err and "asked the prescribed base to be" in err and "m in one step" in err, err
    assert "times its Young's modulus 6e+10 Pa" in err and "constraints were off" in err, err
    assert "larger or faster than the structure can follow" in err, err
