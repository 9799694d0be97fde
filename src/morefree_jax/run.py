"""The pure functions of a training run: `make_run_fns(config, env) -> RunFns`, and the contract
(RunFns, AgentEntry) that every agent of the registry (registry.py) implements.

    env = envs_mjx.make("point_umaze")            # any ResetFreeEnv (a notebook may bring its own)
    fns = make_run_fns(config, env)                # config from config.resolve_config
    state = fns.prefill(fns.init(key))             # RunState: agent, replay, stream, planner, schedule, key
    state, metrics = fns.collect(state)            # one chunk of the stream (goal choice incl. PEG's search),
                                                   # with an update every train_every steps (interleaved)
    state, metrics = fns.train_updates(state)      # a chunk's worth of updates in one lax.scan: the
                                                   # pretraining, and the updates under update_cadence=chunk
    metrics, result = fns.evaluate(state.agent, key)
    views = fns.visitation(state.replay)           # evaluate.visitation: task-relevant share, heatmaps

Nothing is jitted and nothing reads host state: every function works unbatched and under `jax.vmap` over
seeds (driver.py jits them vmapped over a seed axis, in the style of purejaxrl's make_train). Everything
random comes from keys inside RunState, so a run resumes exactly from a saved RunState.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from envs_mjx.normalise import NormalisedObservations
from morefree_jax import replay as replay_lib
from morefree_jax.agent import Agent, AgentState, EnvSpec, make_agent
from morefree_jax.back_starts import BackStarts, init_back_starts, record_back_start
from morefree_jax.collect import (
    StreamState,
    advance_steps,
    chunk_metrics,
    collect_chunk,
    collect_config_for,
    init_stream,
    prefill_stream,
    start_chunk,
)
from morefree_jax.config_tree import ConfigError
from morefree_jax.evaluate import evaluate_policy, evaluation_metrics, visitation
from morefree_jax.goal_schedule import GOAL_TYPE_NAMES, GoalType, ScheduleState, init_schedule
from morefree_jax.imagination import GoalPools
from morefree_jax.planner import PlannerState, start_search
from morefree_jax.precision import resolve_precision
from morefree_jax.variants import variant

GOAL_POOL_SIZE = 64  # evaluation goals / initial states sampled per chunk for the imagination goal mix

# Run settings the pure functions read (with config.agent, config.planner and config.schedule). The others
# (seed, run dir, step budget, cadence of logs, evaluations and checkpoints) only steer the host driver, so
# compiled functions can be reused across them (driver.train(..., programs=...)).
COMPILED_RUN_KEYS = ("env", "agent", "prefill", "train_every", "eval_episodes", "hard_reset_every",
                     "subgoal_threshold", "visitation_bins", "codegen", "update_cadence")


@struct.dataclass
class RunState:
    """Everything a run needs to continue exactly. go_counts (2, 3): chunks and go phases that reached
    their goal (task success), per goal type (planner, eval, initial). back_starts: where the successful
    back chunks started (back_starts.py; analysis only, nothing reads it back)."""

    agent: AgentState
    replay: replay_lib.ReplayState
    stream: StreamState
    planner: PlannerState
    schedule: ScheduleState
    go_counts: jax.Array
    key: jax.Array
    back_starts: BackStarts


class RunFns(NamedTuple):
    """The pure functions of a run (module docstring) and the static facts the host driver needs."""

    init: Callable  # key -> RunState
    prefill: Callable  # RunState -> RunState
    collect: Callable  # RunState -> (RunState, metrics)
    train_updates: Callable | None  # RunState -> (RunState, metrics); None: collect also trains
    evaluate: Callable  # (AgentState, key) -> (metrics, EvalResult)
    visitation: Callable  # ReplayState -> {"task_relevant", "xy", ...} (evaluate.visitation)
    env: Any
    agent: Agent
    chunk_len: int
    updates_per_chunk: int
    config: Any  # config.Config; the functions read compiled_settings(config) of it
    # "interleaved": collect also runs the chunk's updates, one per train_every env steps (train_updates
    # then serves the pretraining only); "chunk": train_updates runs them after collect (config.RunConfig).
    update_cadence: str = "chunk"


class AgentEntry(NamedTuple):
    """One agent of the registry (registry.py): what `agent=<name>` runs.

    config_sections: the parts of config.Config its learner reads (documentation and `make train` help).
    make_run_fns: (config, env) -> RunFns. prefill: the run.prefill it sets (a model-free agent's seed
    phase); None keeps the task's. configure: (config, name) -> config, the agent's own settings (a
    world-model variant's schedule and imagination goals); None sets nothing."""

    name: str
    description: str
    config_sections: tuple[str, ...]
    make_run_fns: Callable
    prefill: int | None = None
    configure: Callable | None = None


def compiled_settings(config) -> tuple:
    """The parts of `config` the run functions depend on; equal settings give identical functions."""
    run = config.run
    agent = dataclasses.replace(config.agent, precision=resolve_precision(config.agent.precision))
    return (agent, config.planner, config.schedule, config.baseline,
            *(getattr(run, key) for key in COMPILED_RUN_KEYS))


def keep_if_finite(new_state, old_state):
    """(new_state if every array in it is finite else old_state, finite?). A non-finite update (seen
    rarely in the exploration actor's gradient with the cpu preset) is dropped instead of poisoning every
    later update and, through the policy, the stream and the replay."""
    leaf_finite = jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(new_state)
                             if jnp.issubdtype(x.dtype, jnp.inexact)])
    # all() as the flag at argmin (False wherever one is): XLA turns jnp.all of stacked scalars into a chain
    # of ands and copies that chain into every leaf's select (leaves^2 ops, which made the train program's
    # compile several times longer, seed vmap included: docs/performance.md, "Compile time"); an argmin stays
    # one reduction.
    finite = leaf_finite[jnp.argmin(leaf_finite)]
    return jax.tree.map(lambda new, old: jnp.where(finite, new, old), new_state, old_state), finite


def check_run_config(config, env) -> None:
    """One-line ConfigErrors before anything compiles."""
    run = config.run
    run.require_task_defaults()
    if run.prefill < config.agent.replay.length:
        raise ConfigError(f"run.prefill ({run.prefill}) must be >= replay.length "
                          f"({config.agent.replay.length}) so that training has a sequence to sample")
    # Fail now, not after compiling, if the replay does not fit (clear message from init_replay).
    replay_lib.init_replay(config.agent.replay, env.observation_size, env.action_size)


def make_run_fns(config, env, agent: Agent | None = None) -> RunFns:
    """The run's pure functions of a world-model agent (registry.py: every variant of variants.py) for
    `env`; agent: built from config.agent unless given. Other agents' factories: their registry entries."""
    if config.agent.normalise_observations:
        env = NormalisedObservations(env)
    check_run_config(config, env)
    agent = agent or make_agent(config.agent, EnvSpec.from_env(env))
    run = config.run
    collect_cfg = collect_config_for(env, config.schedule, variant(run.agent).explore, run.subgoal_threshold,
                                     run.hard_reset_every)
    updates = max(1, round(collect_cfg.chunk_len / run.train_every))
    interleaved = run.update_cadence == "interleaved"
    if interleaved and collect_cfg.chunk_len % run.train_every:
        raise ConfigError(f"run.train_every ({run.train_every}) must divide the chunk of "
                          f"{collect_cfg.chunk_len} steps under update_cadence=interleaved; choose a divisor "
                          "or update_cadence=chunk")
    parts = _Parts(config, env, agent, collect_cfg, updates)
    return RunFns(parts.init, parts.prefill, parts.collect_and_train if interleaved else parts.collect,
                  parts.train_updates, parts.evaluate, parts.visitation, env, agent, collect_cfg.chunk_len,
                  updates, config, run.update_cadence)


@dataclasses.dataclass(frozen=True)
class _Parts:
    """The run's static pieces; its methods are the pure functions RunFns hands out."""

    config: Any  # config.Config
    env: Any
    agent: Agent
    collect_cfg: Any
    updates_per_chunk: int

    def init(self, key) -> RunState:
        key_agent, key_stream, key_run = jax.random.split(key, 3)
        goal_size = self.env.observation_size
        return RunState(
            agent=self.agent.init(key_agent),
            replay=replay_lib.init_replay(self.config.agent.replay, goal_size, self.env.action_size),
            stream=init_stream(self.env, self.agent, key_stream),
            planner=start_search(self.config.planner, jnp.zeros(goal_size)),
            schedule=init_schedule(goal_size),
            go_counts=jnp.zeros((2, 3), jnp.float32),
            key=key_run,
            back_starts=init_back_starts(),
        )

    def prefill(self, state: RunState) -> RunState:
        key, key_prefill = jax.random.split(state.key)
        stream, transitions = prefill_stream(self.env, self.agent, self.collect_cfg, state.stream,
                                             key_prefill, self.config.run.prefill)
        return state.replace(stream=stream, replay=replay_lib.add(state.replay, *transitions), key=key)

    def collect(self, state: RunState):
        key, key_chunk = jax.random.split(state.key)
        stream, schedule, planner, transitions, metrics = collect_chunk(
            self.env, self.agent, self.collect_cfg, self.config.planner, self.config.schedule, state.agent,
            state.stream, state.schedule, state.planner, key_chunk, self.goal_bounds(state.replay))
        go_counts, successful_back = self.go_summary(state, metrics, planner)
        back_starts = record_back_start(state.back_starts, self.env, state.replay, successful_back)
        state = state.replace(replay=replay_lib.add(state.replay, *transitions), stream=stream,
                              schedule=schedule, planner=planner, go_counts=go_counts, key=key,
                              back_starts=back_starts)
        return state, metrics

    def collect_and_train(self, state: RunState):
        """The interleaved cadence: one chunk whose env steps run in blocks of train_every, each followed by
        one update on a batch drawn from the replay as it then stands (the block included), so every step
        acts, and ends its go phase, with the policies and distance of all updates before it."""
        key, key_goal, key_steps, key_updates, key_eval, key_initial = jax.random.split(state.key, 6)
        stream, schedule, planner, metrics = start_chunk(
            self.env, self.agent, self.collect_cfg, self.config.planner, self.config.schedule, state.agent,
            state.stream, state.schedule, state.planner, key_goal, self.goal_bounds(state.replay))
        pools = self.goal_pools(key_eval, key_initial)
        num, replay_cfg = self.updates_per_chunk, self.config.agent.replay
        step_keys = jax.random.split(key_steps, self.collect_cfg.chunk_len)
        step_keys = step_keys.reshape(num, -1, *step_keys.shape[1:])  # (updates, train_every, key)

        def block(carry, keys):
            agent_state, stream, replay = carry
            block_keys, key_batch, key_update = keys
            stream, transitions, records = advance_steps(self.env, self.agent, self.collect_cfg, agent_state,
                                                         stream, block_keys)
            replay = replay_lib.add(replay, *transitions)
            batch = replay_lib.sample_windows(replay, key_batch, replay_cfg.batch, replay_cfg.length)
            new_state, update_metrics = self.agent.train_step(agent_state, batch, pools, key_update)
            new_state, finite = keep_if_finite(new_state, agent_state)
            return (new_state, stream, replay), (records, update_metrics, finite)

        update_keys = jax.random.split(key_updates, 2 * num).reshape(2, num, -1)
        (agent_state, stream, replay), (records, update_metrics, finite) = jax.lax.scan(
            block, (state.agent, stream, state.replay), (step_keys, *update_keys))
        metrics.update(chunk_metrics(jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), records)))
        go_counts, successful_back = self.go_summary(state, metrics, planner)
        # The 100 locations before the chunk are still in the buffer, just before the chunk's steps.
        before = replay.replace(count=replay.count - self.collect_cfg.chunk_len)
        back_starts = record_back_start(state.back_starts, self.env, before, successful_back)
        metrics.update(self.update_means(update_metrics, finite, agent_state, replay))
        return state.replace(agent=agent_state, replay=replay, stream=stream, schedule=schedule,
                             planner=planner, go_counts=go_counts, key=key, back_starts=back_starts), metrics

    def goal_bounds(self, replay):
        """The goal search's box: the task's bounds within the visited states' range (candidates inside
        states the stream has been in)."""
        task_box = tuple(jnp.asarray(b, jnp.float32) for b in self.env.observation_bounds)
        return replay_lib.visited_range(replay, *task_box)

    def go_summary(self, state: RunState, metrics: dict, planner):
        """(go_counts, successful back chunk?) after a chunk; adds the reach rates and the search count to
        `metrics`."""
        goal_type = jax.nn.one_hot(metrics["goal/type"], 3)
        go_counts = state.go_counts + jnp.stack([goal_type, goal_type * metrics["go/reached"]])
        rates = go_counts[1] / jnp.maximum(go_counts[0], 1.0)
        metrics.update({f"go/reach_rate_{name}": rates[i] for i, name in enumerate(GOAL_TYPE_NAMES)})
        metrics["planner/searches"] = planner.searches.astype(jnp.float32)
        return go_counts, (metrics["goal/type"] == GoalType.INITIAL) & (metrics["go/reached"] > 0)

    def goal_pools(self, key_eval, key_initial) -> GoalPools:
        return GoalPools(jax.vmap(self.env.eval_goals)(jax.random.split(key_eval, GOAL_POOL_SIZE)),
                         jax.vmap(self.env.initial_states)(jax.random.split(key_initial, GOAL_POOL_SIZE)))

    def train_updates(self, state: RunState):
        key, key_pools_eval, key_pools_initial, key_updates = jax.random.split(state.key, 4)
        pools = self.goal_pools(key_pools_eval, key_pools_initial)
        key_batches, key_steps = jax.random.split(key_updates)
        # The replay does not change during the chunk's updates: draw all n batches with one pass over the
        # buffer's valid windows (O(capacity)) instead of one pass per update.
        num, replay_cfg = self.updates_per_chunk, self.config.agent.replay
        batches = replay_lib.sample(state.replay, key_batches, num * replay_cfg.batch, replay_cfg.length)
        batches = jax.tree.map(lambda x: x.reshape(num, replay_cfg.batch, *x.shape[1:]), batches)

        def update(agent_state, inputs):
            batch, key_step = inputs
            new_state, metrics = self.agent.train_step(agent_state, batch, pools, key_step)
            new_state, finite = keep_if_finite(new_state, agent_state)
            return new_state, (metrics, finite)

        agent_state, (metrics, finite) = jax.lax.scan(update, state.agent,
                                                      (batches, jax.random.split(key_steps, num)))
        return state.replace(agent=agent_state, key=key), self.update_means(metrics, finite, agent_state,
                                                                             state.replay)

    @staticmethod
    def update_means(metrics: dict, finite, agent_state: AgentState, replay) -> dict:
        """The updates' metrics averaged over the kept ones, with the dropped count and the totals."""
        kept = jnp.maximum(jnp.sum(finite), 1)
        means = {name: jnp.sum(jnp.where(finite, value, 0.0)) / kept for name, value in metrics.items()}
        means["train/skipped_nonfinite"] = jnp.sum(~finite).astype(jnp.float32)
        means["train/updates"] = agent_state.updates.astype(jnp.float32)
        means["replay/size"] = replay.count.astype(jnp.float32)
        return means

    def evaluate(self, agent_state: AgentState, key):
        result = evaluate_policy(self.env, self.agent, agent_state, key, self.config.run.eval_episodes)
        return evaluation_metrics(result), result

    def visitation(self, replay):
        return visitation(self.env, replay, self.config.run.visitation_bins)
