"""The state estimator run over a recorded time series (issue 29):
``soft-twin-sim estimate``. The record is a :class:`calibration.Recording`
with times -- a CSV (:func:`calibration.read_csv`, column ``t``) or an MCAP
of the twin's and the estimator node's topics
(:func:`mcap_data.read_time_series`) --, the filter the twin's EKF
(:class:`ekf.EKF`) at a fixed step ``dt`` (default: the median spacing of
the rows): between two rows it predicts ``round(dt_rows / dt)`` steps with
the later row's inputs (the command in force when that row was read), then
updates with that row's readings (a reading not seen is dropped).

Out (:class:`EstimationRun`): per row the filter's prediction of the
tip-most sensor's position and its standard deviation, that sensor's
reading, the estimated tip load (payload [kg] or wrench) with its standard
deviation, and the innovation statistics of the update: its normalised
innovation squared (NIS) summed over the accepted readings and their
number of dimensions m. A consistent filter's NIS is chi-square with m
degrees of freedom: mean 1 per dimension, 95 % of the updates inside the
two-sided 95 % band. :func:`soft_twin_core.viz.plots.estimation_figure`
draws the three.
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core.estimation import sensors as sn
from soft_twin_core.estimation.calibration import CalibrationError, _tip_sensor, as_mechanism, position_joints
from soft_twin_core.estimation.ekf import EKF


@dataclass
class EstimationRun:
    """The estimates of a replayed record (module docstring); arrays over
    its N rows. ``sensor``: the tip-most sensor's name; ``wrench_mode``:
    the EKF's (None, "payload", "force", "wrench")."""
    time: np.ndarray
    sensor: str
    measured: np.ndarray            # (N, 3) [m], NaN where not seen
    estimated: np.ndarray           # (N, 3) [m]
    estimated_std: np.ndarray       # (N, 3) [m]
    wrench_mode: str
    wrench: np.ndarray              # (N, 6) [N, N m], world axes
    wrench_std: np.ndarray
    payload: np.ndarray             # (N,) [kg] (NaN unless estimated)
    payload_std: np.ndarray
    nis: np.ndarray                 # (N,) summed over the accepted readings
    nis_dof: np.ndarray             # (N,) their dimensions (0: no update)
    gated: np.ndarray               # (N,) readings gated as outliers
    integrator_failures: int

    def consistency(self):
        """(mean NIS per dimension, fraction of the updates inside their
        two-sided 95 % chi-square band) over the rows with an update."""
        from scipy.stats import chi2
        ok = self.nis_dof > 0
        if not np.any(ok):
            return float("nan"), float("nan")
        m, v = self.nis_dof[ok], self.nis[ok]
        inside = (v >= chi2.ppf(0.025, m)) & (v <= chi2.ppf(0.975, m))
        return float(v.sum() / m.sum()), float(np.mean(inside))

    def summary(self):
        """A dict for the JSON report (the last estimates and the statistics)."""
        mean_nis, inside = self.consistency()
        err = np.linalg.norm(self.estimated - self.measured, axis=1)
        out = {"rows": int(len(self.time)), "sensor": self.sensor, "wrench_mode": self.wrench_mode,
               "mean_nis_per_dof": mean_nis, "nis_inside_95": inside,
               "tip_sensor_rms_error_m": float(np.sqrt(np.nanmean(err ** 2))),
               "gated": int(self.gated.sum()), "integrator_failures": self.integrator_failures,
               "final_wrench": [float(x) for x in self.wrench[-1]],
               "final_wrench_std": [float(x) for x in self.wrench_std[-1]]}
        if self.wrench_mode == "payload":
            out["final_payload_kg"] = float(self.payload[-1])
            out["final_payload_std_kg"] = float(self.payload_std[-1])
        return out

    def rows(self):
        """(header, rows) of a CSV of the estimates, SI units in the header."""
        head = ["t [s]"] + [f"{self.sensor}.{c} measured [m]" for c in "xyz"] + \
            [f"{self.sensor}.{c} estimated [m]" for c in "xyz"] + [f"{self.sensor}.{c} std [m]" for c in "xyz"] + \
            [f"wrench.{c} [{'N' if c[0] == 'f' else 'N m'}]" for c in ("fx", "fy", "fz", "mx", "my", "mz")] + \
            ["payload [kg]", "payload std [kg]", "nis", "nis dof", "gated"]
        body = np.column_stack([self.time, self.measured, self.estimated, self.estimated_std, self.wrench,
                                self.payload, self.payload_std, self.nis, self.nis_dof, self.gated])
        return head, body


def estimate_recording(mech, sensors, rec, *, dt=None, wrench=None, **ekf_options):
    """Run the EKF of ``mech`` with ``sensors`` over the record ``rec``
    (module docstring); ``ekf_options`` go to :class:`ekf.EKF`. Returns an
    :class:`EstimationRun`. CalibrationError for a record without
    increasing times, a bad ``dt``."""
    mech = as_mechanism(mech)
    if rec.time is None or len(rec) < 2:
        raise CalibrationError("estimate: the record needs a time column t and at least two rows")
    t = np.asarray(rec.time, dtype=float)
    if np.any(np.diff(t) <= 0):
        raise CalibrationError("estimate: the record's times must increase")
    dt = float(np.median(np.diff(t))) if dt is None else float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise CalibrationError(f"--dt must be a positive step in s, got {dt}")
    names = position_joints(mech)

    def inputs(r):
        pos = dict(zip(names, rec.joints[r])) if names and rec.joints is not None else None
        return dict(actuation=rec.inputs[r], positions=pos, efforts=rec.row_efforts(r))
    ekf = EKF(mech, sensors, dt, wrench=wrench, **inputs(0), **ekf_options)
    tip = _tip_sensor(mech, ekf.sensors)
    if tip is None:
        raise CalibrationError("estimate: the sensors need a pose sensor or marker (the estimate it draws)")
    where = ekf._where[tip.name]
    N = len(t)
    out = {k: np.full((N, 3), np.nan) for k in ("measured", "estimated", "estimated_std")}
    W, Wsd = np.zeros((N, 6)), np.zeros((N, 6))
    mass, mass_sd = np.full(N, np.nan), np.full(N, np.nan)
    nis, dof, gated = np.zeros(N), np.zeros(N, dtype=int), np.zeros(N, dtype=int)
    for r in range(N):
        if r > 0:
            for _ in range(max(1, int(round((t[r] - t[r - 1]) / dt)))):
                ekf.predict(**inputs(r))
        z = {s.name: rec.readings[s.name][r] for s in ekf.sensors if s.name in rec.readings
             and np.all(np.isfinite(rec.readings[s.name][r]))}
        rep = ekf.update(z)
        for name in rep.accepted:
            nis[r] += rep.nis[name]
            dof[r] += ekf.by_name[name].size
        gated[r] = len(rep.gated)
        zt = rec.readings.get(tip.name, np.full((N, 3), np.nan))[r]
        out["measured"][r] = zt[:3, 3] if np.shape(zt) == (4, 4) else zt
        q = sn.forward(ekf.ws, ekf.q)
        T = sn.predict_measurement(ekf.ws, q, tip, where)
        p = T[:3, 3] if np.shape(T) == (4, 4) else T
        _, H = sn.residual_and_jacobian(ekf.ws, q, tip, where, T if np.shape(T) == (4, 4) else p)
        out["estimated"][r] = p
        out["estimated_std"][r] = np.sqrt(np.clip(np.diag(H[:3] @ ekf.q_covariance() @ H[:3].T), 0.0, None))
        W[r], Wsd[r] = ekf.wrench(), ekf.wrench_std()
        if wrench in ("payload", "force", "wrench"):
            mass[r], mass_sd[r] = ekf.payload_mass_kg()
    return EstimationRun(t, tip.name, out["measured"], out["estimated"], out["estimated_std"], wrench, W, Wsd,
                         mass, mass_sd, nis, dof, gated, int(ekf.health.integrator_failures))
