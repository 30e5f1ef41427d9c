"""Material stresses from the internal wrenches of a rod (beam theory).

At a cross-section with internal wrench ``[N, V2, V3, T, M2, M3]`` (body
frame, x along the tangent; :func:`statics.internal_wrenches`):

- solid circle (radius r) and hollow tube (outer radius r): the largest
  normal stress ``|N|/A + sqrt(M2^2 + M3^2) r / I`` and the torsional shear
  ``|T| r / J`` at the outer fibre; von Mises ``sqrt(sigma^2 + 3 tau^2)``
  there (exact for these sections, transverse shear neglected: it vanishes
  at the outer fibre in the bending plane);
- rectangle (width w along y, height h along z): the corner stress
  ``|N|/A + |M2| (h/2) / I2 + |M3| (w/2) / I3`` and ``tau = |T| b / J``
  (b the smaller side; exact for thin strips); von Mises combined as if
  both were at one point: an upper bound;
- explicit sections and ``sectional`` members have no fibre distance: NaN.

Stresses in Pa. A sample point on the boundary of two members is
evaluated with both cross-sections (the larger stress counts).
"""

import math

import numpy as np


def _geometry(cs):
    """(kind, A, I2, I3, J, c2, c3, b) of a robot file's cross_section
    mapping; kind None when no fibre distance is known."""
    from .model import parse_number
    shape = cs.get("shape", "solid_circle")

    def num(k):
        return parse_number(cs[k], k)
    if shape in ("solid_circle", "hollow_tube"):
        if shape == "solid_circle":
            ro, ri = num("radius"), 0.0
        else:
            ro, ri = num("outer_radius"), num("inner_radius")
        A = math.pi * (ro ** 2 - ri ** 2)
        I = math.pi * (ro ** 4 - ri ** 4) / 4
        J = num("J") if "J" in cs else 2 * I
        return ("round", A, I, I, J, ro, ro, ro)
    if shape == "rectangle":
        w, h = num("width"), num("height")
        a, b = max(w, h), min(w, h)
        J = num("J") if "J" in cs else a * b ** 3 * (1 / 3 - 0.21 * (b / a) * (1 - b ** 4 / (12 * a ** 4)))
        return ("rect", w * h, w * h ** 3 / 12, h * w ** 3 / 12, J, h / 2, w / 2, b)
    return (None,) * 8


def von_mises(W, geom):
    """Von Mises stress [Pa] (P,) of internal wrenches W (P, 6) on a
    cross-section of :func:`_geometry` ``geom`` (NaN if unknown)."""
    kind, A, I2, I3, J, c2, c3, b = geom
    W = np.atleast_2d(W)
    if kind is None:
        return np.full(len(W), np.nan)
    N, T, M2, M3 = W[:, 0], W[:, 3], W[:, 4], W[:, 5]
    if kind == "round":
        sigma = np.abs(N) / A + np.hypot(M2, M3) * c2 / I2
        tau = np.abs(T) * c2 / J
    else:
        sigma = np.abs(N) / A + np.abs(M2) * c2 / I2 + np.abs(M3) * c3 / I3
        tau = np.abs(T) * b / J
    return np.sqrt(sigma ** 2 + 3 * tau ** 2)


def max_von_mises(robot_doc, s, W):
    """(largest von Mises stress [Pa], its arc length [m]) over the sample
    points ``s`` (P,) [m] with internal wrenches ``W`` (P, 6), the members'
    cross-sections taken from the robot file mapping ``robot_doc``; (NaN,
    NaN) if no member has a known fibre distance."""
    from .model import parse_number
    s = np.asarray(s, dtype=float)
    best = np.full(len(s), np.nan)
    start = 0.0
    for seg in robot_doc["segments"]:
        L = parse_number(seg["length"], "length")
        end = start + L
        inside = (s >= start - 1e-12) & (s <= end + 1e-12)
        if "cross_section" in seg and np.any(inside):
            v = von_mises(W[inside], _geometry(seg["cross_section"]))
            best[inside] = np.fmax(best[inside], v)
        start = end
    if not np.any(np.isfinite(best)):
        return math.nan, math.nan
    i = int(np.nanargmax(best))
    return float(best[i]), float(s[i])
