"""Stopping a soft_twin node on SIGINT or SIGTERM: exit status 0, no traceback,
whenever the signal comes. Used by the twin (``soft_twin.node``) and the
estimator (``soft_twin.estimator``).

rclpy's own handlers shut the context down from a signal thread while the
executor may be building a wait set, a timer publishing or the node creating
a publisher: "RCLError: failed to initialize wait set: the given context is
not valid" (exit status 1: 5 of 20 SIGTERMs in the twin's signal test, 4 of
28 and 2 of 38 SIGINTs in issue 15) and "Failed to publish: publisher's
context is invalid" (the estimator's test, once in CI-like runs), and a
signal during the start-up gave a traceback or death by the signal.

Here a signal only records itself (:class:`StopSignals`; the handler never
raises: an exception raised wherever the main thread happens to be can land
in a ctypes callback of the kernel compiler, where Python prints it as
"Exception ignored", or be a KeyboardInterrupt that CPython remembers and
turns into death by SIGINT at exit). The main loop (:func:`spin_until_stopped`)
sees it within 0.1 s; ``main`` then calls :func:`tear_down`: it stops the
executor (waiting for running callbacks), destroys the node and shuts the
context down, in that order, and returns 0. A node's start-up can ask :meth:`StopSignals.requested` between
its steps and give up at the next one.

From the moment the teardown starts, a watchdog gives it
``TEARDOWN_TIMEOUT_S``: a teardown stuck below the node's code is logged with
the main thread's place and the process exits anyway, with status 0 (the
stop was asked for, and the node's own parts -- stepping thread, plan,
recording, live view -- close before the middleware's part; an MCAP
recording still open then is closed by the watchdog, so that it stays
readable). Once in 200 signals of a CI run, a node stayed for 60 s after
SIGINT during its start-up, between two log lines where only rclpy's
``destroy_node`` ran.
"""

import os
import signal
import sys
import threading
import traceback

import rclpy

TEARDOWN_TIMEOUT_S = 10.0     # after a stop signal: the longest wait for a node's teardown
HARD_EXIT_DELAY_S = 5.0       # after the watchdog's time: the exit that needs no Python at all


def arm_hard_exit(delay_s, message):
    """A last resort below the watchdog: after ``delay_s`` a thread of the C
    library (a POSIX timer, SIGEV_THREAD) writes ``message`` to stderr
    (perror) and a second one calls ``_exit(0)``. It runs without the GIL:
    the Python watchdog cannot run while the main thread holds the GIL in a
    stuck call (seen once in 16 SIGINTs of the estimator's signal test: no
    watchdog line and no exit for 30 s after "shutting down"). Linux and
    glibc only; returns False (nothing armed) elsewhere."""
    import ctypes
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        create, settime = libc.timer_create, libc.timer_settime
    except (OSError, AttributeError):
        return False

    class SigEvent(ctypes.Structure):      # glibc's struct sigevent (64 bytes), SIGEV_THREAD member
        _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int), ("notify", ctypes.c_int),
                    ("function", ctypes.c_void_p), ("attribute", ctypes.c_void_p), ("pad", ctypes.c_int * 8)]

    class TimeSpec(ctypes.Structure):
        _fields_ = [("sec", ctypes.c_long), ("nsec", ctypes.c_long)]

    class ITimerSpec(ctypes.Structure):
        _fields_ = [("interval", TimeSpec), ("value", TimeSpec)]
    text = ctypes.create_string_buffer(message.encode())
    _HARD_EXIT_KEEP.append(text)                 # the C string must outlive this call
    for function, value, at in ((libc.perror, ctypes.addressof(text), delay_s), (libc._exit, 0, delay_s + 0.2)):
        sev = SigEvent(value, 0, 2, ctypes.cast(function, ctypes.c_void_p).value, None)   # 2: SIGEV_THREAD
        timer = ctypes.c_void_p()
        if create(1, ctypes.byref(sev), ctypes.byref(timer)) != 0:                      # 1: CLOCK_MONOTONIC
            return False
        its = ITimerSpec(TimeSpec(0, 0), TimeSpec(int(at), int((at % 1) * 1e9)))
        if settime(timer, 0, ctypes.byref(its), None) != 0:
            return False
        _HARD_EXIT_KEEP.append(timer)
    return True


_HARD_EXIT_KEEP = []


class StopSignals:
    """SIGINT and SIGTERM, handled in Python instead of by rclpy (see the
    module docstring). Install before ``rclpy.init(...,
    signal_handler_options=SignalHandlerOptions.NO)``; ``logger_name``: the
    logger of the handler's and the watchdog's lines."""

    def __init__(self, logger_name, teardown_timeout_s=None):
        self.logger_name = logger_name
        self.received = None          # the first signal's number
        self.starting = True          # the handler says the start-up step will end first
        self.teardown_timeout_s = TEARDOWN_TIMEOUT_S if teardown_timeout_s is None else teardown_timeout_s
        self._torn_down = threading.Event()
        self._watchdog = None
        self._last_acts = []

    def install(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handle)

    def _handle(self, signum, frame):
        if self.received is not None:
            return                    # already stopping
        self.received = signum
        if self.starting:
            rclpy.logging.get_logger(self.logger_name).info(
                f"{self.name}: stopping at the end of the start-up step under way")

    def requested(self):
        """True once a signal came. A True answer starts the teardown, so it
        also starts the teardown's watchdog (:meth:`begin_teardown`)."""
        if self.received is None:
            return False
        self.begin_teardown()
        return True

    @property
    def name(self):
        return signal.Signals(self.received).name if self.received is not None else None

    def begin_teardown(self):
        """Time the teardown from here: if it has not ended
        (:meth:`end_teardown`) within ``teardown_timeout_s``, a watchdog
        thread logs where the main thread is stuck and ends the process with
        status 0. Idempotent."""
        if self._watchdog is None:
            self._watchdog = threading.Thread(target=self._watch, args=(threading.main_thread().ident,),
                                              name="teardown_watchdog", daemon=True)
            self._watchdog.start()
            arm_hard_exit(self.teardown_timeout_s + HARD_EXIT_DELAY_S,
                          f"[{self.logger_name}] {self.name or 'stop'}: the teardown and its watchdog did not end "
                          f"within {self.teardown_timeout_s + HARD_EXIT_DELAY_S:.0f} s (the GIL held by a stuck "
                          f"call); exiting")

    def end_teardown(self):
        self._torn_down.set()

    def add_last_act(self, fn):
        """``fn()`` is called by the watchdog before it ends the process (e.g.
        closing an MCAP recording so that it stays readable); an exception
        in it is logged and the exit goes on."""
        self._last_acts.append(fn)

    def _watch(self, main_ident):
        if self._torn_down.wait(self.teardown_timeout_s):
            return
        rclpy.logging.get_logger(self.logger_name).warning(
            f"{self.name or 'stop'}: the teardown did not end within {self.teardown_timeout_s:.0f} s "
            f"(the main thread is in {_where(main_ident)}); exiting without waiting for it")
        for fn in self._last_acts:
            try:
                fn()
            except Exception as e:     # noqa: BLE001 - the exit must go on
                rclpy.logging.get_logger(self.logger_name).error(
                    f"before the exit: {getattr(fn, '__qualname__', fn)}: {type(e).__name__}: {e}")
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(0)


def _where(thread_ident, depth=6):
    """The innermost ``depth`` frames of a thread, innermost first, on one line."""
    frame = sys._current_frames().get(thread_ident)
    if frame is None:
        return "an unknown place"
    return " <- ".join(f"{f.name} ({os.path.basename(f.filename)}:{f.lineno})"
                       for f in reversed(traceback.extract_stack(frame)[-depth:]))


def spin_until_stopped(executor, stop, period_s=0.1):
    """Spin ``executor`` until a stop signal came (seen within ``period_s``)
    or the context was shut down."""
    stop.starting = False
    while stop.received is None and rclpy.ok():
        executor.spin_once(timeout_sec=period_s)


def tear_down(stop, logger, executor, node, detail=""):
    """A node main's ``finally``, in this order: log "<SIGNAL>: shutting
    down<detail>" (after a signal, and start the watchdog), stop the executor
    (waiting for the callbacks under way), destroy the node (which closes its
    own parts first), shut the context down. ``executor``, ``node``: None when
    not made yet."""
    stop.starting = False
    if stop.received is not None:
        stop.begin_teardown()
        logger.info(f"{stop.name}: shutting down{detail}")
    if executor is not None:
        executor.shutdown()
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown()
    stop.end_teardown()
