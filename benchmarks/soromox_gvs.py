"""SoRoMoX's variable-strain (GVS) cantilever statics, for the matched-basis cross-check (issue 28).

The benchmark cantilever (L = 0.5 m, r = 0.01 m, E = 1 MPa, G = E / 3,
1000 kg/m^3, along +x, gravity -z; shear stiffness G A, no correction
factor, as SoRoMoX builds it) in SoRoMoX's GVS model: every strain
component a Legendre series of order p on [0, L], p = 1 .. 5, with 8, 16
and 32 Gauss points (its Magnus steps and quadrature). The equilibrium:
SoRoMoX's ``potential_force(q) = 0`` (elastic and gravitational), solved by
scipy's Levenberg-Marquardt with JAX's Jacobian, gravity raised in 8 steps.
And without gravity, about the straight rod: the lowest six natural
frequencies [Hz] (``K x = w^2 M(0) x``, SoRoMoX's stiffness and inertia
matrices: the inertia's projection on the basis). Written: each order's
and Gauss count's tip position [m], residual and frequencies
(``test/data/soromox_gvs_cantilever.json``, which
``test/unit/test_strain_basis.py`` checks the engine's fourth-order Magnus
field against: a Galerkin solution depends on the space the basis spans,
not on how it is scaled, so Legendre order p here and there is the same
problem).

SoRoMoX needs JAX, which the project does not depend on: run this in a
virtual environment of its own (about 25 s an equilibrium, JAX's
compilation most of it):

    python3 -m venv /tmp/peers && /tmp/peers/bin/pip install soromox==0.5.0
    /tmp/peers/bin/python benchmarks/soromox_gvs.py
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import eigh
from scipy.optimize import root

from _soromox import BASE_POSE, GRAVITY, LENGTH, link, write_reference
from soromox.systems.components import JointSpec
from soromox.systems.gvs import GVS, GVSSegment, StrainBasisSpec

ALL = ["kappa_x", "kappa_y", "kappa_z", "sigma_x", "sigma_y", "sigma_z"]
ORDERS, GAUSS_POINTS, LOAD_STEPS = (1, 2, 3, 4, 5), (8, 16, 32), 8


def cantilever(order, gauss_points, g):
    """The cantilever in SoRoMoX's GVS model, along +x, gravity g [m/s^2]
    along -z."""
    seg = GVSSegment(link=link(LENGTH), joint=JointSpec.fixed(), basis=StrainBasisSpec("legendre", ALL, order),
                     num_gauss_points=gauss_points)
    return GVS.from_segments([seg], gravity=jnp.array([0.0, 0.0, -g]), base_pose=jnp.array(BASE_POSE))


def equilibrium(order, gauss_points):
    """(tip position [m], |potential force| at the solution) under gravity
    raised in LOAD_STEPS steps, each solved from the last."""
    q = None
    for k in range(1, LOAD_STEPS + 1):
        rob = cantilever(order, gauss_points, -GRAVITY[2] * k / LOAD_STEPS)
        force = rob.potential_force
        jac = jax.jacfwd(lambda x, rob=rob: rob.potential_force(x))
        q = np.zeros(rob.num_coordinates) if q is None else q
        q = root(lambda x: np.asarray(force(jnp.asarray(x))), q, jac=lambda x: np.asarray(jac(jnp.asarray(x))),
                 method="lm", options=dict(xtol=1e-15, ftol=1e-15, gtol=1e-15)).x
    residual = float(np.abs(np.asarray(force(jnp.asarray(q)))).max())
    tip = np.asarray(rob.forward_kinematics(jnp.asarray(q), jnp.array(LENGTH)))[:3, 3]
    return tip, residual


def frequencies(order, gauss_points, count=6):
    """The lowest ``count`` natural frequencies [Hz] about the straight rod,
    no gravity."""
    rob = cantilever(order, gauss_points, 0.0)
    M = np.asarray(rob.inertia_matrix(jnp.zeros(rob.num_coordinates)))
    w2 = eigh(np.asarray(rob.stiffness_matrix()), M, eigvals_only=True)[:count]
    return np.sqrt(np.maximum(w2, 0.0)) / (2 * np.pi)


def main():
    rows = []
    for order in ORDERS:
        for n in GAUSS_POINTS:
            t = time.perf_counter()
            tip, res = equilibrium(order, n)
            f = frequencies(order, n)
            rows.append(dict(order=order, gauss_points=n, tip_m=[float(x) for x in tip], residual_n=res,
                             frequencies_hz=[float(x) for x in f]))
            print(f"order {order}, {n:2d} Gauss points: tip {np.round(tip, 8)} m, residual {res:.1e} N, "
                  f"frequencies {np.round(f, 6)} Hz ({time.perf_counter() - t:.1f} s)", flush=True)
    write_reference("soromox_gvs_cantilever.json", "soromox_gvs.py", rows, basis="legendre")
    return 0


if __name__ == "__main__":
    sys.exit(main())
