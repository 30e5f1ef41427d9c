"""SoRoMoX's variable-strain (GVS) dynamics of the released cantilever, for
a cross-check of the fourth-order Magnus dynamics (issue 28).

The benchmark cantilever of ``soromox_gvs.py`` (L = 0.5 m, r = 0.01 m,
E = 1 MPa, G = E / 3, 1000 kg/m^3, along +x, gravity -z, undamped, shear
stiffness G A), every strain component a Legendre series of order p = 1
and 3, with 16 and 32 Gauss points (its Magnus steps and quadrature),
released from the straight rest shape and rolled out to t = 0.3 s by its
default solver (Tsit5, explicit, fixed step dt = 1e-4 s, as
``soromox_pcs_dynamics.py``). Written: the tip position [m] at t = 0.1, 0.2
and 0.3 s for each order and Gauss count
(``test/data/soromox_gvs_release.json``, which ``test/unit/test_magnus4.py``
checks :mod:`soft_twin_core.solve.magnus4` against). The tips of a release
are physical quantities: how either model scales its coordinates does not
enter.

SoRoMoX needs JAX, which the project does not depend on: run this in a
virtual environment of its own:

    python3 -m venv /tmp/peers && /tmp/peers/bin/pip install soromox==0.5.0
    /tmp/peers/bin/python benchmarks/soromox_gvs_dynamics.py
"""

import sys

import numpy as np

from _soromox import GRAVITY, write_reference
from _soromox import release as release_from_rest
from soromox_gvs import cantilever

ORDERS, GAUSS_POINTS, DT, TIMES = (1, 3), (16, 32), 1e-4, (0.1, 0.2, 0.3)      # -, -, s, s


def release(order, gauss_points, dt=DT):
    """(tips [m] at TIMES, wall time [s] of the rollout after its first call)."""
    tips, walls = release_from_rest(cantilever(order, gauss_points, -GRAVITY[2]), TIMES, dt, 2)
    return tips, walls[-1]


def main():
    rows = []
    for order in ORDERS:
        for n in GAUSS_POINTS:
            tips, wall = release(order, n)
            half = release(order, n, DT / 2)[0]
            step_change = float(np.abs(np.array(tips) - np.array(half)).max())
            rows.append(dict(order=order, gauss_points=n, times_s=list(TIMES),
                             tips_m=[[float(x) for x in p] for p in tips], rollout_wall_s=wall,
                             change_at_half_dt_m=step_change))
            print(f"order {order}, {n} Gauss points: tip at {TIMES[-1]} s {np.round(tips[-1], 8)} m "
                  f"(dt / 2 changes it {step_change:.1e} m); rollout {wall:.2f} s", flush=True)
    write_reference("soromox_gvs_release.json", "soromox_gvs_dynamics.py", rows, basis="legendre", solver="Tsit5",
                    dt_s=DT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
