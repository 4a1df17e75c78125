PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install install-gpu test lint run bench bench-quick clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# The Python client (clients/python) too: its tests run against this checkout's service. The `ray` extra
# too: the scale-out's failure test (tests/e2e/test_scaleout.py) runs on a real local Ray cluster in CI.
$(STAMP): $(BIN)/python pyproject.toml constraints.txt clients/python/pyproject.toml
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev,ray]' -e 'clients/python[numpy]'
	touch $(STAMP)

install: $(STAMP)

# CUDA for the encoder (CORTEXLOC_DEVICE=cuda|auto): onnxruntime-gpu replaces the CPU wheel, since both
# install the same `onnxruntime` module and pip cannot swap a dependency through an extra.
install-gpu: $(STAMP)
	$(BIN)/pip uninstall --quiet -y onnxruntime
	$(BIN)/pip install --quiet -c constraints.txt -e '.[gpu]'

lint: install
	$(BIN)/ruff check .

test: install lint
	$(BIN)/pytest -q

run: install
	$(BIN)/cortexloc serve

bench: install
	$(BIN)/python benchmarks/run_all.py

bench-quick: install
	$(BIN)/python benchmarks/run_all.py --quick

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
