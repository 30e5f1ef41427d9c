"""Physical plausibility of robot files (issue 25, item 9): impossible
geometry is an error naming the field; implausible values (a likely unit
slip) are a PlausibilityWarning naming the field and the slip, printed by
the CLI and logged by the node. Before the fix each of these robots loaded
and converged silently (exit 0). Every shipped robot and scenario stays
warning-free."""
import copy
import math
import os
import subprocess
import sys
import warnings

import pytest
import yaml

from soft_twin_core.limits import PlausibilityWarning
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import ModelError, example_files, model_from_dict

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
ROBOTS = os.path.join(ROOT, "config", "robots")


def _robot(name):
    with open(os.path.join(ROBOTS, name + ".yaml")) as fh:
        return yaml.safe_load(fh)


def _caught(fn, *args):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        fn(*args)
    return [str(x.message) for x in w if issubclass(x.category, PlausibilityWarning)]


def test_every_shipped_robot_and_scenario_is_warning_free():
    from soft_twin_core.files.scenario import load_scenario
    from soft_twin_core.robot.mechanism import load_mechanism
    robots, scenarios = example_files("robots"), example_files("scenarios")
    assert len(robots) >= 10 and len(scenarios) >= 9
    for name, path in robots.items():
        assert _caught(load_mechanism, str(path)) == [], name
    for name, path in scenarios.items():
        assert _caught(load_scenario, str(path)) == [], name


@pytest.mark.parametrize("edit, field, slip", [
    (lambda d: d["segments"][0].update(length=150), "segments[0].length: 150 m", "millimetres? 150 mm = 0.15 m"),
    (lambda d: d["segments"][1]["material"].update(youngs_modulus=1.0),
     "segments[1].material.youngs_modulus: 1 Pa", "megapascals? 1 MPa = 1e+06 Pa"),
    (lambda d: d["segments"][2]["cross_section"].update(radius=8), "segments[2].cross_section.radius: 8 m",
     "millimetres?"),
    (lambda d: d["segments"][0]["material"].update(density=1.1), "segments[0].material.density: 1.1 kg/m^3",
     "g/cm^3? 1.1 g/cm^3 = 1100 kg/m^3"),
    (lambda d: d.update(base={"position": [0, 0, 0], "rpy": [0, 90, 0]}), "robot.base.rpy: [0.0, 90.0, 0.0]",
     "degrees?"),
])
def test_unit_slips_in_a_classic_robot_warn_naming_field_and_slip(edit, field, slip):
    d = _robot("tendon_arm")
    edit(d)
    got = _caught(model_from_dict, d)
    assert len(got) == 1 and got[0].startswith(field) and slip in got[0], got


def test_unit_slips_in_a_tree_robot_warn_naming_the_body():
    d = _robot("pan_tilt_arm")
    member = next(b for b in d["bodies"] if b["type"] == "member")
    member["segments"][0]["length"] = 450.0
    link = next(b for b in d["bodies"] if b["type"] == "link" and b.get("joint", {}).get("type") == "revolute")
    link["joint"]["rpy"] = [0.0, 90.0, 0.0]
    got = _caught(mechanism_from_dict, d, ROBOTS)
    assert any(g.startswith(f"bodies[{d['bodies'].index(member)}] ({member['name']}).segments[0].length: 450 m")
               for g in got), got
    assert any(".joint.rpy: [0.0, 90.0, 0.0] has an angle over 2 pi rad; degrees?" in g for g in got), got


def test_revolute_limits_in_degrees_are_an_error():
    d = _robot("pan_tilt_arm")
    k, link = next((k, b) for k, b in enumerate(d["bodies"]) if b.get("joint", {}).get("type") == "revolute")
    link["joint"]["limits"] = [-90, 90]
    link["joint"].pop("reference", None)
    with pytest.raises(ModelError, match=r"joint.limits: \[-90, 90\] rad is beyond \+-2 pi on a revolute joint; "
                                         r"degrees\? \[-90, 90\] deg = \[-1.571, 1.571\] rad"):
        mechanism_from_dict(d, ROBOTS)
    link["joint"]["limits"] = [-math.pi, math.pi]       # a full turn either way is fine
    mechanism_from_dict(d, ROBOTS)
    link["joint"]["limits"] = [1.0, -1.0]
    with pytest.raises(ModelError, match="need lower < upper"):
        mechanism_from_dict(d, ROBOTS)


def test_a_chamber_outside_its_tube_is_an_error_and_a_tendon_outside_a_warning():
    d = _robot("pneumatic_arm")
    k, ch = next((k, a) for k, a in enumerate(d["actuators"]) if a.get("type") == "chamber")
    ok = copy.deepcopy(d)
    ch["offset"] = [9, 0]                              # mm meant, on a tube of 15 mm radius or so
    with pytest.raises(ModelError, match=rf"actuators\[{k}\] \({ch['name']}\).offset: \[9, 0\] m .* is outside the "
                                         r"cross-section of radius .* a chamber must lie inside the material"):
        model_from_dict(d)
    assert _caught(model_from_dict, ok) == []
    t = _robot("tendon_arm")
    t["actuators"][0]["offset"] = [0.02, 0.0]          # outside the 8-12 mm radius sections
    got = _caught(model_from_dict, t)
    assert len(got) == 1 and got[0].startswith("actuators[0] (tendon_y_pos).offset: [0.02, 0] m") \
        and "spacer disks" in got[0], got
    # a rectangle: each half-width
    g = _robot("soft_gripper")
    fingers = [b for b in g["bodies"] if b["type"] == "member"]
    fingers[0]["actuators"][0]["offset"] = [0.0, -0.006]      # height 0.01: |z| <= 0.005
    got = _caught(mechanism_from_dict, g, ROBOTS)
    assert any("offset: [0, -0.006] m" in x and "0.016 m x 0.01 m rectangular" in x for x in got), got


def test_duplicate_segment_names_are_rejected_with_the_name():
    d = _robot("tendon_arm")
    d["segments"][2]["name"] = d["segments"][0]["name"]
    with pytest.raises(ModelError, match=r"segments\[2\].name: 'proximal' is already used by segments\[0\]"):
        model_from_dict(d)


def _cli(*args):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "soft_twin_core.cli", *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=300)


def test_cli_prints_the_warning_on_stderr_and_still_solves(tmp_path):
    d = _robot("tendon_arm")
    d["base"] = {"position": [0, 0, 0], "rpy": [0, 0, 90]}     # meant: degrees
    robot = tmp_path / "r.yaml"
    robot.write_text(yaml.safe_dump(d))
    scen = tmp_path / "s.yaml"
    scen.write_text(yaml.safe_dump({"robot": str(robot), "actuation": {}}))
    p = _cli("statics", str(scen))
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if "warning" in ln]
    assert lines == ["soft-twin-sim: warning: robot.base.rpy: [0.0, 0.0, 90.0] has an angle over 2 pi rad; "
                     "degrees? [0.0, 0.0, 90.0] deg = [0.0, 0.0, 1.5708] rad (angles are in radians)"], p.stderr


def test_node_config_collects_the_warnings_for_the_log():
    pytest.importorskip("rclpy", reason="soft_twin.config needs the ROS venv")
    from soft_twin.config import config_from_values, load_robot
    d = _robot("tendon_arm")
    d["segments"][0]["material"]["youngs_modulus"] = 2.0
    r = load_robot(config_from_values({"robot_description": yaml.safe_dump(d)}))
    assert len(r.warnings) == 1 and "segments[0].material.youngs_modulus: 2 Pa" in r.warnings[0]
    assert load_robot(config_from_values({})).warnings == ()
