"""The twin's clock: a thread that calls the node's step every period.

Why not an rclpy timer: every timer tick wakes the executor, and rclpy 7.1's
Python executor rebuilds its whole wait set on each wake (every publisher's
and subscription's QoS event handler, every service, the parameter
services): measured with py-spy on the default node at rest, 200 wakes/s
took 75 % of the time the process held the GIL (~2.5 ms a wake), more than
the steps and the publishing together, and a service computing in the
same process (IK) waited for the GIL behind it. A plain thread sleeping to
its next deadline costs nothing between ticks; the executor now wakes only
for inputs, services and the diagnostics timer.

The deadlines are on the monotonic clock, ``period`` apart from the last
(re)start; a tick that comes late is not repeated (the node's step works
out from the wall clock how many twin steps are due, so no time is lost).
"""

import threading
import time


class Stepper:
    """Calls ``tick()`` every ``period`` s (monotonic clock) in a daemon
    thread named ``name``, from :meth:`start` until :meth:`close`.
    ``tick`` must not raise (wrap it: the node's ``_guarded``)."""

    def __init__(self, tick, period, name="soft_twin_step"):
        if not period > 0:
            raise ValueError(f"period: must be > 0 s, got {period!r}")
        self._tick = tick
        self._period = float(period)
        self._name = name
        self._cond = threading.Condition()
        self._closed = False
        self._restart = False
        self._thread = None
        self.ticks = 0

    @property
    def period(self):
        return self._period

    def start(self):
        with self._cond:
            if self._thread is not None or self._closed:
                return
            self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
            self._thread.start()

    def set_period(self, period):
        """A new period, the schedule restarted from now (first tick one
        period from now)."""
        if not period > 0:
            raise ValueError(f"period: must be > 0 s, got {period!r}")
        with self._cond:
            self._period = float(period)
            self._restart = True
            self._cond.notify_all()

    def close(self, timeout=5.0):
        """Stop ticking and wait (at most ``timeout`` s) for a tick under way."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)

    def _run(self):
        with self._cond:
            deadline = time.monotonic() + self._period
        while True:
            with self._cond:
                while not self._closed:
                    if self._restart:
                        self._restart = False
                        deadline = time.monotonic() + self._period
                    wait = deadline - time.monotonic()
                    if wait <= 0:
                        break
                    self._cond.wait(wait)
                if self._closed:
                    return
                period = self._period
            self._tick()
            self.ticks += 1
            deadline += period
            now = time.monotonic()
            if deadline <= now:             # late by a period or more: the next tick now, then on schedule
                deadline = now
