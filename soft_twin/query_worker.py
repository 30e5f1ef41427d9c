"""A warm worker process for the node's heavy queries (issue 13: the IK
service), so they do not share the node's GIL with the 200 Hz twin.

Why: the IK body costs ~8-12 ms of CPU, all of it Python and small numpy
calls holding the GIL, and the same interpreter steps the twin at 200 Hz,
publishes its states and runs the executor's spin loop (45-95 % of one CPU
at rest, measured per thread from /proc by benchmarks/bench_ik.py --node).
A second process has its own interpreter and can run on the other core, and
the IK then takes no GIL time from the twin either.

Measured (issue 13, the 2 CPUs shared with other agents, load 5-9): it does
not answer faster. With this benchmark's processes ahead of the other
sessions (``--autogroup-nice -10``, near idle for them) the node answered
in median 12-17 ms from its service thread and 15-23 ms from the worker
(the worker hop costs ~2-3 ms: pickling and two process wake-ups; the GIL
contention it removes was 0-8 ms); under the full load both took 25-60 ms,
the worker slightly more (it competes as one more runnable process). So it
is **off by default** (``SOFT_TWIN_IK_WORKER=1`` in the node's environment
turns it on) and kept for a measurement on an idle machine (bench_ik.py
--node --worker, --ab).

:class:`QueryWorker` owns one child process (``python -m
soft_twin.query_worker FD``, in a session of its own so that a Ctrl-C or a
SIGINT/SIGTERM to the node's process group never reaches it: the node stops
it, and it exits by itself when the node's end of the pipe closes, so a
killed node leaves nothing behind). The node starts it at its first IK
request (nodes that never answer one never pay for it); until it is ready
(imports and kernel warm-up, a few seconds), while it is busy with another
request, or if it died, :meth:`call` returns None and the caller computes in
its own thread as before (answers never depend on where they were computed).
The model goes to the worker once per model (pickled, ~13 kB); a call sends
only the state and the request.
"""

import os
import threading
import time

def enabled():
    """True when the node's environment sets SOFT_TWIN_IK_WORKER=1. Off by
    default: measured on the shared 2-CPU machine it did not answer faster
    than the service thread (see the module docstring and README)."""
    return os.environ.get("SOFT_TWIN_IK_WORKER", "0").strip() == "1"


# the functions a worker may run: soft_twin.twin.<name>
ALLOWED = ("inverse_kinematics",)


def _warm_up(tw, model):
    """One IK solve on the model (kernels loaded, caches built): the first
    real request then costs what the others do."""
    import numpy as np
    from soft_twin_core import statics as st
    if model is None or not model.actuators:
        return
    try:
        n = len(model.actuators)
        q = st.solve_statics(model).q
        u = np.zeros(n)
        u[0] = 0.5 if model.actuators[0].kind == "tendon" else 0.0
        tw.inverse_kinematics(model, q, 5, st.solve_statics(model, u).tip_pose, True, u_current=np.zeros(n))
    except Exception:
        pass


def _serve(conn):
    """The worker's loop: ("model", token, model) stores a model (and warms
    up on it); ("call", token, name, args, kwargs) answers ("ok", result) or
    ("error", text); ("stop",) or a closed pipe ends it."""
    from soft_twin import twin as tw
    try:     # one BLAS thread for good: idle OpenBLAS threads spin and take CPU time from the node
        from threadpoolctl import threadpool_limits
        threadpool_limits(limits=1, user_api="blas")
    except ImportError:
        pass
    models = {}
    if conn.poll(0.5):                  # the node's model first: warm up on it before saying ready
        msg = conn.recv()
        if msg[0] == "model":
            models[msg[1]] = msg[2]
            _warm_up(tw, msg[2])
    conn.send(("ready",))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] == "stop":
            return
        if msg[0] == "model":
            models.clear()
            models[msg[1]] = msg[2]
            _warm_up(tw, msg[2])
            continue
        _, token, name, args, kwargs = msg
        try:
            if name not in ALLOWED or token not in models:
                raise RuntimeError(f"worker: cannot run {name!r} (model {token!r} known: {token in models})")
            w0, c0 = time.perf_counter(), time.process_time()
            res = getattr(tw, name)(models[token], *args, **kwargs)
            out = ("ok", res, (time.perf_counter() - w0, time.process_time() - c0))
        except Exception as e:  # reported to the caller, who computes in its own thread
            out = ("error", f"{type(e).__name__}: {e}")
        try:
            conn.send(out)
        except (EOFError, OSError):
            return


def _picklable(model):
    """A shallow copy of the model without its private caches that cannot
    be pickled (e.g. ``_tree``, the compiled multibody arrays; the worker
    rebuilds them on first use)."""
    import copy
    import pickle
    out = copy.copy(model)
    for k, v in list(vars(out).items()):
        if k.startswith("_"):
            try:
                pickle.dumps(v)
            except Exception:
                object.__delattr__(out, k)
    return out


class QueryWorker:
    """One warm worker process; thread-safe (one request at a time, others
    answered None: compute locally)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._proc = self._conn = None
        self._ready = False
        self._model_token = None
        self._models_sent = 0
        self.calls = self.fallbacks = 0
        self.last_error = ""
        self.last_timing = None
        self._gave_up = False

    def start(self, model=None):
        """Start the child in the background (returns at once), warming up
        on ``model`` (the node's robot) if given."""
        import subprocess
        import sys
        from multiprocessing.connection import Pipe
        if self._proc is not None:
            return self
        first = None
        if model is not None:
            try:
                first = ("model", self._models_sent + 1, _picklable(model))
                import pickle
                pickle.dumps(first)
            except Exception as e:       # a model the worker cannot take: compute in the node
                self.last_error = f"worker not started: the model cannot be sent ({type(e).__name__}: {e})"
                return self
        parent, child = Pipe()
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "soft_twin.query_worker", str(child.fileno())], pass_fds=(child.fileno(),),
                start_new_session=True, stdin=subprocess.DEVNULL)
        except OSError as e:
            self.last_error = f"worker not started: {e}"
            parent.close()
            return self
        finally:
            child.close()
        self._conn = parent
        if first is not None:
            self._models_sent += 1
            self._model_token = (self._models_sent, model)
            parent.send(first)
        return self

    def ensure_started(self, model):
        """Start the worker (warming up on ``model``) unless it runs or was
        given up on; returns at once."""
        if self._proc is None and not self._gave_up:
            self._gave_up = True          # one start per node: a worker that died is not restarted
            with self._lock:
                self.start(model)

    def _alive(self):
        return self._proc is not None and self._proc.poll() is None

    @property
    def ready(self):
        return self._ready

    def state(self):
        """"ready", "starting" or "off" (never started, stopped or lost)."""
        if self._lock.acquire(blocking=False):
            try:
                self._check_ready()
            finally:
                self._lock.release()
        if self._ready:
            return "ready"
        return "starting" if self._alive() else "off"

    def _check_ready(self):
        if self._ready:
            return True
        if self._conn is None or not self._alive():
            return False
        if self._conn.poll(0):
            try:
                self._ready = self._conn.recv()[0] == "ready"
            except (EOFError, OSError):
                return False
        return self._ready

    def call(self, name, model, *args, timeout=30.0, **kwargs):
        """``soft_twin.twin.<name>(model, *args, **kwargs)`` in the worker, or
        None when the worker is not ready, busy, or failed (the caller then
        computes it itself)."""
        if not self._lock.acquire(blocking=False):
            self.fallbacks += 1
            return None
        try:
            if not self._check_ready():
                self.fallbacks += 1
                return None
            try:
                if self._model_token is None or self._model_token[1] is not model:
                    self._models_sent += 1
                    self._model_token = (self._models_sent, model)
                    self._conn.send(("model", self._models_sent, _picklable(model)))
                self._conn.send(("call", self._model_token[0], name, args, kwargs))
                if not self._conn.poll(timeout):
                    raise TimeoutError
                answer = self._conn.recv()
                status, out = answer[0], answer[1]
            except (EOFError, OSError, TimeoutError, ValueError) as e:
                self.last_error = f"worker lost: {type(e).__name__}: {e}"
                self._broken()
                self.fallbacks += 1
                return None
            if status != "ok":
                self.last_error = out
                self.fallbacks += 1
                return None
            self.calls += 1
            self.last_timing = answer[2]      # (wall, CPU) [s] of the computation in the worker
            return out
        finally:
            self._lock.release()

    def _broken(self):
        """The worker died or hung: stop it; the node computes locally from now on."""
        self._ready = False
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(5.0)

    def close(self):
        with self._lock:
            if self._conn is not None:
                try:
                    self._conn.send(("stop",))
                except (EOFError, OSError):
                    pass
            if self._proc is not None:
                import subprocess
                try:
                    self._proc.wait(2.0)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait(2.0)
            if self._conn is not None:
                self._conn.close()
            self._proc = self._conn = None
            self._ready = False


def main(argv=None):
    """The worker process: ``python -m soft_twin.query_worker FD`` (FD: its
    end of the pipe, a multiprocessing Connection)."""
    import signal
    import sys
    from multiprocessing.connection import Connection
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)      # the node stops it (or the pipe closes)
    argv = sys.argv[1:] if argv is None else argv
    _serve(Connection(int(argv[0])))


if __name__ == "__main__":
    main()
