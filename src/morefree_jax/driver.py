"""The host driver of training runs: prefill, then chunks of collect -> train, with evaluation, logging,
checkpoints and Ctrl-C; re-running the same config on its run dirs resumes them exactly.

    summaries = train(config)                      # one seed (config.run.seed), one run dir
    summaries = train(config, seeds=(0, 1, 2))     # three seeds in one program, a run dir each

The pure functions of a run are in run.py, compiled over a seed axis in compile.py. Per chunk there
are two compiled calls, `collect` and `train_updates`, each advancing every seed; both take and return the
whole RunState of all seeds with its buffers donated. This module only keeps the cadence: step counting,
logs, evaluations, checkpoints, the stop flag. Each seed writes its own run dir (config.json with its seed,
metrics.jsonl, TensorBoard, plots, checkpoints of its own state), so every tool that reads one run reads
any seed of a group; a group's checkpoints are written at the same steps and resume at the newest step
that every seed has.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import pathlib
import signal
import sys
import time
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp

import envs_mjx
from morefree_jax.back_starts import stored_back_starts
from morefree_jax.checkpoint import CheckpointError, RunCheckpointer, check_run_dir_config, latest_valid
from morefree_jax.compile import (
    Programs,
    compile_programs,
    compiler_options,
    seed_sharding,
    seed_slice,
    stack_seeds,
)
from morefree_jax.config import RESUMABLE_KEYS, Config, ConfigError, config_from_dict, config_to_dict
from morefree_jax.logger import DROPPED_SHARE, RunLogger
from morefree_jax.precision import default_precision, stored_precision
from morefree_jax.registry import make_run_fns
from morefree_jax.run import RunFns, RunState, compiled_settings
from morefree_jax.run_lock import RunDirLock
from morefree_jax.seeds import check_seeds, seed_configs


class RunSummary(NamedTuple):
    env_steps: int
    interrupted: bool
    last_metrics: dict
    run_dir: str


def eval_keys(seeds: tuple[int, ...], step: int) -> jax.Array:
    """Evaluation keys depend on the seed and step only (never on the run's key stream)."""
    return jnp.stack([jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), 1), step)
                      for seed in seeds])


def settle_precision(config: Config, seeds=None) -> Config:
    """config with agent.precision "auto" made concrete: the precision recorded in the group's run dirs (a
    resume keeps it) or, for new run dirs, this machine's default (precision.py)."""
    if config.agent.precision != "auto":
        return config
    seeds = check_seeds((config.run.seed,) if seeds is None else seeds)
    stored = {stored_precision(c.run.resolved_run_dir) for c in seed_configs(config, seeds)} - {None}
    if len(stored) > 1:
        raise ConfigError(f"the run dirs of this group were made with different precisions {sorted(stored)}; "
                          "resume them separately")
    precision = stored.pop() if stored else default_precision()
    return dataclasses.replace(config, agent=dataclasses.replace(config.agent, precision=precision))


def build_programs(config: Config, num_seeds: int = 1) -> Programs:
    """The run functions of `config` compiled for `num_seeds` seeds (sharded over devices when several)."""
    fns = make_run_fns(config, envs_mjx.make(config.run.env))
    return compile_programs(fns, num_seeds, seed_sharding(num_seeds), config.run.seed_axis)


def train(config: Config, seeds=None, programs: Programs | None = None,
          progress: str = "auto") -> list[RunSummary]:
    """Trains (or resumes) every seed until config.run.total_steps; one RunSummary per seed.

    programs: compiled functions to reuse (notebooks, tests); they must come from a config with the same
    compiled settings (run.compiled_settings) and seed count.
    """
    seeds = check_seeds((config.run.seed,) if seeds is None else seeds)
    config = settle_precision(config, seeds)
    if programs is None:
        programs = build_programs(config, len(seeds))
    elif (compiled_settings(programs.fns.config) != compiled_settings(config)
          or programs.num_seeds != len(seeds)):
        raise ConfigError("programs were compiled for another learner config or seed count; "
                          "build them with build_programs(config, len(seeds))")
    configs = seed_configs(config, seeds)
    locks = []
    try:  # one writer per run dir, held for the whole run (run_lock.py)
        for seed_config in configs:
            locks.append(RunDirLock(seed_config.run.resolved_run_dir))
            locks[-1].acquire()
        return _Driver(configs, programs, progress).run()
    except BaseException:
        for lock in locks:
            lock.remove_if_unused()  # a refused start leaves no empty run dir behind
        raise
    finally:
        for lock in locks:
            lock.release()


class _Driver:
    """The host cadence of one group of seeds (module docstring)."""

    def __init__(self, configs: list[Config], programs: Programs, progress: str):
        self.configs, self.programs = configs, programs
        self.settings = configs[0].run  # the host settings every seed shares
        self.seeds = tuple(config.run.seed for config in configs)
        self.run_dirs = [config.run.resolved_run_dir for config in configs]
        self.config_dicts = [config_to_dict(config) for config in configs]
        self.progress = progress
        self.last_save = time.monotonic()
        self.changes: list[dict] = []  # per seed: resumable settings changed since the last start
        self.loggers: list[RunLogger] = []

    def run(self) -> list[RunSummary]:
        state, steps, checkpointers, resumed = self.start()
        resume_step = steps if resumed else None
        self.loggers = loggers = [
            RunLogger(run_dir, config_dict, self.settings.total_steps, resume_step=resume_step,
                      progress=self.progress if index == 0 else "off",  # one progress line a group
                      changes=changes)
            for index, (run_dir, config_dict, changes) in enumerate(zip(
                self.run_dirs, self.config_dicts, self.changes, strict=True))]
        stop, last = _StopFlag(), [{} for _ in self.seeds]
        try:
            if not resumed:
                state, steps = self.warm_start(state, loggers[0])
                self.maybe_checkpoint(checkpointers, state, 0, steps)
            while steps < self.settings.total_steps and not stop.requested:
                previous, (state, metrics) = steps, self.chunk(state, loggers[0])
                steps += self.programs.fns.chunk_len
                records = self.after_chunk(loggers, checkpointers, state, metrics, previous, steps)
                last = [record or before for record, before in zip(records, last, strict=True)]
            self.save(checkpointers, state, steps)
        finally:
            stop.restore()
            for item in (*loggers, *checkpointers):
                item.close()
        return [RunSummary(steps, stop.requested, record, run_dir)
                for record, run_dir in zip(last, self.run_dirs, strict=True)]

    def start(self):
        """(state, env_steps, checkpointers, resumed) for fresh or resumed run dirs."""
        checkpointers, self.changes = [], []
        for run_dir, config_dict in zip(self.run_dirs, self.config_dicts, strict=True):
            self.changes.append(check_run_dir_config(run_dir, config_dict, RESUMABLE_KEYS))
            checkpointers.append(RunCheckpointer(run_dir, config_dict, self.settings.checkpoint_every,
                                                 self.settings.keep_checkpoints,
                                                 ignore_config_keys=RESUMABLE_KEYS))
        fresh = self.programs.init(jnp.stack([jax.random.PRNGKey(seed) for seed in self.seeds]))
        templates = [seed_slice(fresh, index) for index in range(len(self.seeds))]
        restored = restore_group(checkpointers, templates)
        if restored is None:
            return fresh, 0, checkpointers, False
        states, steps = restored
        where = f"{self.run_dirs[0]}/checkpoints/{steps}" + (f" and {len(self.seeds) - 1} more seeds"
                                                            if len(self.seeds) > 1 else "")
        changed = "".join(f"; {key}: {old} -> {new}" for key, (old, new) in self.changes[0].items())
        print(f"resuming from step {steps} (checkpoint {where}){changed}", flush=True)
        return stack_seeds(states, self.programs.sharding), steps, checkpointers, True

    def warm_start(self, state: RunState, logger: RunLogger) -> tuple[RunState, int]:
        """Prefill with random actions, then PEG's pretraining updates (fresh runs only)."""
        with logger.timer("prefill"):
            state = jax.block_until_ready(self.programs.prefill(state))
        if self.programs.train_updates is None:  # model-free agents: collect trains
            return state, self.settings.prefill
        for _ in range(math.ceil(self.settings.pretrain / self.programs.fns.updates_per_chunk)):
            state, _ = self.programs.train_updates(state)
        return state, self.settings.prefill

    def chunk(self, state: RunState, logger: RunLogger):
        with logger.timer("collect"):
            state, collect_metrics = jax.block_until_ready(self.programs.collect(state))
        if self.programs.train_updates is None or self.programs.fns.update_cadence == "interleaved":
            return state, collect_metrics  # the collect chunk trained too (model-free; interleaved updates)
        with logger.timer("train"):
            state, train_metrics = jax.block_until_ready(self.programs.train_updates(state))
        return state, {**collect_metrics, **train_metrics}

    def after_chunk(self, loggers, checkpointers, state, metrics, previous: int, steps: int) -> list[dict]:
        """Logs, evaluates and checkpoints when `steps` crosses the configured multiples; the records."""
        crossed = lambda every: steps // every > previous // every  # noqa: E731
        records = [{} for _ in self.seeds]
        if crossed(self.settings.log_every):
            values, timing = jax.device_get(metrics), loggers[0].timing_metrics()
            for index, logger in enumerate(loggers):
                record = {**seed_slice(values, index), **timing}
                record.update({key: int(record[key]) for key in ("train/updates", "replay/size")})
                if self.programs.train_updates is not None:  # the model-based learners drop non-finite ones
                    record[DROPPED_SHARE] = 1 - record["train/updates"] / self.attempted_updates(steps)
                records[index] = logger.log(steps, record)
        if crossed(self.settings.eval_every):
            eval_metrics, _ = self.programs.evaluate(state.agent, eval_keys(self.seeds, steps))
            views = jax.device_get(self.programs.visitation(state.replay))
            eval_metrics = jax.device_get(eval_metrics)
            for index, logger in enumerate(loggers):
                records[index].update(logger.log(steps, seed_slice(eval_metrics, index)))
                records[index].update(logger.log_visitation(steps, seed_slice(views, index)))
                self.save_back_starts(logger, seed_slice(state.back_starts, index), steps)
        self.maybe_checkpoint(checkpointers, state, previous, steps)
        return records

    def attempted_updates(self, steps: int) -> int:
        """Updates tried by env step `steps` (pretraining, then a chunk's worth per chunk); the agent state's
        `updates` counts the kept ones, as keep_if_finite reverts it with a dropped update."""
        per_chunk = self.programs.fns.updates_per_chunk
        pretrain = math.ceil(self.settings.pretrain / per_chunk) * per_chunk
        return max(pretrain + (steps - self.settings.prefill) // self.programs.fns.chunk_len * per_chunk, 1)

    @staticmethod
    def save_back_starts(logger: RunLogger, starts, steps: int) -> None:
        """plots/back_starts.npz once a back chunk has succeeded (agents with Back-and-Forth Go-Explore)."""
        xy, stream_step = stored_back_starts(starts)
        if len(stream_step):
            logger.log_back_starts(steps, xy, stream_step)

    def maybe_checkpoint(self, checkpointers, state, previous: int, steps: int) -> None:
        """At multiples of checkpoint_every, or when checkpoint_minutes have passed since the last save."""
        every = self.settings.checkpoint_every
        due_by_time = time.monotonic() - self.last_save >= 60 * self.settings.checkpoint_minutes
        if steps // every > previous // every or due_by_time:
            self.save(checkpointers, state, steps)

    def save(self, checkpointers, state, steps: int) -> None:
        """Every seed's own state into its own run dir, all at the same step, after every log is on disk."""
        for logger in self.loggers:
            logger.flush()
        for index, checkpointer in enumerate(checkpointers):
            checkpointer.save(steps, seed_slice(state, index), {"env_steps": steps}, force=True)
        self.last_save = time.monotonic()


def restore_group(checkpointers, templates):
    """(per-seed states, step) at the newest step every seed has a good checkpoint of; None when no seed
    has one. A kill between the seeds' saves of one step leaves some seeds a step ahead: they resume from
    their previous checkpoint of the common step."""
    found = [_latest(checkpointer, template)
             for checkpointer, template in zip(checkpointers, templates, strict=True)]
    if all(restored is None for restored in found):
        return None
    if any(restored is None for restored in found):
        missing = [str(c.run_dir) for c, r in zip(checkpointers, found, strict=True) if r is None]
        raise CheckpointError(f"seeds of this group have checkpoints but {', '.join(missing)} has none; "
                              "resume with the seeds that have them or use new run dirs")
    common = min(restored.step for restored in found)
    states = []
    for checkpointer, template, restored in zip(checkpointers, templates, found, strict=True):
        if restored.step != common:
            restored = checkpointer.restore_step(common, template)
        states.append(restored.state)
    return states, common  # checkpoints are saved at step == env_steps


def _latest(checkpointer: RunCheckpointer, template):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        restored = checkpointer.latest_valid(template)
    for warning in caught:
        print(f"warning: {warning.message}", file=sys.stderr)
    return restored


class _StopFlag:
    """Ctrl-C (SIGINT) or SIGTERM: finish the current chunk, save a checkpoint, stop. A second Ctrl-C
    interrupts at once (the last periodic checkpoint is still there)."""

    def __init__(self):
        self.requested = False
        self._previous = {}
        for signum in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(ValueError):  # not the main thread: no signal handling
                self._previous[signum] = signal.signal(signum, self._handle)

    def _handle(self, signum, frame):
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True
        print("\nstopping after this chunk (a checkpoint will be saved; Ctrl-C again to quit now)",
              file=sys.stderr, flush=True)

    def restore(self):
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def restore_run(run_dir) -> tuple[RunFns, RunState, int]:
    """(run functions, the newest good checkpoint's state, its step) of one run dir (any seed of a group),
    read-only (safe beside a live run). The config comes from the run dir's config.json."""
    path = pathlib.Path(run_dir) / "config.json"
    if not path.exists():
        raise ConfigError(f"{run_dir} is not a run dir (no config.json)")
    config = config_from_dict(Config, json.loads(path.read_text()))
    config = dataclasses.replace(config, run=dataclasses.replace(config.run, run_dir=str(run_dir)))
    fns = make_run_fns(config, envs_mjx.make(config.run.env))
    template = jax.jit(fns.init, compiler_options=compiler_options(fns))(jax.random.PRNGKey(config.run.seed))
    restored = latest_valid(run_dir, template, config_to_dict(config),
                            ignore_config_keys=RESUMABLE_KEYS)
    if restored is None:
        raise CheckpointError(f"no checkpoint in {pathlib.Path(run_dir) / 'checkpoints'} yet")
    return fns, restored.state, restored.step
