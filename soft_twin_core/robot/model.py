"""Immutable PCS robot model, built from a plain dict or a YAML file.

A robot is a chain of *segments* (physical members: length, cross-section
and material -- or, instead of those two, explicit ``sectional`` stiffness,
inertia and damping values -- reference strain, free strain modes), each
discretised into ``sections`` pieces of constant strain (piecewise constant
strain, PCS).
Consecutive segments may be joined by a rigid offset transform (members at
fixed angles). Actuators (tendons, fluidic chambers) belong to the model.

The generalised coordinates ``q`` are the values of the *free* strain modes
of every section, section by section, in the order
[axial, shear_y, shear_z, torsion, bending_y, bending_z]; fixed modes stay
at the reference strain ``f0``. So ``q0`` (the rest configuration) is the
free part of ``f0``: a straight rod at rest has axial strain 1, not 0.

Units: SI (m, kg, s, N, Pa, rad).
"""

import math
import numbers
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from soft_twin_core._blas import block_diag
from soft_twin_core.errors import ModelError
from soft_twin_core.lie import exp_so3, se3_from_rp
from soft_twin_core.limits import (MAX_SECTIONS_PER_SEGMENT, MAX_SECTIONS_TOTAL, check_limit, load_yaml_text,
                                   read_text)
from soft_twin_core.robot import plausibility
from soft_twin_core.robot.strain_bases import (STRAIN_NAMES, cf_layout, midpoint_samples, parse_strain_basis,
                                               segment_columns)

_MODE_GROUPS = {
    "all": STRAIN_NAMES,
    "bending": ("bending_y", "bending_z"),
    "bending_torsion": ("torsion", "bending_y", "bending_z"),
    "shear": ("shear_y", "shear_z"),
}


# ----------------------------------------------------------------------------
# Cross-section and material
# ----------------------------------------------------------------------------

@dataclass(frozen=True)
class CrossSection:
    """Geometric properties of a centroidal, principal-axis cross-section.

    area A [m^2]; second moments I2 (about local y), I3 (about local z) [m^4];
    torsion constant J [m^4]; shear areas A2 = shear_y * A, A3 = shear_z * A.
    """
    area: float
    I2: float
    I3: float
    J: float
    shear_y: float = 1.0
    shear_z: float = 1.0

    @staticmethod
    def solid_circle(radius):
        A = np.pi * radius**2
        I = np.pi * radius**4 / 4
        return CrossSection(A, I, I, 2 * I, 1.0, 1.0)

    @staticmethod
    def hollow_tube(outer_radius, inner_radius):
        A = np.pi * (outer_radius**2 - inner_radius**2)
        I = np.pi * (outer_radius**4 - inner_radius**4) / 4
        return CrossSection(A, I, I, 2 * I, 1.0, 1.0)

    @staticmethod
    def rectangle(width, height):
        """width along local y, height along local z. J from the series
        approximation J = a b^3 (1/3 - 0.21 (b/a)(1 - b^4/(12 a^4))), a >= b."""
        A = width * height
        I2 = width * height**3 / 12     # about y: height is along z
        I3 = height * width**3 / 12
        a, b = max(width, height), min(width, height)
        J = a * b**3 * (1 / 3 - 0.21 * (b / a) * (1 - b**4 / (12 * a**4)))
        return CrossSection(A, I2, I3, J, 1.0, 1.0)


@dataclass(frozen=True)
class Material:
    """Young's modulus E [Pa], shear modulus G [Pa], density [kg/m^3],
    viscosity [Pa s] for Kelvin-Voigt strain-rate damping."""
    E: float
    G: float
    density: float
    viscosity: float = 0.0


# ----------------------------------------------------------------------------
# Sections, actuators, model
# ----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Section:
    """One PCS piece: constant strain over ``length``.

    K, D, M: 6x6 stiffness [N, N m^2], damping [N s, N m^2 s] and inertia
    density [kg/m, kg m] matrices acting on [linear; angular] strains/twists.
    ``f0`` reference strain; ``free`` boolean mask of free modes;
    ``offset_after`` rigid transform from this section's end to the next
    section's start (identity inside a segment); ``basis``: the segment's
    strain basis (:class:`strain_bases.StrainBasis`, shared by its sections;
    None: each section's strain is its own coordinates, PCS).
    """
    length: float
    K: np.ndarray
    D: np.ndarray
    M: np.ndarray
    f0: np.ndarray
    free: np.ndarray
    segment: str
    offset_after: np.ndarray
    basis: object = None


@dataclass(frozen=True, eq=False)
class Actuator:
    """A tendon (input: tension [N], >= 0) or fluidic chamber (input: gauge
    pressure [Pa]) routed from arc length ``start`` to ``end`` [m] at an offset
    ``d(s)`` [m] from the centre line in the cross-section's (y, z) plane.

    routing: "straight" (constant ``offset``), "converging" (offset varies
    linearly from ``offset`` at start to ``offset_end`` at end) or "helical"
    (radius ``radius``, angle ``phase + 2 pi turns_per_meter (s - start)``
    from the y axis).

    tendon_model: "distributed" (exact: the tendon acts along its whole
    path, tau = -T d(ell)/dq) or "point_moment" (the slides' model (b): the
    pure follower moment ``-T d(end) x e_x`` at the termination ``end``;
    equivalent to "distributed" for straight tendons in a planar,
    inextensible, unshearable arm).

    limit: the declared maximum input -- tension [N] for a tendon, |gauge
    pressure| [Pa] for a chamber -- a finite float > 0, or ``math.inf``
    when the robot file declares none (unlimited).

    lower, upper: the admissible input range [lower, upper] (see
    :func:`actuator_range`): ``limit`` (|u| <= limit) intersected with the
    robot file's optional ``min``/``max``; a tendon's lower bound is never
    below 0 (it can only pull). A missing bound is unbounded on that side
    (a chamber without ``min`` may take any suction). Every consumer (the
    node, the offline runners, IK, the planners, calibration) checks inputs
    with :func:`check_actuator_input`.

    friction: the Coulomb coefficient mu >= 0 [-] between a tendon and its
    sheath (or guide holes), 0 for a frictionless tendon. The tension decays
    along the routing by the capstan law ``T(s) = u exp(-mu theta(s))``,
    theta(s) the angle [rad] the tendon path's tangent has turned between
    ``start`` and s (:mod:`soft_twin_core.engine.forces`): the branch of a
    tendon being pulled in (slipping towards the actuator). Distributed
    tendon model only.
    """
    name: str
    kind: str                  # "tendon" | "chamber"
    start: float
    end: float
    routing: str
    offset: np.ndarray
    offset_end: np.ndarray
    radius: float = 0.0
    phase: float = 0.0
    turns_per_meter: float = 0.0
    area: float = 0.0          # chamber area [m^2]
    tendon_model: str = "distributed"   # or "point_moment" (slides part C, model (b))
    limit: float = math.inf    # declared maximum input: tension [N] or |pressure| [Pa]
    lower: float = None        # admissible range [lower, upper]; None: from kind and limit
    upper: float = None
    friction: float = 0.0      # tendon-sheath Coulomb coefficient [-] (capstan decay)

    def __post_init__(self):
        lo, hi = actuator_range(self.kind, self.limit)
        if self.lower is not None:
            lo = max(lo, float(self.lower))
        if self.upper is not None:
            hi = min(hi, float(self.upper))
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    def offset_at(self, s):
        """Offset d(s) (..., 3) in the cross-section frame (x component 0) and
        its arc-length derivative d'(s)."""
        s = np.asarray(s, dtype=float)
        d = np.zeros(s.shape + (3,))
        dd = np.zeros(s.shape + (3,))
        if self.routing == "straight":
            d[..., 1:] = self.offset
        elif self.routing == "converging":
            frac = (s - self.start) / (self.end - self.start)
            slope = (self.offset_end - self.offset) / (self.end - self.start)
            d[..., 1:] = self.offset + frac[..., None] * (self.offset_end - self.offset)
            dd[..., 1:] = slope
        else:  # helical
            k = 2 * np.pi * self.turns_per_meter
            ang = self.phase + k * (s - self.start)
            d[..., 1] = self.radius * np.cos(ang)
            d[..., 2] = self.radius * np.sin(ang)
            dd[..., 1] = -self.radius * k * np.sin(ang)
            dd[..., 2] = self.radius * k * np.cos(ang)
        return d, dd

    def offset_second_derivative(self, s):
        """d''(s) (..., 3) [1/m]: zero for straight and converging routings,
        ``-k^2 d`` (k = 2 pi turns_per_meter) for a helix."""
        s = np.asarray(s, dtype=float)
        if self.routing != "helical":
            return np.zeros(s.shape + (3,))
        d, _ = self.offset_at(s)
        return -(2 * np.pi * self.turns_per_meter) ** 2 * d

    @property
    def force_per_unit_input(self):
        """Tension equivalent per unit input: +1 for tendons, -area for chambers
        (a pressurised chamber pushes where a tendon pulls)."""
        return 1.0 if self.kind == "tendon" else -self.area


def actuator_range(kind, limit=math.inf):
    """The input range [lower, upper] implied by an actuator's ``kind`` and
    ``limit`` alone: a tendon [0, limit], a chamber [-limit, limit]."""
    limit = float(limit)
    return (0.0, limit) if kind == "tendon" else (-limit, limit)


# reasons of a rejected actuator input (:func:`check_actuator_input`)
ACTUATOR_REJECT_REASONS = ("non_finite", "negative_tension", "over_limit", "under_limit")


def check_actuator_input(act, value):
    """None if ``value`` is an admissible input of actuator ``act``, else
    (reason, message): "non_finite", "negative_tension" (a tendon below 0
    N), "over_limit" (|value| above ``limit``, or above ``max``) or
    "under_limit" (below ``min``). The one rule for the node, the offline runners, IK, the
    planners and calibration; the message names the actuator, the value and
    the bound."""
    v = float(value)
    unit = "N" if act.kind == "tendon" else "Pa"
    what = "tension" if act.kind == "tendon" else "pressure"
    if not math.isfinite(v):
        return "non_finite", f"{act.kind} {act.name}: {what} {v} is not finite"
    if act.kind == "tendon" and v < 0:
        return "negative_tension", f"tendon {act.name}: tension must be >= 0 N, got {v:g} N"
    rng = f"(robot file; admissible range [{act.lower:g}, {act.upper:g}] {unit})"
    if abs(v) > act.limit:
        return "over_limit", (f"{act.kind} {act.name}: |{what}| {abs(v):g} {unit} exceeds its declared "
                              f"limit {act.limit:g} {unit} {rng}")
    if v > act.upper:
        return "over_limit", (f"{act.kind} {act.name}: {what} {v:g} {unit} exceeds its declared "
                              f"max {act.upper:g} {unit} {rng}")
    if v < act.lower:
        return "under_limit", (f"{act.kind} {act.name}: {what} {v:g} {unit} is below its declared "
                               f"min {act.lower:g} {unit} {rng}")
    return None


def actuator_bounds_of(model):
    """(lower, upper) arrays (n_actuators,) of the declared input ranges."""
    acts = model.actuators
    return (np.array([a.lower for a in acts], dtype=float), np.array([a.upper for a in acts], dtype=float))


@dataclass(frozen=True, eq=False)
class RobotModel:
    """Immutable PCS robot model. Build with :func:`model_from_dict` or
    :func:`load_model`. Algorithms take ``(model, q, ...)`` and never modify it."""
    name: str
    sections: tuple
    base_pose: np.ndarray               # 4x4, world <- base
    gravity: np.ndarray                 # (3,) world frame [m/s^2]
    actuators: tuple = ()
    kinematic_map: str = "exponential"  # or "cayley"
    quadrature_points: int = 2
    # derived (filled in __post_init__)
    n_sections: int = field(init=False)
    lengths: np.ndarray = field(init=False)
    s_starts: np.ndarray = field(init=False)
    total_length: float = field(init=False)
    free_mask: np.ndarray = field(init=False)     # (n, 6) bool
    free_index: np.ndarray = field(init=False)    # indices into the flattened (n*6)
    n_dof: int = field(init=False)
    f0: np.ndarray = field(init=False)            # (n, 6)
    q0: np.ndarray = field(init=False)
    K_q: np.ndarray = field(init=False)           # (n_dof, n_dof) generalised stiffness
    D_q: np.ndarray = field(init=False)           # generalised damping
    offsets: np.ndarray = field(init=False)       # (n, 4, 4)
    has_offsets: bool = field(init=False)

    def __post_init__(self):
        set_ = object.__setattr__
        n = len(self.sections)
        if n == 0:
            raise ModelError("segments: a robot needs at least one section")
        set_(self, "n_sections", n)
        lengths = np.array([sec.length for sec in self.sections])
        set_(self, "lengths", lengths)
        set_(self, "s_starts", np.concatenate([[0.0], np.cumsum(lengths)[:-1]]))
        set_(self, "total_length", float(lengths.sum()))
        mask = np.array([sec.free for sec in self.sections], dtype=bool)
        set_(self, "free_mask", mask)
        set_(self, "free_index", np.flatnonzero(mask.ravel()))
        set_(self, "n_dof", int(mask.sum()))
        f0 = np.array([sec.f0 for sec in self.sections], dtype=float)
        set_(self, "f0", f0)
        set_(self, "q0", f0.ravel()[self.free_index].copy())
        Kfull = block_diag([sec.length * sec.K for sec in self.sections])
        Dfull = block_diag([sec.length * sec.D for sec in self.sections])
        idx = self.free_index
        set_(self, "K_q", Kfull[np.ix_(idx, idx)])
        set_(self, "D_q", Dfull[np.ix_(idx, idx)])
        offs = np.array([sec.offset_after for sec in self.sections])
        set_(self, "offsets", offs)
        set_(self, "has_offsets", bool(np.abs(offs - np.eye(4)).max() > 0))
        for arr in (self.lengths, self.s_starts, self.free_mask, self.free_index, self.f0,
                    self.q0, self.K_q, self.D_q, self.offsets, self.base_pose, self.gravity):
            arr.setflags(write=False)

    # --- conversions between q and per-section strains -------------------
    def strains(self, q):
        """Per-section strains (n_sections, 6) from q (free modes) and f0."""
        q = self.check_q(q)
        xi = np.empty(q.shape[:-1] + (6 * self.n_sections,), dtype=np.result_type(q, float))
        xi[...] = self.f0.ravel()
        xi[..., self.free_index] = q
        return xi.reshape(q.shape[:-1] + (self.n_sections, 6))

    def q_from_strains(self, strains):
        """Free modes of per-section strains (n_sections, 6); the fixed modes
        must equal f0 (else ModelError)."""
        xi = np.asarray(strains, dtype=float)
        if xi.shape != (self.n_sections, 6):
            raise ModelError(f"strains: expected shape ({self.n_sections}, 6), got {xi.shape}")
        fixed = ~self.free_mask
        if np.any(np.abs(xi[fixed] - self.f0[fixed]) > 1e-12):
            raise ModelError("strains: fixed (not free) modes must equal the reference strain f0")
        return xi.ravel()[self.free_index].copy()

    def check_q(self, q, name="q"):
        q = np.asarray(q)
        if q.dtype.kind not in "fc":
            q = q.astype(float)
        if q.shape[-1:] != (self.n_dof,):
            raise ValueError(f"{name}: expected shape (..., {self.n_dof}) for this model "
                             f"({self.n_sections} sections, {self.n_dof} free modes), got {q.shape}")
        if np.iscomplexobj(q):
            if not np.all(np.isfinite(q.real)):
                raise ValueError(f"{name}: contains NaN or inf")
        elif not np.all(np.isfinite(q)):
            raise ValueError(f"{name}: contains NaN or inf")
        return q

    def locate(self, s):
        """Section index and local abscissa x in [0, L_i] of arc lengths s [m].
        A boundary belongs to the later section; s = total length to the last."""
        s = np.asarray(s, dtype=float)
        if np.any(s < -1e-12) or np.any(s > self.total_length + 1e-12):
            raise ValueError(f"s: arc lengths must lie in [0, {self.total_length}] m, "
                             f"got min {s.min()}, max {s.max()}")
        idx = np.searchsorted(self.s_starts, s, side="right") - 1
        idx = np.clip(idx, 0, self.n_sections - 1)
        x = np.clip(s - self.s_starts[idx], 0.0, self.lengths[idx])
        return idx, x

    @property
    def actuator_names(self):
        return tuple(a.name for a in self.actuators)

    @property
    def tree(self):
        """The multibody model of this description (a chain of soft joints,
        :func:`soft_chain.robot_tree`), built once."""
        return self.chain[0]

    @property
    def chain(self):
        """(:attr:`tree`, the section of :attr:`sections` each soft joint
        stands for, the variable-strain segments' :class:`strain_bases.SegmentBasis`
        es): :func:`soft_chain.robot_tree`, built once."""
        t = self.__dict__.get("_chain")
        if t is None:
            from soft_twin_core.robot.soft_chain import robot_tree  # here: start-up (numba)
            t = robot_tree(self)
            object.__setattr__(self, "_chain", t)
        return t

    @property
    def mass(self):
        return float(sum(sec.length * sec.M[0, 0] for sec in self.sections))


# ----------------------------------------------------------------------------
# Building from dicts / YAML with validation
# ----------------------------------------------------------------------------

# A decimal number as written in a YAML file: PyYAML (a YAML 1.1 parser)
# reads only spellings with a dot and a signed exponent (1.0e+6) as floats;
# 1e6, 1.0e6 and 71.7e9 arrive as strings. Robot and scenario files accept
# all of these, and nothing else (no hex, no underscores inside strings).
_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = {"nan", "inf", "infinity", ".nan", ".inf"}


def parse_number(v, where, error=None):
    """The float value of a number in a robot or scenario file: an int or
    float (not a bool), or a string spelling a decimal number such as
    ``"1e6"`` or ``"1.0e6"`` (which YAML 1.1 leaves as strings). The value
    must be finite. Raises ``error`` (default ModelError) naming ``where``.

    The one number parser of the robot files (:mod:`model`) and the
    scenario files (:mod:`scenario`)."""
    error = ModelError if error is None else error
    if isinstance(v, str):
        text = v.strip()
        if _NUMBER_RE.fullmatch(text):
            v = float(text)
        elif text.lower().lstrip("+-") in _NON_FINITE:
            raise error(f"{where}: must be finite, got {v!r}")
        else:
            raise error(f"{where}: expected a number, got {v!r}")
    elif isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise error(f"{where}: expected a number, got {v!r}")
    try:
        v = float(v)
    except OverflowError:   # a huge int
        raise error(f"{where}: must be finite, got {v!r}") from None
    if not math.isfinite(v):
        raise error(f"{where}: must be finite, got {v!r}")
    return v


def parse_numbers(v, shape, where, error=None):
    """An array of the given shape (``None`` entries: any length) of numbers
    parsed by :func:`parse_number` from nested lists; raises ``error``
    (default ModelError) naming ``where`` with the expected shape."""
    error = ModelError if error is None else error

    def rec(x, dims, path):
        if not dims:
            return parse_number(x, where + path, error)
        if isinstance(x, np.ndarray):
            x = x.tolist()
        if not isinstance(x, (list, tuple)) or (dims[0] is not None and len(x) != dims[0]):
            raise error(f"{where}: expected {_shape_text(shape)} numbers, got {v!r}")
        return [rec(xi, dims[1:], f"{path}[{i}]") for i, xi in enumerate(x)]
    out = np.array(rec(v, tuple(shape), ""), dtype=float)
    if out.size == 0:
        out = out.reshape(tuple(0 if k is None else k for k in shape))
    return out


def _shape_text(shape):
    return " x ".join("N" if k is None else str(k) for k in shape)


def _num(d, key, where, *, positive=False, nonneg=False, default=None):
    if key not in d:
        if default is not None:
            return float(default)
        raise ModelError(f"{where}.{key}: missing (required)")
    v = parse_number(d[key], f"{where}.{key}")
    if positive and v <= 0:
        raise ModelError(f"{where}.{key}: must be > 0, got {v!r}")
    if nonneg and v < 0:
        raise ModelError(f"{where}.{key}: must be >= 0, got {v!r}")
    return v


def _vec(d, key, n, where, default=None):
    if key not in d:
        if default is not None:
            return np.array(default, dtype=float)
        raise ModelError(f"{where}.{key}: missing (required)")
    v = d[key]
    try:
        return parse_numbers(v, (n,), f"{where}.{key}")
    except ModelError:
        raise ModelError(f"{where}.{key}: expected {n} finite numbers, got {v!r}") from None


def _check_keys(d, allowed, where):
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping, got {d!r}")
    unknown = set(d) - set(allowed)
    if unknown:
        raise ModelError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(allowed)}")


def pose_from_dict(d, where):
    """{position: [x,y,z], rpy: [roll,pitch,yaw]} (or quaternion [x,y,z,w]) -> 4x4."""
    if d is None:
        return np.eye(4)
    _check_keys(d, {"position", "rpy", "quaternion"}, where)
    p = _vec(d, "position", 3, where, default=[0, 0, 0])
    if "quaternion" in d and "rpy" in d:
        raise ModelError(f"{where}: give rpy or quaternion, not both")
    if "quaternion" in d:
        x, y, z, w = _vec(d, "quaternion", 4, where)
        nq = np.sqrt(x * x + y * y + z * z + w * w)
        if nq < 1e-9:
            raise ModelError(f"{where}.quaternion: zero quaternion")
        x, y, z, w = x / nq, y / nq, z / nq, w / nq
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    else:
        r, pch, y = _vec(d, "rpy", 3, where, default=[0, 0, 0])
        plausibility.check_angles(f"{where}.rpy", (r, pch, y))
        R = exp_so3(np.array([0, 0, y])) @ exp_so3(np.array([0, pch, 0])) @ exp_so3(np.array([r, 0, 0]))
    return se3_from_rp(R, p)


def _cross_section(d, where):
    _check_keys(d, {"shape", "radius", "outer_radius", "inner_radius", "width", "height",
                    "area", "I2", "I3", "J", "shear_factor_y", "shear_factor_z"}, where)
    shape = d.get("shape", "solid_circle")
    if shape == "solid_circle":
        cs = CrossSection.solid_circle(_num(d, "radius", where, positive=True))
    elif shape == "hollow_tube":
        ro = _num(d, "outer_radius", where, positive=True)
        ri = _num(d, "inner_radius", where, nonneg=True)
        if ri >= ro:
            raise ModelError(f"{where}.inner_radius: must be < outer_radius ({ro}), got {ri}")
        cs = CrossSection.hollow_tube(ro, ri)
    elif shape == "rectangle":
        cs = CrossSection.rectangle(_num(d, "width", where, positive=True),
                                    _num(d, "height", where, positive=True))
    elif shape == "explicit":
        cs = CrossSection(_num(d, "area", where, positive=True), _num(d, "I2", where, positive=True),
                          _num(d, "I3", where, positive=True), _num(d, "J", where, positive=True))
    else:
        raise ModelError(f"{where}.shape: expected one of solid_circle, hollow_tube, rectangle, "
                         f"explicit, got {shape!r}")
    ky = _num(d, "shear_factor_y", where, positive=True, default=cs.shear_y)
    kz = _num(d, "shear_factor_z", where, positive=True, default=cs.shear_z)
    J = _num(d, "J", where, positive=True, default=cs.J)   # explicit torsion constant wins
    return CrossSection(cs.area, cs.I2, cs.I3, J, ky, kz)


def _material(d, where):
    _check_keys(d, {"youngs_modulus", "shear_modulus", "poisson_ratio", "density", "viscosity"},
                where)
    E = _num(d, "youngs_modulus", where, positive=True)
    if "shear_modulus" in d and "poisson_ratio" in d:
        raise ModelError(f"{where}: give shear_modulus or poisson_ratio, not both")
    if "shear_modulus" in d:
        G = _num(d, "shear_modulus", where, positive=True)
    else:
        nu = _num(d, "poisson_ratio", where, default=0.5)
        if not -1.0 < nu <= 0.5:
            raise ModelError(f"{where}.poisson_ratio: must be in (-1, 0.5], got {nu}")
        G = E / (2 * (1 + nu))
    return Material(E, G, _num(d, "density", where, positive=True),
                    _num(d, "viscosity", where, nonneg=True, default=0.0))


def _free_modes(v, where):
    if v is None:
        v = "all"
    if isinstance(v, str):
        if v not in _MODE_GROUPS:
            raise ModelError(f"{where}: expected 'all', 'bending', 'bending_torsion', 'shear' or a "
                             f"list of {list(STRAIN_NAMES)}, got {v!r}")
        names = _MODE_GROUPS[v]
    else:
        if not isinstance(v, (list, tuple)):
            raise ModelError(f"{where}: expected 'all', 'bending', 'bending_torsion', 'shear' or a "
                             f"list of {list(STRAIN_NAMES)}, got {v!r}")
        names = list(v)
        for nm in names:
            if nm not in STRAIN_NAMES:
                raise ModelError(f"{where}: unknown strain mode {nm!r}; expected names from "
                                 f"{list(STRAIN_NAMES)}")
        if not names:
            raise ModelError(f"{where}: at least one free mode is needed")
    return np.array([nm in names for nm in STRAIN_NAMES])


def section_matrices(cs, mat):
    """Stiffness K, damping D and inertia density M (6x6) of a cross-section.

    K = diag(EA, G A2, G A3, G J, E I2, E I3); D = viscosity * diag(3A, A2, A3,
    J, 3 I2, 3 I3) (Kelvin-Voigt with incompressible 3x factor on normal
    strains); M = density * diag(A, A, A, I2 + I3, I2, I3) (polar inertia for
    rotation about the axis).
    """
    A2, A3 = cs.shear_y * cs.area, cs.shear_z * cs.area
    K = np.diag([mat.E * cs.area, mat.G * A2, mat.G * A3, mat.G * cs.J, mat.E * cs.I2, mat.E * cs.I3])
    D = mat.viscosity * np.diag([3 * cs.area, A2, A3, cs.J, 3 * cs.I2, 3 * cs.I3])
    M = mat.density * np.diag([cs.area, cs.area, cs.area, cs.I2 + cs.I3, cs.I2, cs.I3])
    return K, D, M


# Keys of the ``sectional`` block, in the order of the strain modes
# [axial, shear_y, shear_z, torsion, bending_y, bending_z].
SECTIONAL_STIFFNESS_KEYS = ("EA", "GA2", "GA3", "GJ", "EI2", "EI3")
SECTIONAL_INERTIA_KEYS = ("mass_per_length", "J1", "J2", "J3")


def _sectional(d, where):
    """K, D, M (6x6) of an explicit ``sectional`` block, independent of any
    geometric cross-section::

        stiffness: {EA, GA2, GA3, GJ, EI2, EI3}      # N, N, N, N m^2, N m^2, N m^2; all > 0
        inertia: {mass_per_length, J1, J2, J3}      # kg/m; kg m (polar about x, about y, about z); all > 0
        damping: {EA, GA2, GA3, GJ, EI2, EI3}       # optional, each >= 0 (default 0): N s, N m^2 s

    K = diag(EA, GA2, GA3, GJ, EI2, EI3), M = diag(m, m, m, J1, J2, J3),
    D = diag(damping) (zero for omitted keys).
    """
    _check_keys(d, {"stiffness", "inertia", "damping"}, where)
    for key in ("stiffness", "inertia"):
        if key not in d:
            raise ModelError(f"{where}.{key}: missing (required)")
    st, inn = d["stiffness"], d["inertia"]
    _check_keys(st, set(SECTIONAL_STIFFNESS_KEYS), where + ".stiffness")
    _check_keys(inn, set(SECTIONAL_INERTIA_KEYS), where + ".inertia")
    k = [_num(st, key, where + ".stiffness", positive=True) for key in SECTIONAL_STIFFNESS_KEYS]
    m, J1, J2, J3 = (_num(inn, key, where + ".inertia", positive=True) for key in SECTIONAL_INERTIA_KEYS)
    dmp = d.get("damping")
    if dmp is None:
        dmp = {}
    _check_keys(dmp, set(SECTIONAL_STIFFNESS_KEYS), where + ".damping")
    c = [_num(dmp, key, where + ".damping", nonneg=True, default=0.0) for key in SECTIONAL_STIFFNESS_KEYS]
    return np.diag(k), np.diag(c), np.diag([m, m, m, J1, J2, J3])


def _actuator(d, i, total_length):
    where = f"actuators[{i}]"
    _check_keys(d, {"name", "type", "start", "end", "routing", "offset", "offset_end", "radius",
                    "phase", "turns_per_meter", "area", "model", "limit", "min", "max", "friction"}, where)
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise ModelError(f"{where}.name: expected a non-empty string, got {name!r}")
    kind = d.get("type", "tendon")
    if kind not in ("tendon", "chamber"):
        raise ModelError(f"{where}.type: expected 'tendon' or 'chamber', got {kind!r}")
    start = _num(d, "start", where, nonneg=True, default=0.0)
    end = _num(d, "end", where, positive=True, default=total_length)
    if not start < end <= total_length + 1e-12:
        raise ModelError(f"{where}: need 0 <= start < end <= robot length {total_length} m, "
                         f"got start={start}, end={end}")
    routing = d.get("routing", "straight")
    if routing not in ("straight", "converging", "helical"):
        raise ModelError(f"{where}.routing: expected straight, converging or helical, got {routing!r}")
    offset = offset_end = np.zeros(2)
    radius = phase = turns = 0.0
    if routing in ("straight", "converging"):
        offset = _vec(d, "offset", 2, where)
        offset_end = _vec(d, "offset_end", 2, where) if routing == "converging" else offset
    else:
        radius = _num(d, "radius", where, positive=True)
        phase = _num(d, "phase", where, default=0.0)
        turns = _num(d, "turns_per_meter", where, default=0.0)
    area = 0.0
    if kind == "chamber":
        area = _num(d, "area", where, positive=True)
    tmodel = d.get("model", "distributed")
    if tmodel not in ("distributed", "point_moment"):
        raise ModelError(f"{where}.model: expected 'distributed' or 'point_moment', got {tmodel!r}")
    limit = math.inf
    if d.get("limit") is not None:
        limit = _num(d, "limit", where, positive=True)
    lower, upper = _input_bounds(d, where, kind, limit)
    friction = _num(d, "friction", where, nonneg=True, default=0.0)
    if friction > 0 and (kind != "tendon" or tmodel != "distributed"):
        raise ModelError(f"{where}.friction: sheath friction ({friction:g}) applies to a tendon of the "
                         f"'distributed' model only, not to a {kind}" + (f" of the {tmodel} model" if kind ==
                                                                          "tendon" else ""))
    return Actuator(name, kind, start, min(end, total_length), routing, offset, offset_end,
                    radius, phase, turns, area, tmodel, limit, lower, upper, friction)


def _input_bounds(d, where, kind, limit):
    """[lower, upper] of an actuator: ``limit`` (|u| <= limit; [0, limit] for
    a tendon) intersected with the optional ``min``/``max`` [N or Pa] (the
    tighter bound wins, so a study may vary ``limit`` under a file's
    ``max``); an empty range is an error."""
    unit = "N" if kind == "tendon" else "Pa"
    lo, hi = actuator_range(kind, limit)
    if d.get("min") is not None:
        m = _num(d, "min", where)
        if kind == "tendon" and m < 0:
            raise ModelError(f"{where}.min: {m:g} N is below 0 N: a tendon can only pull (tension >= 0)")
        lo = max(lo, m)
    if d.get("max") is not None:
        hi = min(hi, _num(d, "max", where))
    if not lo < hi:
        raise ModelError(f"{where}: empty input range [{lo:g}, {hi:g}] {unit} (min {d.get('min')}, max "
                         f"{d.get('max')}, limit {d.get('limit')}): need lower < upper")
    return lo, hi


def model_from_dict(d, n_sections_override=None):
    """Build a :class:`RobotModel` from a plain dict (the YAML schema in
    config/*.yaml). ``n_sections_override`` replaces every segment's section
    count (for convergence studies). Raises ModelError naming the bad field."""
    if isinstance(d, dict) and "bodies" in d:
        raise ModelError("robot: an articulated robot (tree schema: bodies/frames), not a classic single-chain "
                         "robot (segments); load it with soft_twin_core.robot.mechanism.mechanism_from_dict")
    _check_keys(d, {"name", "base", "gravity", "kinematic_map", "quadrature_points",
                    "segments", "actuators", "obstacles", "contact"}, "robot")
    segs = d.get("segments")
    if not isinstance(segs, list) or not segs:
        raise ModelError("robot.segments: expected a non-empty list of segments")
    check_limit("robot.segments: number of segments", len(segs), MAX_SECTIONS_TOTAL, ModelError)
    sections = []
    seg_names, spans = [], []        # for the unique names and the actuator offset check
    for k, sd in enumerate(segs):
        where = f"segments[{k}]"
        _check_keys(sd, {"name", "length", "sections", "cross_section", "material", "sectional",
                         "reference_strain", "free_modes", "offset_to_next", "strain_basis"}, where)
        length = _num(sd, "length", where, positive=True)
        plausibility.check_length(where, length)
        n = sd.get("sections", 1) if n_sections_override is None else n_sections_override
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ModelError(f"{where}.sections: expected an integer >= 1, got {n!r}")
        # resource bounds, before any allocation (soft_twin_core.limits)
        check_limit(f"{where}.sections" if n_sections_override is None else
                    "sections per segment (the override, e.g. --sections)", n, MAX_SECTIONS_PER_SEGMENT, ModelError)
        check_limit("robot: total sections (sum of segments[*].sections)",
                    len(sections) + n, MAX_SECTIONS_TOTAL, ModelError)
        if "sectional" in sd:
            both = [key for key in ("cross_section", "material") if key in sd]
            if both:
                raise ModelError(f"{where}.sectional: give either sectional or cross_section + material, "
                                 f"not both (also got {' and '.join(both)})")
            K, D, M = _sectional(sd["sectional"], where + ".sectional")
        else:
            if "cross_section" not in sd:
                raise ModelError(f"{where}.cross_section: missing (required, with material, "
                                 f"unless sectional is given)")
            if "material" not in sd:
                raise ModelError(f"{where}.material: missing (required, with cross_section, "
                                 f"unless sectional is given)")
            try:
                cs = _cross_section(sd["cross_section"], where + ".cross_section")
            except OverflowError:
                raise ModelError(f"{where}.cross_section: dimensions overflow (check the units: metres)") from None
            mat = _material(sd["material"], where + ".material")
            plausibility.check_cross_section(where + ".cross_section", sd["cross_section"])
            plausibility.check_material(where + ".material", mat.E, mat.G, mat.density,
                                        "shear_modulus" in sd["material"])
        f0 = _vec(sd, "reference_strain", 6, where, default=[1, 0, 0, 0, 0, 0])
        if f0[0] <= 0:
            raise ModelError(f"{where}.reference_strain: axial strain must be > 0, got {f0[0]}")
        free = _free_modes(sd.get("free_modes", "all"), where + ".free_modes")
        off = pose_from_dict(sd.get("offset_to_next"), where + ".offset_to_next")
        basis = parse_strain_basis(sd.get("strain_basis"), [m for m, f in zip(STRAIN_NAMES, free) if f],
                                   where + ".strain_basis")
        if basis is not None:                  # enough sections for its functions, checked here
            lengths = np.full(n, length / n)
            most = max(basis.functions(a) for a in range(int(free.sum())))
            if basis.magnus == 4 and most > 2 * n:
                raise ModelError(f"{where}.strain_basis: {n} sections have {2 * n} Gauss points, where the "
                                 f"fourth-order step (magnus: 4) puts the mass, for {most} basis functions a "
                                 f"mode (a singular mass matrix); give the segment at least {(most + 1) // 2} "
                                 f"sections")
            samples = cf_layout(lengths)[2] if basis.magnus == 4 else midpoint_samples(lengths)
            segment_columns(basis, samples, int(free.sum()), where + ".strain_basis")
        if "sectional" not in sd:
            K, D, M = section_matrices(cs, mat)
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D)) and np.all(np.isfinite(M))
                and np.all(np.diag(K) > 0) and np.all(np.diag(M) > 0)):
            src = "sectional gives" if "sectional" in sd else "cross_section and material give"
            raise ModelError(f"{where}: {src} a non-finite or zero stiffness or "
                             f"inertia (K diagonal {np.diag(K).tolist()}); check the values and units")
        name = str(sd.get("name", f"segment{k}"))
        if name in seg_names:
            raise ModelError(f"{where}.name: {name!r} is already used by segments[{seg_names.index(name)}]; "
                             f"segment names must be unique")
        seg_names.append(name)
        s_at = sum(x.length for x in sections)
        spans.append((s_at, s_at + length, None if "sectional" in sd else
                      plausibility.section_extent(sd["cross_section"]), f"{where} ({name})"))
        for j in range(n):
            sections.append(Section(length / n, K, D, M, f0, free, name,
                                    off if j == n - 1 else np.eye(4), basis))
    total = sum(s.length for s in sections)
    acts = d.get("actuators", []) or []
    if not isinstance(acts, list):
        raise ModelError("robot.actuators: expected a list")
    actuators = tuple(_actuator(a, i, total) for i, a in enumerate(acts))
    names = [a.name for a in actuators]
    if len(set(names)) != len(names):
        raise ModelError(f"robot.actuators: names must be unique, got {names}")
    plausibility.check_actuator_offsets(actuators, spans, ModelError)
    kmap = d.get("kinematic_map", "exponential")
    if kmap not in ("exponential", "cayley"):
        raise ModelError(f"robot.kinematic_map: expected 'exponential' or 'cayley', got {kmap!r}")
    fourth = [k for k, sd in enumerate(segs) if (sd.get("strain_basis") or {}).get("magnus") == 4]
    if fourth and kmap != "exponential":
        raise ModelError(f"segments[{fourth[0]}].strain_basis.magnus: 4 is the exponential map's fourth-order "
                         f"step; kinematic_map must be 'exponential', got {kmap!r}")
    nq = d.get("quadrature_points", 2)
    if isinstance(nq, bool) or not isinstance(nq, int) or not 1 <= nq <= 20:
        raise ModelError(f"robot.quadrature_points: expected an integer in 1..20, got {nq!r}")
    return RobotModel(
        name=str(d.get("name", "robot")),
        sections=tuple(sections),
        base_pose=pose_from_dict(d.get("base"), "robot.base"),
        gravity=_vec(d, "gravity", 3, "robot", default=[0, 0, -9.81]),
        actuators=actuators,
        kinematic_map=kmap,
        quadrature_points=nq,
    )


def read_yaml_file(path, error=None, what="file"):
    """Parsed YAML of ``path``; an unreadable, binary, oversized or too
    deeply nested file or bad YAML raises ``error`` (default ModelError)
    naming the file (limits: soft_twin_core.limits)."""
    error = ModelError if error is None else error
    # size, encoding (a binary file) and nesting are checked before parsing
    return load_yaml_text(read_text(path, error, what), f"{what} {path}", error)


def robot_mapping(d, source):
    """The robot description mapping of parsed YAML (a top-level ``robot:``
    key is accepted too); ModelError otherwise."""
    if isinstance(d, dict) and "robot" in d and "segments" not in d:
        d = d["robot"]
    if not isinstance(d, dict):
        raise ModelError(f"{source}: expected a mapping (the robot description) at top level")
    return d


# ----------------------------------------------------------------------------
# The example robot and scenario files, by name
# ----------------------------------------------------------------------------

def config_dirs():
    """Folders that may hold the example files (``robots/``, ``scenarios/``),
    in search order: the package data of ``pip install .``
    (``soft_twin_core/config``), the source checkout's ``config/``, the
    ROS package's ``share/soft_twin/config`` under ``sys.prefix`` (``make
    setup``), under the prefix this package is installed in and under
    every prefix of ``AMENT_PREFIX_PATH`` (colcon)."""
    here = Path(__file__).resolve().parents[1]          # the package soft_twin_core/
    cands = [here / "config", here.parent / "config", Path(sys.prefix) / "share" / "soft_twin" / "config"]
    if len(here.parents) > 3:      # <prefix>/lib/pythonX.Y/site-packages/soft_twin_core
        cands.append(here.parents[3] / "share" / "soft_twin" / "config")
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            cands.append(Path(prefix) / "share" / "soft_twin" / "config")
    out = []
    for c in cands:
        if (c / "robots").is_dir() and c not in out:
            out.append(c)
    return out


def example_files(kind):
    """{name: path} of the example files of ``kind`` ("robots" or
    "scenarios"); a name found in several :func:`config_dirs` is taken from
    the first."""
    if kind not in ("robots", "scenarios"):
        raise ValueError(f"kind: expected 'robots' or 'scenarios', got {kind!r}")
    out = {}
    for c in config_dirs():
        for f in sorted((c / kind).glob("*.yaml")):
            out.setdefault(f.stem, f)
    return dict(sorted(out.items()))


def find_file(name, kind, error=None):
    """The file a user means by ``name``: an existing path as given, else
    (a bare name without a directory part, with or without ``.yaml``) the
    example file of that name (:func:`example_files`). A missing path is
    returned unchanged (opening it reports the error); an unknown bare name
    raises ``error`` (default ModelError) listing the examples."""
    error = ModelError if error is None else error
    text = os.fspath(name)
    p = Path(os.path.expanduser(text))
    if p.is_file() or p.is_absolute() or os.sep in text or (os.altsep and os.altsep in text):
        return p
    stem = p.name[:-5] if p.name.endswith(".yaml") else p.name
    found = example_files(kind).get(stem)
    if found is not None:
        return found
    what = "robot file" if kind == "robots" else "scenario"
    if kind == "scenarios" and stem in example_files("robots"):
        raise error(f"scenario {text!r}: {stem} is an example robot, not a scenario. {robot_not_scenario_hint(stem)}")
    raise error(f"{what} {text!r}: no such file, nor an example of that name "
                f"(examples: {', '.join(example_files(kind)) or 'none installed'})")


def robot_not_scenario_hint(name):
    """How to use the robot ``name`` where a scenario was expected: the
    example scenarios built on it, or a scenario file naming it."""
    import re
    uses = []
    for sname, f in example_files("scenarios").items():
        try:
            text = f.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            continue
        if re.search(rf"^robot:\s*(\S*/)?{re.escape(name)}(\.yaml)?\s*(#.*)?$", text, re.M):
            uses.append(sname)
    uses.sort(key=lambda n: "statics" not in n)          # a statics example first
    how = (f"The example scenarios on it: {', '.join(uses)} (e.g. `soft-twin-sim statics {uses[0]}`). "
           if uses else "")
    return (how + f"Or write a scenario file with `robot: {name}` and its actuation and loads; "
            f"`soft-twin-sim workspace {name}` takes a robot directly.")


def load_model(path, n_sections_override=None):
    """Load a robot description from a YAML file (a top-level ``robot:`` key
    is accepted too). ``path`` may also name an example robot, from any
    working directory: ``load_model("tendon_arm")`` (see :func:`find_file`)."""
    path = find_file(path, "robots")
    d = robot_mapping(read_yaml_file(path, ModelError, "robot file"), f"robot file {path}")
    if isinstance(d, dict) and "bodies" in d:
        raise ModelError(f"robot file {path}: an articulated robot (tree schema: bodies); load it with "
                         f"soft_twin_core.robot.mechanism.load_mechanism")
    return model_from_dict(d, n_sections_override)


def with_sections(model_dict, n):
    """Convenience for convergence studies: the same robot with n sections per segment."""
    return model_from_dict(model_dict, n_sections_override=n)


def straight_state(model):
    """q at rest (the reference strains)."""
    return model.q0.copy()


@dataclass
class State:
    """Per-call mutable state, kept apart from the model: strains q (free
    modes), strain rates qdot, time t [s]."""
    q: np.ndarray
    qdot: np.ndarray
    t: float = 0.0

    @staticmethod
    def rest(model):
        return State(model.q0.copy(), np.zeros(model.n_dof), 0.0)

    def copy(self):
        return State(self.q.copy(), self.qdot.copy(), self.t)


def benchmark_cantilever_dict(n_sections=10, free_modes="all", length=0.5, radius=0.01):
    """The common benchmark case of docs/CONVENTIONS.md: L = 0.5 m, r = 0.01 m,
    E = 1 MPa, Poisson 0.5, 1000 kg/m^3, along +x, gravity -z."""
    return {
        "name": "benchmark_cantilever",
        "gravity": [0.0, 0.0, -9.81],
        "segments": [{
            "name": "rod", "length": length, "sections": n_sections,
            "cross_section": {"shape": "solid_circle", "radius": radius},
            "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.5, "density": 1000.0},
            "free_modes": free_modes,
        }],
    }


BEND45_RADIUS = 100.0                    # the 45-degree bend's arc radius (the classic problem has no units)


def bend45_dict(n_sections=8):
    """The 45-degree bend (Bathe and Bolourchi, 1979): a cantilever
    pre-curved to a 45-degree arc of radius 100 in the xy plane (towards
    +y), a unit square section, E = 1e7, G = E / 2 (A = 1, I = 1/12, J =
    1/6), every strain mode free, no gravity; the classic load is 600 out of
    its plane at the tip. Its length (78.5) trips the plausibility warning
    for metres: the problem has no units."""
    E, G, A, I, J = 1e7, 5e6, 1.0, 1.0 / 12, 1.0 / 6
    return {
        "name": "bend45",
        "gravity": [0.0, 0.0, 0.0],
        "segments": [{
            "name": "bend", "length": BEND45_RADIUS * math.pi / 4, "sections": n_sections,
            "reference_strain": [1.0, 0.0, 0.0, 0.0, 0.0, 1.0 / BEND45_RADIUS], "free_modes": "all",
            "sectional": {"stiffness": {"EA": E * A, "GA2": G * A, "GA3": G * A, "GJ": G * J, "EI2": E * I,
                                        "EI3": E * I},
                          "inertia": {"mass_per_length": 1.0, "J1": 1.0, "J2": 1.0, "J3": 1.0}},
        }],
    }
