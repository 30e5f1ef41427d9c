"""The statics of a classic model for the tests, through the one solver of
every robot: :func:`constrained.solve_equilibrium` on the model's
mechanism (:func:`mechanism.from_robot_model`) and
:func:`outputs.state_outputs`, with the fields the tests read (the rod's
own statics front end is gone: this is not a second solver, only the
shape of the answer the tests were written against)."""

from dataclasses import dataclass

import numpy as np

from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.solve.constrained import free_problem, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs


@dataclass
class Statics:
    q: np.ndarray
    strains: np.ndarray           # (n_sections, 6)
    tip_pose: np.ndarray          # 4x4 world
    base_wrench_world: np.ndarray  # the support's reaction [f; m], world axes, about the base origin
    iterations: int
    residual: float
    stable: bool
    tangent: object
    equilibrium: object


def mechanism(model):
    """The model's mechanism (made once per model)."""
    return from_robot_model(model)


def solve_statics(model, actuation=None, loads=None, q_init=None, **options):
    """The equilibrium of a classic model under actuation (dict or vector)
    and :class:`loads.Loads`; ``options``: :func:`solve_equilibrium`'s."""
    mech = mechanism(model)
    eq = solve_equilibrium(mech, actuation, loads=loads, q_init=q_init, **options)
    out = state_outputs(mech, eq.q, eq.lam, eq.inputs)
    return Statics(eq.q, model.strains(eq.q), out.frames["tip"], out.base_wrench, eq.iterations, eq.residual,
                   eq.stable, eq.tangent, eq)


def problem(model, u, loads):
    """The compiled :class:`equilibrium.Problem` of a classic model under
    inputs u and :class:`loads.Loads` (:func:`constrained.free_problem`)."""
    mech = mechanism(model)
    return free_problem(mech, make_inputs(mech, u, loads=loads))
