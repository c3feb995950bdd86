# The two set-up commands of the README: `make run` and `make test`.
# Everything the project needs is installed from here into .venv; CI and new machines start bare.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PACKAGES := cell drivers estimator api fakes
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: install kernels checks lint test run bench clean browser

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) kernels

# The estimator's numba kernels, compiled once and cached (a fresh checkout takes ~15 s), and
# the OPC UA standard address space written once as a shelf; the suite's workers and the
# service then load them.
kernels: $(STAMP)
	$(BIN)/python -m estimator.kernels
	$(BIN)/python -m api.plc.opcua_address_space

lint: $(STAMP)
	$(BIN)/ruff check $(PACKAGES) tests
	$(BIN)/mypy
	$(BIN)/lint-imports

# Two xdist workers, one test file per worker at a time (its module fixtures, CPU burners and
# servers stay in one process), the real-time UR files one after another, longest work first
# (the groups and the order are in tests/conftest.py). Most tests wait on simulated motion in
# real time, so two workers nearly halve the time on 2 cores.
# `make test TEST_WORKERS=0` runs the suite in one process. The slowest tests are listed at
# the end of every run, to keep the suite within its time budget.
TEST_WORKERS ?= 2

# lint, the kernels' compile and the browser check run side by side before the suite
checks: $(STAMP)
	@$(MAKE) --no-print-directory -j3 lint kernels browser

test: checks
	$(BIN)/pytest -n $(TEST_WORKERS) --dist loadgroup --no-loadscope-reorder --durations=25

# Headless Chromium for the operator-page tests: Debian's package, never a browser download.
# Installs only when missing and we are root; otherwise the browser tests skip with a reason.
browser:
	@if [ ! -x /usr/bin/chromium ]; then \
		if [ "$$(id -u)" = 0 ]; then \
			apt-get install -y --no-install-recommends chromium \
			|| { apt-get update && apt-get install -y --no-install-recommends chromium; }; \
		else \
			echo "browser: /usr/bin/chromium missing and not root; browser tests will skip"; \
		fi; \
	fi

run: install
	$(BIN)/cell serve --host $(HOST) --port $(PORT)

bench: install
	$(BIN)/cell bench

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache
