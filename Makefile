# The two set-up commands of the README: `make run` and `make test`.
# Everything the project needs is installed from here into .venv; CI and new machines start bare.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PACKAGES := cell drivers estimator api fakes
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: install lint test run bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

lint: install
	$(BIN)/ruff check $(PACKAGES) tests
	$(BIN)/mypy

test: lint
	$(BIN)/pytest

run: install
	$(BIN)/cell serve --host $(HOST) --port $(PORT)

bench: install
	$(BIN)/cell bench

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache
