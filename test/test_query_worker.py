"""The node's IK worker process (soft_twin.query_worker): the same answers
as computing in the node's own thread, None (compute locally) while it is
not started, busy or gone, a new model sent when the robot changes, and
no process left behind."""

import time

import numpy as np
import pytest

from soft_twin import twin as tw
from soft_twin.query_worker import QueryWorker
from soft_twin_core import statics as st
from soft_twin_core.model import load_model


@pytest.fixture(scope="module")
def model():
    return load_model("tendon_arm")


@pytest.fixture(scope="module")
def worker(model):
    w = QueryWorker().start(model)
    end = time.monotonic() + 120
    while w.state() != "ready" and time.monotonic() < end:
        time.sleep(0.05)
    assert w.state() == "ready", w.last_error
    yield w
    w.close()


def test_same_answer_as_in_thread(worker, model):
    q = st.solve_statics(model).q
    for u in ([1.0, 0.0, 0.5, 0.0], [0.0, 2.0, 0.0, 1.0]):
        T = st.solve_statics(model, u).tip_pose
        for position_only in (True, False):
            args = (q, 10, T, position_only, 1e-6, None)
            mine = tw.inverse_kinematics(model, *args, u_current=np.zeros(4))
            theirs = worker.call("inverse_kinematics", model, *args, u_current=np.zeros(4))
            assert theirs is not None, worker.last_error
            assert theirs.success == mine.success and theirs.message == mine.message
            np.testing.assert_array_equal(theirs.extra["u"], mine.extra["u"])
            np.testing.assert_array_equal(theirs.q, mine.q)
    assert worker.calls >= 4


def test_busy_worker_answers_none(worker, model):
    q = st.solve_statics(model).q
    T = st.solve_statics(model, [1.0, 0.0, 0.5, 0.0]).tip_pose
    out = []
    with worker._lock:                        # another request under way
        out.append(worker.call("inverse_kinematics", model, q, 10, T, True))
    assert out == [None]


def test_model_change_is_sent(worker, model):
    other = load_model("pneumatic_arm")
    q = st.solve_statics(other).q
    u = np.array([2e4 if a.kind != "tendon" else 1.0 for a in other.actuators])
    T = st.solve_statics(other, u).tip_pose
    r = worker.call("inverse_kinematics", other, q, 10, T, True, 1e-6, None, u_current=np.zeros(len(u)))
    assert r is not None and r.success, (worker.last_error, r and r.message)
    mine = tw.inverse_kinematics(other, q, 10, T, True, 1e-6, None, u_current=np.zeros(len(u)))
    np.testing.assert_array_equal(r.extra["u"], mine.extra["u"])


def test_not_started_and_lost_worker_fall_back(model):
    q = st.solve_statics(model).q
    T = st.solve_statics(model, [1.0, 0.0, 0.5, 0.0]).tip_pose
    idle = QueryWorker()
    assert idle.state() == "off" and idle.call("inverse_kinematics", model, q, 10, T, True) is None
    w = QueryWorker().start(model)
    try:
        end = time.monotonic() + 120
        while w.state() != "ready" and time.monotonic() < end:
            time.sleep(0.05)
        proc = w._proc
        proc.kill()
        proc.wait(10)
        assert w.call("inverse_kinematics", model, q, 10, T, True) is None
        assert "worker lost" in w.last_error and w.state() == "off"
    finally:
        w.close()
    assert proc.poll() is not None


def test_signals_to_the_group_do_not_reach_it(model):
    """A Ctrl-C to the node's process group must not kill the worker with a
    traceback: it runs in a session of its own and ignores SIGINT/SIGTERM."""
    import os
    import signal
    w = QueryWorker().start(model)
    try:
        assert os.getsid(w._proc.pid) != os.getsid(0)       # a group signal cannot reach it
        end = time.monotonic() + 120
        while w.state() == "starting" and time.monotonic() < end:
            time.sleep(0.05)
        assert w.state() == "ready"
        os.kill(w._proc.pid, signal.SIGINT)                 # and it ignores direct ones
        os.kill(w._proc.pid, signal.SIGTERM)
        q = st.solve_statics(model).q
        T = st.solve_statics(model, [1.0, 0.0, 0.5, 0.0]).tip_pose
        assert w.call("inverse_kinematics", model, q, 10, T, True) is not None, w.last_error
    finally:
        w.close()


def test_ensure_started_starts_once(model):
    w = QueryWorker()
    try:
        w.ensure_started(model)
        proc = w._proc
        assert proc is not None
        w.ensure_started(model)
        assert w._proc is proc
    finally:
        w.close()
    w.ensure_started(model)            # given up after one start: stays off
    assert w.state() == "off"


def test_close_ends_the_process(model):
    w = QueryWorker().start(model)
    proc = w._proc
    w.close()
    assert proc.poll() is not None and w.state() == "off"
