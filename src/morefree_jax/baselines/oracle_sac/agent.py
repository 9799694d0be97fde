"""Oracle SAC: episodic SAC on the evaluation task with its sparse reward, the only agent with resets.

    AGENT.make_run_fns(config, env)          # registry entry "oracle_sac"; the stream: sac/stream.py

It follows MEDAL's oracle.py (docs/baselines.md, "Oracle SAC"): each episode starts from the
initial-state distribution with an evaluation goal and lasts the evaluation episode length or until
success; the reward is the task's sparse success in {0, 1}. MEDAL marks the last step of every episode LAST
and its SAC drops the bootstrap there (not_done = 0), timeouts included; we do the same. The learner is
goal-conditioned SAC (sac/learner.py) whose input is observation ++ goal.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax

from morefree_jax.baselines.baseline_config import ModelFreeConfig
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.baselines.sac.buffer import TransitionBuffer, sample
from morefree_jax.baselines.sac.stream import SEED_STEPS, make_stream_fns, sac_batch
from morefree_jax.run import AgentEntry


@dataclasses.dataclass(frozen=True)
class OracleSAC:
    """Episodic SAC on the sparse task reward (module docstring)."""

    config: ModelFreeConfig
    env: Any
    episodic = True
    num_buffers = 1
    keeps_task_goal = False  # every episode draws its goal
    ends_on_success = True  # MEDAL's oracle.py: an episode ends on the task's success (its reward)
    acts_in_seed_phase = False  # MEDAL's oracle.py: uniform random actions
    periodic_metrics = {}  # metrics logged every n steps: none
    demo_rows = (0,)  # leading rows per buffer that hold demonstrations

    def fill_buffers(self, buffers, key):
        # No demonstrations. MEDAL's oracle.py loads the forward demos when a task has them
        # (docs/baselines.md, "Oracle SAC"); the paper says only MEDAL uses demonstrations ("MEDAL also uses
        # demonstrations and Oracle uses resets"), and the paper wins.
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


def make_oracle_sac_fns(config, env):
    return make_stream_fns(config, env, OracleSAC(config.baseline, env))


AGENT = AgentEntry("oracle_sac", "Oracle: episodic SAC on the evaluation task, sparse reward (the only agent "
                   "with resets)", ("baseline.sac",), make_oracle_sac_fns, prefill=SEED_STEPS)
