#!/usr/bin/env bash
# make test / make test-quick: pytest in two phases.
#   1. every test not marked `quiet`, on WORKERS pytest-xdist workers (the 2 cores);
#   2. the `quiet` ones (they measure a real-time rate or a wall time) in one
#      process, alone on the machine (once it is quiet: test/machine_load.py).
# Usage: run_tests.sh PYTHON WORKERS [pytest arguments...] (the selection applies to
# both phases). Exit code: the first phase's failure, else the second's; a phase
# that selected no test (pytest's 5) counts as passed unless neither selected one.
set -u
PY=$1
WORKERS=$2
shift 2
SOFT_TWIN_TEST_PHASE=parallel "$PY" -m pytest -n "$WORKERS" --dist worksteal "$@"
first=$?
# the first phase's processes (nodes, Dask workers, browsers) wind down before the rates are measured
"$PY" test/machine_load.py
SOFT_TWIN_TEST_PHASE=quiet "$PY" -m pytest -p no:xdist "$@"
second=$?
if [ "$first" -eq 5 ] && [ "$second" -eq 5 ]; then
    exit 5
fi
[ "$first" -eq 5 ] && first=0
[ "$second" -eq 5 ] && second=0
[ "$first" -ne 0 ] && exit "$first"
exit "$second"
