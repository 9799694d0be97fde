"""Train an agent on a reset-free task; re-running the same command resumes from the last checkpoint.

    python -m experiments.train env=point_umaze agent=morefree preset=cpu seed=0 steps=200000 [key=value ...]
    python -m experiments.train env=point_umaze seeds=0,1,2     # three seeds in one program, a run dir each

Keys: env, agent (one of the registry's, listed below), preset (paper, cpu, debug), seed, steps; any
dotted config key (wm.deter=64, planner.iterations=3, schedule.alpha=0.3,
run.eval_every=5000, or run keys without "run.": eval_every=5000). The run dir is
runs/<env>/<agent>/seed<seed> unless run_dir=... is given (with seeds=: <run_dir>/seed<k>). Bad input exits
with code 2 and one line.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import sys

import envs_mjx
from morefree_jax import runtime
from morefree_jax.checkpoint import CheckpointError, ConfigMismatchError
from morefree_jax.config import ConfigError, resolve_config
from morefree_jax.run_lock import RunDirError


def _runtime_line() -> str:
    settings = runtime.settings()
    line = f"runtime {settings['mode']}, allocator {settings['allocator']}"
    if settings["allocator"] != "jemalloc":
        line += " (with libjemalloc2 installed, `make train` preloads jemalloc: ~15% faster updates)"
    return line


def disk_error_line(error: OSError) -> str:
    """One line for a failed write: the file, the reason, and the free space where it was written."""
    path = error.filename or "a file"
    line = f"could not write {path} ({error.strerror or error})"
    if error.filename:
        existing = pathlib.Path(error.filename).resolve()
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        line += f"; {shutil.disk_usage(existing).free / 2**20:.1f} MiB free there"
    return line + "; checkpoints already written are kept: free space and re-run the same command to resume"


def split_seeds(argv: list[str]) -> tuple[tuple[int, ...] | None, list[str]]:
    """(the seeds of a `seeds=0,1,2` argument or None, the other arguments); one-line ConfigErrors."""
    given = [arg for arg in argv if arg.startswith("seeds=")]
    if not given:
        return None, argv
    if len(given) > 1 or any(arg.startswith(("seed=", "run.seed=")) for arg in argv):
        raise ConfigError("give either seed=<k> or seeds=<k,...> (once), not both")
    from morefree_jax.seeds import parse_seeds

    return parse_seeds(given[0].partition("=")[2]), [arg for arg in argv if arg not in given]


def agents_help() -> str:
    """One line per agent of the registry: name, description and the config sections it reads."""
    from morefree_jax.registry import AGENTS

    width = max(map(len, AGENTS))
    rows = [f"  {name:<{width}}  {entry.description} [{', '.join(entry.config_sections)}]"
            for name, entry in AGENTS.items()]
    return "Agents:\n" + "\n".join(rows)


def _learner_precision(config, seeds) -> str:
    """agent.precision as given or as recorded in the first run dir: read before JAX starts (XLA flags)."""
    from morefree_jax.precision import stored_precision
    from morefree_jax.seeds import seed_configs

    if config.agent.precision != "auto":
        return config.agent.precision
    first = seed_configs(config, seeds or (config.run.seed,))[0]
    return stored_precision(first.run.resolved_run_dir) or "auto"


def main(argv: list[str]) -> int:
    if any(arg in ("-h", "--help") for arg in argv):
        print(__doc__ + "\n" + agents_help())
        return 0
    # Before any JAX computation (XLA flags, allocator settings); paper-size learners use the `large` mode
    # unless MOREFREE_JAX_RUNTIME says otherwise (see morefree_jax.runtime).
    paper = "preset=paper" in argv and runtime.MODE_VARIABLE not in os.environ
    try:
        seeds, argv = split_seeds(argv)
        config = resolve_config(argv, envs_mjx.ALL_ENVS)
        runtime.configure("large" if paper else None, _learner_precision(config, seeds))
        from morefree_jax import driver  # imports jax: after the cheap checks

        config = driver.settle_precision(config, seeds or None)

        seeds = seeds or (config.run.seed,)
        programs = driver.build_programs(config, len(seeds))
        fns, run_dirs = programs.fns, [c.run.resolved_run_dir for c in driver.seed_configs(config, seeds)]
        plural = "s" if len(seeds) > 1 else ""
        print(f"run dir{plural} {', '.join(run_dirs)}: {config.run.agent} on {config.run.env}, preset "
              f"{config.run.preset}, seed{plural} {','.join(map(str, seeds))}, chunk {fns.chunk_len} steps, "
              f"{fns.updates_per_chunk} updates/chunk", flush=True)
        print(_runtime_line(), flush=True)
        summary = driver.train(config, seeds, programs)[0]
    except (ConfigError, ConfigMismatchError, CheckpointError, RunDirError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a second Ctrl-C: stop now; the last checkpoint written stays
        print("interrupted; re-run the same command to resume from the last checkpoint", file=sys.stderr)
        return 130
    except OSError as error:  # e.g. a full disk: which file, and how much space is left
        print(f"error: {disk_error_line(error)}", file=sys.stderr)
        return 2
    except ValueError as error:  # validation in the task / replay / schedule constructors
        print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 2
    if summary.interrupted:
        print(f"interrupted at step {summary.env_steps}; checkpoint saved; re-run the same command to resume")
        return 130
    print(f"done: {summary.env_steps} env steps; run dirs {', '.join(run_dirs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
