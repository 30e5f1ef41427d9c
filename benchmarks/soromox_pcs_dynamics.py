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

import datetime
import json
import os
import platform
import sys
import time
from importlib.metadata import version

import numpy as np

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
from soromox.systems.components import LinkSpec  # noqa: E402
from soromox.systems.pcs import PCS  # noqa: E402
from soromox.systems.system_state import SystemState  # noqa: E402

LENGTH, RADIUS, E, DENSITY = 0.5, 0.01, 1.0e6, 1000.0
G = E / 3                                # Poisson 0.5
SEGMENTS, DT, TIMES = (8, 16), 1e-4, (0.1, 0.2, 0.3)
OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "test", "data", "soromox_pcs_release.json")


def cantilever(n):
    """n equal PCS segments along +x (identity base pose: quaternion x, y,
    z, w first), gravity -z."""
    links = [LinkSpec.circular(length=LENGTH / n, radius=RADIUS, density=DENSITY,
                               reference_strain=[0, 0, 0, 1, 0, 0], young_modulus=E, shear_modulus=G)
             for _ in range(n)]
    return PCS.from_links(links, gravity=jnp.array([0.0, 0.0, -9.81]),
                          base_pose=jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))


def release(n):
    """(tips [m] at TIMES, wall time [s] of the rollout after its first
    call, the first call's [s])."""
    rob = cantilever(n)
    nq = rob.num_coordinates
    start = SystemState(t=jnp.array(0.0), y=jnp.zeros(2 * nq))
    walls = []
    for _ in range(3):
        t = time.perf_counter()
        out = rob.rollout_to(start, t1=TIMES[-1], solver_dt=DT, save_ts=jnp.array(TIMES))
        jax.block_until_ready(out.y)
        walls.append(time.perf_counter() - t)
    tips = [np.asarray(rob.forward_kinematics(out.y[k, :nq], jnp.array(LENGTH)))[:3, 3] for k in range(len(TIMES))]
    return tips, min(walls[1:]), walls[0]


def main():
    rows = []
    for n in SEGMENTS:
        tips, wall, first = release(n)
        rows.append(dict(segments=n, times_s=list(TIMES), tips_m=[[float(x) for x in p] for p in tips],
                         rollout_wall_s=wall, first_call_wall_s=first))
        print(f"{n} segments: tip at {TIMES[-1]} s {np.round(tips[-1], 8)} m; {TIMES[-1]} s simulated in "
              f"{wall:.3f} s ({first:.1f} s with JAX's compilation)", flush=True)
    out = dict(source=f"soromox {version('soromox')} (jax {version('jax')}), benchmarks/soromox_pcs_dynamics.py",
               date=datetime.date.today().isoformat(),
               machine=f"{platform.machine()}, Python {platform.python_version()}, load {os.getloadavg()[0]:.2f}",
               model=dict(length_m=LENGTH, radius_m=RADIUS, youngs_modulus_pa=E, shear_modulus_pa=G,
                          density_kg_m3=DENSITY, gravity_m_s2=[0.0, 0.0, -9.81], strains="all six",
                          shear_stiffness="G A", solver="Tsit5", dt_s=DT),
               results=rows)
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    with open(OUT, "w") as f:
        json.dump(out, f, indent=1)
    print(f"written: {os.path.relpath(OUT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
