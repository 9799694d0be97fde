PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
ENV ?= point_umaze
AGENT ?= morefree
PRESET ?= cpu
SEED ?= 0
TEST_WORKERS ?= 2
STEPS ?= 1000000
ARGS ?=
RUN_DIR ?= runs/$(ENV)/$(AGENT)/seed$(SEED)

.PHONY: install test test-slow lint bench clean train evaluate

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

# Re-running the same command resumes the run from its last checkpoint. Extra dotted keys: ARGS="wm.deter=64".
train:
	PYTHONPATH=src:. $(PY) -m experiments.train env=$(ENV) agent=$(AGENT) preset=$(PRESET) seed=$(SEED) \
		steps=$(STEPS) $(ARGS)

evaluate:
	PYTHONPATH=src:. $(PY) -m experiments.evaluate run_dir=$(RUN_DIR) $(ARGS)

clean:
	rm -rf bench/ .pytest_cache build *.egg-info src/*.egg-info
