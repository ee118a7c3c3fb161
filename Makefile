# mmslam: every target does its own set-up (venv, editable install, LLVM for Sionna RT on the CPU).
#   make demo   set up, then run the main job on the built-in default scenario
#   make test   set up, then run the whole test suite (slow end-to-end tests included)
#   make bench  set up, then run the benchmarks
#   make test-min  the fast tests in a second venv (.venv-min) holding the lowest version of every
#               dependency that pyproject.toml allows (uv's --resolution lowest-direct)
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mmslam-installed
VENV_MIN ?= .venv-min
MIN_STAMP := $(VENV_MIN)/.mmslam-installed
DEMO_ARGS ?=

.PHONY: setup llvm demo test test-fast test-min bench clean

setup: $(STAMP) llvm

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@# compile the filter's numba kernels now, not in the first run (a pip install gets a notice instead)
	$(PY) -m mmslam.slam.filter.precompile
	@touch $(STAMP)

# the lowest allowed direct dependencies (transitive ones: the newest they allow, as pip would pick);
# its own numba cache: kernels of another numba version would otherwise replace the main venv's
$(MIN_STAMP): pyproject.toml
	@test -x $(VENV_MIN)/bin/python || $(PYTHON) -m venv $(VENV_MIN)
	$(VENV_MIN)/bin/python -m pip install --quiet --upgrade pip uv
	$(VENV_MIN)/bin/python -m uv pip install --quiet --python $(VENV_MIN)/bin/python --resolution lowest-direct -e '.[dev]'
	@touch $(MIN_STAMP)

# Sionna RT (Dr.Jit) on the CPU needs libLLVM >= 16; Debian 12's default libLLVM-15 aborts.
llvm: $(STAMP)
	@if $(PY) -m mmslam.backend --check >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing libllvm19 (Sionna RT on the CPU needs LLVM >= 16)"; \
	  (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || \
	   (apt-get update -qq && apt-get install -y -qq libllvm19)) && $(PY) -m mmslam.backend --check >/dev/null; \
	else \
	  echo "error: no libLLVM >= 16 found; run: sudo apt-get install -y libllvm19 (or set DRJIT_LIBLLVM_PATH)" >&2; exit 1; \
	fi

demo: setup
	$(VENV)/bin/mmslam demo $(DEMO_ARGS)

# the tests in one process per core (pytest-xdist; worksteal: the few long end-to-end tests do not leave a core idle)
test: setup
	$(PY) -m pytest -q -n auto --dist worksteal

test-fast: setup
	$(PY) -m pytest -q -n auto --dist worksteal -m "not slow"

test-min: $(MIN_STAMP) llvm
	NUMBA_CACHE_DIR=$(abspath $(VENV_MIN))/numba-cache $(VENV_MIN)/bin/python -m pytest -q -n auto --dist worksteal -m "not slow"

bench: setup
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done
	@echo "== benchmarks/bench_filter.py --city (the city defaults' VA row)"; $(PY) benchmarks/bench_filter.py --city --variants proposed

clean:
	rm -rf $(VENV) $(VENV_MIN) out .pytest_cache build *.egg-info
