# The two commands of the README. Both create the local virtual environment when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-newest bench-quick venv browser stress

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev,bluesky]'
	touch $(STAMP)

venv: $(STAMP)

# README command 1: a full closed-loop alignment on the simulated rig, with a report
SEED ?=
demo: $(STAMP)
	$(BIN)/alignctl demo --config configs/sim.yaml --out out/demo $(if $(SEED),--seed $(SEED))

# README command 2: lint, the type check, the import contracts, the benchmarks in their small CI mode, the test suite (last, so
# its summary closes the output)
test: $(STAMP) browser
	$(BIN)/ruff check alignd drivers tests bench
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(MAKE) --no-print-directory bench-quick
	$(MAKE) --no-print-directory test-newest NEWEST_ARGS="$(NEWEST_SUBSET)"
	$(BIN)/python -m pytest

# on the newest Python the suite less its slowest files (faults, soak, solver accuracy, the
# wheel install), which the main run covers
NEWEST_SUBSET := --ignore=tests/test_faults_daemon.py --ignore=tests/test_faults_link.py \
	--ignore=tests/test_faults_motion.py --ignore=tests/test_faults_camera.py \
	--ignore=tests/test_solve_methods.py --ignore=tests/test_install.py

bench-quick: $(STAMP)
	@set -e; for b in bench/*.py; do echo "== $$b --quick"; $(BIN)/python $$b --quick; done

# The type check and the suite on the newest supported Python as well. PY_NEWEST: a Python
# 3.13; pyenv's when there is one. CI runs a fast subset (NEWEST_ARGS in .ci/run): the fault,
# soak, solver-accuracy and wheel tests (Python-independent, minutes) run on $(PY) only.
NEWEST_ARGS ?=
PY_NEWEST ?= $(or $(shell pyenv prefix 3.13 2>/dev/null | sed 's|$$|/bin/python3|'),python3.13)
VENV_NEWEST := .venv-newest
$(VENV_NEWEST)/.installed: pyproject.toml constraints.txt
	test -x $(VENV_NEWEST)/bin/python || $(PY_NEWEST) -m venv $(VENV_NEWEST)
	$(VENV_NEWEST)/bin/python -m pip install --quiet --upgrade pip
	$(VENV_NEWEST)/bin/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $@

test-newest: $(VENV_NEWEST)/.installed
	$(VENV_NEWEST)/bin/python --version
	$(VENV_NEWEST)/bin/mypy --python-version 3.13
	$(VENV_NEWEST)/bin/python -m pytest $(NEWEST_ARGS)

# the whole suite 5 times with one CPU-bound process per core beside it (never flakes)
RUNS ?= 5
stress: $(STAMP)
	@mkdir -p out; RUNS=$(RUNS) PY=$(BIN)/python tests/stress.sh

# headless Chromium for the dashboard's browser test (tests/test_web.py): installed with
# apt-get when missing and we are root; otherwise that test skips and says why
browser:
	@if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing chromium and chromium-driver for the browser test"; \
		apt-get install -y -q chromium chromium-driver >/dev/null \
		|| { apt-get update -q >/dev/null && apt-get install -y -q chromium chromium-driver >/dev/null; } \
		|| echo "could not install chromium: the browser test will skip"; \
	else echo "no chromium and not root: the browser test will skip"; fi
