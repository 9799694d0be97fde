"""The run functions of the model-free agents' stream, with the same RunFns contract as the world-model
agents (morefree_jax.run), so driver.train, the programs over seeds, checkpoints, evaluation, logs and plots
serve both. Each agent brings its learner (oracle_sac/, r3l/, medal/; ibc/ extends the stream).

    fns = make_stream_fns(config, env, learner)  # learner: OracleSAC, R3L or MEDAL (their agent.py)
    state = fns.prefill(fns.init(key))           # the seed phase: no updates (acting: agent's choice)
    state, metrics = fns.collect(state)          # one fused chunk: act, one SAC update, env step, store

`collect` is the whole training step: each of its `config.baseline.chunk_len` env steps, inside one
`lax.scan`, picks the action, runs the acting agent's SAC update (UTD 1), steps the env and writes the
transition into the device replay (MEDAL's order), with no host round trip. There is no separate train call
(`train_updates` is None). The stream is episodic for oracle_sac and reset-free (hard resets only) for
r3l and medal (baselines/r3l/agent.py, baselines/medal/agent.py).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.back_starts import BackStarts, init_back_starts
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.baselines.sac.buffer import Stored, TransitionBuffer, init_buffer, insert_where
from morefree_jax.batching import lazy_cond
from morefree_jax.evaluate import evaluate_policy, evaluation_metrics, visitation, visited_rows
from morefree_jax.run import RunFns

FORWARD, BACKWARD = 0, 1  # who acts: the forward (task) agent or the backward one
SEED_STEPS = 10_000  # the seed phase (MEDAL's num_seed_frames): run.prefill of oracle_sac, r3l and medal


def sac_batch(stored, reward) -> sac.SACBatch:
    """A SAC batch of stored transitions: the inputs are observation ++ goal."""
    return sac.SACBatch(obs=jnp.concatenate([stored.obs, stored.goal], -1), action=stored.action,
                        reward=reward, next_obs=jnp.concatenate([stored.next_obs, stored.goal], -1),
                        not_done=stored.not_done)


def act_by_direction(config, forward: sac.SACState, backward: sac.SACState, direction, obs_goal, key):
    """The acting agent's sampled action (both actors' parameters selected by `direction`, one forward
    pass)."""
    params = jax.tree.map(lambda f, b: jnp.where(direction == FORWARD, f, b),
                          forward.actor.params, backward.actor.params)
    return sac.act(config, params, obs_goal, key)



@struct.dataclass
class ModelFreeStream:
    """The env stream: the current goal, the task goal (the forward goal; MEDAL keeps it across backward
    segments), who acts (FORWARD / BACKWARD), steps into the episode or segment, and the stream position
    (drives the hard resets)."""

    env_state: Any
    goal: jax.Array
    task_goal: jax.Array
    direction: jax.Array
    segment_step: jax.Array
    steps: jax.Array


@struct.dataclass
class ModelFreeRunState:
    """Everything a model-free run needs to continue exactly. replay: one buffer per direction.
    back_starts: always empty (no agent here has a back phase); kept so the driver reads every run alike."""

    agent: Any
    replay: tuple[TransitionBuffer, ...]
    stream: ModelFreeStream
    key: jax.Array
    back_starts: BackStarts


@dataclasses.dataclass(frozen=True)
class ForwardPolicy:
    """The forward SAC policy behind the agent interface evaluate_policy uses (deterministic: tanh of the
    Gaussian mean, as MEDAL evaluates; no latent)."""

    learner: Any

    def goal_context(self, agent_state, goals):
        return goals

    def initial_latent(self, shape=()):
        return jnp.zeros((*shape, 1))

    def act(self, agent_state, latent, prev_action, obs, goal, key, mode):
        params = self.learner.forward_sac(agent_state).actor.params
        obs_goal = jnp.concatenate([obs, goal], -1)
        return sac.act(self.learner.config.sac, params, obs_goal, key, deterministic=True), latent


def make_stream_fns(config, env, learner) -> RunFns:
    """RunFns (morefree_jax.run) of a model-free agent whose learner steers this stream."""
    parts = StreamParts(config, env, learner)
    return RunFns(parts.init, parts.prefill, parts.collect, None, parts.evaluate, parts.visitation, env,
                  ForwardPolicy(parts.learner), config.baseline.chunk_len, config.baseline.chunk_len, config)


class _Pending(NamedTuple):
    """The previous env step's transition, stored at the start of the next step (StreamParts.step)."""

    transition: Stored
    direction: jax.Array  # the buffer it goes to
    valid: jax.Array  # False at the start of a chunk: the last chunk stored its own


def _store(buffers: tuple[TransitionBuffer, ...], pending: _Pending) -> tuple[TransitionBuffer, ...]:
    return tuple(insert_where(buffer, pending.transition, pending.valid & (pending.direction == index))
                 for index, buffer in enumerate(buffers))


@dataclasses.dataclass(frozen=True)
class StreamParts:
    """The stream's static pieces; its methods are the pure functions RunFns hands out (ibc/segments.py
    extends them with IBC's segments)."""

    config: Any
    env: Any
    learner: Any

    @property
    def hard_reset_every(self) -> int:
        return self.config.run.hard_reset_every or self.env.hard_reset_every

    def init(self, key) -> ModelFreeRunState:
        key_agent, key_reset, key_goal, key_run = jax.random.split(key, 4)
        size, capacity = self.env.observation_size, self.config.baseline.replay_capacity
        goal = self.env.eval_goals(key_goal)
        stream = ModelFreeStream(env_state=self.env.reset(key_reset), goal=goal, task_goal=goal,
                                 direction=jnp.asarray(FORWARD, jnp.int32),
                                 segment_step=jnp.zeros((), jnp.int32), steps=jnp.zeros((), jnp.int32))
        buffers = tuple(init_buffer(capacity, size, self.env.action_size)
                        for _ in range(self.learner.num_buffers))
        buffers = self.learner.fill_buffers(buffers, jax.random.fold_in(key, 1))  # MEDAL: demonstrations
        return ModelFreeRunState(agent=self.learner.init(key_agent), replay=buffers, stream=stream,
                                 key=key_run, back_starts=init_back_starts())

    def prefill(self, state: ModelFreeRunState) -> ModelFreeRunState:
        return self.run_steps(state, self.config.run.prefill, learn=False)[0]

    def collect(self, state: ModelFreeRunState):
        state, records = self.run_steps(state, self.config.baseline.chunk_len, learn=True)
        return state, self.chunk_metrics(state, records)

    def run_steps(self, state: ModelFreeRunState, length: int, learn: bool):
        key, key_steps = jax.random.split(state.key)
        step = lambda carry, k: self.step(carry, k, learn)  # noqa: E731
        nothing = _Pending(self.empty_transition(), state.stream.direction, jnp.zeros((), bool))
        (agent, replay, stream, pending), records = jax.lax.scan(
            step, (state.agent, state.replay, state.stream, nothing), jax.random.split(key_steps, length))
        replay = _store(replay, pending)  # the chunk's last transition: a checkpoint holds the whole stream
        return state.replace(agent=agent, replay=replay, stream=stream, key=key), records

    def empty_transition(self) -> Stored:
        """A transition of zeros: what a chunk's first step has pending (nothing; `valid` is False)."""
        obs, actions = jnp.zeros(self.env.observation_size), jnp.zeros(self.env.action_size)
        return Stored(obs, obs, actions, jnp.zeros(()), obs, jnp.zeros(()))

    def step(self, carry, key, learn: bool):
        """One env step of the stream (module docstring); `learn` False is the seed phase.

        MEDAL's order (oracle.py, medal.py): draw the action, update on the replay as it stands, step the
        env, store the transition. The store is carried to the start of the next step (`_Pending`): the
        update and the env step then share no buffer, so XLA does not copy the whole replay to run them
        side by side, as it did with the store in the same step (docs/baselines.md, "Order within a step").
        An agent's first update therefore needs a filled replay: the seed phase (run.prefill) or MEDAL's
        demonstrations provide it, as MEDAL's seed frames do."""
        agent, buffers, stream, pending = carry
        buffers = _store(buffers, pending)
        key_act, key_update, key_next = jax.random.split(key, 3)
        obs, goal = stream.env_state.obs, stream.goal
        if learn or self.learner.acts_in_seed_phase:
            action = self.learner.act(agent, stream.direction, jnp.concatenate([obs, goal]), key_act)
        else:
            action = jax.random.uniform(key_act, (self.env.action_size,), minval=-1.0, maxval=1.0)
        metrics = {}
        if learn:
            agent, metrics = self.learner.update(agent, buffers, stream.direction, stream.steps, key_update)
        env_state = self.env.step(stream.env_state, action)
        success = self.env.success(env_state.obs, goal) & (stream.direction == FORWARD)
        # A learner without the task's success (R3L) ends segments on the time limit alone; the success is
        # then only counted (stream/successes) and evaluated, never acted on.
        acted_on = success if self.learner.ends_on_success else jnp.zeros((), bool)
        end, reset = self.segment_end(stream, acted_on)
        stored = Stored(obs, goal, action, success.astype(jnp.float32), env_state.obs, 1.0 - end)
        agent = self.learner.observe(agent, env_state.obs)
        record = {"success": success, "end": end, "direction": stream.direction, **metrics}
        pending = _Pending(stored, stream.direction, jnp.ones((), bool))
        return (agent, buffers, self.next_segment(stream, env_state, end, reset, key_next), pending), record

    def segment_end(self, stream: ModelFreeStream, success):
        """(the episode or segment ends on this step, the env resets after it)."""
        steps_in = stream.segment_step + 1
        if self.learner.episodic:
            end = success | (steps_in >= self.env.eval_episode_length)
            return end, end
        hard_reset = (stream.steps + 1) % self.hard_reset_every == 0
        return success | (steps_in >= self.config.baseline.switch_every) | hard_reset, hard_reset

    def next_segment(self, stream: ModelFreeStream, env_state, end, reset, key) -> ModelFreeStream:
        """After an end: the other direction (forward after a reset), with a fresh goal of its kind."""
        key_reset, key_eval, key_backward = jax.random.split(key, 3)
        env_state = lazy_cond(reset, lambda: self.env.reset(key_reset), lambda: env_state)
        flipped = jnp.where(reset | self.learner.episodic, FORWARD, 1 - stream.direction)
        direction = jnp.where(end, flipped, stream.direction).astype(jnp.int32)
        redraw = (reset | end) if not self.learner.keeps_task_goal else reset
        task_goal = jnp.where(redraw, self.env.eval_goals(key_eval), stream.task_goal)
        fresh_goal = jnp.where(direction == FORWARD, task_goal, self.learner.backward_goal(key_backward))
        return ModelFreeStream(env_state=env_state, goal=jnp.where(end, fresh_goal, stream.goal),
                               task_goal=task_goal, direction=direction,
                               segment_step=jnp.where(end, 0, stream.segment_step + 1),
                               steps=stream.steps + 1)

    def chunk_metrics(self, state: ModelFreeRunState, records: dict) -> dict:
        forward = (records.pop("direction") == FORWARD).astype(jnp.float32)
        metrics = {"stream/successes": jnp.sum(records.pop("success").astype(jnp.float32)),
                   "stream/segments": jnp.sum(records.pop("end").astype(jnp.float32)),
                   "stream/forward_share": jnp.mean(forward)}
        masks = {"forward": forward, "backward": 1.0 - forward}
        for name, values in records.items():
            if name.startswith("sac/") and self.learner.num_buffers == 1:
                metrics[name] = jnp.mean(values)
            elif name.startswith("sac/"):
                for direction, mask in masks.items():  # each agent's updates only
                    metrics[f"{direction}/{name[4:]}"] = jnp.sum(values * mask) / jnp.maximum(mask.sum(), 1)
            elif name == "r3l/rnd_loss":
                metrics[name] = jnp.sum(values) / jnp.maximum(masks["backward"].sum(), 1)
            else:  # a classifier's loss: updated every n steps, zeros between
                every = self.learner.periodic_metrics[name]
                metrics[name] = jnp.sum(values) / jnp.maximum(jnp.ceil(len(values) / every), 1)
        updates = [getattr(state.agent, part).updates for part in ("forward", "backward")
                   if hasattr(state.agent, part)] or [state.agent.updates]
        metrics["train/updates"] = sum(updates).astype(jnp.float32)
        metrics["replay/size"] = sum(buffer.count for buffer in state.replay).astype(jnp.float32)
        return metrics

    def evaluate(self, agent_state, key):
        result = evaluate_policy(self.env, ForwardPolicy(self.learner), agent_state, key,
                                 self.config.run.eval_episodes)
        return evaluation_metrics(result), result

    def visitation(self, replay: tuple[TransitionBuffer, ...]):
        """Over all buffers, the stream's own transitions (no demonstrations): evaluate.visitation's shares
        weighted by each buffer's visited rows, its histograms summed."""
        bins = self.config.run.visitation_bins
        buffers = list(zip(replay, self.learner.demo_rows, strict=True))
        parts = [visitation(self.env, buffer, bins, skip) for buffer, skip in buffers]
        sizes = [jnp.sum(visited_rows(buffer, skip)).astype(jnp.float32) for buffer, skip in buffers]
        total = jnp.maximum(sum(sizes), 1.0)

        def combined(values):
            if values[0].ndim == 0:  # a share of the rows: each buffer weighs by its visited rows
                return sum(value * size for value, size in zip(values, sizes, strict=True)) / total
            return sum(values)  # a histogram of counts

        return {name: combined([part[name] for part in parts]) for name in parts[0]}

