"""URDF export of the rigid part and import of a rigid URDF with soft
members mounted on it (soft_twin_core.robot.urdf)."""

import numpy as np
import pytest
import yaml

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.mechanism import load_mechanism, mechanism_from_dict
from soft_twin_core.robot.model import ModelError, find_file
from soft_twin_core.robot.urdf import bodies_from_urdf, to_urdf


def _random_state(tree, rng):
    return (tree.q0 + 0.3 * rng.standard_normal(tree.nq), rng.standard_normal(tree.nv),
            rng.standard_normal(tree.nv))


def test_round_trip_through_urdf_keeps_the_dynamics(tmp_path):
    d = yaml.safe_load(find_file("pan_tilt_arm", "robots").read_text())
    mech = mechanism_from_dict(d)
    (tmp_path / "pan_tilt.urdf").write_text(to_urdf(mech))
    arm = next(b for b in d["bodies"] if b["type"] == "member")
    again = mechanism_from_dict({"name": "again", "gravity": d["gravity"], "urdf": "pan_tilt.urdf",
                                 "bodies": [arm], "frames": d["frames"]}, str(tmp_path))
    assert again.joint_names == mech.joint_names and again.tree.nv == mech.tree.nv
    rng = np.random.default_rng(1)
    for _ in range(3):
        q, v, a = _random_state(mech.tree, rng)
        t1 = alg.rnea(mech.tree, Workspace(mech.tree), q, v, a)
        t2 = alg.rnea(again.tree, Workspace(again.tree), q, v, a)
        assert np.abs(t1 - t2).max() < 1e-12 * max(1.0, np.abs(t1).max())
    # load_mechanism resolves the urdf next to the robot file
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump({"name": "r", "urdf": "pan_tilt.urdf", "bodies": [arm]}))
    assert load_mechanism(tmp_path / "robot.yaml").tree.nv == mech.tree.nv


def test_exported_urdf_gives_pinocchio_our_rigid_dynamics():
    pin = pytest.importorskip("pinocchio")
    d = yaml.safe_load(find_file("pan_tilt_arm", "robots").read_text())
    d["bodies"] = [b for b in d["bodies"] if b["type"] == "link"]
    d.pop("frames")
    mech = mechanism_from_dict(d)
    model = pin.buildModelFromXML(to_urdf(mech))
    model.gravity.linear = np.array(d["gravity"], float)
    data = model.createData()
    rng = np.random.default_rng(2)
    for _ in range(5):
        q, v, a = (rng.uniform(-1, 1, 2) for _ in range(3))
        ours = alg.rnea(mech.tree, Workspace(mech.tree), q, v, a) - 0.05 * v      # minus the joint dampers
        ref = pin.rnea(model, data, q, v, a)
        assert np.abs(ours - ref).max() < 1e-12


def test_urdf_errors_name_the_element():
    with pytest.raises(ModelError, match="invalid XML"):
        bodies_from_urdf("<robot", "r.urdf")
    bad = ('<robot name="r"><link name="a"/><link name="b"/>'
           '<joint name="j" type="planar"><parent link="a"/><child link="b"/></joint></robot>')
    with pytest.raises(ModelError, match="joint 'j': type 'planar' is not supported"):
        bodies_from_urdf(bad, "r.urdf")
    with pytest.raises(ModelError, match="robot.urdf: .*missing.urdf"):
        mechanism_from_dict({"name": "r", "urdf": "missing.urdf", "bodies": []}, "/nonexistent")
