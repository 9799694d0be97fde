PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
ENV ?= point_umaze
AGENT ?= morefree
PRESET ?= cpu
SEED ?= 0
# SEEDS=0,1,2: several seeds in one program (a run dir each); overrides SEED.
SEEDS ?=
TEST_WORKERS ?= 2
# Empty STEPS = the task's budget (its default_config: point_umaze 2e5 ... ant 8e5).
STEPS ?=
ARGS ?=
RUN_DIR ?= runs/$(ENV)/$(AGENT)/seed$(SEED)
# jemalloc preloaded where installed (libjemalloc2): ~15% faster learner steps (see morefree_jax/runtime.py).
ALLOC_ENV = $(shell $(PY) -c "import morefree_jax.runtime as r; r.print_allocator_env()" 2>/dev/null)

# make experiment: TASK (default ENV), AGENTS, SEEDS (default 0,1,2). make plots: RUNS, OUT, TASK (default all),
# MARKS (steps of the results table, e.g. 20000,100000), WINDOW (e.g. 75000:100000: the window table),
# PLOT_AGENTS (only these agents, e.g. oracle_sac,r3l; default all).
TASK ?=
AGENTS ?= morefree,rf_peg
DEFAULT_SEEDS := 0,1,2
# make plots reads runs/ where it exists, else the committed run records (a fresh clone redraws results/).
RUNS ?= $(if $(wildcard runs/*),runs,results/data)
DATA ?= results/data
OUT ?= results
MARKS ?=
WINDOW ?=
PLOT_AGENTS ?=

.PHONY: install test test-slow lint bench bench-bar clean train evaluate probe experiment sweep plots records demos

# CUDA=12 or CUDA=13 also installs the CUDA build of the pinned JAX (NVIDIA GPUs); empty = CPU only.
# SWEEP=1: Ray for make sweep (the dev extras have it too).
CUDA ?=
comma := ,
install:
	@case "$(CUDA)" in ""|12|13) ;; *) echo "error: CUDA=$(CUDA) is not supported; use CUDA=12, CUDA=13 or leave it empty (CPU)"; exit 2;; esac
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev$(if $(CUDA),$(comma)cuda$(CUDA))$(if $(SWEEP),$(comma)sweep)]"

test:
	$(PY) -m pytest -m "not slow" -q -n $(TEST_WORKERS) --dist loadfile --durations=30

test-slow:
	$(PY) -m pytest -m slow -q

lint:
	$(VENV)/bin/ruff check .

bench:
	env $(ALLOC_ENV) $(PY) -m experiments.benchmarks $(BENCH_ARGS)

# The model-free speed bar's rows alone (a few minutes): TORCH_PYTHON=<a Python with torch> for the PyTorch side.
bench-bar:
	env $(ALLOC_ENV) $(if $(TORCH_PYTHON),TORCH_PYTHON=$(TORCH_PYTHON)) $(PY) -m experiments.benchmarks.model_free

# Re-running the same command resumes the run from its last checkpoint. Extra dotted keys: ARGS="wm.deter=64".
train:
	env $(ALLOC_ENV) PYTHONPATH=src:. $(PY) -m experiments.train env=$(ENV) agent=$(AGENT) preset=$(PRESET) \
		$(if $(SEEDS),seeds=$(SEEDS),seed=$(SEED)) \
		$(if $(STEPS),steps=$(STEPS)) $(ARGS)

# Each agent's seeds in one program (a process per agent, one per core); re-run to resume; then the plots.
experiment:
	env $(ALLOC_ENV) PYTHONPATH=src:. $(PY) -m experiments.experiment task=$(or $(TASK),$(ENV)) agents=$(AGENTS) \
		seeds=$(or $(SEEDS),$(DEFAULT_SEEDS)) $(if $(STEPS),steps=$(STEPS)) preset=$(PRESET) $(ARGS)

# A grid of runs as Ray tasks (experiments/grids/*.toml; RAY_ADDRESS=<cluster> to run on a cluster); re-run
# to resume; then the figures in the grid's <runs>/results.
GRID ?= experiments/grids/debug.toml
sweep:
	PYTHONPATH=src:. $(PY) -m experiments.sweep grid=$(GRID)

# Figures (PNG, SVG) and results tables of every run dir below RUNS, written to OUT.
plots:
	PYTHONPATH=src:. $(PY) -m experiments.plots runs=$(RUNS) out=$(OUT) $(if $(TASK),task=$(TASK)) \
		$(if $(MARKS),marks=$(MARKS)) $(if $(WINDOW),window=$(WINDOW)) \
		$(if $(PLOT_AGENTS),agents=$(PLOT_AGENTS))

# The run records of every run dir below RUNS (results/data/<task>/<group>/seed<k>.jsonl + .npz): commit them.
records:
	@if [ "$(RUNS)" = "$(DATA)" ]; then echo "error: make records needs RUNS=<a directory of run dirs>, e.g. RUNS=runs"; exit 2; fi
	PYTHONPATH=src:. $(PY) -m experiments.records runs=$(RUNS) out=$(DATA) $(ARGS)

evaluate:
	env $(ALLOC_ENV) PYTHONPATH=src:. $(PY) -m experiments.evaluate_checkpoint run_dir=$(RUN_DIR) $(ARGS)

# Where a run's goal policy ends its episodes and its learned distance on the way (docs/training.md).
probe:
	env $(ALLOC_ENV) PYTHONPATH=src:. $(PY) -m experiments.analysis.goal_probe run_dir=$(RUN_DIR) $(ARGS)

# MEDAL's scripted demonstrations -> envs_mjx/demos/<task>.npz and checksums.json. Without ENV (not the
# point_umaze default of the other targets) every task with demonstrations; ENV=push: one task.
DEMOS_ENV = $(if $(filter command line environment,$(origin ENV)),$(ENV),all)
demos:
	env $(ALLOC_ENV) PYTHONPATH=src:. $(PY) -m experiments.make_demos env=$(DEMOS_ENV)

clean:
	rm -rf bench/ .pytest_cache build *.egg-info src/*.egg-info
