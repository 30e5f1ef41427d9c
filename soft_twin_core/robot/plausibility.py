"""Physical plausibility of robot files (issue 25, item 9).

Two levels:

- impossible geometry is an error (ModelError naming the field): a
  chamber offset (or helical radius) outside the cross-section it runs in,
  revolute joint limits beyond +-2 pi;
- a tendon outside the cross-section is a warning, not an error: tendons
  guided by spacer disks around a thin backbone (a common continuum-robot
  design) do run outside the backbone's section; otherwise it is a unit
  slip;
- implausible values are a :class:`limits.PlausibilityWarning` naming the
  field and the likely unit slip: a soft member longer than 10 m
  (millimetres?), a cross-section dimension over 1 m (millimetres?), a
  Young's or shear modulus under 1 kPa (MPa?) or over 1 TPa, a density
  outside 10-100,000 kg/m^3 (g/cm^3?), an angle over 2 pi (degrees?).

The thresholds are far outside the soft robots this twin is for (the
shipped ones: 0.1-1 m long, radii 5-20 mm, E 0.1-10 MPa, 1000-1200 kg/m^3)
and outside any real material (E: aerogels ~1e4 Pa ... diamond 1.2e12 Pa;
density: polymer foams ~15 ... osmium 22,600 kg/m^3).
"""

import math
import warnings

from soft_twin_core.limits import PlausibilityWarning

MAX_MEMBER_LENGTH = 10.0          # m
MAX_SECTION_SIZE = 1.0            # m: radius, width, height
MIN_MODULUS, MAX_MODULUS = 1e3, 1e12     # Pa
MIN_DENSITY, MAX_DENSITY = 10.0, 1e5     # kg/m^3: the lightest foams ~15, g/cm^3 values 0.9-2.5
TWO_PI = 2.0 * math.pi


def warn(message):
    warnings.warn(message, PlausibilityWarning, stacklevel=3)


def check_length(where, length):
    if length > MAX_MEMBER_LENGTH:
        warn(f"{where}.length: {length:g} m is implausibly long for a soft member (over "
             f"{MAX_MEMBER_LENGTH:g} m); millimetres? {length:g} mm = {length / 1000:g} m (units are SI)")


def check_cross_section(where, d):
    """Warnings for the dimensions of a cross_section mapping (already validated)."""
    for key in ("radius", "outer_radius", "inner_radius", "width", "height"):
        v = d.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and v > MAX_SECTION_SIZE:
            warn(f"{where}.{key}: {v:g} m is implausibly large for a soft member's cross-section (over "
                 f"{MAX_SECTION_SIZE:g} m); millimetres? {v:g} mm = {v / 1000:g} m (units are SI)")


def check_material(where, E, G, density, has_G):
    for key, v in (("youngs_modulus", E),) + ((("shear_modulus", G),) if has_G else ()):
        if v < MIN_MODULUS:
            warn(f"{where}.{key}: {v:g} Pa is implausibly soft (under {MIN_MODULUS:g} Pa); megapascals? "
                 f"{v:g} MPa = {v * 1e6:g} Pa (units are SI: Pa)")
        elif v > MAX_MODULUS:
            warn(f"{where}.{key}: {v:g} Pa is stiffer than any material (over {MAX_MODULUS:g} Pa); "
                 f"check the units (SI: Pa)")
    if density < MIN_DENSITY:
        warn(f"{where}.density: {density:g} kg/m^3 is implausibly light (under {MIN_DENSITY:g} kg/m^3); "
             f"g/cm^3? {density:g} g/cm^3 = {density * 1000:g} kg/m^3 (units are SI)")
    elif density > MAX_DENSITY:
        warn(f"{where}.density: {density:g} kg/m^3 is denser than any material (over {MAX_DENSITY:g} "
             f"kg/m^3); check the units (SI: kg/m^3)")


def check_angles(where, values):
    """Warning for angles (rad) over 2 pi in magnitude: degrees?"""
    vals = [float(v) for v in values]
    if any(abs(v) > TWO_PI for v in vals):
        shown = [round(v, 6) for v in vals]
        rad = [round(math.radians(v), 4) for v in vals]
        warn(f"{where}: {shown} has an angle over 2 pi rad; degrees? {shown} deg = {rad} rad "
             f"(angles are in radians)")


def check_revolute_limits(where, limits, error):
    """Error for revolute joint limits beyond +-2 pi (a joint that turns
    more than a full turn either way is not a limit; likely degrees)."""
    lo, hi = limits
    if abs(lo) > TWO_PI + 1e-9 or abs(hi) > TWO_PI + 1e-9:
        raise error(f"{where}.limits: [{lo:g}, {hi:g}] rad is beyond +-2 pi on a revolute joint; "
                    f"degrees? [{lo:g}, {hi:g}] deg = [{math.radians(lo):.4g}, {math.radians(hi):.4g}] rad "
                    f"(angles are in radians; omit limits for an unlimited joint)")


def section_extent(d):
    """(kind, size) of a cross_section mapping for the offset check:
    ("circle", radius), ("rect", (half width, half height)), or None
    (explicit: no geometry to check against)."""
    shape = d.get("shape", "solid_circle")
    if shape == "solid_circle":
        return "circle", float(d["radius"])
    if shape == "hollow_tube":
        return "circle", float(d["outer_radius"])
    if shape == "rectangle":
        return "rect", (0.5 * float(d["width"]), 0.5 * float(d["height"]))
    return None


def _inside(extent, y, z):
    kind, size = extent
    tol = 1e-9
    if kind == "circle":
        return math.hypot(y, z) <= size * (1 + tol) + 1e-15
    return abs(y) <= size[0] * (1 + tol) + 1e-15 and abs(z) <= size[1] * (1 + tol) + 1e-15


def _describe(extent):
    kind, size = extent
    if kind == "circle":
        return f"the cross-section of radius {size:g} m"
    return f"the {2 * size[0]:g} m x {2 * size[1]:g} m rectangular cross-section"


def check_actuator_offsets(actuators, spans, error):
    """Error for a chamber (warning for a tendon) whose path leaves the
    cross-section of a segment it runs along. ``spans``: [(s0, s1, extent or None, where)]
    of the segments in arc length. The offset is linear in s on a segment
    (straight, converging), so its ends decide; a helix keeps its radius."""
    for i, a in enumerate(actuators):
        for s0, s1, extent, seg in spans:
            lo, hi = max(s0, a.start), min(s1, a.end)
            if extent is None or hi <= lo:
                continue
            if a.routing == "helical":
                if not _inside(extent, a.radius, 0.0) or (extent[0] == "rect" and not _inside(extent, 0.0, a.radius)):
                    _outside(a, error, f"actuators[{i}] ({a.name}).radius: {a.radius:g} m is outside "
                             f"{_describe(extent)} of {seg}")
                    break
                continue
            for s in (lo, hi):
                d = a.offset_at(s)[0]
                y, z = float(d[1]), float(d[2])
                if not _inside(extent, y, z):
                    key = "offset" if a.routing == "straight" or s == a.start else "offset_end"
                    _outside(a, error, f"actuators[{i}] ({a.name}).{key}: [{y:g}, {z:g}] m (at s = {s:g} m) is "
                             f"outside {_describe(extent)} of {seg}")
                    break
            else:
                continue
            break


def _outside(a, error, text):
    if a.kind == "chamber":
        raise error(f"{text}: a chamber must lie inside the material (millimetres? units are SI)")
    warn(f"{text}: a tendon guided by spacer disks around a thin backbone? Otherwise "
         f"millimetres? (units are SI)")
