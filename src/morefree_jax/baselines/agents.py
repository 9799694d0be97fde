"""The model-free agents' learners and how each one's stream is steered: Oracle SAC and R3L (MEDAL: medal.py).

    agent = make_model_free_agent("r3l", config.baseline, env)
    state = agent.init(key)                                     # learner state (SAC nets, rewards)
    state, metrics = agent.update(state, buffers, direction, step, key)   # one UTD-1 step of the actor

Both are goal-conditioned SAC learners (baselines/sac.py) whose input is observation ++ goal.

oracle_sac (baselines.md section 2: MEDAL's oracle.py) trains on the evaluation task episodically: each
episode starts from the initial-state distribution with an evaluation goal and lasts the evaluation
episode length or until success; the reward is the task's sparse success in {0, 1}. MEDAL marks the last
step of every episode LAST and its SAC drops the bootstrap there (not_done = 0), timeouts included; we do
the same. It is the only agent that gets resets.

r3l (section 5: MoReFree's R3L, built on MEDAL's FBRL): one reset-free stream; a forward SAC towards an
evaluation goal rewarded by a VICE-style classifier of goal examples against the forward policy's states
(no env reward), and a backward SAC with an initial state in its goal slot rewarded by RND novelty.
Control switches every `switch_every` steps or when the forward policy reaches its goal; the switch step is
stored with not_done = 0. Each env step updates only the acting agent (MEDAL); the classifier learns every
`classifier.train_every` steps, the RND predictor on every backward step. Choices where MoReFree is silent:
the classifier sees the observation alone (a goal example carries its goal in itself), with fresh draws
of the evaluation-goal distribution as its goal examples; the backward goal slot holds a random initial
state (FBRL's backward goal), which RND's reward ignores.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.baselines import rewards, sac
from morefree_jax.baselines.buffer import TransitionBuffer, sample
from morefree_jax.baselines.config import ModelFreeConfig
from morefree_jax.batching import lazy_cond

FORWARD, BACKWARD = 0, 1


@struct.dataclass
class R3LState:
    forward: sac.SACState
    backward: sac.SACState
    classifier: Any  # NetState
    rnd: rewards.RNDState


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


@dataclasses.dataclass(frozen=True)
class OracleSAC:
    """Episodic SAC on the sparse task reward (module docstring)."""

    config: ModelFreeConfig
    env: Any
    episodic = True
    num_buffers = 1
    keeps_task_goal = False  # every episode draws its goal
    acts_in_seed_phase = False  # MEDAL's oracle.py: uniform random actions
    periodic_metrics = {}  # metrics logged every n steps: none
    demo_rows = (0,)  # leading rows per buffer that hold demonstrations

    def fill_buffers(self, buffers, key):
        # No demonstrations. baselines.md section 2 says MEDAL's oracle.py loads the forward demos when a
        # task has them; the paper says only MEDAL uses demonstrations ("MEDAL also uses demonstrations
        # and Oracle uses resets"), and the paper wins.
        return buffers

    def backward_goal(self, key):  # never acts backward (episodic); the stream asks for one regardless
        return self.env.initial_states(key)

    def init(self, key):
        return sac.init(self.config.sac, 2 * self.env.observation_size, self.env.action_size, key)

    def forward_sac(self, state) -> sac.SACState:
        return state

    def act(self, state, direction, obs_goal, key):
        return sac.act(self.config.sac, state.actor.params, obs_goal, key)

    def observe(self, state, obs):
        return state

    def update(self, state, buffers: tuple[TransitionBuffer, ...], direction, step, key):
        key_sample, key_update = jax.random.split(key)
        stored = sample(buffers[0], key_sample, self.config.sac.batch_size)
        return sac.update(self.config.sac, state, sac_batch(stored, stored.reward), key_update)


@dataclasses.dataclass(frozen=True)
class R3L:
    """Forward SAC on a goal classifier, backward SAC on RND novelty, reset-free (module docstring)."""

    config: ModelFreeConfig
    env: Any
    episodic = False
    num_buffers = 2
    keeps_task_goal = False  # FBRL: a fresh goal each forward segment
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


def make_model_free_agent(name: str, config: ModelFreeConfig, env):
    from morefree_jax.baselines import demos, medal  # here: medal builds on this module

    agents = {"oracle_sac": OracleSAC, "r3l": R3L,
              "medal": lambda config, env: medal.MEDAL(config, env, demos.load_demos(env.name, env))}
    if name not in agents:
        raise ValueError(f"unknown model-free agent {name!r}; valid: {', '.join(agents)}")
    return agents[name](config, env)
