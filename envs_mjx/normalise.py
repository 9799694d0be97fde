"""Min-max normalised observations: PEG's `NormObsWrapper` for a reset-free task.

    env = NormalisedObservations(envs_mjx.make("push"))   # obs, goals, initial states in [0, 1] units
    env.reset(rng).obs                                    # (obs - low) / (high - low), bounds of the task
    env.success(obs, goal)                                # the task's test, on the de-normalised vectors

PEG trains its 3-block-stacking agent on observations min-max normalised by fixed bounds (docs/tasks.md,
"Observations and the world-model agents"), so that task's planner spread (`std_scale` 0.5) is half the
normalised range, and the world model's reconstruction weighs every dimension by its range. Tasks that take
that config (the Fetch tasks) turn it on with `agent.normalise_observations`; the run functions then wrap
their env in this class, and every vector the world-model agent sees (stream, replay, goals, goal search) is
normalised, while everything measured in the task's units (success, distances, task relevance, visitation
views) is computed on the de-normalised vectors. The physics state (`pipeline_state`) is untouched, so
rendering is unchanged.
"""

from __future__ import annotations

import jax
import numpy as np
from brax.envs.base import State, Wrapper


def in_task_units(env, vectors: jax.Array) -> jax.Array:
    """Observation or goal vectors of `env` in the task's own units (de-normalised if env normalises)."""
    return env.denormalise(vectors) if isinstance(env, NormalisedObservations) else vectors


class NormalisedObservations(Wrapper):
    """A reset-free task whose observations are (obs - low) / (high - low) over its observation_bounds."""

    def __init__(self, env):
        super().__init__(env)
        low, high = (np.asarray(bound, np.float32) for bound in env.observation_bounds)
        if not np.all(high > low):
            raise ValueError(f"cannot normalise {type(env).__name__}: observation_bounds need high > low in "
                             f"every dimension, got width {high - low}")
        self._low, self._width = low, high - low

    def normalise(self, obs: jax.Array) -> jax.Array:
        return (obs - self._low) / self._width

    def denormalise(self, obs: jax.Array) -> jax.Array:
        return obs * self._width + self._low

    def _normalised_state(self, state: State) -> State:
        return state.replace(obs=self.normalise(state.obs))

    def _task_state(self, state: State) -> State:
        return state.replace(obs=self.denormalise(state.obs))

    # ---- brax Env contract ----
    def reset(self, rng: jax.Array) -> State:
        return self._normalised_state(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        # The inner task steps its own state (its obs is recomputed from the physics), so give it back the
        # task-unit observation it produced rather than trusting obs to be unused.
        return self._normalised_state(self.env.step(self._task_state(state), action))

    # ---- reset-free extension: vectors in, through the task's units ----
    def eval_goals(self, rng: jax.Array) -> jax.Array:
        return self.normalise(self.env.eval_goals(rng))

    def initial_states(self, rng: jax.Array) -> jax.Array:
        return self.normalise(self.env.initial_states(rng))

    def evaluation_goals(self, rng: jax.Array, num_episodes: int) -> jax.Array:
        return self.normalise(self.env.evaluation_goals(rng, num_episodes))

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros_like(self._low), np.ones_like(self._low)

    def goal_distance(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        return self.env.goal_distance(self.denormalise(obs), self.denormalise(goal))

    def success(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        return self.env.success(self.denormalise(obs), self.denormalise(goal))

    def reward(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        return self.env.reward(self.denormalise(obs), self.denormalise(goal))

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        return self.env.task_relevant(self.denormalise(obs))

    def xy(self, obs: jax.Array) -> jax.Array:
        return self.env.xy(self.denormalise(obs))

    def side_view(self, obs: jax.Array) -> jax.Array:
        return self.env.side_view(self.denormalise(obs))
