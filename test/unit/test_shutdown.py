"""The last resort of a node's stop (soft_twin.shutdown.arm_hard_exit): a
process whose main thread holds the GIL in a stuck call still exits, with
status 0 and a line on stderr, when the C library's timer fires (the Python
watchdog cannot run then)."""

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_process_stuck_holding_the_gil_exits_cleanly():
    code = ("import ctypes, sys\n"
            f"sys.path.insert(0, {str(ROOT)!r})\n"
            "from soft_twin.shutdown import arm_hard_exit\n"
            "assert arm_hard_exit(0.5, 'stuck: exiting')\n"
            "print('armed', flush=True)\n"
            "ctypes.PyDLL(None).sleep(60)      # a C call that keeps the GIL\n"
            "print('not reached', flush=True)\n")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50)
    took = time.monotonic() - t0
    assert r.returncode == 0 and "armed" in r.stdout and "not reached" not in r.stdout, (r.returncode, r.stdout)
    assert "stuck: exiting" in r.stderr
    assert took < 30                       # the 60 s sleep was cut short
