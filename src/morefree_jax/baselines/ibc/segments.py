"""The ibc agent's run functions (RunFns contract, morefree_jax.run): IBC's reset-free stream of
forward and backward segments (docs/baselines.md, "Segments") with its learners (learner.py), hindsight replay
(her.py) and curriculum (curriculum.py), all in one fused scan per chunk.

    fns = make_ibc_fns(config, env)
    state = fns.prefill(fns.init(key))      # IBC's seed steps: run.prefill = 800, the first 400 random
    state, metrics = fns.collect(state)     # chunk_len env steps, one update of the acting agent each

Each step: act (uniform random during the first `random_steps` of the stream), step the env, write the
transition into the acting direction's replay, extend the forward trace, update the acting agent once.
A segment ends on its direction's success or after the task's segment length (or at a hard reset, the
only env reset). Then, IBC's no_backward_if_forward_succeed: a successful forward segment is followed by
a new forward goal; a failed one by one backward segment; a backward segment by forward. Both goals come
from the curriculum, each from its own uniform draw of a slot (IBC's train.py).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.back_starts import BackStarts, init_back_starts
from morefree_jax.baselines.ibc.curriculum import Curriculum, CurriculumState
from morefree_jax.baselines.ibc.her import SegmentBuffer, end_segment_where, init_segment_buffer, insert_where
from morefree_jax.baselines.ibc.learner import BACKWARD, FORWARD, IBCForwardPolicy, IBCLearner
from morefree_jax.baselines.ibc.tasks import ibc_task
from morefree_jax.baselines.sac.stream import ModelFreeStream as IBCStream
from morefree_jax.baselines.sac.stream import StreamParts
from morefree_jax.batching import lazy_cond
from morefree_jax.evaluate import evaluate_policy, evaluation_metrics
from morefree_jax.run import AgentEntry, RunFns


@struct.dataclass
class IBCRunState:
    """Everything an ibc run needs to continue exactly (the curriculum included). back_starts: always
    empty, kept so the driver reads every run alike."""

    agent: Any
    replay: tuple[SegmentBuffer, SegmentBuffer]
    stream: IBCStream
    curriculum: CurriculumState
    key: jax.Array
    back_starts: BackStarts


def make_ibc_fns(config, env) -> RunFns:
    """RunFns of the ibc agent."""
    cfg = config.baseline.ibc
    task = ibc_task(env, cfg.segment_length)
    if cfg.pool_size < cfg.slots:  # checked here, not per key: the CLI sets keys one at a time
        raise ValueError(f"baseline.ibc.pool_size ({cfg.pool_size}) must be >= baseline.ibc.slots "
                         f"({cfg.slots}): each slot is matched to its own pool trajectory")
    learner = IBCLearner(cfg, env, task)
    parts = IBCParts(config, env, learner, Curriculum(env, task, cfg, cfg.sac.discount))
    return RunFns(parts.init, parts.prefill, parts.collect, None, parts.evaluate, parts.visitation, env,
                  IBCForwardPolicy(learner), config.baseline.chunk_len, config.baseline.chunk_len, config)


@dataclasses.dataclass(frozen=True)
class IBCParts(StreamParts):
    """The model-free run parts (prefill, collect, visitation, hard_reset_every) with IBC's stream."""

    curriculum: Any = None

    def init(self, key) -> IBCRunState:
        key_agent, key_reset, key_curriculum, key_goal, key_run = jax.random.split(key, 5)
        capacity, size = self.config.baseline.replay_capacity, self.env.observation_size
        curriculum = self.curriculum.init(key_curriculum)
        env_state = self.env.reset(key_reset)
        goal = self.curriculum.forward_goal(curriculum, env_state.obs, key_goal)
        stream = IBCStream(env_state=env_state, goal=goal, task_goal=goal,
                           direction=jnp.asarray(FORWARD, jnp.int32),
                           segment_step=jnp.zeros((), jnp.int32), steps=jnp.zeros((), jnp.int32))
        buffers = tuple(init_segment_buffer(capacity, size, self.env.action_size) for _ in range(2))
        return IBCRunState(agent=self.learner.init(key_agent), replay=buffers, stream=stream,
                           curriculum=curriculum, key=key_run,
                           back_starts=init_back_starts())

    def run_steps(self, state: IBCRunState, length: int, learn: bool):
        key, key_steps = jax.random.split(state.key)
        step = lambda carry, k: self.step(carry, k, learn)  # noqa: E731
        carry = (state.agent, state.replay, state.stream, state.curriculum)
        carry, records = jax.lax.scan(step, carry, jax.random.split(key_steps, length))
        agent, replay, stream, curriculum = carry
        state = state.replace(agent=agent, replay=replay, stream=stream, curriculum=curriculum, key=key)
        return state, records

    def step(self, carry, key, learn: bool):
        """One env step of the stream (module docstring); `learn` False is the seed phase."""
        agent, buffers, stream, curriculum = carry
        key_act, key_random, key_update, key_match, key_next = jax.random.split(key, 5)
        obs, goal, forward = stream.env_state.obs, stream.goal, stream.direction == FORWARD
        random_action = jax.random.uniform(key_random, (self.env.action_size,), minval=-1.0, maxval=1.0)
        action = jnp.where(stream.steps < self.config.baseline.ibc.random_steps, random_action,
                           self.learner.act(agent, stream.direction, obs, goal, key_act))
        env_state = self.env.step(stream.env_state, action)
        next_obs = env_state.obs
        success = jnp.where(forward, self.learner.success(FORWARD)(next_obs, goal),
                            self.learner.success(BACKWARD)(next_obs, goal))
        end, reset = self.segment_end(stream, success)
        acting = [stream.direction == d for d in (FORWARD, BACKWARD)]
        buffers = tuple(end_segment_where(insert_where(buffer, obs, goal, action, next_obs, mine), end & mine)
                        for buffer, mine in zip(buffers, acting, strict=True))
        curriculum = self.extend_trace(curriculum, stream, obs, next_obs, end, agent, key_match)
        metrics, updated = {}, jnp.zeros((), bool)
        if learn:
            agent, metrics, updated = self.learner.update(agent, buffers, stream.direction, key_update)
        record = {"success": success, "end": end, "direction": stream.direction, "updated": updated,
                  **metrics}
        stream = self.next_segment(stream, curriculum, env_state, success, end, reset, key_next)
        return (agent, buffers, stream, curriculum), record

    def segment_end(self, stream: IBCStream, success):
        """(the segment ends on this step, the env hard-resets after it)."""
        hard_reset = (stream.steps + 1) % self.hard_reset_every == 0
        full = stream.segment_step + 1 >= self.curriculum.task.segment_length
        return success | full | hard_reset, hard_reset

    def extend_trace(self, curriculum, stream: IBCStream, obs, next_obs, end, agent, key):
        """Forward steps extend the curriculum's trace; a forward segment's end hands it to the pool."""
        forward = stream.direction == FORWARD
        recorded = self.curriculum.record(curriculum, obs, next_obs, stream.segment_step)
        curriculum = jax.tree.map(lambda new, old: jnp.where(forward, new, old), recorded, curriculum)
        value_fn = lambda o, g, k: self.learner.forward_value(agent, o, g, k)  # noqa: E731
        length = stream.segment_step + 1
        ended = lambda: self.curriculum.end_forward(curriculum, length, value_fn, key)  # noqa: E731
        return lazy_cond(forward & end, ended, lambda: curriculum)

    def next_segment(self, stream: IBCStream, curriculum, env_state, success, end, reset, key) -> IBCStream:
        """After an end: forward again after a successful forward segment, a backward segment, or a hard
        reset; backward after a failed forward segment; a fresh goal of the new direction's kind."""
        key_reset, key_forward, key_backward = jax.random.split(key, 3)
        env_state = lazy_cond(reset, lambda: self.env.reset(key_reset), lambda: env_state)
        failed_forward = (stream.direction == FORWARD) & ~success & ~reset
        after_end = jnp.where(failed_forward, BACKWARD, FORWARD)
        direction = jnp.where(end, after_end, stream.direction).astype(jnp.int32)
        forward_goal = self.curriculum.forward_goal(curriculum, env_state.obs, key_forward)
        backward_goal = self.curriculum.backward_goal(curriculum, env_state.obs, key_backward)
        fresh_goal = jnp.where(direction == FORWARD, forward_goal, backward_goal)
        new_forward = end & (direction == FORWARD)
        return IBCStream(env_state=env_state, goal=jnp.where(end, fresh_goal, stream.goal),
                         task_goal=jnp.where(new_forward, forward_goal, stream.task_goal),
                         direction=direction, segment_step=jnp.where(end, 0, stream.segment_step + 1),
                         steps=stream.steps + 1)

    def chunk_metrics(self, state: IBCRunState, records: dict) -> dict:
        forward = (records.pop("direction") == FORWARD).astype(jnp.float32)
        success, end = records.pop("success").astype(jnp.float32), records.pop("end").astype(jnp.float32)
        updated = records.pop("updated").astype(jnp.float32)
        metrics = {"stream/successes": jnp.sum(success * forward),
                   "stream/backward_successes": jnp.sum(success * (1.0 - forward)),
                   "stream/segments": jnp.sum(end), "stream/forward_segments": jnp.sum(end * forward),
                   "stream/forward_share": jnp.mean(forward)}
        for direction, mask in {"forward": forward * updated, "backward": (1.0 - forward) * updated}.items():
            for name, values in records.items():  # each agent's own updates only
                metrics[f"{direction}/{name[4:]}"] = jnp.sum(values * mask) / jnp.maximum(mask.sum(), 1)
        agent, curriculum = state.agent, state.curriculum
        metrics["train/updates"] = (agent.forward.updates + agent.backward.updates).astype(jnp.float32)
        metrics["replay/size"] = sum(buffer.count for buffer in state.replay).astype(jnp.float32)
        metrics["curriculum/pool"] = jnp.minimum(curriculum.pool_count, self.config.baseline.ibc.pool_size
                                                 ).astype(jnp.float32)
        metrics["curriculum/matches"] = curriculum.matches.astype(jnp.float32)
        return metrics

    def evaluate(self, agent_state, key):
        result = evaluate_policy(self.env, IBCForwardPolicy(self.learner), agent_state, key,
                                 self.config.run.eval_episodes)
        return evaluation_metrics(result), result


IBC_SEED_STEPS = 800  # IBC's num_seed_steps (its first random_steps = 400 act at random): run.prefill
AGENT = AgentEntry("ibc", "IBC: forward/backward SAC + HER, backward only after forward failure, "
                   "bidirectional curriculum", ("baseline.ibc",), make_ibc_fns, prefill=IBC_SEED_STEPS)
