"""A MultiThreadedExecutor that does not starve its own callbacks.

rclpy 7.1 (Jazzy) has a performance bug in ``MultiThreadedExecutor``
(ros2/rclpy#1452, fixed upstream by ros2/rclpy#1547): a callback handed to
the thread pool stays "ready" until a worker starts it, so the spin loop finds
it again and again and re-submits it in a hot loop that holds the GIL, which
keeps the workers from starting. Measured here with a 1 kHz subscription and a
200 Hz timer doing 0.5 ms of work: the stock executor delivered 570 of 5000
messages and 57 timer ticks/s; the single-threaded executor all 5000 and
199 ticks/s.

:class:`TwinExecutor` keeps the stock executor's threading model (a pool of
workers, callback groups decide what may run concurrently) and only changes
the dispatch: after handing a callback to the pool, the spin loop waits until
a worker has picked it up before it looks for more work.
"""

import threading

from rclpy.executors import (ConditionReachedException, ExternalShutdownException,
                             MultiThreadedExecutor, ShutdownException, TimeoutException)


class TwinExecutor(MultiThreadedExecutor):
    """``MultiThreadedExecutor`` whose spin loop waits for each dispatched
    callback to start (see the module docstring)."""

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False):
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
            return
        started = threading.Event()

        def run():
            started.set()
            handler()

        self._executor.submit(run)
        self._futures.append(handler)
        # every worker busy: wait for one (nothing else could run meanwhile),
        # but wake up now and then to notice a shutdown
        while not started.wait(0.1):
            if self._is_shutdown or not self._context.ok():
                break
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()  # raise any exception of a callback

    def shutdown(self, timeout_sec=None):
        """Stop, then wait for the callbacks still running in the pool:
        rclpy 7.1's ``Executor.shutdown`` returns without waiting (its wait
        is skipped once ``_is_shutdown`` is set), so a timer callback could
        still publish while the node is being destroyed."""
        done = super().shutdown(timeout_sec)
        self._executor.shutdown(wait=timeout_sec is None or timeout_sec > 0)
        return done
