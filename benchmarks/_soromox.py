"""What the SoRoMoX reference scripts share (soromox_gvs.py, soromox_pcs_dynamics.py,
soromox_gvs_dynamics.py): JAX in double precision, the benchmark cantilever's data and links, a
release from rest, and the reference file they write.
Runs in SoRoMoX's own virtual environment (see either script)."""

import datetime
import json
import os
import platform
import time
from importlib.metadata import version

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
from soromox.systems.components import LinkSpec  # noqa: E402
from soromox.systems.system_state import SystemState  # noqa: E402

LENGTH, RADIUS, E, DENSITY = 0.5, 0.01, 1.0e6, 1000.0      # m, m, Pa, kg/m^3
G = E / 3                                                  # Pa: Poisson 0.5
GRAVITY = (0.0, 0.0, -9.81)                                # m/s^2
BASE_POSE = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)            # along +x: identity (quaternion x, y, z, w first)
DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "test", "data")


def link(length):
    """A straight, solid circular link of the cantilever, of ``length`` [m]
    (shear stiffness G A: SoRoMoX applies no shear factor)."""
    return LinkSpec.circular(length=length, radius=RADIUS, density=DENSITY, reference_strain=[0, 0, 0, 1, 0, 0],
                             young_modulus=E, shear_modulus=G)


def write_reference(name, script, rows, **model):
    """Write ``test/data/<name>`` (JSON): SoRoMoX's and JAX's versions, the
    script, date, machine and load, the cantilever's data plus ``model``,
    and ``rows``; print its path."""
    out = dict(source=f"soromox {version('soromox')} (jax {version('jax')}), benchmarks/{script}",
               date=datetime.date.today().isoformat(),
               machine=f"{platform.machine()}, Python {platform.python_version()}, load {os.getloadavg()[0]:.2f}",
               model=dict(length_m=LENGTH, radius_m=RADIUS, youngs_modulus_pa=E, shear_modulus_pa=G,
                          density_kg_m3=DENSITY, gravity_m_s2=list(GRAVITY), strains="all six",
                          shear_stiffness="G A", **model),
               results=rows)
    path = os.path.join(DATA, name)
    os.makedirs(DATA, exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"written: {os.path.relpath(path)}")


def release(rob, times, dt, runs):
    """The robot ``rob`` released from rest in its reference shape and
    rolled out to ``times[-1]`` by SoRoMoX's default solver at the fixed
    step ``dt`` [s], ``runs`` times: (tip positions [m] at ``times``, the
    wall time [s] of each run; the first includes JAX's compilation)."""
    nq = rob.num_coordinates
    start = SystemState(t=jnp.array(0.0), y=jnp.zeros(2 * nq))
    walls = []
    for _ in range(runs):
        t = time.perf_counter()
        out = rob.rollout_to(start, t1=times[-1], solver_dt=dt, save_ts=jnp.array(times))
        jax.block_until_ready(out.y)
        walls.append(time.perf_counter() - t)
    tips = [np.asarray(rob.forward_kinematics(out.y[k, :nq], jnp.array(LENGTH)))[:3, 3] for k in range(len(times))]
    return tips, walls
