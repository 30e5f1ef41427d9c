"""The articulated twin's query worker (soft_twin.query_worker, issue 25,
item 3): IK and plans computed in a process of its own give the answer the
node's own process gives, exceptions come back as raised, a killed worker
is reported and replaced, and closing leaves no process behind."""

import os
import signal
import time

import numpy as np
import pytest

from soft_twin_core.twin import Twin
from soft_twin.query_worker import QueryError, QueryWorker
from soft_twin_core.planning import paths as pth
from soft_twin_core.robot.mechanism import mechanism_from_dict
from soft_twin_core.robot.model import find_file, read_yaml_file
from soft_twin_core.twin import TwinSettings


@pytest.fixture(scope="module")
def setup():
    desc = read_yaml_file(find_file("pan_tilt_arm", "robots"))
    twin = Twin(mechanism_from_dict(desc), TwinSettings(mode="dynamic"))
    # a twin somewhere else than its rest: commands moved, a few steps taken
    twin.set_joint_commands({"pan": 0.2, "tilt": -0.1}, {})
    twin.set_actuation([1.0, 0.0, 0.5, 0.0])
    twin.step(5)
    worker = QueryWorker(desc)
    yield twin, worker
    worker.close()


def test_worker_answers_as_the_node_process_would(setup):
    twin, worker = setup
    target = twin.outputs().tip_pose[:3, 3] + [0.0, 0.01, 0.005]
    local = twin.query_copy().inverse_kinematics(target, 1e-7)
    remote = worker.run("inverse_kinematics", twin.query_state(), target, 1e-7)
    assert remote.reached and remote.status == local.status and remote.names == local.names
    np.testing.assert_allclose(remote.values, local.values, rtol=0, atol=1e-12)
    np.testing.assert_allclose(remote.q, local.q, rtol=0, atol=1e-12)
    assert remote.position_error <= 1e-7
    # the twin itself was not touched by either query
    assert twin.positions == {"pan": 0.2, "tilt": -0.1}


def test_worker_plans_as_the_node_process_would(setup):
    twin, worker = setup
    p0 = twin.outputs().tip_pose[:3, 3]
    path = pth.path_from_dict({"type": "line", "start": p0.tolist(), "end": (p0 + [0.0, 0.02, 0.01]).tolist(),
                               "duration": 1.0, "sample_period": 0.25}, "path")
    local = twin.query_copy().plan(path, tolerance=1e-7)
    remote = worker.run("plan", twin.query_state(), path, tolerance=1e-7)
    np.testing.assert_allclose(remote.joints, local.joints, rtol=0, atol=1e-12)
    np.testing.assert_allclose(remote.u, local.u, rtol=0, atol=1e-12)


def test_worker_exceptions_come_back_as_raised(setup):
    twin, worker = setup
    with pytest.raises(ValueError, match="could not convert"):        # the node answers a ValueError
        worker.run("inverse_kinematics", twin.query_state(), "not a target", 1e-7)
    with pytest.raises(AttributeError):
        worker.run("no_such_method", twin.query_state())


def test_a_killed_worker_is_reported_and_replaced(setup):
    twin, _ = setup
    worker = QueryWorker(read_yaml_file(find_file("pan_tilt_arm", "robots")))
    try:
        assert worker.run("query_state", twin.query_state())["positions"] == twin.positions
        pid = next(iter(worker._pool._processes))
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(QueryError, match="died"):
            worker.run("query_state", twin.query_state())
        assert worker.run("query_state", twin.query_state())["positions"] == twin.positions   # a new one
        new_pid = next(iter(worker._pool._processes))
        assert new_pid != pid
    finally:
        worker.close()
    end = time.monotonic() + 10.0
    while time.monotonic() < end and _alive(new_pid):
        time.sleep(0.05)
    assert not _alive(new_pid), "the worker process outlived close()"


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:                      # a zombie not yet reaped counts as gone
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split()[2] != "Z"
    except FileNotFoundError:
        return False
