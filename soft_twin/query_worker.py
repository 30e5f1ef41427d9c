"""Long queries of an articulated twin (IK, path planning) in a process of
their own (issue 25, item 3).

An articulated IK or plan is hundreds of milliseconds of Python. Run in the
node's process, it held the GIL against the stepping clock and the input
callbacks: under a 1 kHz joint-command flood with IK and plan calls back
to back, the step rate of the pan-tilt arm fell to 172-186 Hz (442 steps
dropped in 30 s), although either load alone left it at 198-199 Hz. In a
worker process the query runs on the other core and the node's threads
only wait for its answer (the wait releases the GIL).

The worker builds its own copy of the mechanism from the robot
description (a plain dict) once, at start; each query carries the twin's
plain state (:meth:`soft_twin_core.twin.Twin.query_state`)
and runs on the worker's twin, so the answer is the one the node would
have computed itself. Exceptions (PlanError, StaticsError, ...) come back
as they were raised. A worker that died (killed, out of memory) is
replaced at the next query, which then fails with a clear message.
"""

import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

_twin = None          # the worker process's twin


def _start_worker(description):
    """Worker initializer: ignore SIGINT (the node stops its worker itself;
    a Ctrl-C in the terminal reaches the whole process group) and build
    the twin."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    global _twin
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    from soft_twin_core.robot.model import robot_mapping
    from soft_twin_core.twin import Twin
    from soft_twin_core.twin import TwinSettings
    _twin = Twin(mechanism_from_dict(robot_mapping(description, "robot description")),
                            TwinSettings(mode="quasi_static"))
    try:      # warm-up: the solver's kernels load now, not during the first query
        _twin.inverse_kinematics(_twin.outputs().tip_pose[:3, 3])
    except Exception:       # noqa: BLE001 - a robot the IK cannot serve says so at its first query
        pass


def _exit_with_parent(parent, period=0.5):
    """The worker ends when the node's process does (a kill -9 of the node
    leaves no orphan computing on)."""
    while os.getppid() == parent:
        time.sleep(period)
    os._exit(0)


def _ready():
    return _twin is not None


def _run(method, state, args, kwargs):
    """``method`` of the worker's twin, set to ``state`` first."""
    _twin.load_query_state(state)
    return getattr(_twin, method)(*args, **kwargs)


class QueryError(RuntimeError):
    """The worker process failed (not the query)."""


class QueryWorker:
    """One worker process for one robot description; :meth:`run` blocks
    the calling thread (without the GIL) until the answer comes."""

    def __init__(self, description):
        self._description = description
        self._lock = threading.Lock()
        self._pool = None
        self._start()

    def _start(self):
        ctx = multiprocessing.get_context("spawn")     # no fork of a threaded process
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_start_worker,
                                         initargs=(self._description,))
        main = threading.current_thread() is threading.main_thread()
        # the child inherits an ignored SIGINT (kept over exec, and Python then
        # installs no handler): a Ctrl-C during its start prints no traceback
        old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            self._pool.submit(_ready)                  # the process starts now, not at the first query
        finally:
            if main:
                signal.signal(signal.SIGINT, old)

    def run(self, method, state, *args, **kwargs):
        """The twin's ``method(*args, **kwargs)`` computed in the worker on
        ``state``; its exceptions re-raised here; QueryError if the worker
        process died (a new one is started for the next query)."""
        with self._lock:
            pool = self._pool
        try:
            return pool.submit(_run, method, state, args, kwargs).result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    pool.shutdown(wait=False, cancel_futures=True)
                    self._start()
            raise QueryError("the query worker process died during the query (restarted; try again)") from None

    def close(self):
        """Stop the worker now (a query under way is abandoned)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=5.0)
