# The two commands of the README. Both create the local virtual environment when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench-quick venv

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

# README command 1: a full closed-loop alignment on the simulated rig, with a report
SEED ?=
demo: $(STAMP)
	$(BIN)/alignctl demo --config configs/sim.yaml --out out/demo $(if $(SEED),--seed $(SEED))

# README command 2: lint, the type check, the import contracts, the benchmarks in their small CI mode, the test suite (last, so
# its summary closes the output)
test: $(STAMP)
	$(BIN)/ruff check alignd drivers tests bench
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(MAKE) --no-print-directory bench-quick
	$(BIN)/python -m pytest

bench-quick: $(STAMP)
	@set -e; for b in bench/*.py; do echo "== $$b --quick"; $(BIN)/python $$b --quick; done
