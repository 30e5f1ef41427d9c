"""What the O(n) step's Newton matrix leaves out, and what it costs in iterations.

The compiled theta step (``integrators.run_steps``) iterates on the
velocities with the articulated-body factorisation of

    A = M(q_t) + theta h D + (theta h)^2 K,

while the residual's exact Jacobian (times h) is

    A + theta h (dtau/dv - D) + (theta h)^2 (dtau/dq - K),

with tau the inverse dynamics with stiffness and damping
(:func:`algorithms.rnea_derivatives`). A simplified Newton iteration with A
contracts its error by about the spectral radius of ``A^-1 Delta`` a step,
Delta the part left out. This script splits Delta into the velocity
products (``theta h (dtau/dv - D)``, Coriolis and centrifugal) and the
configuration dependence of the inertial and gravity forces (``(theta h)^2
(dtau/dq - K)``), at states along the benchmark cantilever's released swing
(``benchmark_cantilever_dict(n, "all")``, undamped, gravity), and prints the
Newton iterations the step took over that second.

Run: PYTHONPATH=. .venv/bin/python benchmarks/newton_contraction.py
"""

import os

import numpy as np

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import MechanismSimulator, dense_stiffness_damping

CASES = ((6, 8e-3, 0.5), (6, 8e-3, 0.51), (10, 2e-3, 0.5), (16, 2.5e-3, 0.5))
TIMES = (0.2, 0.4, 0.6, 0.8)        # states along the swing [s]
TOL = 1e-4                          # the node's Newton tolerance


def spectral_radius(A, X):
    return float(np.max(np.abs(np.linalg.eigvals(np.linalg.solve(A, X)))))


def contraction(mech, dt, theta, t):
    """(whole, velocity part, configuration part) of rho(A^-1 Delta) at the
    state the simulator reaches at time t, and its largest velocity."""
    tree = mech.tree
    sim = MechanismSimulator(mech, dt, theta, tol=TOL, max_iterations=10)
    sim.step(n=int(round(t / dt)))
    K, D = dense_stiffness_damping(tree)
    ws = Workspace(tree)
    th = theta * dt
    M = alg.crba(tree, ws, sim.q).copy()
    dq, dv = alg.rnea_derivatives(tree, ws, sim.q, sim.v, sim.a)
    A = M + th * D + th * th * K
    Xv, Xq = th * (dv - D), th * th * (dq - K)
    return spectral_radius(A, Xv + Xq), spectral_radius(A, Xv), spectral_radius(A, Xq), float(np.abs(sim.v).max())


def main():
    print(f"[load {os.getloadavg()[0]:.2f} (1 min)]  rho: spectral radius of A^-1 Delta (whole / velocity products / "
          f"configuration of the inertial and gravity forces)")
    print(f"{'sections':>8} {'dt':>7} {'theta':>5} {'it/step':>8}  " +
          "  ".join(f"{'t = %g s' % t:>20}" for t in TIMES))
    for n, dt, theta in CASES:
        mech = from_robot_model(model_from_dict(benchmark_cantilever_dict(n, "all")))
        sim = MechanismSimulator(mech, dt, theta, tol=TOL, max_iterations=10)
        steps = int(round(1.0 / dt))
        sim.step(n=steps)
        cols = []
        for t in TIMES:
            whole, vel, conf, _ = contraction(mech, dt, theta, t)
            cols.append(f"{whole:.3f} / {vel:.3f} / {conf:.3f}")
        print(f"{n:>8} {dt * 1e3:>4.3g} ms {theta:>5.3g} {sim.newton_iterations / steps:>8.2f}  " +
              "  ".join(f"{c:>20}" for c in cols))


if __name__ == "__main__":
    main()
