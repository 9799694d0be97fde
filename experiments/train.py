"""Train an agent on a reset-free task; re-running the same command resumes from the last checkpoint.

    python -m experiments.train env=point_umaze agent=morefree preset=cpu seed=0 steps=200000 [key=value ...]

Keys: env, agent (a variant: morefree, rf_peg, peg, dreamer_gc, mf_no_bfge, mf_no_imag, mf_task_only),
preset (paper, cpu, debug), seed, steps; any dotted config key (wm.deter=64, planner.iterations=3,
schedule.alpha=0.3, run.eval_every=5000, or run keys without "run.": eval_every=5000). The run dir is
runs/<env>/<agent>/seed<seed> unless run_dir=... is given. Bad input exits with code 2 and one line.
"""

from __future__ import annotations

import os
import sys

import envs_mjx
from morefree_jax import runtime
from morefree_jax.checkpoint import CheckpointError, ConfigMismatchError
from morefree_jax.config_run import ConfigError, resolve_config


def _runtime_line() -> str:
    settings = runtime.settings()
    line = f"runtime {settings['mode']}, allocator {settings['allocator']}"
    if settings["allocator"] != "jemalloc":
        line += " (with libjemalloc2 installed, `make train` preloads jemalloc: ~15% faster updates)"
    return line


def main(argv: list[str]) -> int:
    if any(arg in ("-h", "--help") for arg in argv):
        print(__doc__)
        return 0
    # Before any JAX computation (XLA flags, allocator settings); paper-size learners use the `large` mode
    # unless MOREFREE_JAX_RUNTIME says otherwise (see morefree_jax.runtime).
    paper = "preset=paper" in argv and runtime.MODE_VARIABLE not in os.environ
    runtime.configure("large" if paper else None)
    try:
        config = resolve_config(argv, envs_mjx.ALL_ENVS)
        from morefree_jax.loop import prepare_run  # imports jax: after the cheap checks

        run = prepare_run(config)
        print(f"run dir {run.run_dir}: {config.run.agent} on {config.run.env}, preset {config.run.preset}, "
              f"seed {config.run.seed}, chunk {run.chunk_len} steps, {run.updates_per_chunk} updates/chunk",
              flush=True)
        print(_runtime_line(), flush=True)
        summary = run.train()
    except (ConfigError, ConfigMismatchError, CheckpointError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except ValueError as error:  # validation in the task / replay / schedule constructors
        print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 2
    if summary.interrupted:
        print(f"interrupted at step {summary.env_steps}; checkpoint saved; re-run the same command to resume")
        return 130
    print(f"done: {summary.env_steps} env steps; run dir {summary.run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
