"""MEDAL (docs/baselines.md, "MEDAL"; MEDAL's `medal.py`, `cfgs/medal.yaml`, `MEDALBackwardAgent`).

    AGENT.make_run_fns(config, env)     # registry entry "medal": loads the task's demonstrations
    agent = MEDAL(config.baseline, env, load_demos(env.name, env)); state = agent.init(key)

Two goal-conditioned SAC learners (baselines/sac/learner.py, MEDAL's settings) in one reset-free stream. The
forward agent pursues the task goal on the env's sparse reward; the backward agent is rewarded by a
discriminator D of demonstration states against the states it visits, r = -log(1 - sigmoid(D(s')) + eps),
so it learns to return to where the demonstrations go. D is an MLP of 128 on the full input (observation
++ goal slot), BCE with mixup, 400 demonstration states + 400 backward states per batch, one Adam step
every 10 env steps after the seed phase. Control switches every `switch_every` steps or on forward
success (the switch is stored with not_done = 0); after a hard reset the forward agent acts.

Goals as MEDAL sets them: the forward goal is the task goal drawn at each reset and kept across backward
segments (MEDAL does not change it when control returns); the backward goal slot holds a fresh draw of
the goal distribution (EARL's `sample_goal_state`), which the discriminator sees but the demonstrations'
states decide. The seed phase acts with the (untrained) policies, not uniformly (medal.yaml).

Demonstrations (baselines/medal/demos.py): the forward buffer starts with the forward demonstrations and their
0/1 rewards; the backward buffer with the forward and the reverse ones, their goal slot relabelled with
a draw of the goal distribution each (MEDAL relabels reverse demonstrations with each of EARL's finitely
many goal states; our tasks' goal distributions are continuous). D's positives are the forward
demonstrations' states; its negatives are drawn from the backward buffer past the demonstrations.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.baselines.baseline_config import ModelFreeConfig
from morefree_jax.baselines.medal.demos import load_demos
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.baselines.sac import rewards
from morefree_jax.baselines.sac.buffer import Stored, TransitionBuffer, sample, sample_from, write_rows
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
class MEDALState:
    forward: sac.SACState
    backward: sac.SACState
    discriminator: Any  # NetState


@dataclasses.dataclass(frozen=True, eq=False)  # eq=False: hashed by identity (it holds numpy arrays)
class MEDAL:
    """Forward SAC on the sparse reward, backward SAC on a demonstration discriminator (module docstring).
    demos: {"forward": DemoSet, optionally "reverse": DemoSet} (baselines/medal/demos.py)."""

    config: ModelFreeConfig
    env: Any
    demos: dict
    episodic = False
    num_buffers = 2
    keeps_task_goal = True
    ends_on_success = True  # MEDAL sees the env reward, the task's success
    acts_in_seed_phase = True

    @property
    def periodic_metrics(self) -> dict[str, int]:
        return {"medal/discriminator_loss": self.config.discriminator.train_every}

    def init(self, key):
        keys = jax.random.split(key, 3)
        size, cfg = self.env.observation_size, self.config
        return MEDALState(forward=sac.init(cfg.sac, 2 * size, self.env.action_size, keys[0]),
                          backward=sac.init(cfg.sac, 2 * size, self.env.action_size, keys[1]),
                          discriminator=rewards.init_classifier(cfg.discriminator, 2 * size, keys[2]))

    def forward_sac(self, state: MEDALState) -> sac.SACState:
        return state.forward

    def act(self, state: MEDALState, direction, obs_goal, key):
        return act_by_direction(self.config.sac, state.forward, state.backward, direction, obs_goal, key)

    def observe(self, state, obs):
        return state

    def backward_goal(self, key):
        return self.env.eval_goals(key)

    @property
    def demo_rows(self) -> tuple[int, int]:
        """Leading rows of the forward and backward buffers that fill_buffers wrote demonstrations into."""
        return len(self.demos["forward"].actions), self.backward_demo_count

    @property
    def backward_demo_count(self) -> int:
        return sum(len(demo.actions) for demo in self.demos.values())

    def fill_buffers(self, buffers: tuple[TransitionBuffer, ...], key) -> tuple[TransitionBuffer, ...]:
        """The demonstrations written into the empty buffers (module docstring)."""
        forward_demos = _stored(self.demos["forward"])
        backward_demos = _concat([_stored(demo) for demo in self.demos.values()])
        relabel = jax.vmap(self.env.eval_goals)(jax.random.split(key, len(backward_demos.action)))
        backward_demos = backward_demos._replace(goal=relabel)
        return write_rows(buffers[FORWARD], forward_demos), write_rows(buffers[BACKWARD], backward_demos)

    def update(self, state: MEDALState, buffers, direction, step, key):
        """The acting agent's SAC step (the other's metrics are zeros); D every train_every steps."""
        cfg, keys = self.config, jax.random.split(key, 5)
        forward_stored = sample(buffers[FORWARD], keys[0], cfg.sac.batch_size)
        backward_stored = sample(buffers[BACKWARD], keys[1], cfg.sac.batch_size)

        def forward_step():
            batch = sac_batch(forward_stored, forward_stored.reward)
            agent, metrics = sac.update(cfg.sac, state.forward, batch, keys[2])
            return state.replace(forward=agent), metrics

        def backward_step():
            next_input = jnp.concatenate([backward_stored.next_obs, backward_stored.goal], -1)
            reward = rewards.classifier_reward(cfg.discriminator, state.discriminator, next_input)
            agent, metrics = sac.update(cfg.sac, state.backward, sac_batch(backward_stored, reward), keys[3])
            return state.replace(backward=agent), metrics

        new_state, metrics = lazy_cond(direction == FORWARD, forward_step, backward_step)
        new_state, loss = lazy_cond(
            step % cfg.discriminator.train_every == 0,
            lambda: self.update_discriminator(new_state, buffers[BACKWARD], keys[4]),
            lambda: (new_state, jnp.zeros(())))
        return new_state, {**metrics, "medal/discriminator_loss": loss}

    def update_discriminator(self, state: MEDALState, backward: TransitionBuffer, key):
        half = self.config.discriminator.batch // 2
        key_positive, key_negative, key_mix = jax.random.split(key, 3)
        demos = self.demos["forward"]
        positives = jnp.concatenate([demos.observations, demos.goals], -1)
        positives = positives[jax.random.randint(key_positive, (half,), 0, len(positives))]
        visited = sample_from(backward, key_negative, half, start=self.backward_demo_count)
        negatives = jnp.concatenate([visited.obs, visited.goal], -1)
        discriminator, loss = rewards.update_classifier(self.config.discriminator, state.discriminator,
                                                        positives, negatives, key_mix)
        return state.replace(discriminator=discriminator), loss


def _stored(demo) -> Stored:
    return Stored(obs=demo.observations, goal=demo.goals, action=demo.actions, reward=demo.rewards,
                  next_obs=demo.next_observations, not_done=1.0 - demo.terminals)


def _concat(parts: list[Stored]) -> Stored:
    return Stored(*(jnp.concatenate(fields, 0) for fields in zip(*parts, strict=True)))


def make_medal_fns(config, env):
    return make_stream_fns(config, env, MEDAL(config.baseline, env, load_demos(env.name, env)))


AGENT = AgentEntry("medal", "MEDAL: forward SAC on the sparse reward, backward SAC back to demonstration "
                   "states (demos)", ("baseline.sac", "baseline.discriminator", "baseline.switch_every"),
                   make_medal_fns, prefill=SEED_STEPS)
