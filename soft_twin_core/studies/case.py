"""One case of a design study: build its scenario, compute, record a row.

:func:`run_case` is what a Dask worker runs (through :func:`run_cases`, a
chunk of cases per task); it never raises for a case: a case whose build or
solve fails comes back with ``status = "failed"`` and the reason in
``error``. Outputs (columns, prefixed by the computation):

statics (:func:`scenario.run_statics`, any robot, cold start from the rest shape):
  ``tip_pose``: ``tip_position_{x,y,z}`` [m, world] and
  ``tip_quaternion_{x,y,z,w}`` (w >= 0); ``base_wrench``:
  ``base_wrench_{fx,fy,fz,mx,my,mz}`` [N, N m] (the support's reaction,
  world axes, about the base origin); ``max_stress``: ``max_stress_pa``
  and its arc length along its member ``max_stress_s_m``
  (:func:`outputs.max_von_mises`, von Mises at every member's samples);
  ``iterations``, ``residual``, ``stable``; ``strains``:
  ``strains_<section>_<mode>``; the main member's (a rod's backbone)
  ``backbone``: ``backbone_s_<i>`` [m] and
  ``backbone_<i>_{x,y,z}`` [m, world]; ``internal_wrenches``:
  ``internal_wrenches_<i>_{fx,...,mz}`` (body frame, at the backbone samples).
dynamics (:func:`scenario.run_dynamics` from rest, the scenario's
  profiles): the state at the end: ``tip_pose``, ``base_wrench`` (with
  inertia), ``strains``; ``settling_time``: ``settling_time_s`` (the first
  time after which the tip stays within ``settling_band`` of its travel
  from the static equilibrium under the final inputs; NaN if it never does
  within the duration) and ``settled``; ``max_tip_speed``:
  ``max_tip_speed_m_s``; ``iterations``: the most Newton iterations of a step;
  ``tip_velocity`` (``tip_velocity_{x,y,z}`` [m/s], world) and
  ``strain_rates`` (``strain_rates_<section>_<mode>``) at the end.
workspace (:mod:`workspace_map`): ``volume_m3``, ``hull_area_m2``,
  ``dimension``, ``samples_ok``, ``samples_failed``, ``{x,y,z}_{min,max}_m``;
  the point cloud goes to the study's points table (row key ``_points``).

Every row also has ``compute_time_s`` (wall time of the case in its
worker), ``started_unix_s`` (when it started) and ``worker`` (host:pid).
"""

import math
import os
import socket
import time
import warnings

import numpy as np

from soft_twin_core.files.scenario import run_dynamics, run_statics
from soft_twin_core.limits import PlausibilityWarning
from soft_twin_core.planning.reach import summary_columns, workspace_of
from soft_twin_core.robot.model import STRAIN_NAMES
from soft_twin_core.solve.outputs import max_von_mises
from soft_twin_core.studies.study import build_scenario, case_documents, parameter_columns
from soft_twin_core.warmup import run

_VEC3 = ("x", "y", "z")
_WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")


def _quaternion(R):
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(np.asarray(R).reshape(3, 3)).as_quat()   # [x, y, z, w]
    return -q if q[3] < 0 else q


def _pose_cols(prefix, p, R, out):
    for a, v in zip(_VEC3, p):
        out[f"{prefix}tip_position_{a}"] = float(v)
    for a, v in zip(("x", "y", "z", "w"), _quaternion(R)):
        out[f"{prefix}tip_quaternion_{a}"] = float(v)


def _strain_cols(prefix, strains, out):
    for i, row in enumerate(np.asarray(strains)):
        for name, v in zip(STRAIN_NAMES, row):
            out[f"{prefix}strains_{i}_{name}"] = float(v)


def settling_time(t, p, p_ref, band):
    """The first time t_s after which |p(t) - p_ref| <= band |p_ref - p(0)|
    for every later sample (p (N, 3), t (N,)); 0 if it always holds, NaN if
    the last sample is still outside the band."""
    t = np.asarray(t, dtype=float)
    d = np.linalg.norm(np.asarray(p, dtype=float) - p_ref, axis=1)
    tol = band * np.linalg.norm(np.asarray(p_ref) - np.asarray(p[0]))
    outside = np.flatnonzero(d > tol)
    if len(outside) == 0:
        return 0.0
    k = outside[-1] + 1
    return float(t[k]) if k < len(t) else math.nan


def _statics(study, sc, robot, opts, out):
    r = run_statics(sc, opts["points_per_section"])
    rec = set(study.record)
    P = "statics."
    if "tip_pose" in rec:
        _pose_cols(P, r["tip_position"], r["tip_rotation"], out)
    if "base_wrench" in rec:
        for a, v in zip(_WRENCH, r["base_wrench"]):
            out[f"{P}base_wrench_{a}"] = float(v)
    if "max_stress" in rec:
        smax, s_at = max_von_mises(sc.mech, r["members"])
        out[P + "max_stress_pa"], out[P + "max_stress_s_m"] = smax, s_at
    if "iterations" in rec:
        out[P + "iterations"] = int(r["iterations"])
    if "residual" in rec:
        out[P + "residual"] = float(r["residual"])
    if "stable" in rec:
        out[P + "stable"] = bool(r["stable"])
    if "strains" in rec:
        _strain_cols(P, r["strains"], out)
    if "backbone" in rec:           # the backbone samples: arc length and position
        for i, (s_i, p) in enumerate(zip(r["backbone_s"], r["backbone_positions"])):
            out[f"{P}backbone_s_{i}"] = float(s_i)
            for a, v in zip(_VEC3, p):
                out[f"{P}backbone_{i}_{a}"] = float(v)
    if "internal_wrenches" in rec:
        for i, w in enumerate(r["internal_wrenches"]):
            for a, v in zip(_WRENCH, w):
                out[f"{P}internal_wrenches_{i}_{a}"] = float(v)


def _dynamics(study, sc, robot, opts, out):
    from scipy.spatial.transform import Rotation
    r = run_dynamics(sc, opts["duration"], opts["dt"], 0, opts["theta"], None, 10, opts["record_every"])
    if "error" in r:
        raise RuntimeError(f"dynamics: {r['error']}")
    rec = set(study.record)
    P = "dynamics."
    if "tip_pose" in rec:
        _pose_cols(P, r["tip_position"][-1], Rotation.from_quat(r["tip_orientation"][-1]).as_matrix(), out)
    if "base_wrench" in rec:
        for a, v in zip(_WRENCH, r["base_wrench"][-1]):
            out[f"{P}base_wrench_{a}"] = float(v)
    if "settling_time" in rec:
        T = r["time"][-1]
        eq = run_statics(sc, 1, time=T)           # the equilibrium under the final inputs
        ts = settling_time(r["time"], r["tip_position"], np.asarray(eq["tip_position"]), opts["settling_band"])
        out[P + "settling_time_s"] = ts
        out[P + "settled"] = bool(np.isfinite(ts))
    if "max_tip_speed" in rec:
        out[P + "max_tip_speed_m_s"] = float(np.linalg.norm(np.asarray(r["tip_velocity"]), axis=1).max())
    if "iterations" in rec:
        out[P + "iterations"] = int(max(r["newton_iterations"]))
    if "strains" in rec:
        _strain_cols(P, r["strains"][-1], out)
    if "tip_velocity" in rec:
        for a, v in zip(_VEC3, r["tip_velocity"][-1]):
            out[f"{P}tip_velocity_{a}"] = float(v)
    if "strain_rates" in rec:
        for i, row in enumerate(np.asarray(r["strain_rates"][-1])):
            for name, v in zip(STRAIN_NAMES, row):
                out[f"{P}strain_rates_{i}_{name}"] = float(v)


def _workspace(study, sc, robot, opts, out):
    w = workspace_of(sc, opts)
    for k, v in summary_columns(w["hull"], len(w["failed"])).items():
        out["workspace." + k] = v
    names = sc.mech.actuator_names
    pts = {"sample": np.arange(len(w["U"])).tolist(), "corner": w["corner"].tolist()}
    for j, nm in enumerate(names):
        pts[nm] = w["U"][:, j].tolist()
    for j, a in enumerate(_VEC3):
        pts[f"tip_position_{a}"] = w["points"][:, j].tolist()
    out["_points"] = pts


def run_case(study, index, values, key):
    """The results row of one case (a dict; see the module docstring)."""
    t0 = time.perf_counter()
    started = time.time()
    row = {"case": int(index), "case_key": key}
    row.update(parameter_columns(study, values))
    row["status"], row["error"] = "ok", ""
    outs = {}
    try:
        robot, _ = case_documents(study, values)      # the case's cross-sections, for the stresses
        with warnings.catch_warnings():             # reported once per field by study.validate_cases
            warnings.simplefilter("ignore", PlausibilityWarning)
            sc = build_scenario(study, values)
        for name, fn in (("statics", _statics), ("dynamics", _dynamics), ("workspace", _workspace)):
            if name in study.compute:
                fn(study, sc, robot, study.compute[name], outs)
    except Exception as e:          # a case never aborts the study: its reason is recorded
        row["status"], row["error"] = "failed", f"{type(e).__name__}: {e}"[:2000]
        outs = {}
    row.update(outs)
    row["compute_time_s"] = time.perf_counter() - t0
    row["started_unix_s"] = started
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return row


def run_cases(study, chunk):
    """Rows of a chunk of cases [(index, values, key), ...] (one Dask task)."""
    _warm()
    return [run_case(study, i, v, k) for i, v, k in chunk]


_WARM = {"done": False, "seconds": None}


def _warm():
    """Load the compiled kernels (numba's disk cache) once per process, so
    the first case does not pay for it; returns the time it took."""
    if not _WARM["done"]:
        t0 = time.perf_counter()
        run()
        _quaternion(np.eye(3))            # imports scipy.spatial.transform (~0.5 s) here, not in a case
        _WARM["done"], _WARM["seconds"] = True, time.perf_counter() - t0
    return _WARM["seconds"]
