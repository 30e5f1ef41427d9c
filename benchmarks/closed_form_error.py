"""How far the seeds' part C closed form (soft_twin_core.solve.cantilever)
predicts a tip-loaded cantilever: its tip error against the continuum BVP
(soft_twin_core.reference.continuum, independent of the PCS engine) as the
load grows, and its cost against the engine's statics.

The arm: 0.3 m, r = 10 mm, E = 1 MPa, every strain mode free. Loads, in
units of EI/L^2 (force) and EI/L (moment): a transverse tip force, dead
(fixed in the world) and follower (turning with the tip), and a tip moment
about a bending axis (exact: the control). The figure: tip error / L and
tip error / tip deflection against the load; a table of the same.

Run: .venv/bin/python benchmarks/closed_form_error.py [--out docs/figures/closed_form_error.png]
"""

import argparse
import os
import sys

import numpy as np

from _timing import fmt, machine, per_call
from soft_twin_core.reference.continuum import solve_cosserat_statics
from soft_twin_core.robot.mechanism import from_robot_model, tip_frame
from soft_twin_core.robot.model import model_from_dict
from soft_twin_core.solve.cantilever import member_closed_form
from soft_twin_core.solve.constrained import FrameLoad, solve_equilibrium

L = 0.3


def arm(sections=10):
    d = {"name": "arm", "gravity": [0, 0, 0], "segments": [{
        "name": "s", "length": L, "sections": sections, "cross_section": {"shape": "solid_circle", "radius": 0.01},
        "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1000.0}}]}
    return from_robot_model(model_from_dict(d), d)


def sweep(mech, loads):
    """Rows (load, kind, deflection / L, error / L) for each load and kind."""
    K = mech.tree.joints[0].section.K
    EI = K[4, 4]
    rows = []
    for w in loads:
        F = np.array([0, 0, -w * EI / L ** 2])
        M = np.array([0, w * EI / L, 0])
        cases = {"dead force": (dict(tip_force_world=F), np.r_[F, 0, 0, 0]),
                 "follower force": (dict(tip_wrench_body=np.r_[F, 0, 0, 0]), np.r_[F, 0, 0, 0]),
                 "moment": (dict(tip_wrench_body=np.r_[0, 0, 0, M]), np.r_[0, 0, 0, M])}
        for kind, (load, g) in cases.items():
            ref = solve_cosserat_statics(K, L, **load).tip_pose()[:3, 3]
            tip = member_closed_form(mech, g).tip[:3, 3]
            rows.append((w, kind, np.linalg.norm(ref - [L, 0, 0]) / L, np.linalg.norm(tip - ref) / L))
    return rows


def plot(rows, out):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), constrained_layout=True)
    for kind, style in (("dead force", "o-"), ("follower force", "s--"), ("moment", "^:")):
        r = np.array([(w, d, e) for w, k, d, e in rows if k == kind])
        floor = np.maximum(r[:, 2], 1e-16)
        axes[0].loglog(r[:, 0], floor, style, label=kind, ms=4)
        axes[1].loglog(r[:, 0], np.maximum(r[:, 2] / r[:, 1], 1e-16), style, label=kind, ms=4)
    axes[0].set(xlabel="tip load [EI/L^2 (force), EI/L (moment)]", ylabel="tip position error / L",
                title="closed form vs continuum BVP")
    axes[1].axhline(0.01, color="grey", lw=0.8)
    axes[1].text(0.012, 0.012, "1 % of the deflection", color="grey", fontsize=8)
    axes[1].set(xlabel="tip load [EI/L^2 (force), EI/L (moment)]", ylabel="tip error / tip deflection")
    for ax in axes:
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=8)
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    fig.savefig(out, dpi=120)
    print(f"figure: {out}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/figures/closed_form_error.png")
    args = ap.parse_args(argv)
    mech = arm()
    loads = np.geomspace(0.01, 5.0, 16)
    rows = sweep(mech, loads)
    print(f"# {machine()}, load average {os.getloadavg()[0]:.2f}")
    print(f"{'load':>8} {'kind':>15} {'deflection/L':>13} {'error/L':>10} {'error/deflection':>17}")
    for w, kind, d, e in rows:
        print(f"{w:8.3g} {kind:>15} {d:13.3g} {e:10.2e} {e / d:17.2e}")
    EI = mech.tree.joints[0].section.K[4, 4]
    g = np.r_[0, 0, -0.3 * EI / L ** 2, 0, 0, 0]
    load = [FrameLoad(tip_frame(mech), g, "world")]
    solve_equilibrium(mech, point_loads=load)
    print(f"closed form (41 poses):              {fmt(per_call(lambda: member_closed_form(mech, g)))} a call")
    print(f"engine statics, 10 sections (cold):  {fmt(per_call(lambda: solve_equilibrium(mech, point_loads=load)))}"
          " a call")
    plot(rows, args.out)


if __name__ == "__main__":
    sys.exit(main())
