"""Design studies: a study file turned into cases, every case validated.

A study varies fields of a base robot and scenario (parameter axes, each
addressed by its path in the robot or scenario document), samples them
with a design (full grid, random, Latin hypercube; seeded) and says what to
compute per case (statics, dynamics, a workspace over the actuation space)
and what to record. This module reads the file, builds the cases and checks
every case's robot and scenario before anything runs; running them is
:mod:`study_dask` (on a Dask cluster) and :mod:`study_case` (one case).

Schema (YAML; SI units; paths relative to the study file)::

    name: tendon_offsets                   # optional (default: the file's stem)
    robot: tendon_arm                      # optional: robot file path or example name
                                           # (default: the scenario's robot)
    scenario: tendon_arm_statics           # optional: scenario path, example name or an
                                           # inline mapping (default: gravity only, no input)
    parameters:                            # the axes; a path is into the robot document,
                                           # or into the scenario's with the prefix scenario.
      - path: segments[0].material.youngs_modulus
        range: [1.0e6, 4.0e6]              # uniform (random, lhs); grid: `count` points
        scale: log                         # optional: log-uniform / geometric grid
      - path: actuators[0].offset[0]
        values: [0.005, 0.007, 0.009]      # grid only; any YAML values (vectors, names)
      - path: segments[2].cross_section.radius
        normal: {mean: 0.008, std: 2.0e-4} # random, lhs
      - {path: "segments[1].length", range: [-0.05, 0.05], relative: true}   # base * (1 + x)
      - {path: scenario.actuation.tendon_y_pos, range: [0.0, 5.0], count: 6}
                                           # (in {...} flow style a path with [ ] needs quotes)
    design: {type: lhs, samples: 200, seed: 1}   # grid (every combination) | random | lhs
    compute:                               # one or more of:
      statics: {points_per_section: 10}    # (or `statics: true`)
      dynamics: {duration: 3.0, dt: 0.005, theta: 0.5, record_every: 1, settling_band: 0.02}
      workspace: {samples: 200, design: lhs, seed: 0, corners: true,
                  limits: {tendon_y_pos: 10.0}, limit: 10.0}   # see workspace_map
    record: [tip_pose, base_wrench, max_stress, iterations, residual, stable,
             settling_time, max_tip_speed]   # optional, this is the default; also strains,
                                             # backbone, internal_wrenches (statics), tip_velocity,
                                             # strain_rates (dynamics): every output of the runner

A path is a chain of mapping keys and list indices, ``segments[0].material.
youngs_modulus``, ``actuators[1].offset`` (a whole vector: grid values are
then vectors), ``actuators[1].offset[0]`` (one component),
``scenario.loads[0].force[2]``. Every step but the last must exist in the
base document; the last may be a new key of an existing mapping (e.g.
``actuators[0].limit``). The robot's and scenario's own checks validate
each case (:func:`validate_cases`): a bad value is reported with the case
index and the field's path (``case 3 (segments[0].length = -0.1):
segments[0].length: must be > 0, got -0.1``).

Output column names: every parameter by its path (a vector-valued one as
``path[i]``), then ``status`` (``ok`` / ``failed``), ``error`` and the
recorded outputs prefixed by what computed them (``statics.tip_position_x``,
``dynamics.settling_time_s``, ``workspace.volume_m3``); see
:mod:`study_case`.
"""

import copy
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from soft_twin_core.errors import StudyError, CaseValidationError
from soft_twin_core.files.scenario import ScenarioError, scenario_from_dict
from soft_twin_core.files.timeline import n_steps_for
from soft_twin_core.limits import MAX_STUDY_SAMPLES, PlausibilityWarning, check_limit
from soft_twin_core.planning.reach import actuation_ranges, parse_workspace_options
from soft_twin_core.robot.model import ModelError, find_file, parse_number, read_yaml_file, robot_mapping


FORMAT_VERSION = 1
DESIGNS = ("grid", "random", "lhs")
COMPUTES = ("statics", "dynamics", "workspace")
# what ``record`` may name, per computation (see study_case)
RECORDS = {
    "statics": ("tip_pose", "base_wrench", "max_stress", "iterations", "residual", "stable", "strains",
                "backbone", "internal_wrenches"),
    "dynamics": ("tip_pose", "base_wrench", "settling_time", "max_tip_speed", "iterations", "strains",
                 "tip_velocity", "strain_rates"),
    "workspace": ("workspace",),
}
DEFAULT_RECORD = ("tip_pose", "base_wrench", "max_stress", "iterations", "residual", "stable",
                  "settling_time", "max_tip_speed", "workspace")


# ----------------------------------------------------------------------------
# Paths into documents
# ----------------------------------------------------------------------------

_TOKEN = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)|\[(\d+)\]|(\.)")


def parse_path(text):
    """``"segments[0].material.youngs_modulus"`` -> ("robot", ["segments", 0,
    "material", "youngs_modulus"]); a leading ``scenario.`` addresses the
    scenario document, a leading ``robot.`` (optional) the robot's.
    StudyError on a malformed path."""
    if not isinstance(text, str) or not text:
        raise StudyError(f"expected a path such as segments[0].length, got {text!r}")
    keys, pos, want_key = [], 0, True
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise StudyError(f"malformed path {text!r} at character {pos + 1}")
        name, index, dot = m.groups()
        if dot:
            if want_key:
                raise StudyError(f"malformed path {text!r}: empty name at character {pos + 1}")
            want_key = True
        elif name is not None:
            if not want_key:
                raise StudyError(f"malformed path {text!r}: missing '.' before {name!r}")
            keys.append(name)
            want_key = False
        else:
            if want_key and keys:
                raise StudyError(f"malformed path {text!r}: index after '.'")
            if not keys:
                raise StudyError(f"malformed path {text!r}: starts with an index")
            keys.append(int(index))
        pos = m.end()
    if want_key:
        raise StudyError(f"malformed path {text!r}: ends with '.'")
    if keys[0] == "scenario":
        doc, keys = "scenario", keys[1:]
    elif keys[0] == "robot":
        doc, keys = "robot", keys[1:]
    else:
        doc = "robot"
    if not keys:
        raise StudyError(f"path {text!r}: names a whole document, not a field")
    return doc, keys


def format_path(keys):
    out = ""
    for k in keys:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else k)
    return out


def get_path(doc, keys, where="document"):
    """The value at ``keys`` in nested dicts/lists; StudyError naming the
    first step that does not exist."""
    cur = doc
    for i, k in enumerate(keys):
        here = format_path(keys[:i]) or where
        if isinstance(k, int):
            if not isinstance(cur, list):
                raise StudyError(f"{here}: is not a list (cannot take [{k}])")
            if k >= len(cur):
                raise StudyError(f"{here}[{k}]: out of range ({here} has {len(cur)} entries)")
            cur = cur[k]
        else:
            if not isinstance(cur, dict):
                raise StudyError(f"{here}: is not a mapping (cannot take .{k})")
            if k not in cur:
                raise StudyError(f"{format_path(keys[:i + 1])}: not in the {where}")
            cur = cur[k]
    return cur


def set_path(doc, keys, value, where="document"):
    """Set ``keys`` in ``doc`` (in place) to ``value``; the last key may be
    new in an existing mapping, a list index must exist."""
    parent = get_path(doc, keys[:-1], where)
    k = keys[-1]
    if isinstance(k, int):
        if not isinstance(parent, list) or k >= len(parent):
            get_path(doc, keys, where)             # raises with the reason
        parent[k] = value
    else:
        if not isinstance(parent, dict):
            raise StudyError(f"{format_path(keys[:-1])}: is not a mapping (cannot set .{k})")
        parent[k] = value


# ----------------------------------------------------------------------------
# The study file
# ----------------------------------------------------------------------------

@dataclass
class Axis:
    """One parameter axis: ``name`` (the path as column name), ``doc``
    ("robot" or "scenario"), ``keys``; exactly one of ``values`` (grid),
    ``range`` (low, high) or ``normal`` (mean, std); ``count`` (grid points
    of a range), ``scale`` ("linear" or "log"), ``relative`` (value = base
    * (1 + x)), ``base`` (the value in the base document, or None)."""
    name: str
    doc: str
    keys: list
    values: list = None
    range: tuple = None
    normal: tuple = None
    count: int = None
    scale: str = "linear"
    relative: bool = False
    base: object = None

    def grid_values(self):
        if self.values is not None:
            return list(self.values)
        lo, hi = self.range
        if self.scale == "log":
            vals = np.geomspace(lo, hi, self.count)
        else:
            vals = np.linspace(lo, hi, self.count)
        return [self._apply(float(v)) for v in vals]

    def from_unit(self, u):
        """Values of unit-interval samples ``u`` (inverse CDF)."""
        from scipy.special import ndtri          # the standard normal's inverse CDF
        u = np.asarray(u, dtype=float)
        if self.normal is not None:
            x = self.normal[0] + self.normal[1] * ndtri(u)
        elif self.scale == "log":
            lo, hi = np.log(self.range[0]), np.log(self.range[1])
            x = np.exp(lo + u * (hi - lo))
        else:
            x = self.range[0] + u * (self.range[1] - self.range[0])
        return [self._apply(float(v)) for v in x]

    def _apply(self, x):
        return self.base * (1.0 + x) if self.relative else x


@dataclass
class Study:
    """A parsed study: base documents, axes, design, computations."""
    name: str
    source: str
    base_dir: str                 # where the scenario's relative paths resolve
    robot_doc: dict
    scenario_doc: dict            # without its ``robot`` entry
    axes: list
    design: dict                  # {type, samples, seed}
    compute: dict                 # {statics: {...}, dynamics: {...}, workspace: {...}}
    record: tuple
    fingerprint: str = field(default="")

    @property
    def parameter_names(self):
        return [a.name for a in self.axes]


def _number(v, where):
    return parse_number(v, where, StudyError)


def _int(v, where, low=1):
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise StudyError(f"{where}: expected an integer >= {low}, got {v!r}")
    return v


def _check_keys(d, allowed, where):
    if not isinstance(d, dict):
        raise StudyError(f"{where}: expected a mapping, got {d!r}")
    unknown = set(d) - set(allowed)
    if unknown:
        raise StudyError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(allowed)}")


def _load_robot_doc(ref, base_dir, where):
    p = ref if os.path.isabs(ref) else os.path.join(base_dir, ref)
    if not os.path.isfile(p):
        p = ref                     # an example robot's name
    try:
        path = find_file(p, "robots")
        return copy.deepcopy(robot_mapping(read_yaml_file(path, ModelError, "robot file"), f"robot file {path}"))
    except ModelError as e:
        raise StudyError(f"{where}: {e}") from None


def _axis(d, i, robot_doc, scenario_doc):
    where = f"parameters[{i}]"
    _check_keys(d, {"path", "values", "range", "normal", "count", "scale", "relative"}, where)
    if "path" not in d:
        raise StudyError(f"{where}.path: missing (e.g. segments[0].material.youngs_modulus)")
    try:
        doc, keys = parse_path(d["path"])
    except StudyError as e:
        raise StudyError(f"{where}.path: {e}") from None
    base_doc = robot_doc if doc == "robot" else scenario_doc
    if doc == "scenario" and keys[0] == "robot":
        raise StudyError(f"{where}.path: vary the robot's fields by their robot path "
                         f"({format_path(keys[1:]) or 'segments[0]...'}), not through scenario.robot")
    try:
        base = get_path(base_doc, keys[:-1], f"{doc} document")
        if isinstance(keys[-1], int):
            base = get_path(base_doc, keys, f"{doc} document")
        else:
            if not isinstance(base, dict):
                raise StudyError(f"{format_path(keys[:-1])}: is not a mapping")
            base = base.get(keys[-1])
    except StudyError as e:
        raise StudyError(f"{where}.path {d['path']!r}: {e}") from None
    name = ("scenario." if doc == "scenario" else "") + format_path(keys)
    kinds = [k for k in ("values", "range", "normal") if k in d]
    if len(kinds) != 1:
        raise StudyError(f"{where}: give exactly one of values, range or normal, got {kinds or 'none'}")
    ax = Axis(name, doc, keys)
    scale = d.get("scale", "linear")
    if scale not in ("linear", "log"):
        raise StudyError(f"{where}.scale: expected 'linear' or 'log', got {scale!r}")
    ax.scale = scale
    rel = d.get("relative", False)
    if not isinstance(rel, bool):
        raise StudyError(f"{where}.relative: expected true or false, got {rel!r}")
    if rel:
        if "values" in d:
            raise StudyError(f"{where}.relative: only with range or normal")
        try:
            ax.base = _number(base, f"{where}: base value of {name}")
        except StudyError:
            raise StudyError(f"{where}.relative: the base document has no number at {name} "
                             f"(got {base!r})") from None
        ax.relative = True
    if "values" in d:
        v = d["values"]
        if not isinstance(v, list) or not v:
            raise StudyError(f"{where}.values: expected a non-empty list, got {v!r}")
        ax.values = [_plain(x, f"{where}.values[{j}]") for j, x in enumerate(v)]
        if "count" in d:
            raise StudyError(f"{where}.count: only with range (values gives the grid itself)")
    elif "range" in d:
        r = d["range"]
        if not isinstance(r, list) or len(r) != 2:
            raise StudyError(f"{where}.range: expected [low, high], got {r!r}")
        lo, hi = _number(r[0], f"{where}.range[0]"), _number(r[1], f"{where}.range[1]")
        if not lo <= hi:
            raise StudyError(f"{where}.range: expected low <= high, got [{lo}, {hi}]")
        if scale == "log" and lo <= 0:
            raise StudyError(f"{where}.range: a log scale needs low > 0, got [{lo}, {hi}]")
        ax.range = (lo, hi)
        if "count" in d:
            ax.count = _int(d["count"], f"{where}.count")
            check_limit(f"{where}.count", ax.count, MAX_STUDY_SAMPLES, StudyError)
    else:
        n = d["normal"]
        _check_keys(n, {"mean", "std"}, f"{where}.normal")
        if "mean" not in n or "std" not in n:
            raise StudyError(f"{where}.normal: expected {{mean: ..., std: ...}}, got {n!r}")
        mu, sd = _number(n["mean"], f"{where}.normal.mean"), _number(n["std"], f"{where}.normal.std")
        if sd < 0:
            raise StudyError(f"{where}.normal.std: must be >= 0, got {sd}")
        if scale == "log":
            raise StudyError(f"{where}.scale: log applies to range, not normal")
        ax.normal = (mu, sd)
        if "count" in d:
            raise StudyError(f"{where}.count: only with range")
    return ax


def _plain(x, where):
    """A grid value as plain YAML data (numbers as floats where written as
    numbers, strings and lists kept)."""
    if isinstance(x, bool) or x is None:
        return x
    if isinstance(x, (int, float)):
        return float(x)
    if isinstance(x, str):
        try:
            return parse_number(x, where, StudyError)
        except StudyError:
            return x
    if isinstance(x, list):
        return [_plain(v, f"{where}[{j}]") for j, v in enumerate(x)]
    if isinstance(x, dict):
        return {k: _plain(v, f"{where}.{k}") for k, v in x.items()}
    raise StudyError(f"{where}: unsupported value {x!r}")


def _compute(d):
    if not isinstance(d, dict) or not d:
        raise StudyError(f"study.compute: expected a mapping with one or more of {list(COMPUTES)}, got {d!r}")
    _check_keys(d, COMPUTES, "study.compute")
    out = {}
    for key, v in d.items():
        where = f"study.compute.{key}"
        if v is False or v is None:
            continue
        if v is True:
            v = {}
        if not isinstance(v, dict):
            raise StudyError(f"{where}: expected true or a mapping of options, got {v!r}")
        if key == "statics":
            _check_keys(v, {"points_per_section"}, where)
            out[key] = {"points_per_section": _int(v.get("points_per_section", 10), where + ".points_per_section")}
        elif key == "dynamics":
            _check_keys(v, {"duration", "dt", "theta", "record_every", "settling_band"}, where)
            if "duration" not in v:
                raise StudyError(f"{where}.duration: missing (simulated time in s)")
            o = {"duration": _number(v["duration"], where + ".duration"),
                 "dt": _number(v.get("dt", 1e-3), where + ".dt"),
                 "theta": _number(v.get("theta", 0.5), where + ".theta"),
                 "record_every": _int(v.get("record_every", 1), where + ".record_every"),
                 "settling_band": _number(v.get("settling_band", 0.02), where + ".settling_band")}
            try:
                n_steps_for(o["duration"], o["dt"])
            except ScenarioError as e:
                raise StudyError(f"{where}: {e}") from None
            if not 0.5 <= o["theta"] <= 1.0:
                raise StudyError(f"{where}.theta: expected 0.5 <= theta <= 1, got {o['theta']}")
            if not 0 < o["settling_band"] < 1:
                raise StudyError(f"{where}.settling_band: expected a fraction in (0, 1), got {o['settling_band']}")
            out[key] = o
        else:
            out[key] = parse_workspace_options(v, where, StudyError)
    if not out:
        raise StudyError("study.compute: nothing to compute")
    return out


def _canonical(x):
    return json.dumps(x, sort_keys=True, separators=(",", ":"), default=repr)


def study_from_dict(d, base_dir=".", source="<dict>", name=None):
    """Parse a study mapping (see the module docstring); StudyError naming
    the field."""
    _check_keys(d, {"name", "description", "robot", "scenario", "parameters", "design", "compute", "record"},
                "study")
    # --- base documents
    scen = d.get("scenario")
    scen_dir = base_dir
    if scen is None:
        scen_doc = {"gravity": True}
    elif isinstance(scen, dict):
        scen_doc = copy.deepcopy(scen)
    elif isinstance(scen, str):
        p = scen if os.path.isabs(scen) else os.path.join(base_dir, scen)
        if not os.path.isfile(p):
            p = scen
        try:
            path = find_file(p, "scenarios", ScenarioError)
        except ScenarioError as e:
            raise StudyError(f"study.scenario: {e}") from None
        scen_doc = read_yaml_file(path, StudyError, "scenario")
        if not isinstance(scen_doc, dict):
            raise StudyError(f"study.scenario: {path}: expected a mapping at top level")
        scen_dir = os.path.dirname(os.path.abspath(path))
    else:
        raise StudyError(f"study.scenario: expected a path, an example's name or a mapping, got {scen!r}")
    robot = d.get("robot")
    if robot is not None:
        if not isinstance(robot, str):
            raise StudyError(f"study.robot: expected a robot file path or an example's name, got {robot!r}")
        robot_doc = _load_robot_doc(robot, base_dir, "study.robot")
    else:
        r = scen_doc.get("robot")
        if r is None:
            raise StudyError("study.robot: missing (give robot, or a scenario that names its robot)")
        if isinstance(r, dict):
            robot_doc = copy.deepcopy(r)
        elif isinstance(r, str):
            robot_doc = _load_robot_doc(r, scen_dir, "study.scenario.robot")
        else:
            raise StudyError(f"study.scenario.robot: expected a path or a mapping, got {r!r}")
    scen_doc = {k: v for k, v in scen_doc.items() if k != "robot"}
    # --- axes
    params = d.get("parameters") or []
    if not isinstance(params, list):
        raise StudyError(f"study.parameters: expected a list of axes, got {params!r}")
    axes = [_axis(p, i, robot_doc, scen_doc) for i, p in enumerate(params)]
    names = [a.name for a in axes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise StudyError(f"study.parameters: each path at most once, repeated: {dup}")
    # --- design
    des = d.get("design") or {"type": "grid"}
    _check_keys(des, {"type", "samples", "seed"}, "study.design")
    kind = des.get("type", "grid")
    if kind not in DESIGNS:
        raise StudyError(f"study.design.type: expected one of {list(DESIGNS)}, got {kind!r}")
    design = {"type": kind, "seed": des.get("seed", 0)}
    if isinstance(design["seed"], bool) or not isinstance(design["seed"], int) or design["seed"] < 0:
        raise StudyError(f"study.design.seed: expected an integer >= 0, got {design['seed']!r}")
    if kind == "grid":
        if "samples" in des:
            raise StudyError("study.design.samples: a grid takes every combination (give count per axis)")
        for i, a in enumerate(axes):
            if a.normal is not None:
                raise StudyError(f"parameters[{i}]: a normal distribution needs design random or lhs")
            if a.range is not None and a.count is None:
                raise StudyError(f"parameters[{i}].count: a range on a grid needs count (number of points)")
        n_grid = 1                  # the number of cases, before any is made (soft_twin_core.limits)
        for a in axes:
            n_grid *= len(a.values) if a.values is not None else a.count
        check_limit("study.parameters: cases of the grid (the product of the counts)", n_grid,
                    MAX_STUDY_SAMPLES, StudyError)
    else:
        design["samples"] = _int(des.get("samples"), "study.design.samples") if "samples" in des else None
        if design["samples"] is None:
            raise StudyError(f"study.design.samples: missing (number of cases of a {kind} design)")
        check_limit("study.design.samples", design["samples"], MAX_STUDY_SAMPLES, StudyError)
        for i, a in enumerate(axes):
            if a.values is not None:
                raise StudyError(f"parameters[{i}].values: a list of values needs design grid "
                                 f"(random and lhs sample a range or a normal)")
            if a.count is not None:
                raise StudyError(f"parameters[{i}].count: only on a grid")
    # --- compute and record
    compute = _compute(d.get("compute", {"statics": True}))
    rec = d.get("record")
    if rec is None:
        record = tuple(r for r in DEFAULT_RECORD if any(r in RECORDS[c] for c in compute))
    else:
        if not isinstance(rec, list) or not all(isinstance(r, str) for r in rec):
            raise StudyError(f"study.record: expected a list of names, got {rec!r}")
        known = sorted({r for c in compute for r in RECORDS[c]})
        for r in rec:
            if r not in known:
                raise StudyError(f"study.record: {r!r} is not an output of {sorted(compute)}; "
                                 f"choose from {known}")
        record = tuple(rec)
    st = Study(name=name or str(d.get("name") or Path(source).stem), source=source, base_dir=scen_dir,
               robot_doc=robot_doc, scenario_doc=scen_doc, axes=axes, design=design, compute=compute,
               record=record)
    st.fingerprint = hashlib.sha256(_canonical({
        "v": FORMAT_VERSION, "robot": robot_doc, "scenario": scen_doc, "compute": compute,
        "record": list(record), "axes": [[a.name, a.base if a.relative else None] for a in axes],
    }).encode()).hexdigest()[:16]
    return st


def load_study(path):
    """Parse a study file; StudyError naming the bad field."""
    d = read_yaml_file(path, StudyError, "study file")
    if not isinstance(d, dict):
        raise StudyError(f"study file {path}: expected a mapping at top level")
    return study_from_dict(d, os.path.dirname(os.path.abspath(path)), str(path))


# ----------------------------------------------------------------------------
# Cases
# ----------------------------------------------------------------------------

@dataclass
class Case:
    """One case: ``index`` in the study, ``values`` {parameter name: value},
    ``key`` (a hash of the study's fingerprint and the values: the same
    case of the same study has the same key, whatever its index)."""
    index: int
    values: dict
    key: str


def design_matrix(study):
    """The parameter values of every case: a list of {name: value}.
    grid: every combination (the last axis fastest); random: independent
    uniform (or normal) samples from ``numpy.random.default_rng(seed)``;
    lhs: ``scipy.stats.qmc.LatinHypercube(d, rng=seed)`` mapped through
    each axis's inverse CDF. No axes: one case, the base documents."""
    axes, des = study.axes, study.design
    if not axes:
        return [{}]
    if des["type"] == "grid":
        import itertools
        grids = [a.grid_values() for a in axes]
        return [dict(zip(study.parameter_names, combo)) for combo in itertools.product(*grids)]
    n, d = des["samples"], len(axes)
    if des["type"] == "random":
        u = np.random.default_rng(des["seed"]).random((n, d))
    else:
        from scipy.stats import qmc
        u = qmc.LatinHypercube(d, rng=des["seed"]).random(n)
    cols = [a.from_unit(u[:, j]) for j, a in enumerate(axes)]
    return [{a.name: cols[j][i] for j, a in enumerate(axes)} for i in range(n)]


def make_cases(study):
    out = []
    for i, values in enumerate(design_matrix(study)):
        key = hashlib.sha256((study.fingerprint + _canonical(values)).encode()).hexdigest()[:16]
        out.append(Case(i, values, key))
    return out


def case_documents(study, values):
    """(robot_doc, scenario_doc) of a case: deep copies of the base
    documents with the values set; the scenario's ``robot`` is the robot
    mapping itself."""
    robot = copy.deepcopy(study.robot_doc)
    scen = copy.deepcopy(study.scenario_doc)
    for a in study.axes:
        set_path(robot if a.doc == "robot" else scen, a.keys, values[a.name], f"{a.doc} document")
    scen["robot"] = robot
    return robot, scen


def build_scenario(study, values):
    """The :class:`scenario.Scenario` of a case (its robot model inside);
    ScenarioError naming the field (robot fields by their robot path,
    ``segments[0].length: ...``; scenario fields as ``scenario.<field>``)."""
    _, scen = case_documents(study, values)
    try:
        sc = scenario_from_dict(scen, study.base_dir, source=f"{study.source} case")
    except ScenarioError as e:
        msg = str(e)
        if msg.startswith("scenario.robot: "):
            msg = msg[len("scenario.robot: "):]
        raise ScenarioError(msg) from None
    return sc


def validate_cases(study, cases):
    """Build every case's robot and scenario (the model's and scenario's own
    checks) and check the computations' needs (the workspace's actuator
    ranges); raise :class:`CaseValidationError` listing every bad case by
    index with its parameter values and the field, before anything runs."""
    import warnings
    errors = []
    flagged = {}                  # plausibility warnings by field: [(case index, message)]
    for c in cases:
        vals = ", ".join(f"{k} = {_short(v)}" for k, v in c.values.items())
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", PlausibilityWarning)
                sc = build_scenario(study, c.values)
                if "workspace" in study.compute:
                    actuation_ranges(sc.mech, study.compute["workspace"], StudyError)
        except (ScenarioError, ModelError, StudyError) as e:
            errors.append((c.index, (f"({vals}) " if vals else "") + str(e)))
            continue
        for w in caught:
            if issubclass(w.category, PlausibilityWarning):
                text = str(w.message)
                flagged.setdefault(text.split(": ", 1)[0], []).append((c.index, vals, text))
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if errors:
        raise CaseValidationError(errors, len(cases))
    for field_name, hits in flagged.items():     # one line per field, not one per case
        idx, vals, text = hits[0]
        cases_text = f"{len(hits)} of {len(cases)} cases" if len(cases) > 1 else "the case"
        warnings.warn(f"{cases_text} (first: case {idx}{f', {vals}' if vals else ''}): {text}",
                      PlausibilityWarning, stacklevel=2)


def _short(v):
    return f"{v:.6g}" if isinstance(v, float) else repr(v)


def parameter_columns(study, values):
    """{column: value} of a case's parameters: a vector value becomes the
    columns ``name[i]``; numbers stay floats, other values their text."""
    out = {}
    for name in study.parameter_names:
        v = values[name]
        if isinstance(v, list):
            for j, x in enumerate(v):
                out[f"{name}[{j}]"] = x if isinstance(x, float) else json.dumps(x)
        elif isinstance(v, (float, int)) and not isinstance(v, bool):
            out[name] = float(v)
        else:
            out[name] = v if isinstance(v, str) else json.dumps(v)
    return out


def is_finite_number(v):
    return isinstance(v, float) and math.isfinite(v)
