PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
ENV ?= point_umaze
AGENT ?= morefree
PRESET ?= cpu
SEED ?= 0
TEST_WORKERS ?= 2

.PHONY: install test test-slow lint bench clean

install:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"

test:
	$(PY) -m pytest -m "not slow" -q -n $(TEST_WORKERS) --dist loadfile

test-slow:
	$(PY) -m pytest -m slow -q

lint:
	$(VENV)/bin/ruff check .

bench:
	$(PY) -m experiments.bench $(BENCH_ARGS)

clean:
	rm -rf bench/ .pytest_cache build *.egg-info src/*.egg-info
