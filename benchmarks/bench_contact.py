"""Contact's cost: a soft arm lying on a table against the same arm in the air.

The default arm's material and section (0.45 m, r = 10 mm, E = 2 MPa,
bending and torsion), N sections, clamped horizontally 2 mm above a table
(plane) so that it lies on it over most of its length (7 contact points
pressed, at a 45 mm spacing); dynamics at dt = 2 ms, implicit midpoint,
after the arm has settled. Reported per step: the same arm without
obstacles (the compiled O(n) integrator), with the table (the compiled
contact step, engine/contact_step.py: the contacts' forces, stiffness and
damping, its Newton matrix kept while the same points touch), and their
ratio; and the statics solve from the settled state.

Issue 27's goal: at most 2x the cost without contact at the same dt.

Then robots with constraint rows and obstacles (the catheter on its
prescribed base, the planar parallel robot pressed by a ball): the compiled
contact step against the Python KKT step.

Run: .venv/bin/python benchmarks/bench_contact.py [--sections 5 10 20] [--spacing 0.045]
(--spacing 0.03: about 10 contacts pressed; --friction 0.5: friction at the contact surface)
"""

import argparse
import os
import time

import numpy as np

from _timing import fmt, machine, per_call
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium


def arm(n, table, spacing=0.045, friction=0.0):
    d = {"name": f"arm_{n}", "gravity": [0, 0, -9.81],
         "segments": [{"name": "arm", "length": 0.45, "sections": n,
                       "cross_section": {"shape": "solid_circle", "radius": 0.010},
                       "material": {"youngs_modulus": 2.0e6, "poisson_ratio": 0.5, "density": 1100.0,
                                    "viscosity": 2.0e3},
                       "free_modes": "bending_torsion"}]}
    if table:
        d["obstacles"] = [{"name": "table", "type": "plane", "point": [0, 0, -0.012], "normal": [0, 0, 1],
                           "damping": 5.0, "friction": friction, "stiction_velocity": 1e-3}]
        d["contact"] = {"spacing": spacing}
    return from_robot_model(model_from_dict(d), d)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", type=int, nargs="+", default=[5, 10, 20])
    ap.add_argument("--spacing", type=float, default=0.045, help="between contact points [m]")
    ap.add_argument("--friction", type=float, default=0.0, help="the table's Coulomb mu (stiction velocity 1 mm/s)")
    args = ap.parse_args()
    print(f"# {machine()}, load {os.getloadavg()[0]:.2f}, friction {args.friction:g}")
    print(f"{'sections':>8} {'contacts':>8} {'free step':>12} {'on table':>12} {'ratio':>6} {'statics':>12}")
    for n in args.sections:
        times = []
        for table in (False, True):
            mech = arm(n, table, args.spacing, args.friction)
            sim = MechanismSimulator(mech, 2e-3, 0.5, tol=1e-6)
            sim.step(n=500)                      # settle (and compile)
            times.append(per_call(lambda: sim.step(), number=50))
        mech = arm(n, True, args.spacing, args.friction)
        eq = solve_equilibrium(mech)
        t0 = time.perf_counter()
        solve_equilibrium(mech, q_init=eq.q)
        t_static = time.perf_counter() - t0
        print(f"{n:>8} {len(eq.contacts):>8} {fmt(times[0]):>12} {fmt(times[1]):>12} {times[1] / times[0]:>6.1f} "
              f"{fmt(t_static):>12}")
    with_rows()


def with_rows(n=200):
    """Robots with constraint rows and obstacles (the compiled contact step
    solves the rows by their Schur complement): wall time per step over n
    steps from rest, the compiled step against the Python KKT step, Newton
    iterations a step; the catheter also without its vessel."""
    import yaml
    from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
    from soft_twin_core.robot.model import find_file
    with open(find_file("planar_parallel_robot", "robots")) as f:
        d = yaml.safe_load(f)
    d["obstacles"] = [{"name": "ball", "type": "sphere", "center": [-0.0715, 0.0, 0.2], "radius": 0.02,
                       "friction": 0.2, "stiction_velocity": 1e-3, "damping": 1.0}]      # pressing on rod 1
    d["contact"] = {"spacing": 0.01}
    cases = [("catheter in its vessel, dt 1 ms", load_mechanism(find_file("catheter_in_vessel", "robots")), 1e-3, None),
             ("  the same without the vessel", load_mechanism(find_file("catheter_in_vessel", "robots")), 1e-3, ()),
             ("parallel robot on a ball, dt 5 ms", mechanism_from_dict(d), 5e-3, None)]
    print(f"\n# constraint rows and obstacles, {n} steps from rest, load {os.getloadavg()[0]:.2f}")
    print(f"{'robot':>34} {'dof':>4} {'rows':>4} {'compiled':>10} {'it/step':>7} {'Python KKT':>10} {'it/step':>7}")
    for name, mech, dt, obstacles in cases:
        row = []
        for compiled in (True, False):
            kw = {} if obstacles is None else {"obstacles": obstacles}
            sim = MechanismSimulator(mech, dt, compiled=compiled, **kw)
            sim.step()                         # (compile)
            it0, t0 = sim.newton_iterations, time.perf_counter()
            sim.step(n=n)
            row += [(time.perf_counter() - t0) / n, (sim.newton_iterations - it0) / n]
        print(f"{name:>34} {mech.tree.nv:>4} {mech.n_constraint_rows:>4} {fmt(row[0]):>10} {row[1]:>7.2f} "
              f"{fmt(row[2]):>10} {row[3]:>7.2f}")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
