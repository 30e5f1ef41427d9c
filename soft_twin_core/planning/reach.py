"""The reachable workspace of a robot over its actuation space.

(Not :mod:`workspace`, which holds the engine's per-call arrays.)

The actuator inputs (tendon tensions [N], chamber pressures [Pa]) are
sampled within their limits -- every corner of the actuation box plus a
Latin-hypercube, random or grid design inside it -- and the static
equilibrium is solved for each, cold-started from the rest shape (so every
sample is independent of the others and of the order it is solved in,
which is what lets a study split them over workers). The positions of the
robot's tip frame (:func:`mechanism.tip_frame`) form the point cloud; any
robot (a classic rod, a tree with joint commands, a closed chain) goes
through the same equilibrium solver; its volume estimate is the **convex hull**'s
(:func:`hull_summary`, Qhull through ``scipy.spatial.ConvexHull``), which
over-estimates a non-convex workspace (no alpha shape: its radius would be
one more tuning knob; the hull's vertices are the boundary reported).
A workspace that lies in a plane or on a line (one actuated direction) has
volume 0 and reports the area or length of its hull in that plane.

Options (``compute.workspace`` of a study, or ``soft-twin-sim workspace``)::

    samples: 200          # design points inside the box (grid: points per actuator)
    design: lhs           # lhs | random | grid
    seed: 0
    corners: true         # also every corner of the actuation box (2^k, k <= 10)
    actuators: [tendon_y_pos, tendon_z_pos]   # which inputs vary (default: all);
                                              # the others keep the scenario's values
    limit: 10.0           # the range [0, limit] of every varied input, unless
    limits: {tendon_y_pos: 8.0, chamber_1: [0, 4.0e4]}   # per actuator: max or [min, max]

An input's range is its entry in ``limits``, else ``limit``, else its
``limit`` in the robot file (``[0, limit]``); an actuator with none of them
is an error, and so is a range beyond the robot file's declared limit, or a
negative tension.
"""

import math

import numpy as np

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError
from soft_twin_core.limits import MAX_STUDY_SAMPLES, check_limit
from soft_twin_core.robot.mechanism import tip_frame
from soft_twin_core.robot.model import parse_number
from soft_twin_core.solve.constrained import make_inputs, solve_equilibrium

_OPTION_KEYS = {"samples", "design", "seed", "corners", "actuators", "limit", "limits"}


def parse_workspace_options(v, where, error=ValueError):
    """Checked options (see the module docstring); ``error`` naming ``where``."""
    if v is None or v is True:
        v = {}
    if not isinstance(v, dict):
        raise error(f"{where}: expected a mapping of options, got {v!r}")
    unknown = set(v) - _OPTION_KEYS
    if unknown:
        raise error(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(_OPTION_KEYS)}")
    n = v.get("samples", 200)
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise error(f"{where}.samples: expected an integer >= 0, got {n!r}")
    check_limit(f"{where}.samples", n, MAX_STUDY_SAMPLES, error)     # before any allocation (issue 25)
    design = v.get("design", "lhs")
    if design not in ("lhs", "random", "grid"):
        raise error(f"{where}.design: expected lhs, random or grid, got {design!r}")
    seed = v.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise error(f"{where}.seed: expected an integer >= 0, got {seed!r}")
    corners = v.get("corners", True)
    if not isinstance(corners, bool):
        raise error(f"{where}.corners: expected true or false, got {corners!r}")
    acts = v.get("actuators")
    if acts is not None and (not isinstance(acts, list) or not acts or not all(isinstance(a, str) for a in acts)):
        raise error(f"{where}.actuators: expected a non-empty list of actuator names, got {acts!r}")
    limit = None
    if v.get("limit") is not None:
        limit = parse_number(v["limit"], f"{where}.limit", error)
        if limit <= 0:
            raise error(f"{where}.limit: must be > 0, got {limit}")
    limits = {}
    for name, r in (v.get("limits") or {}).items():
        w = f"{where}.limits.{name}"
        if isinstance(r, list):
            if len(r) != 2:
                raise error(f"{w}: expected a maximum or [min, max], got {r!r}")
            lo, hi = parse_number(r[0], w + "[0]", error), parse_number(r[1], w + "[1]", error)
        else:
            lo, hi = 0.0, parse_number(r, w, error)
        if not lo < hi:
            raise error(f"{w}: expected min < max, got [{lo}, {hi}]")
        limits[str(name)] = (lo, hi)
    if not corners and n == 0:
        raise error(f"{where}: no samples (samples: 0 and corners: false)")
    return {"samples": n, "design": design, "seed": seed, "corners": corners, "actuators": acts,
            "limit": limit, "limits": limits}


def actuation_ranges(model, opts, error=ValueError):
    """(indices, low, high) of the varied actuators of ``model``; ``error``
    naming the actuator whose range is missing or not allowed."""
    names = list(model.actuator_names)
    if not names:
        raise error("workspace: the robot has no actuators")
    varied = opts["actuators"] or names
    for nm in list(varied) + list(opts["limits"]):
        if nm not in names:
            raise error(f"workspace: unknown actuator {nm!r}; the robot has {names}")
    idx, lo, hi = [], [], []
    for nm in varied:
        a = model.actuators[names.index(nm)]
        if nm in opts["limits"]:
            r = opts["limits"][nm]
        elif opts["limit"] is not None:
            r = (0.0, opts["limit"])
        elif math.isfinite(a.upper):            # the robot file's range (limit, min, max)
            r = (max(0.0, a.lower), a.upper)
        else:
            raise error(f"workspace: actuator {nm} has no limit in the robot file; give "
                        f"compute.workspace.limits.{nm} (or limit) for the range to sample")
        if a.kind == "tendon" and r[0] < 0:
            raise error(f"workspace.limits.{nm}: a tendon tension must be >= 0 N, got {r[0]}")
        if max(abs(r[0]), abs(r[1])) > a.limit * (1 + 1e-12):
            raise error(f"workspace.limits.{nm}: [{r[0]}, {r[1]}] exceeds the robot file's limit {a.limit}")
        if r[0] < a.lower or r[1] > a.upper:
            raise error(f"workspace.limits.{nm}: [{r[0]}, {r[1]}] lies outside the robot file's range "
                        f"[{a.lower}, {a.upper}] (min/max)")
        idx.append(names.index(nm))
        lo.append(float(r[0]))
        hi.append(float(r[1]))
    return np.array(idx, dtype=int), np.array(lo), np.array(hi)


def sample_actuations(model, opts, base=None):
    """(U, is_corner): the sampled input vectors (n, n_actuators), the
    actuators not varied at ``base`` (default 0); the corners of the box
    first (if ``corners``, at most 2^10 of them), then the design points."""
    idx, lo, hi = actuation_ranges(model, opts)
    k = len(idx)
    base = np.zeros(len(model.actuators)) if base is None else np.asarray(base, dtype=float)
    unit = []
    if opts["corners"]:
        if k > 10:
            raise ValueError(f"workspace: {k} varied actuators give 2^{k} corners; set corners: false")
        unit.append(np.array([[(c >> j) & 1 for j in range(k)] for c in range(2 ** k)], dtype=float))
    n = opts["samples"]
    if n:
        if opts["design"] == "lhs":
            from scipy.stats import qmc
            unit.append(qmc.LatinHypercube(k, rng=opts["seed"]).random(n))
        elif opts["design"] == "random":
            unit.append(np.random.default_rng(opts["seed"]).random((n, k)))
        else:
            import itertools
            if float(n) ** k > MAX_STUDY_SAMPLES:     # before any allocation (issue 25)
                raise ValueError(f"workspace: a grid of {n} points per actuator over {k} actuators gives "
                                 f"{float(n) ** k:.4g} samples, which exceeds the limit of {MAX_STUDY_SAMPLES} "
                                 f"(soft_twin_core.limits)")
            g = np.linspace(0.0, 1.0, n)
            unit.append(np.array(list(itertools.product(g, repeat=k)), dtype=float))
    u = np.concatenate(unit, axis=0)
    U = np.tile(base, (len(u), 1))
    U[:, idx] = lo + u * (hi - lo)
    n_corner = 2 ** k if opts["corners"] else 0
    return U, np.arange(len(U)) < n_corner


def tip_positions(scenario, U):
    """Positions (n, 3) [m, world] of the robot's tip frame
    (:func:`mechanism.tip_frame`) at the static equilibria under the
    scenario's loads, joint commands and gravity with the actuator inputs
    ``U`` (n, n_actuators), each cold-started from the reference shape; a
    sample whose solve fails gives NaN and its reason in the returned list
    of (row, message). Any robot: a classic rod, a tree, a closed chain."""
    mech = scenario.mech
    ref = mech.frame(tip_frame(mech))
    ws = Workspace(mech.tree)
    loads, frame_loads = scenario.loads_at(None), scenario.frame_loads_at(None)
    P = np.full((len(U), 3), np.nan)
    failed = []
    for i, u in enumerate(U):
        try:
            inp = make_inputs(mech, u, scenario.efforts, scenario.positions, None, loads, frame_loads)
            eq = solve_equilibrium(mech, inputs=inp, targets=_base_targets(scenario))
            P[i] = alg.point_poses(mech.tree, ws, eq.q, [ref.joint], [ref.x])[0][:3, 3]
        except (StaticsError, ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            failed.append((i, f"{type(e).__name__}: {e}"))
    return P, failed


def _base_targets(scenario):
    """A prescribed base at its pose at t = 0 (None: no prescribed base)."""
    g = scenario.base_pose_at(0.0)
    return None if g is None else [g if c.name == "base" else None for c in scenario.mech.constraints]


def hull_summary(points):
    """Volume estimate and boundary of a point cloud (n, 3) [m] (NaN rows
    ignored): ``volume_m3`` and ``area_m2`` of the convex hull (3-D), or, for
    a planar cloud (the third singular value of the centred points below
    1e-9 of the first), volume 0 and ``area_m2`` the planar hull's area
    (``length_m`` for a line); ``dimension``; ``extent_min``/``extent_max``
    (3,); ``boundary``: indices (into ``points``) of the hull's vertices;
    ``facets``: its triangles (3-D) or its polygon (2-D) as index arrays."""
    from scipy.spatial import ConvexHull
    P = np.asarray(points, dtype=float)
    ok = np.flatnonzero(np.all(np.isfinite(P), axis=1))
    out = {"n_points": int(len(ok)), "volume_m3": 0.0, "area_m2": 0.0, "length_m": 0.0, "dimension": 0,
           "extent_min": np.full(3, np.nan), "extent_max": np.full(3, np.nan),
           "boundary": np.zeros(0, int), "facets": np.zeros((0, 3), int),
           "method": "convex hull (scipy.spatial.ConvexHull / Qhull)"}
    if len(ok) == 0:
        return out
    Q = P[ok]
    out["extent_min"], out["extent_max"] = Q.min(axis=0), Q.max(axis=0)
    c = Q - Q.mean(axis=0)
    _, s, Vt = np.linalg.svd(c, full_matrices=False)
    if s[0] <= 1e-15:
        out["boundary"] = ok[:1]
        return out
    rank = int(np.sum(s > 1e-9 * s[0]))
    out["dimension"] = rank
    if rank >= 3 and len(Q) >= 4:
        h = ConvexHull(Q)
        out["volume_m3"], out["area_m2"] = float(h.volume), float(h.area)
        out["boundary"], out["facets"] = ok[h.vertices], ok[h.simplices]
    elif rank == 2 or (rank >= 3 and len(Q) < 4):
        out["dimension"] = 2
        xy = c @ Vt[:2].T
        h = ConvexHull(xy)
        out["area_m2"] = float(h.volume)          # 2-D: volume is the area
        out["boundary"] = ok[h.vertices]
        out["facets"] = ok[h.vertices][None, :]
    else:
        t = c @ Vt[0]
        out["length_m"] = float(t.max() - t.min())
        out["boundary"] = ok[[int(np.argmin(t)), int(np.argmax(t))]]
    return out


def summary_columns(hs, n_failed):
    """Flat {name: value} of a :func:`hull_summary` for a results row."""
    out = {"volume_m3": hs["volume_m3"], "hull_area_m2": hs["area_m2"], "dimension": hs["dimension"],
           "samples_ok": hs["n_points"], "samples_failed": int(n_failed)}
    for j, ax in enumerate("xyz"):
        out[f"{ax}_min_m"] = float(hs["extent_min"][j])
        out[f"{ax}_max_m"] = float(hs["extent_max"][j])
    return out


def workspace_of(scenario, opts):
    """Sample, solve and summarise one robot's workspace: a dict with
    ``U`` (inputs), ``corner`` (mask), ``points`` (n, 3), ``failed``
    [(row, reason)], ``hull`` (:func:`hull_summary`)."""
    U, corner = sample_actuations(scenario.mech, opts, scenario.actuation)
    P, failed = tip_positions(scenario, U)
    return {"U": U, "corner": corner, "points": P, "failed": failed, "hull": hull_summary(P)}
