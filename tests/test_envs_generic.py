"""The task API contract, checked on every registered task."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training
from conftest import cached_env, compiled_rollout

import envs_mjx


def test_rollout_200_steps_shapes_and_finite(env_name):
    env = cached_env(env_name)
    state0, final, observations = compiled_rollout(env_name, 200)(jax.random.PRNGKey(0))
    assert state0.obs.shape == (env.observation_size,)
    assert observations.shape == (200, env.observation_size)
    assert bool(jnp.all(jnp.isfinite(observations)))
    assert final.reward.shape == () and final.done.shape == ()
    assert float(final.done) == 0.0, "a reset-free task never terminates"


def test_same_key_same_trajectory_different_keys_differ(env_name):
    rollout = compiled_rollout(env_name, 200)
    _, _, obs_a = rollout(jax.random.PRNGKey(1))
    _, _, obs_b = rollout(jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(obs_a), np.asarray(obs_b))
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
    goal = env.eval_goals(key_goal)
    init = env.initial_states(key_init)
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


def test_brax_training_wrappers_vmap_and_step_without_retracing(env_name):
    """brax's training wrappers (vmap over instances, episodes of 5, auto-reset) in one compiled step per
    task, which must not retrace when only the action values change (a weakly typed action must not
    change the state's dtypes)."""
    env = training.wrap(cached_env(env_name), episode_length=5)
    # chex keys its counter on the definition site, which every parametrization of this test shares.
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(state, action):
        return env.step(state, action)

    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(3), 4))
    for i in range(6):  # crosses the episode end, so AutoResetWrapper resets once
        state = step(state, jnp.full((4, env.action_size), 0.1 * i))
    assert state.obs.shape == (4, env.observation_size)
    assert bool(jnp.all(jnp.isfinite(state.obs)))


def test_registry_errors_list_valid_names():
    with pytest.raises(ValueError, match="valid envs:"):
        envs_mjx.make("no_such_task")
