"""SoRoMoX's PCS dynamics of the released cantilever, for a cross-check of the engine's dynamics.

The benchmark cantilever (L = 0.5 m, r = 0.01 m, E = 1 MPa, G = E / 3,
1000 kg/m^3, along +x, gravity -z, undamped; every strain free, shear
stiffness G A) cut into n = 8 and 16 piecewise-constant-strain segments in
SoRoMoX's PCS model, released from the straight rest shape and rolled out
to t = 0.3 s by its default solver (Tsit5, explicit, fixed step dt =
1e-4 s: 1e-3 s diverges on 4 segments; halving dt changes no digit
printed). Written: the tip position [m] at t = 0.1, 0.2 and 0.3 s for each
n, and the wall time of a rollout after JAX's compilation
(``test/data/soromox_pcs_release.json``, which ``test/unit/test_dynamics.py``
checks the engine's dynamics against, at the same n).

SoRoMoX needs JAX, which the project does not depend on: run this in a
virtual environment of its own:

    python3 -m venv /tmp/peers && /tmp/peers/bin/pip install soromox==0.5.0
    /tmp/peers/bin/python benchmarks/soromox_pcs_dynamics.py
"""

import sys

import jax.numpy as jnp
import numpy as np

from _soromox import BASE_POSE, GRAVITY, LENGTH, link, write_reference
from _soromox import release as release_from_rest
from soromox.systems.pcs import PCS

SEGMENTS, DT, TIMES = (8, 16), 1e-4, (0.1, 0.2, 0.3)          # -, s, s


def cantilever(n):
    """n equal PCS segments along +x, gravity -z."""
    return PCS.from_links([link(LENGTH / n) for _ in range(n)], gravity=jnp.array(GRAVITY),
                          base_pose=jnp.array(BASE_POSE))


def release(n):
    """(tips [m] at TIMES, wall time [s] of the rollout after its first
    call, the first call's [s])."""
    tips, walls = release_from_rest(cantilever(n), TIMES, DT, 3)
    return tips, min(walls[1:]), walls[0]


def main():
    rows = []
    for n in SEGMENTS:
        tips, wall, first = release(n)
        rows.append(dict(segments=n, times_s=list(TIMES), tips_m=[[float(x) for x in p] for p in tips],
                         rollout_wall_s=wall, first_call_wall_s=first))
        print(f"{n} segments: tip at {TIMES[-1]} s {np.round(tips[-1], 8)} m; {TIMES[-1]} s simulated in "
              f"{wall:.3f} s ({first:.1f} s with JAX's compilation)", flush=True)
    write_reference("soromox_pcs_release.json", "soromox_pcs_dynamics.py", rows, solver="Tsit5", dt_s=DT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
