"""Accuracy per generalised coordinate (issue 28): the tip error of a
cantilever's statics against the number of its coordinates, for piecewise
constant strain with n sections, PCS(n), for a global Legendre strain
basis of order p and for FEM-like linear and cubic elements
(soft_twin_core.solve.strain_basis, on a 128-section backbone), and the
wall time of each solve; and the first three bending frequencies in each
(against the Rayleigh beam: Euler-Bernoulli with rotary inertia).

The arm: the common benchmark cantilever (L = 0.5 m, r = 10 mm, E = 1 MPa,
1000 kg/m^3, along +x; bending modes free, so 2 coordinates per section or
per basis function). Loads: its own weight (a large deflection: the tip
hangs 0.45 m down), a transverse tip force of 0.05 N, and the same force at
mid-span (a kink in the shear force: a global basis converges slower).
Reference: PCS at 400 sections (its own error about 1e-6 L). Also in 3D
the Princeton beam (config/scenarios/princeton_beam.yaml: 8.896 N at 30
degrees), against the continuum reference.

In 3D, the 45-degree bend (Bathe and Bolourchi, 1979; Simo and Vu-Quoc,
1986): a cantilever pre-curved to a 45-degree arc of radius R = 100 in the
xy plane, a unit square section (E = 1e7, G = E / 2, A = 1, I = 1/12, J =
1/6), loaded by 600 out of its plane at the tip; every strain mode free,
errors relative to R, against the continuum boundary-value reference
(soft_twin_core.reference.continuum, independent of PCS), whose tip (47.15,
15.68, 53.47) is within 0.1 % of R of the literature's 8-element values
(about 47.2, 15.8, 53.4; their base tangent along y there).

Run: .venv/bin/python benchmarks/accuracy_per_dof.py [--out docs/figures/accuracy_per_dof.png]
"""

import argparse
import os
import sys
import warnings

import numpy as np

from _timing import best_of, machine
from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.files.runs import scenario_inputs
from soft_twin_core.files.scenario import load_scenario
from soft_twin_core.reference.continuum import solve_cosserat_statics
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import BEND45_RADIUS, bend45_dict, benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import free_problem, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs
from soft_twin_core.solve.strain_basis import fem_basis, legendre_basis, modal_frequencies, solve_reduced

L = 0.5
CASES = {
    "own weight": Loads(),
    "tip force 0.05 N": Loads(point=(PointLoad(L, (0.0, 0.0, -0.05, 0.0, 0.0, 0.0)),), gravity=False),
    "mid-span force 0.05 N": Loads(point=(PointLoad(L / 2, (0.0, 0.0, -0.05, 0.0, 0.0, 0.0)),), gravity=False),
}


BEND_R = BEND45_RADIUS
BEND_LENGTH = BEND_R * np.pi / 4
BEND_LOADS = Loads(point=(PointLoad(BEND_LENGTH, (0.0, 0.0, 600.0, 0.0, 0.0, 0.0)),), gravity=False)


def bend(n):
    """The 45-degree bend (module docstring) in n sections."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")              # 78.5 "m" long: the classic problem has no units
        return from_robot_model(model_from_dict(bend45_dict(n)))


def bend_reference():
    """The bend's tip [same units as R] from the continuum reference."""
    K = bend(1).tree.joints[0].section.K
    return solve_cosserat_statics(K, BEND_LENGTH, f0=(1, 0, 0, 0, 0, 1 / BEND_R),
                                  tip_force_world=(0.0, 0.0, 600.0)).tip_pose()[:3, 3]


PRINCETON = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "config", "scenarios",
                         "princeton_beam.yaml")
PRINCETON_L = 0.508


def princeton(n):
    """(mechanism, inputs) of the Princeton beam scenario (an aluminium strip
    0.508 m long, 8.896 N at its tip at 30 degrees to its thin direction)
    in n sections."""
    sc = load_scenario(PRINCETON, n)
    return sc.mech, scenario_inputs(sc, 0.0)


def princeton_reference():
    """Its tip [m] from the continuum reference (0.3 % of the tip's
    deflection from Obrezkov et al.'s large-deflection beam, 2022, given in
    the scenario)."""
    mech, inp = princeton(1)
    return solve_cosserat_statics(mech.tree.joints[0].section.K, PRINCETON_L,
                                  tip_force_world=tuple(inp.loads.wrench[0, :3])).tip_pose()[:3, 3]


def _with_loads(robot, loads):
    """n -> (mechanism, inputs) of ``robot(n)`` under ``loads``."""
    def setup(n):
        m = robot(n)
        return m, make_inputs(m, loads=loads)
    return setup


def arm(n):
    return from_robot_model(model_from_dict(benchmark_cantilever_dict(n, "bending", length=L)))


def tip(mech, q, inp):
    return state_outputs(mech, q, np.zeros(0), inp).frames["tip"][:3, 3]


def rayleigh_frequencies(E=1e6, r=0.01, rho=1000.0):
    """The cantilever's first three bending frequencies [Hz] with rotary
    inertia (Rayleigh's quotient on the Euler-Bernoulli mode shapes; the
    unit tests' reference, test_strain_basis.py)."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "test", "unit"))
    from test_strain_basis import _rayleigh_beam_frequencies
    return _rayleigh_beam_frequencies(E, r, rho, L)[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/figures/accuracy_per_dof.png")
    args = ap.parse_args(argv)
    print(f"# accuracy per coordinate, {machine()}, load {os.getloadavg()[0]:.2f}")
    rows = {}
    cases = [(name, _with_loads(arm, loads), None, L, "L") for name, loads in CASES.items()]
    cases.append(("45-degree bend, tip force 600 (3D)", _with_loads(bend, BEND_LOADS), bend_reference(), BEND_R, "R"))
    cases.append(("Princeton beam, 8.9 N at 30 deg (3D)", princeton, princeton_reference(), PRINCETON_L, "L"))
    for name, setup, p_ref, scale, unit in cases:
        if p_ref is None:
            ref, ref_inp = setup(400)
            p_ref = tip(ref, solve_equilibrium(ref, inputs=ref_inp).q, ref_inp)
        pcs, leg, lin, cub = [], [], [], []
        for n in (1, 2, 4, 8, 16, 32, 64):
            m, inp = setup(n)
            t, sol = best_of(lambda: solve_equilibrium(m, inputs=inp), 3)
            pcs.append((m.tree.nv, np.linalg.norm(tip(m, sol.q, inp) - p_ref) / scale, t))
        backbone, inp = setup(128)
        pb = free_problem(backbone, inp)
        for p in range(0, 8):
            B = legendre_basis(backbone, p)
            t, (q, _, _) = best_of(lambda: solve_reduced(pb, B, backbone.tree.q0, load_steps=8), 3)
            leg.append((B.shape[1], np.linalg.norm(tip(backbone, q, inp) - p_ref) / scale, t))
        for out, degree, counts in ((lin, 1, (1, 2, 4, 8, 16)), (cub, 3, (1, 2, 4, 8))):
            for e in counts:
                B = fem_basis(backbone, e, degree)
                t, (q, _, _) = best_of(lambda: solve_reduced(pb, B, backbone.tree.q0, load_steps=8), 3)
                out.append((B.shape[1], np.linalg.norm(tip(backbone, q, inp) - p_ref) / scale, t))
        rows[name] = (pcs, leg, lin, cub, unit)
        print(f"\n## {name}\n| basis | coordinates | tip error / {unit} | time |\n|---|---:|---:|---:|")
        for label, data in (("PCS", pcs), ("Legendre", leg), ("linear elements", lin), ("cubic elements", cub)):
            for c, e, t in data:
                print(f"| {label} | {c} | {e:.2e} | {t * 1e3:.2f} ms |")
    print("\n## first three bending frequencies, relative error against the Rayleigh beam\n"
          "| basis | coordinates per bending direction | f1 | f2 | f3 |\n|---|---:|---:|---:|---:|")
    ray = rayleigh_frequencies()
    backbone = arm(128)
    for label, mech, B in ([(f"PCS({n})", arm(n), None) for n in (8, 16, 32, 64, 128)]
                           + [(f"Legendre({p})", backbone, legendre_basis(backbone, p)) for p in (3, 5, 7, 11)]
                           + [(f"linear({e})", backbone, fem_basis(backbone, e, 1)) for e in (4, 8, 11)]
                           + [(f"cubic({e})", backbone, fem_basis(backbone, e, 3)) for e in (1, 2, 4)]):
        B = np.eye(mech.tree.nv) if B is None else B
        f = modal_frequencies(mech, B, count=6)[0:6:2]
        print(f"| {label} | {B.shape[1] // 2} | " + " | ".join(f"{x:+.1e}" for x in f / ray - 1) + " |")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(2, len(rows), figsize=(4.3 * len(rows), 7.5), layout="constrained")
    for c, (name, (pcs, leg, lin, cub, unit)) in enumerate(rows.items()):
        for data, label, mk in ((pcs, "PCS(n sections)", "o-"), (leg, "Legendre(order p), 128-section backbone",
                                                                    "s-"),
                                (lin, "linear elements", "^-"), (cub, "cubic elements", "v-")):
            d = np.array(data)
            axs[0, c].loglog(d[:, 0], np.maximum(d[:, 1], 1e-12), mk, label=label)
            axs[1, c].loglog(1e3 * d[:, 2], np.maximum(d[:, 1], 1e-12), mk, label=label)
        axs[0, c].set_title(name)
        axs[0, c].set_xlabel("generalised coordinates")
        axs[1, c].set_xlabel("wall time of the solve [ms]")
        for r in range(2):
            axs[r, c].set_ylabel(f"tip error / {unit}")
            axs[r, c].grid(alpha=0.3, which="both")
    axs[0, 0].legend(fontsize=8)
    fig.suptitle("Cantilever statics: tip error against coordinates and against time (references: PCS, 400 "
                 "sections; the 3-D cases: the continuum boundary-value solution)")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"\nfigure: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
