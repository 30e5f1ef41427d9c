"""Damping of the example robots (issue 15, item 9): the first bending modes
have damping ratios of a silicone arm, and the default arm settles after a
tendon step at the node's default step (5 ms, implicit midpoint)."""
import os

import numpy as np
import pytest

from soft_twin_core.engine import loads as ld
from soft_twin_core.reference import dynamics as dy
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference import statics as st
from soft_twin_core.robot.model import load_model
from soft_twin_core.solve.constrained import MechanismSimulator
from rod_statics import mechanism, solve_statics

ROBOTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "robots")


def modal_damping(model, n_modes=2):
    """(frequencies [Hz], damping ratios) of the lowest modes of the
    equations of motion linearised at the equilibrium under gravity:
    eigenvalues of [[0, I], [-M^-1 Kt, -M^-1 D]]."""
    loads = ld.Loads()
    eq = solve_statics(model, None, loads)
    Kt = st.tangent(model, eq.q, np.zeros(len(model.actuators)), loads)
    M = dy.mass_matrix(model, eq.q)
    n = model.n_dof
    A = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-np.linalg.solve(M, Kt), -np.linalg.solve(M, model.D_q)]])
    lam = np.linalg.eigvals(A)
    lam = lam[lam.imag > 1e-9]
    lam = lam[np.argsort(np.abs(lam))][:n_modes]
    return np.abs(lam) / (2 * np.pi), -lam.real / np.abs(lam)


@pytest.mark.parametrize("name", ["tendon_arm", "pneumatic_arm", "elbow_arm"])
def test_first_bending_modes_damped_like_silicone(name):
    f, zeta = modal_damping(load_model(os.path.join(ROBOTS, name + ".yaml")))
    print(name, f, zeta)
    assert np.all(f > 0.5) and np.all(f < 5.0), f
    assert np.all(zeta >= 0.05) and np.all(zeta <= 0.16), zeta


@pytest.mark.parametrize("tendon", ["tendon_y_pos", "tendon_z_pos"])
def test_default_arm_settles_after_10N_tendon_step(tendon):
    """From rest under gravity, 10 N on one tendon, stepped like the node
    (dt = 5 ms, theta = 0.5): 2 s later the tip stays within 15 % of its
    travel from the final equilibrium, 3.5 s later within 6 %. (With the
    former viscosity, 2.0e3 Pa s, it was 50-94 % after 2 s.)"""
    model = load_model(os.path.join(ROBOTS, "tendon_arm.yaml"))
    loads = ld.Loads()
    u = {tendon: 10.0}
    q0 = solve_statics(model, None, loads).q
    q1 = solve_statics(model, u, loads).q
    p0, p1 = kin.tip_pose(model, q0)[:3, 3], kin.tip_pose(model, q1)[:3, 3]
    travel = np.linalg.norm(p1 - p0)
    assert travel > 0.1
    sim = MechanismSimulator(mechanism(model), 0.005, 0.5, q=q0, tol=1e-4, max_iterations=10)   # the node's
    err = []
    for _ in range(800):
        sim.step(u, loads=loads)
        err.append(np.linalg.norm(kin.tip_pose(model, sim.q)[:3, 3] - p1))
    err = np.array(err) / travel
    t = 0.005 * np.arange(1, 801)
    print(tendon, f"travel {travel:.3f} m, after 1 s {err[t >= 1].max():.3f}, 2 s {err[t >= 2].max():.3f}, "
          f"3.5 s {err[t >= 3.5].max():.3f} of the travel")
    assert err[t >= 2.0].max() < 0.15
    assert err[t >= 3.5].max() < 0.06
