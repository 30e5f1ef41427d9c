"""The fourth-order Magnus step in dynamics (issue 28): how the error of a
variable-strain rod falls with its sections under the second-order step
(each section the field's midpoint strain, its mass on its arc: the robot
file's ``strain_basis``) and the fourth-order one (Magnus-4 between the
Gauss points, the mass at them: soft_twin_core.solve.magnus4; "robot4" its
commutator-free form, two sections an interval and a constant B, as the
robot file's ``strain_basis: {..., magnus: 4}`` builds it), and what a
step's passes cost on each engine tree.

The arm: the common benchmark cantilever (L = 0.5 m, r = 10 mm, E = 1 MPa,
1000 kg/m^3), every strain mode a Legendre series of order 3 (24
coordinates). Three errors, each against the same field on 64 sections
under the fourth-order step (the discretisation's error alone; the two
steps share the field's limit):

- statics under its own weight (the tip 0.45 m down);
- the first three natural frequencies (their largest relative error);
- a swing: released straight under gravity, 0.5 s at dt = 10 ms by the
  engine's theta-method (theta 1/2), the tip's largest distance from the
  reference's over the steps.

Cost, two measures: one inverse-dynamics pass (the engine's compiled RNEA,
best of repeats) on each tree, the unit of a Newton iteration; and a step
of dt = 10 ms as each runs today (best of 3 x 20 steps from rest): the
robot file's steps, second and fourth order, are the robot's own
(:class:`MechanismSimulator`: the compiled reduced step), Magnus-4 with
the commutator the study's :func:`magnus4.simulate` (Python over the
compiled passes). The Magnus-4 tree has 2n + 1 intervals of 6
coordinates and 2n point inertias for n sections, the commutator-free
tree 4n + 2 sections, so a pass costs about twice and four times the
second-order tree's at the same n.

Run: .venv/bin/python benchmarks/magnus4_dynamics.py [--out docs/figures/magnus4_dynamics.png] [--quick]
"""

import argparse
import os
import sys
import time

import numpy as np

from _timing import machine, per_call
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve import magnus4 as m4
from soft_twin_core.solve.constrained import MechanismSimulator, free_problem, make_inputs
from soft_twin_core.solve.strain_basis import legendre_basis, solve_reduced

L, ORDER, DT, SWING = 0.5, 3, 0.01, 0.5


def _arm(n, magnus=None):
    """The cantilever on n sections: PCS, or the robot file's basis with the ``magnus`` step."""
    d = benchmark_cantilever_dict(n, "all", length=L)
    if magnus is not None:
        d["segments"][0]["strain_basis"] = {"type": "legendre", "order": ORDER, "magnus": magnus}
    return from_robot_model(model_from_dict(d))


def run(kind, n):
    """(statics tip, first three frequencies, swing tips (steps, 3), RNEA
    seconds a pass, Newton iterations a step) of the field on n sections."""
    arm = _arm(n)
    if kind == "magnus4":
        f = m4.Magnus4Field(arm, ORDER)
        z = m4.solve_magnus4(f, load_steps=4)[1]
    elif kind == "robot4":              # the robot's own tree and basis (the field's energy in its model)
        robot = _arm(n, 4)
        f = m4.LinearField(robot, robot.basis)
        z = m4.solve_magnus4(f, load_steps=4)[1]
    else:
        f = m4.LinearField(arm, legendre_basis(arm, ORDER))
        z = solve_reduced(free_problem(arm, make_inputs(arm)), f.B, arm.tree.q0, load_steps=4)[1]
    freqs = m4.modal_frequencies(f, 6)[[0, 2, 4]]
    _, _, its, tips = m4.simulate(f, SWING, DT, observe=lambda z, zd: f.tip(z)[:3, 3])
    q, v = f.q(z), f.jacobian(z) @ np.ones(f.nz)
    t = per_call(lambda: alg.rnea(f.tree, f.ws, q, v, v, elastic=False))
    return f.tip(z)[:3, 3], freqs, np.array(tips), t, its, step_time(kind, n, f)


def step_time(kind, n, f, steps=20):
    """Seconds a 10 ms step from rest takes as it runs today (best of 3)."""
    best = np.inf
    for _ in range(3):
        if kind == "magnus4":
            t = time.perf_counter()
            m4.simulate(f, steps * DT, DT)
        else:
            sim = MechanismSimulator(_arm(n, 4 if kind == "robot4" else 2), dt=DT)
            t = time.perf_counter()
            sim.step(n=steps)
        best = min(best, (time.perf_counter() - t) / steps)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/figures/magnus4_dynamics.png")
    ap.add_argument("--quick", action="store_true", help="fewer section counts (no figure)")
    a = ap.parse_args(argv)
    sections = {"midpoint": (4, 8, 16) if a.quick else (4, 8, 16, 32, 64, 128),
                "magnus4": (2, 4, 8) if a.quick else (2, 4, 8, 16, 32),
                "robot4": (2, 4, 8) if a.quick else (2, 4, 8, 16, 32)}
    print(f"# {machine()}; load {os.getloadavg()[0]:.2f}; Legendre order {ORDER}, every mode "
          f"({6 * (ORDER + 1)} coordinates)", flush=True)
    ref = run("magnus4", 64)
    rows = {}
    print(f"{'step':>9} {'n':>4} {'statics/L':>10} {'freq rel':>10} {'swing/L':>10} {'RNEA us':>8} {'it/step':>7} "
          f"{'step ms':>8}")
    for kind, ns in sections.items():
        for n in ns:
            st, fr, tips, t, its, step = run(kind, n)
            e = (np.linalg.norm(st - ref[0]) / L, np.abs(fr / ref[1] - 1).max(),
                 np.linalg.norm(tips - ref[2], axis=1).max() / L, t, step)
            rows[kind, n] = e
            print(f"{kind:>9} {n:4d} {e[0]:10.2e} {e[1]:10.2e} {e[2]:10.2e} {t * 1e6:8.1f} {its:7.2f} "
                  f"{step * 1e3:8.2f}", flush=True)
    print(f"# load after: {os.getloadavg()[0]:.2f}")
    if a.quick:
        return 0
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for kind, style in (("midpoint", "o--"), ("magnus4", "s-"), ("robot4", "^:")):
        ns = sections[kind]
        for k, (label, colour) in enumerate((("statics, own weight", "C0"), ("3 frequencies", "C1"),
                                             ("swing, 0.5 s", "C2"))):
            if kind == "robot4" and k != 2:
                continue                                   # on the Magnus-4 curves (the swing shown)
            err = [rows[kind, n][k] for n in ns]
            ax[0].loglog(ns, err, style, color=colour, label=f"{kind}: {label}")
        label = {"midpoint": "midpoint, magnus: 2 (robot's compiled step)", "magnus4": "Magnus-4 (study, Python)",
                 "robot4": "commutator-free, magnus: 4 (robot's compiled step)"}
        ax[1].loglog([rows[kind, n][4] * 1e3 for n in ns], [rows[kind, n][2] for n in ns], style,
                     color={"midpoint": "C2", "magnus4": "C4", "robot4": "C3"}[kind], label=label[kind])
        for n in ns:
            ax[1].annotate(str(n), (rows[kind, n][4] * 1e3, rows[kind, n][2]), fontsize=7,
                           textcoords="offset points", xytext=(3, 3))
    x = np.array([4.0, 32.0])
    ax[0].loglog(x, 2e-1 * (x / 4) ** -2, "k:", lw=0.8, label="slope -2")
    ax[0].loglog(x, 1e-4 * (x / 4) ** -4, "k-.", lw=0.8, label="slope -4")
    ax[0].set_xlabel("sections n")
    ax[0].set_ylabel("error (tip / L, or relative frequency)")
    ax[0].set_title(f"Legendre order {ORDER}, every mode: error against sections")
    ax[0].legend(fontsize=7, loc="lower left")
    ax[1].set_xlabel("CPU time of a 10 ms step [ms] (labels: sections n)")
    ax[1].set_ylabel("swing: largest tip error / L")
    ax[1].set_title("swing error against a step's cost")
    ax[1].legend(fontsize=8, loc="upper right")
    ax[1].xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax[1].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax[1].set_xticks([0.1, 0.2, 0.5, 1, 2, 5])
    for axis in ax:
        axis.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"figure: {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
