"""Session-wide pytest set-up for soft_twin.

* Every test session gets its own ROS_DOMAIN_ID (set here, at conftest import,
  before any test module can import rclpy), so parallel runs on one machine
  never see each other's nodes. Child processes (a node started with
  subprocess) inherit it through os.environ.
* Registers the markers used by the suite (--strict-markers is on).
"""
import os

# ROS 2 domain ids 1..101 are safe on Linux with Fast DDS defaults (0 is the
# default everyone shares). An explicit SOFT_TWIN_TEST_DOMAIN_ID wins.
_domain = os.environ.get("SOFT_TWIN_TEST_DOMAIN_ID")
if not _domain:
    _domain = str(1 + os.getpid() % 101)
os.environ["ROS_DOMAIN_ID"] = _domain
# Tests discover on this machine only.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "ros: starts ROS 2 entities (rclpy nodes, other processes); needs the .venv of `make setup`"
    )
    config.addinivalue_line(
        "markers", "slow: takes tens of seconds (e.g. builds a venv); deselect with -m 'not slow'"
    )


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
