"""Resource bounds on every size an input file can ask for (issue 25, item
7): sections, time steps, output samples, path samples, study cases,
nesting depth, file size and encoding. Each is refused BEFORE anything is
allocated, with an error naming the field, the value and the limit; the CLI
exits 2 with it on stderr (no traceback). Before the fix these were
_ArrayMemoryError (262 TiB, 373 GiB), RecursionError and
UnicodeDecodeError tracebacks, and a study of 1e8 samples validated for
minutes."""
import copy
import os
import subprocess
import sys

import pytest
import yaml

from soft_twin_core import limits
from soft_twin_core.robot.model import ModelError, load_model, model_from_dict, read_yaml_file

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
ROBOTS = os.path.join(ROOT, "config", "robots")


def _cli(*args, timeout=120):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "soft_twin_core.cli", *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=timeout)


def _assert_exit2(p, *needles):
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    assert "Traceback" not in p.stderr, p.stderr[-2000:]
    for n in needles:
        assert n in p.stderr, (n, p.stderr[-2000:])


def _robot(name="tendon_arm"):
    with open(os.path.join(ROBOTS, name + ".yaml")) as fh:
        return yaml.safe_load(fh)


def _write(tmp_path, name, doc):
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return str(p)


# ----------------------------------------------------------------------------
# robot files: sections
# ----------------------------------------------------------------------------

def test_sections_over_the_limit_name_the_field_value_and_limit():
    d = _robot()
    d["segments"][0]["sections"] = 1000000
    with pytest.raises(ModelError) as e:
        model_from_dict(d)
    assert str(e.value).startswith(f"segments[0].sections: 1000000 exceeds the limit of "
                                   f"{limits.MAX_SECTIONS_PER_SEGMENT}")
    # the total over segments, each under the per-segment limit
    d = _robot()
    for s in d["segments"]:
        s["sections"] = limits.MAX_SECTIONS_PER_SEGMENT
    with pytest.raises(ModelError, match=f"total sections.*exceeds the limit of {limits.MAX_SECTIONS_TOTAL}"):
        model_from_dict(d)
    # the override (--sections, sections_per_segment)
    with pytest.raises(ModelError, match="sections per segment.*exceeds the limit"):
        model_from_dict(_robot(), n_sections_override=limits.MAX_SECTIONS_PER_SEGMENT + 1)
    # at the limit it is accepted (a bound, not a ban)
    d = _robot()
    d["segments"] = d["segments"][:1]
    d["segments"][0]["sections"] = 200
    d["actuators"] = []
    assert model_from_dict(d).n_sections == 200


def test_sections_of_a_tree_robot_are_bounded_over_all_members():
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    d = _robot("soft_gripper")
    members = [b for b in d["bodies"] if b.get("type") == "member"]
    assert len(members) >= 3
    d1 = copy.deepcopy(d)
    [b for b in d1["bodies"] if b.get("type") == "member"][0]["segments"][0]["sections"] = 1000000
    with pytest.raises(ModelError, match=r"segments\[0\]\.sections: 1000000 exceeds the limit"):
        mechanism_from_dict(d1, ROBOTS)
    for m in [b for b in d["bodies"] if b.get("type") == "member"]:
        for s in m["segments"]:
            s["sections"] = limits.MAX_SECTIONS_PER_SEGMENT
    with pytest.raises(ModelError, match="total sections of all members"):
        mechanism_from_dict(d, ROBOTS)


def test_cli_sections_1e6_exits_2_naming_the_field(tmp_path):
    d = _robot()
    d["segments"][0]["sections"] = 1000000
    robot = _write(tmp_path, "big.yaml", d)
    scen = _write(tmp_path, "s.yaml", {"robot": robot, "actuation": {}})
    _assert_exit2(_cli("statics", scen), "segments[0].sections: 1000000 exceeds the limit of 500")
    _assert_exit2(_cli("statics", "tendon_arm_statics", "--sections", "100000"),
                  "sections per segment", "exceeds the limit of 500")


# ----------------------------------------------------------------------------
# any file: encoding, nesting, size
# ----------------------------------------------------------------------------

def test_binary_nested_and_oversized_files_are_refused_naming_the_file(tmp_path):
    b = tmp_path / "robot.yaml"
    b.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ModelError, match=f"robot file {b}: not a text file"):
        load_model(str(b))
    n = tmp_path / "nested.yaml"
    n.write_text("robot: tendon_arm\nloads: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ModelError, match=f"nesting deeper than {limits.MAX_NESTING} levels"):
        read_yaml_file(n)
    blocks = tmp_path / "blocks.yaml"                  # block style nests too
    blocks.write_text("".join("  " * i + f"k{i}:\n" for i in range(100)) + "  " * 100 + "x: 1\n")
    with pytest.raises(ModelError, match="nesting deeper"):
        read_yaml_file(blocks)
    big = tmp_path / "big.yaml"
    with open(big, "wb") as fh:                        # sparse: nothing is written
        fh.truncate(limits.MAX_FILE_BYTES + 1)
    with pytest.raises(ModelError, match=f"exceeds the limit of {limits.MAX_FILE_BYTES} bytes"):
        read_yaml_file(big)
    # a nesting of 20 is fine
    ok = tmp_path / "ok.yaml"
    ok.write_text("a: " + "[" * 20 + "1" + "]" * 20 + "\n")
    assert read_yaml_file(ok)["a"] is not None


def test_cli_binary_robot_and_deeply_nested_scenario_exit_2(tmp_path):
    b = tmp_path / "bin.yaml"
    b.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    scen = _write(tmp_path, "s.yaml", {"robot": str(b)})
    _assert_exit2(_cli("statics", scen), f"robot file {b}: not a text file")
    nested = tmp_path / "nested.yaml"
    nested.write_text("robot: tendon_arm\nloads: " + "[" * 5000 + "]" * 5000 + "\n")
    _assert_exit2(_cli("statics", str(nested)), f"scenario {nested}: nesting deeper than 64 levels")
    _assert_exit2(_cli("workspace", str(b)), "not a text file")


def test_node_config_refuses_a_binary_robot_file_naming_it(tmp_path):
    pytest.importorskip("rclpy", reason="soft_twin.config needs the ROS venv")
    from soft_twin.config import ConfigError, config_from_values, load_robot
    b = tmp_path / "robot.yaml"
    b.write_bytes(bytes(range(256)))
    with pytest.raises(ConfigError, match=f"robot_description_file: {b}: not a text file"):
        load_robot(config_from_values({"robot_description_file": str(b)}))
    d = _robot()
    d["segments"][0]["sections"] = 1000000
    with pytest.raises(ConfigError, match=r"segments\[0\]\.sections: 1000000 exceeds the limit"):
        load_robot(config_from_values({"robot_description": yaml.safe_dump(d)}))
    with pytest.raises(ConfigError, match="nesting deeper"):
        load_robot(config_from_values({"robot_description": "a: " + "[" * 5000 + "]" * 5000}))


# ----------------------------------------------------------------------------
# time steps and output samples
# ----------------------------------------------------------------------------

def test_time_steps_and_recorded_samples_are_bounded():
    from soft_twin_core.files.scenario import ScenarioError
    from soft_twin_core.files.timeline import check_output_size, n_steps_for
    with pytest.raises(ScenarioError, match=f"duration / dt: 1e[+]?0?9 s / 0.001 s = 1e[+]12 time steps exceeds "
                                            f"the limit of {limits.MAX_TIME_STEPS}"):
        n_steps_for(1e9, 1e-3)
    assert n_steps_for(10.0, 1e-3) == 10000
    with pytest.raises(ScenarioError, match="record_every: 1 gives .* rows .* exceeds the limit"):
        check_output_size(limits.MAX_RECORDED_ROWS, 1, 0, 10)
    check_output_size(limits.MAX_RECORDED_ROWS, 2, 0, 10)
    with pytest.raises(ScenarioError, match="backbone_every: 1 gives .* backbone points"):
        check_output_size(1_000_000, 10, 1, 1000)


def test_cli_huge_duration_and_points_exit_2():
    _assert_exit2(_cli("dynamics", "tendon_arm_dynamics", "--duration", "1e9", "--dt", "1e-3"),
                  "duration / dt", "exceeds the limit of 10000000 steps")
    _assert_exit2(_cli("statics", "tendon_arm_statics", "--points-per-section", "100000000"),
                  "--points-per-section: 100000000 exceeds the limit of 1000")


def test_plan_with_a_huge_duration_is_refused_before_sampling(tmp_path):
    from soft_twin_core.planning.plan_file import PlanFileError, plan_from_dict
    with open(os.path.join(ROOT, "config", "paths", "tendon_arm_circle.yaml")) as fh:
        d = yaml.safe_load(fh)
    d["path"]["duration"] = "1.0e9"                  # as YAML reads 1.0e9: a string
    with pytest.raises(PlanFileError, match="path.duration / path.sample_period: samples: 5e[+]10 exceeds "
                                            "the limit of 1000000"):
        plan_from_dict(copy.deepcopy(d))
    d["path"]["duration"] = 1000.0                   # 50,000 samples, but 200,000 steps of 5 ms: fine
    d["dynamics"]["dt"] = 1e-6                       # 1e9 steps
    with pytest.raises(PlanFileError, match="path.duration / dynamics.dt: time steps"):
        plan_from_dict(d)
    f = tmp_path / "plan.yaml"
    f.write_text(open(os.path.join(ROOT, "config", "paths", "tendon_arm_circle.yaml")).read()
                 .replace("duration: 4.0", "duration: 1.0e9"))
    _assert_exit2(_cli("plan", str(f), "-o", str(tmp_path / "out")), "path.duration / path.sample_period",
                  "exceeds the limit of 1000000")


# ----------------------------------------------------------------------------
# studies
# ----------------------------------------------------------------------------

def _study(**kw):
    from soft_twin_core.studies.study import study_from_dict
    d = {"name": "t", "scenario": "tendon_arm_statics",
         "parameters": [{"path": "segments[0].material.youngs_modulus", "range": [1e6, 4e6]}],
         "design": {"type": "lhs", "samples": 10, "seed": 1}}
    d.update(kw)
    return study_from_dict(d, os.path.join(ROOT, "config", "studies"))


def test_study_samples_and_grid_size_are_bounded():
    from soft_twin_core.studies.study import StudyError
    with pytest.raises(StudyError, match=f"study.design.samples: 100000000 exceeds the limit of "
                                         f"{limits.MAX_STUDY_SAMPLES}"):
        _study(design={"type": "lhs", "samples": 100000000, "seed": 1})
    with pytest.raises(StudyError, match=r"parameters\[0\]\.count: 100000000 exceeds the limit"):
        _study(parameters=[{"path": "segments[0].material.youngs_modulus", "range": [1e6, 4e6],
                            "count": 100000000}], design={"type": "grid"})
    ax = {"path": "segments[0].material.youngs_modulus", "range": [1e6, 4e6], "count": 1000}
    with pytest.raises(StudyError, match="cases of the grid .* 1000000000 exceeds the limit"):
        _study(parameters=[ax, {**ax, "path": "segments[1].material.youngs_modulus"},
                           {**ax, "path": "segments[2].material.youngs_modulus"}], design={"type": "grid"})
    assert _study().design["samples"] == 10


def test_cli_study_of_1e8_samples_exits_2(tmp_path):
    f = _write(tmp_path, "study.yaml", {
        "scenario": os.path.join(ROOT, "config", "scenarios", "tendon_arm_statics.yaml"),
        "parameters": [{"path": "segments[0].material.youngs_modulus", "range": [1e6, 4e6]}],
        "design": {"type": "lhs", "samples": 100000000}})
    _assert_exit2(_cli("study", f, "-o", str(tmp_path / "o"), "--serial"),
                  "study.design.samples: 100000000 exceeds the limit of 1000000")
    assert not (tmp_path / "o").exists()


def test_binary_urdf_and_deep_json_run_are_clear_errors(tmp_path):
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    (tmp_path / "arm.urdf").write_bytes(b"<robot \xff\xfe>")
    with pytest.raises(ModelError, match="robot.urdf: .*arm.urdf: not a text file"):
        mechanism_from_dict({"name": "r", "urdf": "arm.urdf", "bodies": []}, str(tmp_path))
    deep = tmp_path / "run.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    _assert_exit2(_cli("render", str(deep), "--plot", str(tmp_path / "figs")), "not a JSON run",
                  "the limit is 64 levels")


def test_workspace_samples_are_bounded():
    from soft_twin_core.planning.reach import parse_workspace_options
    with pytest.raises(ValueError, match=r"workspace.samples: 100000000 exceeds the limit of 1000000"):
        parse_workspace_options({"samples": 100000000}, "workspace", ValueError)
