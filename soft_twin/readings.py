"""The estimator's ledger of its inputs (issue 25, item 6): every message
and every sensor reading is counted once, in exactly one place.

Per input topic: the messages ``received`` and those ``lost`` before the
node took them (gaps in the publishers' sequence numbers,
:class:`soft_twin_core.commands.SequenceGaps`). Per sensor reading, after the
node's own checks (shape, finiteness, sensor name: counted by the node as
rejected by reason), the stamp is checked here:

* a zero stamp means "not stamped": the reading counts as taken at arrival;
* ``stale_stamp``: older than ``max_age_s`` before the node's clock (a
  reading stamped 1970, or a clock not synchronised);
* ``future_stamp``: more than ``max_age_s`` ahead of the node's clock;
* ``out_of_order``: older than the last reading accepted from that sensor.

An accepted reading waits for the next filter step. Several readings of one
sensor within one step are *merged* into one (their mean; a pose's rotation
is the chordal mean, projected back onto SO(3)): the step uses one,
the others are counted as ``readings_merged``. The filter keeps its
measurement noise, so a merged reading is weighted conservatively (its
true noise is lower). So, at any time:

    readings_accepted = readings_used + readings_merged + readings_pending

A reset of the estimate starts the counts again from zero (the pending
readings are forgotten; the sequence numbers are still followed).
"""

import numpy as np

from soft_twin_core.commands import SequenceGaps

STAMP_REJECTIONS = ("stale_stamp", "future_stamp", "out_of_order")


def stamp_ns(stamp):
    """A builtin_interfaces/Time as integer nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def merge_readings(readings):
    """One reading from several of the same sensor: the mean; for 4x4
    poses the mean position and the rotation nearest (Frobenius) to the
    mean rotation matrix (the chordal L2 mean)."""
    if len(readings) == 1:
        return readings[0]
    z = np.mean(np.stack(readings), axis=0)
    if z.shape == (4, 4):
        U, _, Vt = np.linalg.svd(z[:3, :3])
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        z[:3, :3] = U @ D @ Vt
        z[3] = (0.0, 0.0, 0.0, 1.0)
    return z


class InputLedger:
    """Counts of the estimator's input topics and its pending sensor readings."""

    def __init__(self, max_age_s=1.0):
        self.max_age_ns = int(max_age_s * 1e9)
        self.received, self.lost, self._gaps = {}, {}, {}
        self.pending = {}                  # sensor name -> [readings]
        self.last_stamp = {}               # sensor name -> newest accepted stamp [ns]
        self.accepted = self.used = self.merged = 0

    def message(self, topic, info, publishers=None):
        """One message taken from ``topic`` (``info``: rclpy's message info
        dict, or None): counted, with the messages lost before it."""
        gaps = self._gaps.setdefault(topic, SequenceGaps())
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else None
        self.received[topic] = self.received.get(topic, 0) + 1
        self.lost[topic] = self.lost.get(topic, 0) + gaps.add(seq, publishers)

    def check_stamp(self, sensor, stamp, now_ns):
        """None if a reading of ``sensor`` stamped ``stamp`` may be used,
        else (reason, text)."""
        t = stamp_ns(stamp)
        if t == 0:
            return None
        if t < now_ns - self.max_age_ns:
            return "stale_stamp", (f"sensor {sensor!r}: reading stamped {t * 1e-9:.3f} s, "
                                   f"{(now_ns - t) * 1e-9:.3f} s before the node's clock (max age "
                                   f"{self.max_age_ns * 1e-9:g} s)")
        if t > now_ns + self.max_age_ns:
            return "future_stamp", (f"sensor {sensor!r}: reading stamped {(t - now_ns) * 1e-9:.3f} s ahead of "
                                    f"the node's clock (max {self.max_age_ns * 1e-9:g} s)")
        last = self.last_stamp.get(sensor)
        if last is not None and t < last:
            return "out_of_order", (f"sensor {sensor!r}: reading stamped {(last - t) * 1e-9:.6f} s before the "
                                    f"last one accepted")
        return None

    def put(self, sensor, z, stamp):
        """An accepted reading, for the next filter step."""
        t = stamp_ns(stamp)
        if t:
            self.last_stamp[sensor] = t
        self.pending.setdefault(sensor, []).append(z)
        self.accepted += 1

    def take(self):
        """{sensor: reading} for one filter step, each sensor's readings merged."""
        out = {name: merge_readings(zs) for name, zs in self.pending.items()}
        n = sum(len(zs) for zs in self.pending.values())
        self.used += len(out)
        self.merged += n - len(out)
        self.pending = {}
        return out

    def reset(self):
        """A reset of the estimate: counts from zero, pending readings and stamps forgotten."""
        self.received = dict.fromkeys(self.received, 0)
        self.lost = dict.fromkeys(self.lost, 0)
        self.pending, self.last_stamp = {}, {}
        self.accepted = self.used = self.merged = 0

    def diagnostics(self):
        pending = sum(len(zs) for zs in self.pending.values())
        out = {"readings_accepted": self.accepted, "readings_used": self.used, "readings_merged": self.merged,
               "readings_pending": pending}
        for topic in sorted(self.received):
            key = topic.strip("/").replace("/", "_")
            out[f"{key}_received"] = self.received[topic]
            out[f"{key}_lost"] = self.lost[topic] if self._gaps[topic].supported else "n/a"
        return out


def accept_reading(ledger, reject, sensor, vector, stamp, now_ns):
    """One sensor reading of an estimator: ``vector()`` the checked
    measurement (a ValueError: rejected as non_finite or malformed), then
    its stamp checked (rejected by reason), then pending in ``ledger`` for
    the next filter step. ``reject(kind, text)`` counts a rejection."""
    try:
        z = vector()
    except ValueError as e:
        text = str(e)
        reject("non_finite" if ("NaN" in text or "finite" in text) else "malformed", f"sensor {sensor!r}: {text}")
        return
    bad = ledger.check_stamp(sensor, stamp, now_ns)
    if bad is not None:
        reject(*bad)
        return
    ledger.put(sensor, z, stamp)
