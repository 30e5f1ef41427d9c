"""Session-wide pytest set-up for soft_twin.

* Every test session gets its own ROS_DOMAIN_ID (set here, at conftest import,
  before any test module can import rclpy), so parallel runs on one machine
  never see each other's nodes. Child processes (a node started with
  subprocess) inherit it through os.environ. The workers of one pytest-xdist
  run (`make test` runs two) get consecutive ids, so they never share one.
* One BLAS thread (OPENBLAS_NUM_THREADS=1 unless set), as the node and the
  command line use, whichever test runs first.
* Registers the markers used by the suite (--strict-markers is on).
* A test marked ``quiet`` measures a real-time rate or a wall time: `make
  test` runs it alone, after the others (they run on two pytest-xdist
  workers; scripts/run_tests.sh, :func:`pytest_collection_modifyitems`).
"""
import os

# ROS 2 domain ids 1..101 are safe on Linux with Fast DDS defaults (0 is the
# default everyone shares). An explicit SOFT_TWIN_TEST_DOMAIN_ID wins.
_domain = os.environ.get("SOFT_TWIN_TEST_DOMAIN_ID")
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")          # "gw0", "gw1", ...
if not _domain and _worker.startswith("gw"):
    _run = int(os.environ.get("PYTEST_XDIST_TESTRUNUID", "0")[:8] or "0", 16)
    _domain = str(1 + (_run + int(_worker[2:])) % 101)
if not _domain:
    _domain = str(1 + os.getpid() % 101)
os.environ["ROS_DOMAIN_ID"] = _domain
# Tests discover on this machine only.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
# One BLAS thread, as in the node and the command line (which set it for their process: a command line
# run in-process would otherwise change it halfway through a session), and in the child processes.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "ros: starts ROS 2 entities (rclpy nodes, other processes); needs the .venv of `make setup`"
    )
    config.addinivalue_line(
        "markers", "slow: takes tens of seconds (e.g. builds a venv); deselect with -m 'not slow'"
    )
    config.addinivalue_line(
        "markers", "quiet: measures a rate or a wall time: `make test` runs it alone, after the others"
    )


def pytest_collection_modifyitems(config, items):
    """SOFT_TWIN_TEST_PHASE=parallel keeps the tests not marked ``quiet``,
    =quiet only those (scripts/run_tests.sh: the first phase on two workers,
    the second alone); unset, every test."""
    phase = os.environ.get("SOFT_TWIN_TEST_PHASE", "")
    if phase not in ("parallel", "quiet"):
        return
    keep, drop = [], []
    for item in items:
        (keep if (item.get_closest_marker("quiet") is not None) == (phase == "quiet") else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def pytest_report_header(config):
    return f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}"


def single_field_corruptions(base, values, n, seed, skip=()):
    """Yield n deep copies of the nested dict/list ``base`` with one field
    (a random path, not in ``skip``) replaced by a random entry of ``values``
    (fuzzing of the input validation)."""
    import copy
    import random

    def paths(d, prefix=()):
        items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else ()
        for k, v in items:
            yield prefix + (k,)
            yield from paths(v, prefix + (k,))
    rng = random.Random(seed)
    all_paths = [p for p in paths(base) if p not in skip]
    for _ in range(n):
        d = copy.deepcopy(base)
        path = rng.choice(all_paths)
        t = d
        for k in path[:-1]:
            t = t[k]
        t[path[-1]] = rng.choice(values)
        yield d
