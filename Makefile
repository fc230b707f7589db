# The two commands of the README. Both create the local virtual environment when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench venv

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

# README command 1: a full closed-loop alignment on the simulated rig, with a report
demo: $(STAMP)
	$(BIN)/alignctl demo --config configs/sim.yaml --out out/demo

# README command 2: lint, the test suite, and the benchmarks in their small CI mode
test: $(STAMP)
	$(BIN)/ruff check alignd drivers tests bench
	$(BIN)/python -m pytest
