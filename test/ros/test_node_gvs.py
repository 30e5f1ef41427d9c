"""The twin node on a robot with variable-strain segments
(config/robots/gvs_arm.yaml: Legendre order 2 in each of three segments;
and the same with the fourth-order step, ``magnus: 4``, on 3 sections a
segment), in a second process, this test process its client over real
rclpy. The published strains are the core's equilibrium in the basis's
coordinates, and they lie on the basis; in dynamic mode a tendon command
bends the arm and it settles there. Every wait is for a condition with a
timeout."""

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from soft_twin.client import start_twin, stop_twin  # noqa: E402
from soft_twin.config import resolve_robot_file  # noqa: E402
from soft_twin_core.robot.mechanism import load_mechanism  # noqa: E402
from soft_twin_core.solve.constrained import solve_equilibrium  # noqa: E402

pytestmark = pytest.mark.ros

NAMES = ["tendon_y_pos", "tendon_y_neg", "tendon_z_pos", "tendon_z_neg"]


@pytest.fixture(scope="module")
def robots(tmp_path_factory):
    """{name: (the file the node loads, its mechanism)}: the GVS arm, and
    the same arm with ``magnus: 4`` on 3 sections a segment."""
    import yaml
    from soft_twin_core.robot.model import read_yaml_file
    path = resolve_robot_file("gvs_arm")
    d = read_yaml_file(path)
    for seg in d["segments"]:
        seg["sections"] = 3
        seg["strain_basis"]["magnus"] = 4
    fourth = tmp_path_factory.mktemp("robots") / "gvs_arm_magnus4.yaml"
    fourth.write_text(yaml.safe_dump(d))
    return {"gvs_arm": ("gvs_arm", load_mechanism(path)),
            "magnus4": (str(fourth), load_mechanism(fourth))}


def _q(mech, strains_msg):
    """q (nv,) from the Strains message (per section, the six strains; the free modes kept)."""
    xi = np.reshape(strains_msg.strains, (-1, 6))
    return np.concatenate([xi[k, mech.tree.joints[j].section.modes] for k, j in enumerate(mech.members[0].joints)])


@pytest.mark.parametrize("robot, mode", [("gvs_arm", "quasi_static"), ("gvs_arm", "dynamic"),
                                         ("magnus4", "dynamic")])
def test_the_node_runs_the_gvs_arm(tmp_path, robots, robot, mode):
    source, mech = robots[robot]
    assert bool(mech.tree.elastic_fields) == (robot == "magnus4")
    proc, c = start_twin(f"twin_gvs_{robot}_{mode}", ["-p", f"mode:={mode}", "-p", f"robot_description_file:={source}"],
                         tmp_path / "node.log", timeout=120.0)
    try:
        u = [3.0, 0.0, 1.5, 0.0]
        ref = solve_equilibrium(mech, u).q
        stamp = c.send_actuation(NAMES, u)
        if mode == "quasi_static":
            assert c.wait_until(lambda: c.state_after(stamp), 10.0), "command never applied"
            _, strains = c.state_after(stamp)
            q = _q(mech, strains)
            assert np.abs(q - ref).max() < 1e-8
        else:                       # the arm swings, then rests at the equilibrium
            def settled():
                s = c.applied(stamp)
                return s is not None and np.abs(_q(mech, s) - ref).max() < 1e-3
            assert c.wait_until(settled, 60.0), "the arm never settled at the equilibrium"
            q = _q(mech, c.strains)
        B = mech.basis
        z = np.linalg.lstsq(B, q - mech.tree.q0, rcond=None)[0]
        assert np.abs(B @ z - (q - mech.tree.q0)).max() < 1e-9           # on the basis
        assert np.abs(q - mech.tree.q0).max() > 0.1                        # and bent
    finally:
        stop_twin(proc, c)
