"""Material stresses of a soft member's cross-section from its internal
wrench (linear elastic beam theory), the one place for them: the
articulated outputs (:mod:`outputs`), the studies' maximum stress
(:mod:`study_case`) and the node's diagnostics use these functions.

At a cross-section with internal wrench ``[N, V2, V3, T, M2, M3]`` (body
frame, x along the tangent; :func:`statics.internal_wrenches`):

* normal: ``sigma = N/A + M2 z/I2 - M3 y/I3`` over the section; its peak
  magnitude is ``|N|/A + sqrt((M2/I2)^2 + (M3/I3)^2) c`` for circles and
  tubes (c = outer radius, I2 = I3) and ``|N|/A + |M2| cz/I2 + |M3| cy/I3``
  for rectangles (corners);
* shear: torsion ``|T| c/J`` (circles, tubes; rectangles: ``|T| b/J`` with b
  the smaller side, thin-wall estimate) plus the peak transverse shear
  ``k |V|/A`` (k = 4/3 solid circle, 2 thin tube, 3/2 rectangle), added as
  an upper bound;
* von Mises ``sqrt(sigma^2 + 3 tau^2)`` at the outer fibre with the
  torsional shear there (the transverse shear vanishes at the outer fibre
  of the bending plane): exact for round sections, for rectangles an upper
  bound (corner normal stress with the mid-side torsional shear);
* explicit sections and ``sectional`` members have no fibre distance: NaN.

Section properties (A, I2, I3, J) are those of the model's stiffness
(:func:`model._cross_section`). Stresses in Pa. The largest von Mises
stress of a solve (:func:`outputs.max_von_mises`) evaluates a point on the
boundary of two sections with both cross-sections (the larger counts).
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core.robot.model import _cross_section


@dataclass(frozen=True, eq=False)
class SectionGeometry:
    """Cross-section geometry of a soft section, for stresses: area A
    [m^2], second moments I2, I3 [m^4], torsion constant J [m^4], extreme
    fibre distances cy, cz [m] along local y and z, shape name."""
    shape: str
    A: float
    I2: float
    I3: float
    J: float
    cy: float
    cz: float


def section_geometry(cs):
    """SectionGeometry of a robot file's ``cross_section`` mapping (already
    validated), None for shapes without a fibre distance (explicit)."""
    shape = cs.get("shape", "solid_circle")
    if shape == "solid_circle":
        cy = cz = float(cs["radius"])
    elif shape == "hollow_tube":
        cy = cz = float(cs["outer_radius"])
    elif shape == "rectangle":
        cy, cz = 0.5 * float(cs["width"]), 0.5 * float(cs["height"])
    else:
        return None
    c = _cross_section(cs, "cross_section")
    return SectionGeometry(shape, c.area, c.I2, c.I3, c.J, cy, cz)


def _stress_parts(g, w):
    """(peak normal, torsional shear at the outer fibre, peak transverse
    shear) [Pa] of wrenches w (..., 6) on a SectionGeometry g."""
    N, V2, V3, T, M2, M3 = (w[..., k] for k in range(6))
    V = np.hypot(V2, V3)
    if g.shape in ("solid_circle", "hollow_tube"):
        normal = np.abs(N) / g.A + np.hypot(M2 / g.I2, M3 / g.I3) * g.cy
        torsion = np.abs(T) * g.cy / g.J
        transverse = (4.0 / 3.0 if g.shape == "solid_circle" else 2.0) * V / g.A
    else:
        normal = np.abs(N) / g.A + np.abs(M2) * g.cz / g.I2 + np.abs(M3) * g.cy / g.I3
        torsion = np.abs(T) * 2 * min(g.cy, g.cz) / g.J
        transverse = 1.5 * V / g.A
    return normal, torsion, transverse


def peak_stresses(geometry, wrench):
    """(normal, shear) peak stresses [Pa] of a cross-section of ``geometry``
    (a SectionGeometry or None) under internal wrenches (..., 6); the shear
    adds the torsional and the transverse peaks (an upper bound). Arrays of
    the leading shape, NaN when the geometry is unknown."""
    w = np.asarray(wrench, dtype=float)
    if geometry is None:
        nan = np.full(w.shape[:-1], np.nan)
        return nan, nan.copy()
    normal, torsion, transverse = _stress_parts(geometry, w)
    return normal, torsion + transverse


def von_mises(wrench, geometry):
    """Von Mises stress [Pa] (P,) of internal wrenches (P, 6) at the outer
    fibre, where the normal stress peaks: sqrt(sigma^2 + 3 tau^2) with the
    torsional shear there (the transverse shear vanishes at the outer fibre
    of the bending plane); NaN if the geometry is unknown."""
    w = np.atleast_2d(np.asarray(wrench, dtype=float))
    if geometry is None:
        return np.full(w.shape[:-1], np.nan)
    normal, torsion, _ = _stress_parts(geometry, w)
    return np.sqrt(normal ** 2 + 3 * torsion ** 2)
