"""The planner and the calibration on a closed chain (through the KKT
system of the constraints): the planar parallel robot with a tendon in
each rod. The frame's sensitivity to the tensions against finite
differences of full equilibrium solves, a platform position reached by
the tensions (checked by an independent equilibrium solve of the answer),
and the calibration's sensitivities through the constraint rows."""

import copy

import numpy as np
import pytest

from soft_twin_core.planning import planner as pl
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import find_file, read_yaml_file
from soft_twin_core.solve import constrained as cs


E_ROD = 2.0e9          # Pa: polymer rods (the file's steel ones bend too little under a tendon for a fit)


def _robot_dict(scale=(1.0, 1.0)):
    d = copy.deepcopy(read_yaml_file(find_file("planar_parallel_robot", "robots")))
    members = [b for b in d["bodies"] if b.get("type") == "member"]
    for b, k in zip(members, scale):
        b["actuators"] = [{"name": f"{b['name']}_tendon", "type": "tendon", "offset": [0.0, 0.0015]}]
        b["segments"][0]["material"]["youngs_modulus"] = E_ROD * k
    return d


@pytest.fixture(scope="module")
def robot():
    return mechanism_from_dict(_robot_dict())


def _platform(mech, u):
    eq = cs.solve_equilibrium(mech, actuation=u)
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.workspace import Workspace
    ref = mech.frame("platform")
    return alg.point_poses(mech.tree, Workspace(mech.tree), eq.q, [ref.joint], [ref.x])[0][:3, 3]


def test_closed_chain_sensitivity_matches_finite_differences(robot):
    s = pl.TipSolver(robot, pl.PlanOptions(frame="platform"))
    assert type(s.statics).__name__ == "_Statics" and s.n_j == 0 and s.n_u == 2     # the KKT path
    u = np.array([6.0, 2.0])
    e = s.statics.solve(u, None)
    g, S = s.frame_motion(e, u)
    h = 1e-3
    fd = np.column_stack([(_platform(robot, u + h * k) - _platform(robot, u - h * k)) / (2 * h) for k in np.eye(2)])
    assert np.abs(fd).max() > 1e-6
    assert np.abs(S[:3] - fd).max() <= 1e-6 * np.abs(fd).max()


def test_closed_chain_platform_target_reached(robot):
    s = pl.TipSolver(robot, pl.PlanOptions(frame="platform", position_weights=(1.0, 0.0, 0.0)))
    target = _platform(robot, np.array([5.0, 1.0]))
    r = s.solve(target, np.zeros(2), None)
    assert r.reached and r.position_error < 1e-3 and abs(r.pose[0, 3] - target[0]) <= 1e-6, r.status
    check = _platform(robot, r.x)
    assert abs(check[0] - target[0]) < 2e-6
    assert np.all(r.x >= 0.0)


def test_closed_chain_calibration_sensitivities():
    """The calibration's sensitivities of the rods' moduli and of a payload
    on the platform's rod end through the constraint rows against finite
    differences (steps of 1 % of each parameter's scale: the rods move
    little, and smaller steps meet the equilibrium's own tolerance; at the
    best step, 1e-4 kg, the payload's column matches to 2e-7).
    (A fit is not tested: the tendons of this clamped parallel robot move
    its platform by under a millimetre, too little to tell the two moduli
    apart at 0.1 mm of sensor noise; known loads per row, issue 29, will.)"""
    from soft_twin_core.estimation import calibration as cal
    from soft_twin_core.estimation import sensors as sn
    from test_calibration import assert_sensitivities
    sensors = [sn.PoseSensor("platform", 1e-4, 2e-3, frame="platform"), sn.marker("mk", 1e-4, member="rod2", s=0.2)]
    U = np.array([[t1, t2] for t1 in (0.0, 4.0, 10.0) for t2 in (0.0, 3.0, 8.0)])
    rec = cal.record_static_sweep(mechanism_from_dict(_robot_dict((1.2, 0.9))), sensors, U, np.random.default_rng(4))
    pb = cal.Problem(_robot_dict(), sensors, rec, ["youngs_modulus:rod1", "youngs_modulus:rod2", "payload_mass"])
    assert_sensitivities(pb, np.array([1.1 * E_ROD, 0.95 * E_ROD, 0.01]), 1e-3, step=1e-2)
