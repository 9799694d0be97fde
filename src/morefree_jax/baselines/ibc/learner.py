"""IBC's learners (docs/baselines.md, "Learner" and "Hindsight relabelling" under "IBC"): a forward and a
backward goal-conditioned SAC, each on its own hindsight replay, updated once per env step only while acting.

    learner = IBCLearner(config.baseline.ibc, env, ibc_task(env))
    state = learner.init(key)
    action = learner.act(state, direction, obs, goal, key)
    state, metrics = learner.update(state, buffers, direction, key)
    v = learner.forward_value(state, obs, goal, key)          # the curriculum's V (mean of 10 actions)

Goals are full observation vectors (goal space = observation space) but each agent sees only its part:
the network input is obs ++ goal * mask, the forward mask on ibc_tasks.forward_goal_dims (IBC's desired
goal: the whole goal state in the EARL tasks, env.goal_dims elsewhere), the backward mask on
ibc_tasks.backward_goal_dims (the whole goal state in the EARL tasks, the proprioceptive dims elsewhere;
IBC's backward_proprioceptive_only makes only its success test proprioceptive there). Both inputs have
one width, so one network shape serves both agents and acting selects parameters, not networks. Forward
success is the task's test; backward success is |proprio(obs) - proprio(goal)| < the task's backward
threshold. Rewards are success - 1 ({-1, 0}), recomputed at sampling (baselines/ibc/her.py). Each update draws
half a batch for the forward agent and a whole one for the backward agent (batch_size).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from morefree_jax.baselines.baseline_config import IBCConfig
from morefree_jax.baselines.ibc.her import SegmentBuffer, sample_her
from morefree_jax.baselines.ibc.tasks import IBCTask, backward_goal_dims, forward_goal_dims, proprio_reached
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.baselines.sac.stream import ForwardPolicy
from morefree_jax.batching import lazy_cond

FORWARD, BACKWARD = 0, 1


@struct.dataclass
class IBCState:
    forward: sac.SACState
    backward: sac.SACState


def dims_mask(size: int, dims) -> jax.Array:
    return jnp.asarray(np.isin(np.arange(size), np.asarray(dims)), jnp.float32)


@dataclasses.dataclass(frozen=True)
class IBCLearner:
    config: IBCConfig
    env: Any
    task: IBCTask
    demo_rows = (0, 0)  # no demonstrations

    @property
    def masks(self) -> tuple[jax.Array, jax.Array]:
        size = self.env.observation_size
        return (dims_mask(size, forward_goal_dims(self.task, self.env)),
                dims_mask(size, backward_goal_dims(self.task, self.env)))

    def init(self, key) -> IBCState:
        key_forward, key_backward = jax.random.split(key)
        size, actions = 2 * self.env.observation_size, self.env.action_size
        return IBCState(forward=sac.init(self.config.sac, size, actions, key_forward),
                        backward=sac.init(self.config.sac, size, actions, key_backward))

    def success(self, direction: int):
        """The direction's success test (obs, goal) -> bool."""
        if direction == FORWARD:
            return self.env.success
        return lambda obs, goal: proprio_reached(self.task, obs, goal)

    def policy_input(self, direction, obs, goal) -> jax.Array:
        forward_mask, backward_mask = self.masks
        return jnp.concatenate([obs, goal * jnp.where(direction == FORWARD, forward_mask, backward_mask)], -1)

    def act(self, state: IBCState, direction, obs, goal, key, deterministic: bool = False):
        params = jax.tree.map(lambda f, b: jnp.where(direction == FORWARD, f, b),
                              state.forward.actor.params, state.backward.actor.params)
        return sac.act(self.config.sac, params, self.policy_input(direction, obs, goal), key, deterministic)

    def batch_size(self, direction: int) -> int:
        """Transitions per update of the direction's agent. IBC's ForwardBackwardReplayBufferWrapper.sample
        hands the forward agent int(rl_batch_size / 2) and the backward agent all of it
        (docs/baselines.md, "Learner" under "IBC", batch row)."""
        full = self.config.sac.batch_size
        return full // 2 if direction == FORWARD else full

    def update(self, state: IBCState, buffers: tuple[SegmentBuffer, SegmentBuffer], direction, key):
        """The acting agent's SAC step on a HER batch of its own replay, if that replay holds an ended
        segment -> (state, metrics, updated?)."""
        key_sample, key_update = jax.random.split(key)

        def step_of(index: int):
            def step():
                batch = sample_her(buffers[index], key_sample, self.batch_size(index),
                                   self.config.her_relabel, self.success(index), self.masks[index])
                agent = state.forward if index == FORWARD else state.backward
                agent, metrics = sac.update(self.config.sac, agent, batch, key_update)
                name = "forward" if index == FORWARD else "backward"
                return state.replace(**{name: agent}), metrics
            return step

        def learn():
            return lazy_cond(direction == FORWARD, step_of(FORWARD), step_of(BACKWARD))

        _, metric_shapes = jax.eval_shape(step_of(FORWARD))
        skip = lambda: (state, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), metric_shapes))  # noqa: E731
        ready = jnp.where(direction == FORWARD, buffers[FORWARD].sampleable, buffers[BACKWARD].sampleable)
        state, metrics = lazy_cond(ready, learn, skip)
        return state, metrics, ready

    def forward_value(self, state: IBCState, obs, goal, key) -> jax.Array:
        """(N,) for obs, goal (N, O): the forward critic's min(Q1, Q2) averaged over value_samples
        actions of the forward policy (HGG's value estimate)."""
        inputs = self.policy_input(FORWARD, obs, goal)
        cfg = self.config.sac

        def one(key_one):
            action = sac.act(cfg, state.forward.actor.params, inputs, key_one)
            return jnp.minimum(*sac.q_values(cfg, state.forward.critic.params, inputs, action))

        return jnp.mean(jax.vmap(one)(jax.random.split(key, self.config.value_samples)), axis=0)


@dataclasses.dataclass(frozen=True)
class IBCForwardPolicy(ForwardPolicy):
    """The forward agent for evaluate_policy: deterministic tanh(mean), goal masked as in training."""

    def act(self, agent_state, latent, prev_action, obs, goal, key, mode):
        return self.learner.act(agent_state, FORWARD, obs, goal, key, deterministic=True), latent
