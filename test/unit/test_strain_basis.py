"""Variable-strain statics by a global Legendre strain basis
(soft_twin_core.solve.strain_basis, issue 28): the basis's columns are the
Legendre polynomials at the sections' midpoints; with the identity as basis
the reduced solve is the engine's own; a transverse tip force on the
benchmark cantilever converges spectrally in the basis order to the
backbone's own PCS solution, far faster per coordinate than PCS sections."""

import numpy as np
import pytest

from soft_twin_core.engine.loads import Loads, PointLoad
from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
from soft_twin_core.solve.constrained import free_problem, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs
from soft_twin_core.solve.strain_basis import legendre_basis, solve_reduced

L = 0.5
TIP_FORCE = Loads(point=(PointLoad(L, (0.0, 0.0, -0.05, 0.0, 0.0, 0.0)),), gravity=False)


def _arm(n):
    return from_robot_model(model_from_dict(benchmark_cantilever_dict(n, "bending", length=L)))


def _tip(mech, q):
    return state_outputs(mech, q, np.zeros(0), make_inputs(mech, loads=TIP_FORCE)).frames["tip"][:3, 3]


def test_the_basis_columns_are_legendre_polynomials_at_the_midpoints():
    mech = _arm(8)
    B = legendre_basis(mech, 3)
    assert B.shape == (mech.tree.nv, 2 * 4)                       # two bending modes, orders 0..3
    mid = (np.arange(8) + 0.5) / 8 * 2 - 1
    P3 = 0.5 * (5 * mid ** 3 - 3 * mid)
    assert np.allclose(B[1::2, 4 + 3], P3, atol=1e-15) and np.allclose(B[0::2, 4 + 3], 0.0)   # mode 1, order 3
    assert np.allclose(B[0::2, 0], 1.0) and np.linalg.matrix_rank(B) == 8
    with pytest.raises(ValueError, match="order: expected an integer >= 0"):
        legendre_basis(mech, -1)
    with pytest.raises(ValueError, match="rigid joints"):
        legendre_basis(load_mechanism("pan_tilt_arm"), 2)


def test_with_the_identity_as_basis_the_reduced_solve_is_the_engines():
    mech = _arm(10)
    pb = free_problem(mech, make_inputs(mech, loads=TIP_FORCE))
    q, z, _ = solve_reduced(pb, np.eye(mech.tree.nv), mech.tree.q0)
    q_full = solve_equilibrium(mech, loads=TIP_FORCE).q
    assert np.abs(q - q_full).max() < 1e-9 * np.abs(q_full).max()
    assert np.array_equal(z, q - mech.tree.q0)


def test_a_tip_force_converges_spectrally_in_the_basis_order():
    """Tip error / L against the 64-section backbone's own solution: orders
    0..3 (2 to 8 coordinates) fall by more than 10x an order up to order 2
    (measured 9.9e-2, 4.6e-4, 4.5e-6, 1.0e-6); order 2 (6 coordinates) is
    75x better than PCS with 16 sections (32 coordinates: 3.4e-4)."""
    back = _arm(64)
    pb = free_problem(back, make_inputs(back, loads=TIP_FORCE))
    p_ref = _tip(back, solve_equilibrium(back, loads=TIP_FORCE).q)
    errs = []
    for p in range(4):
        q, _, _ = solve_reduced(pb, legendre_basis(back, p), back.tree.q0, load_steps=2)
        errs.append(np.linalg.norm(_tip(back, q) - p_ref) / L)
    assert errs[0] > 0.05 and errs[1] < errs[0] / 10 and errs[2] < errs[1] / 10, errs
    pcs16 = _arm(16)
    e16 = np.linalg.norm(_tip(pcs16, solve_equilibrium(pcs16, loads=TIP_FORCE).q) - p_ref) / L
    assert errs[2] < e16 / 50, (errs, e16)
