# soft_twin: two commands for newcomers, `make demo` and `make test`.
# Every target first runs the idempotent set-up (scripts/setup_env.sh): a
# .venv with the pinned ROS 2 Jazzy wheels and the package built into it.
# A run with nothing changed skips the installs and takes a few seconds.

VENV        ?= .venv
PY          := $(VENV)/bin/python
ARGS        ?=
PYTEST_ARGS ?=
# pytest-xdist workers of `make test` and `make test-quick` (0: one process); the tests
# marked `quiet` (a rate, a wall time) run after the others, alone (scripts/run_tests.sh)
WORKERS     ?= 2

export SOFT_TWIN_VENV := $(abspath $(VENV))

.PHONY: setup demo test test-quick test-shuffled run lock clean

setup:
	@bash scripts/setup_env.sh

# The main job: the twin node driven by a demo client; prints a table, writes a PNG,
# an animation (out/demo.gif) and the node's recording (out/demo.mcap).
demo: setup
	$(PY) scripts/demo.py $(ARGS)

# The whole suite. pytest exits 5 when it collected no test: that fails too.
test: setup
	bash scripts/run_tests.sh $(PY) $(WORKERS) $(PYTEST_ARGS)

# The inner loop: test/unit (the physics, the files, the twin's logic; no ROS
# entity, no other process but a few CLI runs; a few minutes on 2 cores).
# The tiers: test/unit, test/integration (command lines, Dask clusters,
# packaging, reference solvers), test/ros (nodes, clients, recordings).
test-quick: setup
	bash scripts/run_tests.sh $(PY) $(WORKERS) test/unit $(PYTEST_ARGS)

# The whole suite in a random order across modules, in one process (pytest-random-order; the
# seed is printed: rerun one order with PYTEST_ARGS=--random-order-seed=N).
test-shuffled: setup
	$(PY) -m pytest --random-order-bucket=global $(PYTEST_ARGS)

# The node alone, e.g. make run ARGS="--ros-args --params-file config/params.yaml -p mode:=dynamic"
run: setup
	$(VENV)/bin/soft_twin_node $(ARGS)

# Re-resolve requirements/constraints.txt after editing requirements/{ros,dev}.txt.
lock:
	bash scripts/lock_requirements.sh

clean:
	rm -rf build $(VENV)
