"""The node's parameters: names, defaults, descriptions and validation
(ROS-free; the node declares them from :data:`PARAMETERS`).

:func:`config_from_values` turns a {name: value} dict into a validated,
immutable :class:`NodeConfig`; :func:`load_robot` resolves and loads the
robot description it names. Both raise :class:`ConfigError` with a reason a
user can act on.
"""

from dataclasses import dataclass
import difflib
import math
import os
from pathlib import Path
import sys
import warnings

from soft_twin_core.limits import MAX_FILE_BYTES, PlausibilityWarning, load_yaml_text, read_text
from soft_twin_core.robot.model import ModelError, model_from_dict, robot_mapping
from soft_twin_core.robot.obstacles import check_unique_names, obstacles_from_list

from soft_twin_core.text import clip, short_list

DEFAULT_ROBOT = "tendon_arm.yaml"
MODES = ("dynamic", "quasi_static")


class ConfigError(ValueError):
    """An invalid parameter value; the message says which and why."""


# name: (default, description). Units in the descriptions; README mirrors them.
PARAMETERS = {
    "robot_description_file": (
        "", "Robot description YAML (see config/robots/). Empty: the default robot "
            "config/robots/tendon_arm.yaml. Relative paths are looked up in the working directory, "
            "then in the package (source checkout or share/soft_twin), then in its config/robots/."),
    "robot_description": (
        "", "Inline robot description (YAML text, same schema as the files); overrides "
            "robot_description_file when non-empty."),
    "sections_per_segment": (
        0, "If > 0, every segment of the description is split into this many PCS sections."),
    "actuator_names": (
        None, "Expected actuator names (string array, any order). Unset: the robot's. Otherwise they "
              "must be exactly the robot's actuators; this order is used for commands without names."),
    "mode": (
        "dynamic", "'dynamic': integrate the dynamics in real time; 'quasi_static': solve the "
                   "static equilibrium for each new input (warm-started)."),
    "step_rate_hz": (
        200.0, "Dynamic mode: integration steps per second of wall time; the step is "
               "dt = 1/step_rate_hz of twin time (Hz, in (0, 2000])."),
    "time_scale": (
        1.0, "Dynamic mode: seconds of twin time per second of wall time (slow motion below 1, e.g. 0.1 "
             "runs the twin ten times slower than real time; in (0, 10]). The step dt is unchanged: the "
             "steps come every dt / time_scale of wall time."),
    "step_on_command": (
        True, "Dynamic mode: a new command (or tip wrench) starts the next step at once instead of "
              "at the next timer tick, so twin time may lead wall time by up to one step; the step "
              "rate is unchanged. Cuts the command-to-state latency by up to one step period. Applies "
              "to inputs arriving at most at the step rate; faster streams are sampled by the timer."),
    "publish_every_n_steps": (
        1, "Dynamic mode: publish the state topics every n-th step (integer >= 1)."),
    "republish_rate_hz": (
        10.0, "Quasi-static mode: rate at which the unchanged state is re-published (Hz, > 0); "
              "each new equilibrium is published at once."),
    "wrench_rate_hz": (
        20.0, "Dynamic mode: rate of the tip and base wrench computation and topics (Hz, > 0; "
              "each costs about one step). Quasi-static: with every equilibrium."),
    "marker_rate_hz": (
        20.0, "Rate of the RViz MarkerArray (Hz, >= 0; 0 = off); only built when subscribed."),
    "diagnostics_rate_hz": (
        1.0, "Rate of the /diagnostics status (Hz, > 0); its statistics cover one period."),
    "base_frame": (
        "base_link", "Frame id of the robot's base (the robot description's world frame); "
                     "stamps every output except the tip wrench."),
    "tip_frame": (
        "tip_link", "Frame id of the tip cross-section (x along the backbone tangent)."),
    "backbone_points_per_section": (
        10, "Backbone samples per section (integer in 1..200); the tip is added."),
    "integrator_theta": (
        0.5, "Dynamic mode: theta of the implicit integrator, in [0.5, 1] (0.5: midpoint rule, "
             "2nd order, no numerical damping; 1: implicit Euler, damps stiff modes)."),
    "integrator_tolerance": (
        1e-4, "Dynamic mode: Newton tolerance of a step (relative to the largest strain rate, in (0, 1e-3])."),
    "max_catchup_steps": (
        4, "Dynamic mode: after a late tick, up to this many steps are taken at once to keep twin "
           "time on wall time; a larger backlog is dropped (counted). Integer >= 1."),
    "max_tip_force_n": (
        1.0e3, "Largest tip force |f| accepted on ~/tip_wrench_command and by statics_query (N, > 0); "
               "a larger one is rejected (over_limit)."),
    "max_tip_torque_nm": (
        1.0e2, "Largest tip moment |m| accepted on ~/tip_wrench_command and by statics_query (N m, > 0); "
               "a larger one is rejected (over_limit)."),
    "plan_output_topic": (
        "~/planned_actuation", "Topic (ActuationCommand) on which ~/plan_path executes a plan: one command "
                               "per sample at its time, for the real robot; the twin follows the same "
                               "commands through ~/actuation."),
    "plan_joint_output_topic": (
        "~/planned_joint_commands", "Topic (sensor_msgs/JointState, positions) on which ~/plan_path executes "
                                    "an articulated robot's joint commands: one per sample at its time, for "
                                    "the real robot; the twin follows them through ~/joint_commands."),
    # --- seeing the twin (issue 12): /tf, recording --------------------------
    "tf_rate_hz": (
        50.0, "Rate of the base, section-start and tip frames on /tf (tf2_msgs/TFMessage, children of "
              "base_frame, the tip is tip_frame; stamped like the published state they belong to). "
              "Hz, >= 0; 0 = off; at or above the state rate: every state."),
    "tf_prefix": (
        "", "Prefix of the base and section frame ids on /tf (<prefix>base, <prefix>section_<i>); "
            "empty: the node's name and a slash (soft_twin/section_1)."),
    "record_file": (
        "", "MCAP file (ROS 2 bag format) recording every topic the node publishes and every input "
            "it receives; empty: not recording. Setting it starts a new recording, '' stops it."),
    "record_max_bytes": (
        0, "Size limit of one recording file, bytes (>= 0; 0 = none): past it the file is closed "
           "(complete) and the recording goes on in <stem>_001.mcap, <stem>_002.mcap, ... "
           "Checked at each chunk (256 KiB of messages). Taken when record_file starts a recording."),
    "record_max_duration_s": (
        0.0, "Duration limit of one recording file, seconds (>= 0; 0 = none): rotates like "
             "record_max_bytes. Taken when record_file starts a recording."),
    "live_view_port": (
        0, "Port of the live 3D view in the browser (http://127.0.0.1:<port>, viser; works offline); "
           "0: off. Integer in 0..65535."),
    # --- contact (issue 27) ------------------------------------------------------
    "obstacles_file": (
        "", "YAML file whose 'obstacles' list (the robot files' schema, base frame) adds obstacles to "
            "the robot file's; empty: none. Setting it rebuilds the twin (state reset); ~/obstacles "
            "adds, moves and removes obstacles at run time."),
}


@dataclass(frozen=True)
class NodeConfig:
    robot_description_file: str
    robot_description: str
    sections_per_segment: int
    actuator_names: tuple
    mode: str
    step_rate_hz: float
    step_on_command: bool
    publish_every_n_steps: int
    republish_rate_hz: float
    wrench_rate_hz: float
    marker_rate_hz: float
    diagnostics_rate_hz: float
    base_frame: str
    tip_frame: str
    backbone_points_per_section: int
    integrator_theta: float
    integrator_tolerance: float
    max_catchup_steps: int
    max_tip_force_n: float
    max_tip_torque_nm: float
    plan_output_topic: str
    plan_joint_output_topic: str = "~/planned_joint_commands"
    # seeing the twin (issue 12)
    tf_rate_hz: float = 50.0
    tf_prefix: str = ""
    record_file: str = ""
    record_max_bytes: int = 0
    record_max_duration_s: float = 0.0
    live_view_port: int = 0
    obstacles_file: str = ""
    time_scale: float = 1.0          # twin seconds per wall second (issue 31: slow motion)

    @property
    def dt(self):
        return 1.0 / self.step_rate_hz

    @property
    def wall_dt(self):
        """Wall time [s] between dynamic steps: dt / time_scale."""
        return self.dt / self.time_scale

    @property
    def robot_key(self):
        """What identifies the robot: a change rebuilds the twin."""
        return (self.robot_description_file, self.robot_description, self.sections_per_segment,
                self.obstacles_file)


# ----------------------------------------------------------------------------
# validators: value -> converted value, or ConfigError
# ----------------------------------------------------------------------------

def _number(name, v, lo=None, hi=None, lo_open=False, hi_open=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{name}: expected a finite number, got {clip(repr(v))}")
    v = float(v)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ConfigError(f"{name}: must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ConfigError(f"{name}: must be {'<' if hi_open else '<='} {hi:g}, got {v:g}")
    return v


def _integer(name, v, lo=None, hi=None):
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(f"{name}: expected an integer, got {clip(repr(v))}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"in {lo}..{hi}" if hi is not None else f">= {lo}"
        raise ConfigError(f"{name}: must be {rng}, got {v}")
    return v


def _boolean(name, v):
    if not isinstance(v, bool):
        raise ConfigError(f"{name}: expected true or false, got {clip(repr(v))}")
    return v


def _string(name, v):
    if not isinstance(v, str):
        raise ConfigError(f"{name}: expected a string, got {clip(repr(v))}")
    return v


def _topic(name, v):
    v = _string(name, v).strip()
    ok = bool(v) and all(c.isalnum() or c in "_/~{}" for c in v) and "//" not in v and not v.endswith("/")
    if not ok or v[0].isdigit():
        raise ConfigError(f"{name}: expected a ROS topic name (letters, digits, _ / ~), got {clip(repr(v))}")
    return v


def _frame(name, v):
    v = _string(name, v).strip()
    if not v or any(c.isspace() for c in v):
        raise ConfigError(f"{name}: expected a non-empty frame id without spaces, got {clip(repr(v))}")
    return v


def _choice(name, v, choices):
    if _string(name, v) not in choices:
        raise ConfigError(f"{name}: expected one of {list(choices)}, got {clip(repr(v))}")
    return v


def _names(name, v):
    if v is None:
        return ()
    if isinstance(v, str) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{name}: expected a list of strings, got {clip(repr(v))}")
    out = tuple(x for x in v if x != "")
    if len(set(out)) != len(out):
        raise ConfigError(f"{name}: names repeated in {short_list(out)}")
    return out


VALIDATORS = {
    "robot_description_file": _string,
    "robot_description": _string,
    "sections_per_segment": lambda n, v: _integer(n, v, 0, 500),
    "actuator_names": _names,
    "mode": lambda n, v: _choice(n, v, MODES),
    "step_rate_hz": lambda n, v: _number(n, v, 0.0, 2000.0, lo_open=True),
    "time_scale": lambda n, v: _number(n, v, 0.0, 10.0, lo_open=True),
    "step_on_command": lambda n, v: _boolean(n, v),
    "publish_every_n_steps": lambda n, v: _integer(n, v, 1, 10000),
    "republish_rate_hz": lambda n, v: _number(n, v, 0.0, 1000.0, lo_open=True),
    "wrench_rate_hz": lambda n, v: _number(n, v, 0.0, 2000.0, lo_open=True),
    "marker_rate_hz": lambda n, v: _number(n, v, 0.0, 1000.0),
    "diagnostics_rate_hz": lambda n, v: _number(n, v, 0.0, 100.0, lo_open=True),
    "base_frame": _frame,
    "tip_frame": _frame,
    "backbone_points_per_section": lambda n, v: _integer(n, v, 1, 200),
    "integrator_theta": lambda n, v: _number(n, v, 0.5, 1.0),
    "integrator_tolerance": lambda n, v: _number(n, v, 0.0, 1e-3, lo_open=True),
    "max_catchup_steps": lambda n, v: _integer(n, v, 1, 1000),
    "max_tip_force_n": lambda n, v: _number(n, v, 0.0, lo_open=True),
    "max_tip_torque_nm": lambda n, v: _number(n, v, 0.0, lo_open=True),
    "plan_output_topic": lambda n, v: _topic(n, v),
    "plan_joint_output_topic": lambda n, v: _topic(n, v),
    # seeing the twin (issue 12)
    "tf_rate_hz": lambda n, v: _number(n, v, 0.0, 2000.0),
    "tf_prefix": lambda n, v: _tf_prefix(n, v),
    "record_file": lambda n, v: _record_file(n, v),
    "record_max_bytes": lambda n, v: _integer(n, v, 0),
    "record_max_duration_s": lambda n, v: _number(n, v, 0.0, 1e9),
    "live_view_port": lambda n, v: _integer(n, v, 0, 65535),
    "obstacles_file": lambda n, v: _string(n, v).strip(),
}


def _tf_prefix(name, v):
    v = _string(name, v)
    if any(c.isspace() for c in v) or v.startswith("/"):
        raise ConfigError(f"{name}: expected a frame id prefix without spaces or a leading '/', got {clip(repr(v))}")
    return v


def _record_file(name, v):
    v = _string(name, v).strip()
    if v and not v.endswith(".mcap"):
        raise ConfigError(f"{name}: expected a file name ending in .mcap (or '' for no recording), "
                          f"got {clip(repr(v))}")
    folder = os.path.dirname(os.path.abspath(v)) if v else ""
    if v and not (os.path.isdir(folder) and os.access(folder, os.W_OK)):
        raise ConfigError(f"{name}: the folder {clip(repr(folder))} does not exist or is not writable")
    return v


def validate(name, value):
    """The converted value of one parameter, or ConfigError."""
    if name not in VALIDATORS:
        raise ConfigError(f"{clip(name)}: unknown parameter")
    return VALIDATORS[name](name, value)


def config_from_values(values):
    """A validated NodeConfig from {name: value} (missing names: defaults)."""
    kw = {name: validate(name, values.get(name, default)) for name, (default, _) in PARAMETERS.items()}
    if kw["base_frame"] == kw["tip_frame"]:
        raise ConfigError(f"base_frame and tip_frame must differ, both are {clip(repr(kw['base_frame']))}")
    return NodeConfig(**kw)


# ----------------------------------------------------------------------------
# The robot description
# ----------------------------------------------------------------------------

def package_roots():
    """Folders holding the package's config/: the source checkout this module
    lives in, the ament index share folder, and <sys.prefix>/share/soft_twin."""
    roots = [Path(__file__).resolve().parents[1]]
    try:
        from ament_index_python.packages import get_package_share_directory
        roots.append(Path(get_package_share_directory("soft_twin")))
    except Exception:  # not on an ament index: fine, try the prefix
        pass
    roots.append(Path(sys.prefix) / "share" / "soft_twin")
    out = []
    for r in roots:
        if (r / "config").is_dir() and r not in out:
            out.append(r)
    return out


def resolve_robot_file(name):
    """The path of a robot description file (see PARAMETERS)."""
    name = name.strip() or DEFAULT_ROBOT
    p = Path(os.path.expanduser(name))
    if p.is_absolute():
        if p.is_file():
            return p
        raise ConfigError(f"robot_description_file: {clip(p)} does not exist")
    tried = [Path.cwd() / p]
    for root in package_roots():
        tried += [root / p, root / "config" / "robots" / p]
        if not p.suffix:
            tried.append(root / "config" / "robots" / (name + ".yaml"))
    for c in tried:
        if c.is_file():
            return c.resolve()
    raise ConfigError(f"robot_description_file: {clip(repr(name))} not found (looked in "
                      f"{clip(', '.join(str(c.parent) for c in tried), 600)})")


@dataclass(frozen=True)
class Robot:
    model: object
    description: dict
    source: str           # file path or "inline"

    sections_per_segment: int = 0
    mechanism: object = None      # soft_twin_core.robot.mechanism.Mechanism of a tree robot file, else None
    warnings: tuple = ()          # plausibility warnings of the robot file (the node logs them)
    mech: object = None           # the Mechanism of any robot file (a classic rod: one member, "backbone")
    obstacles: tuple = ()         # what the members touch at start: the robot file's, then obstacles_file's

    @property
    def articulated(self):
        """A tree robot file (classic rods keep their closed-form IK and rod planner)."""
        return self.mechanism is not None


def load_robot(cfg):
    """(Robot) from cfg.robot_description (inline YAML) or the file it names."""
    if cfg.robot_description.strip():
        text, source = cfg.robot_description, "inline robot_description"
        if len(text) > MAX_FILE_BYTES:
            raise ConfigError(f"robot_description: {len(text)} characters exceeds the limit of {MAX_FILE_BYTES} "
                              f"(soft_twin_core.limits)")
    else:
        path = resolve_robot_file(cfg.robot_description_file)
        # size and encoding (a binary file) checked before parsing: soft_twin_core.limits
        text = read_text(path, ConfigError, "robot_description_file:")
        source = str(path)
    try:
        d = load_yaml_text(text, clip(source), ConfigError)
    except ConfigError as e:
        raise ConfigError(clip(e, 400)) from None
    from soft_twin_core.robot.mechanism import is_tree_file, mechanism_from_dict
    mech = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PlausibilityWarning)
        try:
            mapping = robot_mapping(d, "robot description")
            if is_tree_file(mapping):
                if cfg.sections_per_segment:
                    raise ConfigError(f"sections_per_segment: {source} is an articulated robot (tree schema): "
                                      f"its section counts come from the file; leave sections_per_segment at 0")
                model = mech = mechanism_from_dict(mapping)
            else:
                model = model_from_dict(mapping, cfg.sections_per_segment or None)
        except ModelError as e:
            raise ConfigError(f"{clip(source)}: {clip(e, 400)}") from None
    found = tuple(f"{clip(source)}: {w.message}" for w in caught if issubclass(w.category, PlausibilityWarning))
    if cfg.actuator_names and set(cfg.actuator_names) != set(model.actuator_names):
        raise ConfigError(f"actuator_names {short_list(cfg.actuator_names)} do not match the actuators of "
                          f"{source}: {short_list(model.actuator_names)}")
    if mech is None:
        from soft_twin_core.robot.mechanism import from_robot_model
        one = from_robot_model(model, mapping)
    else:
        one = mech
    try:
        obstacles = check_unique_names(one.obstacles + load_obstacles(cfg.obstacles_file),
                                       "obstacles (the robot file's and obstacles_file's)")
    except ModelError as e:
        raise ConfigError(clip(e, 400)) from None
    return Robot(model, d, source, cfg.sections_per_segment, mech, found, one, obstacles)


def load_obstacles(name):
    """The obstacles of an obstacles file (its ``obstacles`` list), () for
    ''; ConfigError naming the file and the bad field."""
    if not name:
        return ()
    path = Path(os.path.expanduser(name))
    if not path.is_file():
        raise ConfigError(f"obstacles_file: {clip(repr(name))} does not exist")
    d = load_yaml_text(read_text(path, ConfigError, "obstacles_file:"), clip(str(path)), ConfigError)
    if not isinstance(d, dict) or set(d) - {"obstacles"}:
        raise ConfigError(f"obstacles_file: {clip(str(path))}: expected a mapping with one key, 'obstacles' "
                          f"(a list), got {clip(repr(d if not isinstance(d, dict) else sorted(d)))}")
    try:
        return obstacles_from_list(d.get("obstacles"), "obstacles", str(path.parent))
    except ModelError as e:
        raise ConfigError(f"obstacles_file: {clip(str(path))}: {clip(e, 400)}") from None


# parameters rclpy declares itself (not ours, not unknown)
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")


def coerced(name, value):
    """An integer given for one of our float parameters, as that float."""
    default = PARAMETERS[name][0] if name in PARAMETERS else None
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def unknown_parameters_message(names):
    hints = []
    for n in names[:5]:
        near = difflib.get_close_matches(n, list(PARAMETERS) + list(ROS_PARAMETERS), n=1)
        if near:
            hints.append(f"{clip(n, 60)!r} -> {near[0]!r}?")
    return (f"unknown parameter(s) {short_list(names)}: this node has no such parameter"
            + (f" (did you mean {', '.join(hints)})" if hints else "")
            + f"; its parameters: {', '.join(PARAMETERS)}")
