"""How busy the machine is, from /proc/stat (Linux): the tests that measure
a real-time rate check it before they start (test_node_articulated_flood),
and scripts/run_tests.sh waits for the processes of the parallel phase to
wind down before the `quiet` tests run."""

import os
import sys
import time


def _stat():
    with open("/proc/stat") as fh:
        f = [float(x) for x in fh.readline().split()[1:]]
    return sum(f), f[3] + f[4]                    # all, idle + iowait (clock ticks)


def cpus_busy(seconds=1.0):
    """CPUs' worth of work the machine did over the next ``seconds``."""
    a0, i0 = _stat()
    time.sleep(seconds)                           # a measurement window (not a wait for ROS)
    a1, i1 = _stat()
    return (1.0 - (i1 - i0) / max(a1 - a0, 1e-9)) * (os.cpu_count() or 1)


def wait_until_quiet(threshold=0.25, timeout=60.0):
    """Measure 1 s windows until one uses less than ``threshold`` CPUs or
    ``timeout`` [s] passes; returns (quiet, the last window's CPUs, seconds waited)."""
    t0 = time.monotonic()
    while True:
        busy = cpus_busy(1.0)
        waited = time.monotonic() - t0
        if busy < threshold or waited >= timeout:
            return busy < threshold, busy, waited


if __name__ == "__main__":                        # scripts/run_tests.sh, between its phases
    quiet, busy, waited = wait_until_quiet()
    print(f"[run_tests] machine {'quiet' if quiet else 'still busy'} ({busy:.2f} CPUs in use) "
          f"after {waited:.0f} s", file=sys.stderr)
    if not quiet:
        os.system("ps -eo pcpu,etime,args --sort=-pcpu | head -8 >&2")
