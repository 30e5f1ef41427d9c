"""Accuracy per generalised coordinate (issue 28): the tip error of a
cantilever's statics against the number of its coordinates, for piecewise
constant strain with n sections, PCS(n), and for a global Legendre strain
basis of order p (soft_twin_core.solve.strain_basis, on a 128-section
backbone), and the wall time of each solve.

The arm: the common benchmark cantilever (L = 0.5 m, r = 10 mm, E = 1 MPa,
1000 kg/m^3, along +x; bending modes free, so 2 coordinates per section or
per basis function). Loads: its own weight (a large deflection: the tip
hangs 0.45 m down), a transverse tip force of 0.05 N, and the same force at
mid-span (a kink in the shear force: a global basis converges slower).
Reference: PCS at 400 sections (its own error about 1e-6 L).

Run: .venv/bin/python benchmarks/accuracy_per_dof.py [--out docs/figures/accuracy_per_dof.png]
"""

import argparse
import os
import sys

import numpy as np

from _timing import best_of, machine
from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import free_problem, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs
from soft_twin_core.solve.strain_basis import legendre_basis, solve_reduced

L = 0.5
CASES = {
    "own weight": Loads(),
    "tip force 0.05 N": Loads(point=(PointLoad(L, (0.0, 0.0, -0.05, 0.0, 0.0, 0.0)),), gravity=False),
    "mid-span force 0.05 N": Loads(point=(PointLoad(L / 2, (0.0, 0.0, -0.05, 0.0, 0.0, 0.0)),), gravity=False),
}


def arm(n):
    return from_robot_model(model_from_dict(benchmark_cantilever_dict(n, "bending", length=L)))


def tip(mech, q, inp):
    return state_outputs(mech, q, np.zeros(0), inp).frames["tip"][:3, 3]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/figures/accuracy_per_dof.png")
    args = ap.parse_args(argv)
    print(f"# accuracy per coordinate, {machine()}, load {os.getloadavg()[0]:.2f}")
    rows = {}
    backbone = arm(128)
    for name, loads in CASES.items():
        ref = arm(400)
        ref_inp = make_inputs(ref, loads=loads)
        p_ref = tip(ref, solve_equilibrium(ref, loads=loads).q, ref_inp)
        pcs, leg = [], []
        for n in (1, 2, 4, 8, 16, 32, 64):
            m = arm(n)
            t, sol = best_of(lambda: solve_equilibrium(m, loads=loads), 3)
            pcs.append((m.tree.nv, np.linalg.norm(tip(m, sol.q, make_inputs(m, loads=loads)) - p_ref) / L, t))
        inp = make_inputs(backbone, loads=loads)
        pb = free_problem(backbone, inp)
        for p in range(0, 8):
            B = legendre_basis(backbone, p)
            t, (q, _, _) = best_of(lambda: solve_reduced(pb, B, backbone.tree.q0, load_steps=8), 3)
            leg.append((B.shape[1], np.linalg.norm(tip(backbone, q, inp) - p_ref) / L, t))
        rows[name] = (pcs, leg)
        print(f"\n## {name}\n| coordinates | PCS tip error / L | time | | coordinates | Legendre tip error / L | time |")
        print("|---:|---:|---:|---|---:|---:|---:|")
        for k in range(max(len(pcs), len(leg))):
            a = pcs[k] if k < len(pcs) else None
            b = leg[k] if k < len(leg) else None
            print("| " + (f"{a[0]} | {a[1]:.2e} | {a[2] * 1e3:.2f} ms" if a else " | | ") + " | | "
                  + (f"{b[0]} | {b[1]:.2e} | {b[2] * 1e3:.2f} ms" if b else " | | ") + " |")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(2, 3, figsize=(13, 7.5), layout="constrained")
    for c, (name, (pcs, leg)) in enumerate(rows.items()):
        for data, label, mk in ((pcs, "PCS(n sections)", "o-"), (leg, "Legendre(order p), 128-section backbone",
                                                                    "s-")):
            d = np.array(data)
            axs[0, c].loglog(d[:, 0], np.maximum(d[:, 1], 1e-12), mk, label=label)
            axs[1, c].loglog(1e3 * d[:, 2], np.maximum(d[:, 1], 1e-12), mk, label=label)
        axs[0, c].set_title(name)
        axs[0, c].set_xlabel("generalised coordinates")
        axs[1, c].set_xlabel("wall time of the solve [ms]")
        for r in range(2):
            axs[r, c].set_ylabel("tip error / L")
            axs[r, c].grid(alpha=0.3, which="both")
    axs[0, 0].legend(fontsize=8)
    fig.suptitle("Cantilever statics: tip error against coordinates and against time (reference: PCS, 400 sections)")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"\nfigure: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
