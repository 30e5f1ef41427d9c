"""One BLAS thread in the processes the twin owns (soft_twin_core._blas.blas_on_one_thread).

The engine's matrices are small; a second OpenBLAS thread saves no time there
and spins on the other core between calls. The node, the estimator node and
the command line limit BLAS to one thread, unless the user chose a count.
Checked in fresh processes, on the BLAS libraries loaded before the call
(numpy's) and after it (scipy's, which the compiled kernels' LAPACK calls load)."""

import json
import os
import subprocess
import sys

import pytest

_REPORT = """
import json, sys
if sys.argv[1] == "limit":
    from soft_twin_core._blas import blas_on_one_thread
    blas_on_one_thread()
import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS after the call)
from threadpoolctl import threadpool_info
print(json.dumps({i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}))
"""

_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _threads(mode, **env):
    clean = {k: v for k, v in os.environ.items() if k not in _VARS}
    out = subprocess.run([sys.executable, "-c", _REPORT, mode], capture_output=True, text=True, timeout=120,
                         env={**clean, **env}, check=True).stdout
    counts = json.loads(out.strip().splitlines()[-1])
    assert len(counts) >= 2, f"expected numpy's and scipy's BLAS, got {counts}"
    return counts


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU: BLAS uses one thread anyway")
def test_the_entry_points_limit_every_blas_to_one_thread():
    assert max(_threads("plain").values()) > 1          # the default this guards against
    assert set(_threads("limit").values()) == {1}


def test_a_count_the_user_chose_is_kept():
    assert set(_threads("limit", OPENBLAS_NUM_THREADS="2").values()) == {2}


def test_the_suite_runs_on_one_blas_thread():
    import importlib
    importlib.import_module("scipy.linalg")       # (its BLAS loaded)
    from threadpoolctl import threadpool_info
    counts = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert len(counts) >= 2 and set(counts) == {1}, counts


_BLOCK = """
import json
from soft_twin_core._blas import one_blas_thread
import scipy.linalg  # noqa: F401  (its BLAS loads after soft_twin_core._blas)
from threadpoolctl import threadpool_info
def counts():
    return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
before = counts()
with one_blas_thread():
    inside = counts()
print(json.dumps([before, inside, counts()]))
"""


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU: BLAS uses one thread anyway")
def test_a_block_limits_the_blas_libraries_loaded_after_the_module():
    clean = {k: v for k, v in os.environ.items() if k not in _VARS}
    out = subprocess.run([sys.executable, "-c", _BLOCK], capture_output=True, text=True, timeout=120, env=clean,
                         check=True).stdout
    before, inside, after = json.loads(out.strip().splitlines()[-1])
    assert len(before) >= 2 and min(before) > 1
    assert inside == [1] * len(before) and after == before
