"""The task API contract, checked on every registered task."""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training
from conftest import cached_env

import envs_mjx

INSTANCES, STEPS, EPISODE = 4, 200, 100  # the rollouts cross an episode end of the wrappers


@functools.cache
def wrapped_rollout(env_name: str):
    """(brax-wrapped env, jitted rollout): brax's training wrappers (vmap over INSTANCES, episodes of
    EPISODE, auto-reset) driven by STEPS uniform random actions in one lax.scan, one compile per task.
    rollout(key) -> (first state, final state, observations (STEPS, INSTANCES, O), done (STEPS, INSTANCES)).
    """
    env = training.wrap(cached_env(env_name), episode_length=EPISODE)

    def rollout(key):
        key_reset, key_actions = jax.random.split(key)
        first = env.reset(jax.random.split(key_reset, INSTANCES))
        shape = (STEPS, INSTANCES, env.action_size)
        actions = jax.random.uniform(key_actions, shape, minval=-1.0, maxval=1.0)

        def body(state, action):
            state = env.step(state, action)
            return state, (state.obs, state.done)

        final, (observations, done) = jax.lax.scan(body, first, actions)
        return first, final, observations, done

    return env, jax.jit(rollout)


def test_rollout_through_brax_training_wrappers_is_finite_and_never_terminates(env_name):
    env, rollout = wrapped_rollout(env_name)
    first, final, observations, done = rollout(jax.random.PRNGKey(0))
    assert first.obs.shape == (INSTANCES, env.observation_size)
    assert observations.shape == (STEPS, INSTANCES, env.observation_size)
    assert bool(jnp.all(jnp.isfinite(observations)))
    assert final.reward.shape == final.done.shape == (INSTANCES,)
    # A reset-free task never terminates: done comes only from the wrappers' episode ends.
    ends = np.zeros((STEPS, INSTANCES), np.float32)
    ends[EPISODE - 1 :: EPISODE] = 1.0
    np.testing.assert_array_equal(np.asarray(done), ends)


def test_wrapped_step_returns_the_types_it_was_given(env_name):
    """A jitted step is traced once however the action values change only if the state it returns has
    the shapes, dtypes and weak types it was given (a weakly typed action must not change them)."""
    env, _ = wrapped_rollout(env_name)
    first = jax.eval_shape(env.reset, jax.random.split(jax.random.PRNGKey(0), INSTANCES))
    stepped = jax.eval_shape(env.step, first, jnp.full((INSTANCES, env.action_size), 0.5))
    chex.assert_trees_all_equal_shapes_and_dtypes(stepped, first)
    weak_types = functools.partial(jax.tree.map, lambda leaf: leaf.weak_type)
    assert weak_types(stepped) == weak_types(first)


def test_same_key_same_trajectory_different_keys_differ(env_name):
    _, rollout = wrapped_rollout(env_name)
    obs_a, obs_b = rollout(jax.random.PRNGKey(1))[2], rollout(jax.random.PRNGKey(1))[2]
    np.testing.assert_array_equal(np.asarray(obs_a), np.asarray(obs_b))
    assert not np.array_equal(np.asarray(obs_a), np.asarray(rollout(jax.random.PRNGKey(2))[2]))
    env = cached_env(env_name)
    reset = jax.jit(env.reset)
    first, second = reset(jax.random.PRNGKey(1)), reset(jax.random.PRNGKey(2))
    if np.array_equal(np.asarray(first.obs), np.asarray(second.obs)):
        # Allowed only for a task whose original has one fixed initial state (EARL tabletop): then the
        # initial-state distribution is that point, and the reset key still reaches the state's rng.
        fixed = np.asarray(env.initial_states(jax.random.PRNGKey(1)))
        np.testing.assert_array_equal(fixed, np.asarray(env.initial_states(jax.random.PRNGKey(2))))
        np.testing.assert_array_equal(np.asarray(first.obs), fixed)
        assert not np.array_equal(np.asarray(first.info["rng"]), np.asarray(second.info["rng"]))


def test_reset_free_extension(env_name):
    env = cached_env(env_name)
    key_goal, key_init = jax.random.split(jax.random.PRNGKey(4))
    # compiled: op by op, a Fetch task's goal and initial-state samplers take seconds
    goal = jax.jit(env.eval_goals)(key_goal)
    init = jax.jit(env.initial_states)(key_init)
    assert goal.shape == init.shape == (env.observation_size,)
    assert bool(env.success(goal, goal)) and bool(env.task_relevant(goal)) and bool(env.task_relevant(init))
    assert env.xy(init).shape == (2,)
    assert float(env.reward(goal, goal)) == 0.0
    low, high = env.observation_bounds
    assert low.shape == high.shape == (env.observation_size,) and np.all(low <= high)
    assert np.all((np.asarray(goal) >= low) & (np.asarray(goal) <= high))
    # The goal search reads the bounds while collect_chunk is traced: they must not depend on tracing.
    shifted = jax.jit(lambda x: x + jnp.asarray(env.observation_bounds[0]))
    traced_low = shifted(jnp.zeros(env.observation_size))
    np.testing.assert_array_equal(np.asarray(traced_low), low)
    assert env.eval_episode_length > 0 and env.hard_reset_every > 0
    assert all(0 <= d < env.observation_size for d in env.goal_dims)
    # The reset state is an initial state in the task's sense.
    state = jax.jit(env.reset)(jax.random.PRNGKey(5))
    assert bool(env.task_relevant(state.obs))


def test_registry_errors_list_valid_names():
    with pytest.raises(ValueError, match="valid envs:"):
        envs_mjx.make("no_such_task")
