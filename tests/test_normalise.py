"""Min-max normalised observations (envs_mjx/normalise.py) and where the run system turns them on."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from conftest import cached_env

import envs_mjx
from envs_mjx.normalise import NormalisedObservations, in_task_units
from morefree_jax.config import resolve_config
from morefree_jax.registry import make_run_fns


def wrapped_tabletop():
    return NormalisedObservations(cached_env("tabletop"))  # a kinematic step: cheap to compile


def test_observations_goals_and_initial_states_are_the_task_vectors_in_unit_box_coordinates():
    env, inner = wrapped_tabletop(), cached_env("tabletop")
    low, high = (np.asarray(b) for b in inner.observation_bounds)
    key = jax.random.PRNGKey(3)
    action = np.full(inner.action_size, 0.7, np.float32)
    state, raw = jax.jit(env.reset)(key), jax.jit(inner.reset)(key)
    np.testing.assert_allclose(state.obs, (raw.obs - low) / (high - low), atol=1e-6)
    stepped, raw_stepped = jax.jit(env.step)(state, action), jax.jit(inner.step)(raw, action)
    np.testing.assert_allclose(env.denormalise(stepped.obs), raw_stepped.obs, atol=1e-5)
    assert not np.allclose(stepped.obs, raw_stepped.obs)  # the units did change
    np.testing.assert_allclose(env.denormalise(env.eval_goals(key)), inner.eval_goals(key), atol=1e-5)
    np.testing.assert_allclose(env.denormalise(env.initial_states(key)), inner.initial_states(key), atol=1e-5)
    np.testing.assert_allclose(env.denormalise(env.evaluation_goals(key, 6)), inner.evaluation_goals(key, 6),
                               atol=1e-5)
    unit_low, unit_high = env.observation_bounds
    assert np.all(unit_low == 0) and np.all(unit_high == 1)
    assert env.goal_dims == inner.goal_dims and env.eval_episode_length == inner.eval_episode_length
    goals = env.evaluation_goals(key, 4)
    np.testing.assert_allclose(in_task_units(env, goals), inner.evaluation_goals(key, 4), atol=1e-5)
    assert in_task_units(inner, goals) is goals


def test_task_measures_are_taken_in_the_task_units():
    env, inner = wrapped_tabletop(), cached_env("tabletop")
    keys = jax.random.split(jax.random.PRNGKey(5), 8)
    goals = jax.vmap(inner.eval_goals)(keys)
    starts = jax.vmap(inner.initial_states)(keys)
    # 0.3 of the radius on each of the 4 goal dims: 0.6 of the radius, clear of the boundary.
    near = goals.at[:, np.asarray(inner.goal_dims)].add(0.3 * inner.success_threshold)
    for obs in (starts, near):
        for name in ("goal_distance", "success", "reward"):
            ours = jax.vmap(getattr(env, name))(env.normalise(obs), env.normalise(goals))
            np.testing.assert_allclose(ours, jax.vmap(getattr(inner, name))(obs, goals), atol=1e-5)
        np.testing.assert_allclose(jax.vmap(env.xy)(env.normalise(obs)), jax.vmap(inner.xy)(obs), atol=1e-5)
        np.testing.assert_array_equal(jax.vmap(env.task_relevant)(env.normalise(obs)),
                                      jax.vmap(inner.task_relevant)(obs))
    assert bool(jax.vmap(env.success)(env.normalise(near), env.normalise(goals)).all())


def test_bounds_without_width_are_refused_with_one_line():
    class Flat:
        observation_bounds = (np.zeros(3), np.array([1.0, 0.0, 1.0]))

    with pytest.raises(ValueError, match="observation_bounds need high > low") as error:
        NormalisedObservations(Flat())
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("task, agent, wrapped", [
    ("push", "morefree", True), ("pick_place_hard", "rf_peg", True), ("point_umaze", "morefree", False),
    ("sawyer_door", "morefree", False), ("push", "oracle_sac", False),
])
def test_the_fetch_tasks_world_model_agents_see_normalised_observations(task, agent, wrapped):
    config = resolve_config([f"env={task}", f"agent={agent}", "preset=debug"], envs_mjx.ALL_ENVS)
    fns = make_run_fns(config, cached_env(task))
    assert isinstance(fns.env, NormalisedObservations) == wrapped
