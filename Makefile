# The two commands of the README. Both create the local virtual environment when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench-quick venv browser stress

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,bluesky]'
	touch $(STAMP)

venv: $(STAMP)

# README command 1: a full closed-loop alignment on the simulated rig, with a report
SEED ?=
demo: $(STAMP)
	$(BIN)/alignctl demo --config configs/sim.yaml --out out/demo $(if $(SEED),--seed $(SEED))

# README command 2: lint, the benchmarks in their small CI mode, the test suite (last, so
# its summary closes the output)
test: $(STAMP) browser
	$(BIN)/ruff check alignd drivers tests bench
	$(MAKE) --no-print-directory bench-quick
	$(BIN)/python -m pytest

bench-quick: $(STAMP)
	@set -e; for b in bench/*.py; do echo "== $$b --quick"; $(BIN)/python $$b --quick; done

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
