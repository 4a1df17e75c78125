PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
RAY_STAMP := $(VENV)/.installed-ray
ROS_STAMP := $(VENV)/.installed-ros
PEER := .venv-peer
PEER_STAMP := $(PEER)/.installed

.PHONY: install install-gpu install-ros test lint run bench bench-quick clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# The Python client (clients/python) too: its tests run against this checkout's service.
$(STAMP): $(BIN)/python pyproject.toml constraints.txt clients/python/pyproject.toml
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev]' -e 'clients/python[numpy]'
	touch $(STAMP)

# The `ray` extra for the tests and benchmarks only (the scale-out's failure test, tests/e2e/test_scaleout.py,
# runs on a real local Ray cluster in CI); `make run` serves the single process and does not need it.
$(RAY_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev,ray]'
	touch $(RAY_STAMP)

# The `ros` extra (ROS 2 Kilted's wheels) and the ROS 2 node (clients/ros2) for its tests, which run it on
# real rclpy (tests/clients/ros2); `make run` does not need them. `make install-ros` is the README's first
# step of "With ROS 2".
$(ROS_STAMP): $(STAMP) clients/ros2/setup.py
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev,ros]' -e clients/ros2
	touch $(ROS_STAMP)

install-ros: $(ROS_STAMP)

# BrainBlocks 0.7.1, the Temporal Memory's peer in benchmarks/bench_tm_peer.py (docs/benchmarks.md §12), so
# that `make bench` writes the memory's ratio with its reference measured in the same run. A peer, not a
# dependency: its own environment, built from the sdist with cmake and g++, which needs `wheel` and
# pybind11's CMake files (and setuptools < 72 for its setup.py).
$(PEER_STAMP):
	$(PYTHON) -m venv $(PEER) || python3 -m venv $(PEER)
	$(PEER)/bin/pip install --quiet 'setuptools<72' wheel pybind11 numpy
	CMAKE_PREFIX_PATH=$$($(PEER)/bin/python -m pybind11 --cmakedir) \
		$(PEER)/bin/pip install --quiet --no-build-isolation brainblocks==0.7.1
	touch $(PEER_STAMP)

install: $(STAMP)

# CUDA for the encoder (CORTEXLOC_DEVICE=cuda|auto): onnxruntime-gpu replaces the CPU wheel, since both
# install the same `onnxruntime` module and pip cannot swap a dependency through an extra.
install-gpu: $(STAMP)
	$(BIN)/pip uninstall --quiet -y onnxruntime
	$(BIN)/pip install --quiet -c constraints.txt -e '.[gpu]'

lint: install
	$(BIN)/ruff check .

# Both cores (pytest-xdist): the suite is mostly one core's work at a time (24 min in one process, 14.5 on
# two). Tests marked `xdist_group` stay on one worker: the Ray cluster of tests/e2e/test_scaleout.py starts
# once, and never beside another.
test: $(RAY_STAMP) $(ROS_STAMP) lint
	$(BIN)/pytest -q -n 2 --dist loadgroup

run: install
	$(BIN)/cortexloc serve

bench: $(RAY_STAMP) $(PEER_STAMP)
	$(BIN)/cortexloc bench all

bench-quick: $(RAY_STAMP)
	$(BIN)/cortexloc bench all --quick

clean:
	rm -rf $(VENV) $(PEER) .pytest_cache .ruff_cache
