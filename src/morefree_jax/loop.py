"""The training run: prefill, then chunks of collect -> replay -> train, with evaluation, hard resets,
logging and checkpoints of the whole run state; re-running the same config on its run dir resumes it.

    run = prepare_run(config)         # validates, builds env/agent, compiles lazily; errors are one line
    summary = run.train()             # until config.run.total_steps env steps (or Ctrl-C: saves, stops)

Per chunk (design.md section 1) there are two compiled calls: `collect` (goal choice incl. PEG's search
when due, H_G + H_E fused env steps, replay.add) and `train` (chunk_len / train_every updates in one
lax.scan, each on a fresh replay batch). Both take and return the whole RunState with its buffers donated.
Resume is exact: everything random comes from keys inside RunState, and the host only counts steps.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import signal
import sys
import time
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

import envs_mjx
from morefree_jax import replay as replay_lib
from morefree_jax.agent import AgentState, EnvSpec, make_agent
from morefree_jax.checkpoint import RunCheckpointer, check_run_dir_config
from morefree_jax.collect import StreamState, collect_chunk, collect_config_for, init_stream, prefill_stream
from morefree_jax.config_run import RESUMABLE_KEYS, TASK_RUN_KEYS, Config, ConfigError, config_to_dict
from morefree_jax.evaluate import evaluate_policy, evaluation_metrics, visitation
from morefree_jax.go_explore import GOAL_TYPE_NAMES, ScheduleState, init_schedule
from morefree_jax.imagination import GoalPools
from morefree_jax.logger import RunLogger
from morefree_jax.planner import PlannerState, start_search
from morefree_jax.variants import variant

GOAL_POOL_SIZE = 64  # evaluation goals / initial states sampled per chunk for the imagination goal mix


@struct.dataclass
class RunState:
    """Everything a run needs to continue exactly. go_counts (2, 3): chunks and go phases that reached
    their goal (task success), per goal type (planner, eval, initial)."""

    agent: AgentState
    replay: replay_lib.ReplayState
    stream: StreamState
    planner: PlannerState
    schedule: ScheduleState
    go_counts: jax.Array
    key: jax.Array


class RunSummary(NamedTuple):
    env_steps: int
    interrupted: bool
    last_metrics: dict
    run_dir: str


def keep_if_finite(new_state, old_state):
    """(new_state if every array in it is finite else old_state, finite?). A non-finite update (seen
    rarely in the exploration actor's gradient with the cpu preset) is dropped instead of poisoning every
    later update and, through the policy, the stream and the replay."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(new_state)
                                if jnp.issubdtype(x.dtype, jnp.inexact)]))
    return jax.tree.map(lambda new, old: jnp.where(finite, new, old), new_state, old_state), finite


class Run:
    """A prepared run: env, agent and the run's pure functions (jitted on first use)."""

    def __init__(self, config: Config):
        self.config = config
        run = config.run
        unresolved = [key for key in TASK_RUN_KEYS if getattr(run, key) is None]
        if unresolved:
            raise ConfigError(f"run.{', run.'.join(unresolved)} unset: build the config with resolve_config, "
                              "which fills the task's defaults")
        self.env = envs_mjx.make(run.env)
        self.agent = make_agent(config.agent, EnvSpec.from_env(self.env))
        self.collect_cfg = collect_config_for(self.env, config.schedule, variant(run.agent).explore,
                                              run.subgoal_threshold, run.hard_reset_every)
        self.chunk_len = self.collect_cfg.chunk_len
        self.updates_per_chunk = max(1, round(self.chunk_len / run.train_every))
        self.run_dir = run.resolved_run_dir
        self.config_dict = config_to_dict(config)
        if run.prefill < config.agent.replay.length:
            raise ConfigError(f"run.prefill ({run.prefill}) must be >= replay.length "
                              f"({config.agent.replay.length}) so that training has a sequence to sample")
        # Fail now, not after compiling, if the replay does not fit (clear message from init_replay).
        replay_lib.init_replay(config.agent.replay, self.env.observation_size, self.env.action_size)
        self.init = jax.jit(self._init)
        self.prefill = jax.jit(self._prefill, donate_argnums=0)
        self.collect = jax.jit(self._collect, donate_argnums=0)
        self.train_updates = jax.jit(self._train_updates, donate_argnums=0)
        self.evaluate = jax.jit(self._evaluate)
        self.visitation = jax.jit(self._visitation)

    # Run settings that no compiled function reads: a copy of the Run may change them and keep the
    # compiled functions (tests and notebooks run several run dirs / lengths without recompiling).
    HOST_ONLY_KEYS = ("run_dir", "total_steps", "log_every", "eval_every", "checkpoint_every",
                      "keep_checkpoints", "checkpoint_minutes")

    def with_run(self, **changes) -> Run:
        """A Run sharing this one's compiled functions, with host-only run settings changed."""
        unknown = sorted(set(changes) - set(self.HOST_ONLY_KEYS))
        if unknown:
            raise ConfigError(f"with_run can change only {', '.join(self.HOST_ONLY_KEYS)}; got {unknown}")
        twin = copy.copy(self)
        twin.config = dataclasses.replace(self.config, run=dataclasses.replace(self.config.run, **changes))
        twin.run_dir, twin.config_dict = twin.config.run.resolved_run_dir, config_to_dict(twin.config)
        return twin

    # ---- pure functions of the run (jitted in __init__) ------------------------------------------
    def _init(self, key) -> RunState:
        key_agent, key_stream, key_run = jax.random.split(key, 3)
        env, config = self.env, self.config
        goal_size = env.observation_size
        return RunState(
            agent=self.agent.init(key_agent),
            replay=replay_lib.init_replay(config.agent.replay, goal_size, env.action_size),
            stream=init_stream(env, self.agent, key_stream),
            planner=start_search(config.planner, jnp.zeros(goal_size)),
            schedule=init_schedule(goal_size),
            go_counts=jnp.zeros((2, 3), jnp.float32),
            key=key_run,
        )

    def _prefill(self, state: RunState) -> RunState:
        key, key_prefill = jax.random.split(state.key)
        stream, transitions = prefill_stream(self.env, self.agent, self.collect_cfg, state.stream,
                                             key_prefill, self.config.run.prefill)
        replay = replay_lib.add(state.replay, *transitions)
        return state.replace(stream=stream, replay=replay, key=key)

    def _collect(self, state: RunState):
        key, key_chunk = jax.random.split(state.key)
        config = self.config
        task_box = tuple(jnp.asarray(b, jnp.float32) for b in self.env.observation_bounds)
        goal_bounds = replay_lib.visited_range(state.replay, *task_box)  # candidates inside visited states
        stream, schedule, planner, transitions, metrics = collect_chunk(
            self.env, self.agent, self.collect_cfg, config.planner, config.schedule, state.agent,
            state.stream, state.schedule, state.planner, key_chunk, goal_bounds)
        goal_type = jax.nn.one_hot(metrics["goal/type"], 3)
        go_counts = state.go_counts + jnp.stack([goal_type, goal_type * metrics["go/reached"]])
        rates = go_counts[1] / jnp.maximum(go_counts[0], 1.0)
        metrics.update({f"go/reach_rate_{name}": rates[i] for i, name in enumerate(GOAL_TYPE_NAMES)})
        metrics["planner/searches"] = planner.searches.astype(jnp.float32)
        state = state.replace(replay=replay_lib.add(state.replay, *transitions), stream=stream,
                              schedule=schedule, planner=planner, go_counts=go_counts, key=key)
        return state, metrics

    def _train_updates(self, state: RunState):
        key, key_pools_eval, key_pools_initial, key_updates = jax.random.split(state.key, 4)
        env, replay_cfg = self.env, self.config.agent.replay
        pools = GoalPools(jax.vmap(env.eval_goals)(jax.random.split(key_pools_eval, GOAL_POOL_SIZE)),
                          jax.vmap(env.initial_states)(jax.random.split(key_pools_initial, GOAL_POOL_SIZE)))

        # The replay does not change during the chunk's updates: draw all n batches with one pass over the
        # buffer's valid windows (O(capacity)) instead of one pass per update.
        key_batches, key_steps = jax.random.split(key_updates)
        num, size = self.updates_per_chunk, replay_cfg.batch
        batches = replay_lib.sample(state.replay, key_batches, num * size, replay_cfg.length)
        batches = jax.tree.map(lambda x: x.reshape(num, size, *x.shape[1:]), batches)

        def update(agent_state, inputs):
            batch, key_step = inputs
            new_state, metrics = self.agent.train_step(agent_state, batch, pools, key_step)
            new_state, finite = keep_if_finite(new_state, agent_state)
            return new_state, (metrics, finite)

        agent_state, (metrics, finite) = jax.lax.scan(update, state.agent,
                                                      (batches, jax.random.split(key_steps, num)))
        kept = jnp.maximum(jnp.sum(finite), 1)
        means = {name: jnp.sum(jnp.where(finite, value, 0.0)) / kept for name, value in metrics.items()}
        means["train/skipped_nonfinite"] = jnp.sum(~finite).astype(jnp.float32)
        return state.replace(agent=agent_state, key=key), means

    def _evaluate(self, agent_state, key):
        result = evaluate_policy(self.env, self.agent, agent_state, key, self.config.run.eval_episodes)
        return evaluation_metrics(result), result

    def _visitation(self, replay):
        return visitation(self.env, replay, self.config.run.visitation_bins)

    # ---- the host loop ----------------------------------------------------------------------------
    def eval_key(self, step: int) -> jax.Array:
        """Evaluation keys depend on the seed and step only (never on the run's key stream)."""
        return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(self.config.run.seed), 1), step)

    def start(self):
        """(state, env_steps, checkpointer, resumed) for a fresh or resumed run dir."""
        check_run_dir_config(self.run_dir, self.config_dict, RESUMABLE_KEYS)
        checkpointer = RunCheckpointer(self.run_dir, self.config_dict, self.config.run.checkpoint_every,
                                       self.config.run.keep_checkpoints, ignore_config_keys=RESUMABLE_KEYS)
        state = self.init(jax.random.PRNGKey(self.config.run.seed))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            restored = checkpointer.latest_valid(state)
        for warning in caught:
            print(f"warning: {warning.message}", file=sys.stderr)
        if restored is None:
            return state, 0, checkpointer, False
        return restored.state, int(restored.metadata["env_steps"]), checkpointer, True

    def warm_start(self, state: RunState, logger: RunLogger) -> tuple[RunState, int]:
        """Prefill with random actions, then PEG's pretraining updates (fresh runs only)."""
        with logger.timer("prefill"):
            state = jax.block_until_ready(self.prefill(state))
        for _ in range(math.ceil(self.config.run.pretrain / self.updates_per_chunk)):
            state, _ = self.train_updates(state)
        return state, self.config.run.prefill

    def train(self, progress: str = "auto") -> RunSummary:
        state, steps, checkpointer, resumed = self.start()
        self._last_save = time.monotonic()
        run = self.config.run
        logger = RunLogger(self.run_dir, self.config_dict, run.total_steps,
                           resume_step=steps if resumed else None, progress=progress)
        stop = _StopFlag()
        last_metrics: dict = {}
        try:
            if not resumed:
                state, steps = self.warm_start(state, logger)
                self._maybe_checkpoint(checkpointer, state, 0, steps)
            while steps < run.total_steps and not stop.requested:
                previous, (state, metrics) = steps, self._chunk(state, logger)
                steps += self.chunk_len
                last_metrics = self._after_chunk(logger, checkpointer, state, metrics, previous, steps)
            checkpointer.save(steps, state, {"env_steps": steps}, force=True)
        finally:
            stop.restore()
            logger.close()
            checkpointer.close()
        return RunSummary(steps, stop.requested, last_metrics, self.run_dir)

    def _chunk(self, state: RunState, logger: RunLogger):
        with logger.timer("collect"):
            state, collect_metrics = jax.block_until_ready(self.collect(state))
        with logger.timer("train"):
            state, train_metrics = jax.block_until_ready(self.train_updates(state))
        return state, {**collect_metrics, **train_metrics}

    def _after_chunk(self, logger, checkpointer, state, metrics, previous: int, steps: int) -> dict:
        """Logs, evaluates and checkpoints when `steps` crosses the configured multiples."""
        run = self.config.run
        crossed = lambda every: steps // every > previous // every  # noqa: E731
        record = {}
        if crossed(run.log_every):
            values = jax.device_get(metrics)
            values.update({"train/updates": int(state.agent.updates), "replay/size": int(state.replay.count)})
            record = logger.log(steps, {**values, **logger.timing_metrics()})
        if crossed(run.eval_every):
            eval_metrics, _ = self.evaluate(state.agent, self.eval_key(steps))
            record.update(logger.log(steps, jax.device_get(eval_metrics)))
            fraction, histogram = self.visitation(state.replay)
            record.update(logger.log_visitation(steps, float(fraction), jax.device_get(histogram)))
        self._maybe_checkpoint(checkpointer, state, previous, steps)
        return record

    def _maybe_checkpoint(self, checkpointer, state, previous: int, steps: int) -> None:
        """At multiples of checkpoint_every, or when checkpoint_minutes have passed since the last save."""
        every = self.config.run.checkpoint_every
        due_by_time = time.monotonic() - self._last_save >= 60 * self.config.run.checkpoint_minutes
        if steps // every > previous // every or due_by_time:
            checkpointer.save(steps, state, {"env_steps": steps}, force=True)
            self._last_save = time.monotonic()


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


def prepare_run(config: Config) -> Run:
    return Run(config)


def restore_run(run_dir) -> tuple[Run, RunState, int]:
    """(Run, its newest good checkpoint's state, that step) of an existing run dir, read-only (safe beside
    a live run). The config comes from the run dir's config.json."""
    import json
    import pathlib

    from morefree_jax.checkpoint import CheckpointError, latest_valid
    from morefree_jax.config_run import config_from_dict

    path = pathlib.Path(run_dir) / "config.json"
    if not path.exists():
        raise ConfigError(f"{run_dir} is not a run dir (no config.json)")
    config = config_from_dict(Config, json.loads(path.read_text()))
    run = Run(dataclasses.replace(config, run=dataclasses.replace(config.run, run_dir=str(run_dir))))
    template = run.init(jax.random.PRNGKey(config.run.seed))
    restored = latest_valid(run_dir, template, run.config_dict,
                            ignore_config_keys=(*RESUMABLE_KEYS, "run.run_dir"))
    if restored is None:
        raise CheckpointError(f"no checkpoint in {pathlib.Path(run_dir) / 'checkpoints'} yet")
    return run, restored.state, restored.step
