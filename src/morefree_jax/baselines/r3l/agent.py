"""R3L: a forward SAC on a learned goal classifier and a backward SAC on RND novelty, reset-free.

    AGENT.make_run_fns(config, env)          # registry entry "r3l"; the stream: sac/stream.py

MoReFree's R3L, built on MEDAL's FBRL (docs/baselines.md, "R3L"): one reset-free stream; a forward SAC
towards an evaluation goal rewarded by a VICE-style classifier of goal examples against the forward
policy's states (no env reward), and a backward SAC with an initial state in its goal slot rewarded by RND
novelty. Control switches every `switch_every` steps; the switch step is stored with not_done = 0. FBRL,
the template, also switches when the forward policy reaches its goal, which R3L cannot see (it has no reward
or success signal): the task's success is only counted and evaluated here (docs/fidelity.md). Each env
step updates only the acting agent (MEDAL); the classifier learns every `classifier.train_every` steps,
the RND predictor on every backward step. Choices where MoReFree is silent: the classifier sees the
observation alone (a goal example carries its goal in itself), with fresh draws of the evaluation-goal
distribution as its goal examples; the backward goal slot holds a random initial state (FBRL's backward
goal), which RND's reward ignores.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.baselines.baseline_config import ModelFreeConfig
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.baselines.sac import rewards
from morefree_jax.baselines.sac.buffer import sample
from morefree_jax.baselines.sac.stream import (
    BACKWARD,
    FORWARD,
    SEED_STEPS,
    act_by_direction,
    make_stream_fns,
    sac_batch,
)
from morefree_jax.batching import lazy_cond
from morefree_jax.run import AgentEntry


@struct.dataclass
class R3LState:
    forward: sac.SACState
    backward: sac.SACState
    classifier: Any  # NetState
    rnd: rewards.RNDState


@dataclasses.dataclass(frozen=True)
class R3L:
    """Forward SAC on a goal classifier, backward SAC on RND novelty, reset-free (module docstring)."""

    config: ModelFreeConfig
    env: Any
    episodic = False
    num_buffers = 2
    keeps_task_goal = False  # FBRL: a fresh goal each forward segment
    ends_on_success = False  # R3L sees no reward or success: its segments end on the time limit
    acts_in_seed_phase = True  # MEDAL's fbrl.py, R3L's template here, acts with its untrained policies
    demo_rows = (0, 0)

    @property
    def periodic_metrics(self) -> dict[str, int]:
        return {"r3l/classifier_loss": self.config.classifier.train_every}

    def fill_buffers(self, buffers, key):
        return buffers

    def init(self, key):
        keys = jax.random.split(key, 4)
        size, cfg = self.env.observation_size, self.config
        return R3LState(forward=sac.init(cfg.sac, 2 * size, self.env.action_size, keys[0]),
                        backward=sac.init(cfg.sac, 2 * size, self.env.action_size, keys[1]),
                        classifier=rewards.init_classifier(cfg.classifier, size, keys[2]),
                        rnd=rewards.init_rnd(cfg.rnd, size, keys[3]))

    def forward_sac(self, state: R3LState) -> sac.SACState:
        return state.forward

    def act(self, state: R3LState, direction, obs_goal, key):
        return act_by_direction(self.config.sac, state.forward, state.backward, direction, obs_goal, key)

    def backward_goal(self, key):
        return self.env.initial_states(key)

    def observe(self, state: R3LState, obs):
        return state.replace(rnd=rewards.observe(state.rnd, obs))

    def update(self, state: R3LState, buffers, direction, step, key):
        """The acting agent's SAC step (the other's metrics are zeros); the classifier every train_every
        steps; the RND predictor on backward steps."""
        cfg, keys = self.config, jax.random.split(key, 6)
        forward_stored = sample(buffers[FORWARD], keys[0], cfg.sac.batch_size)
        backward_stored = sample(buffers[BACKWARD], keys[1], cfg.sac.batch_size)

        def forward_step():
            reward = rewards.classifier_reward(cfg.classifier, state.classifier, forward_stored.next_obs)
            agent, metrics = sac.update(cfg.sac, state.forward, sac_batch(forward_stored, reward), keys[2])
            return state.replace(forward=agent), metrics, jnp.zeros(())

        def backward_step():
            reward = rewards.rnd_reward(cfg.rnd, state.rnd, backward_stored.next_obs)
            agent, metrics = sac.update(cfg.sac, state.backward, sac_batch(backward_stored, reward), keys[3])
            rnd, rnd_loss = rewards.update_rnd(cfg.rnd, state.rnd, backward_stored.next_obs[:cfg.rnd.batch])
            return state.replace(backward=agent, rnd=rnd), metrics, rnd_loss

        new_state, metrics, rnd_loss = lazy_cond(direction == FORWARD, forward_step, backward_step)
        new_state, classifier_loss = lazy_cond(
            step % cfg.classifier.train_every == 0,
            lambda: self.update_classifier(new_state, buffers, keys[4]), lambda: (new_state, jnp.zeros(())))
        return new_state, {**metrics, "r3l/rnd_loss": rnd_loss, "r3l/classifier_loss": classifier_loss}

    def update_classifier(self, state: R3LState, buffers, key):
        half = self.config.classifier.batch // 2
        key_goals, key_visited, key_mix = jax.random.split(key, 3)
        goal_examples = jax.vmap(self.env.eval_goals)(jax.random.split(key_goals, half))
        visited = sample(buffers[FORWARD], key_visited, half).next_obs
        classifier, loss = rewards.update_classifier(self.config.classifier, state.classifier, goal_examples,
                                                     visited, key_mix)
        return state.replace(classifier=classifier), loss


def make_r3l_fns(config, env):
    return make_stream_fns(config, env, R3L(config.baseline, env))


AGENT = AgentEntry("r3l", "R3L: forward SAC on a learned goal classifier, backward RND exploration (no env "
                   "reward)", ("baseline.sac", "baseline.classifier", "baseline.rnd",
                                        "baseline.switch_every"), make_r3l_fns, prefill=SEED_STEPS)
