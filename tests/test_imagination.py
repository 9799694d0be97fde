"""Imagination goal mix: alpha/2 eval goals, alpha/2 initial states, 1 - alpha replay states."""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.imagination import (
    SOURCE_EVAL,
    SOURCE_INITIAL,
    SOURCE_REPLAY,
    GoalPools,
    sample_imagination_goals,
)

NUM = 20_000


def pools():
    return GoalPools(eval_goals=jnp.full((3, 2), 100.0) + jnp.arange(3.0)[:, None],
                     initial_states=jnp.full((2, 2), -100.0) - jnp.arange(2.0)[:, None])


def test_alpha_mix_fractions_match_within_sampling_error():
    replay = jax.random.uniform(jax.random.PRNGKey(0), (NUM, 2))
    sampler = jax.jit(sample_imagination_goals, static_argnums=(3, 4))
    goals, source = sampler(jax.random.PRNGKey(1), replay, pools(), 0.2, NUM)
    goals, source = np.asarray(goals), np.asarray(source)
    for kind, expected in [(SOURCE_EVAL, 0.1), (SOURCE_INITIAL, 0.1), (SOURCE_REPLAY, 0.8)]:
        frac = np.mean(source == kind)
        sigma = np.sqrt(expected * (1 - expected) / NUM)
        assert abs(frac - expected) < 4 * sigma, (kind, frac)
    assert np.all(goals[source == SOURCE_EVAL] >= 100) and np.all(goals[source == SOURCE_INITIAL] <= -100)
    assert np.all((goals[source == SOURCE_REPLAY] >= 0) & (goals[source == SOURCE_REPLAY] <= 1))
    # Every pool entry is used.
    assert len(np.unique(goals[source == SOURCE_EVAL][:, 0])) == 3


def test_alpha_zero_uses_replay_goals_only_permuted():
    replay = jnp.arange(200.0).reshape(100, 2)
    goals, source = sample_imagination_goals(jax.random.PRNGKey(2), replay, pools(), 0.0, 100)
    assert np.all(np.asarray(source) == SOURCE_REPLAY)
    goals = np.asarray(goals)
    np.testing.assert_array_equal(np.sort(goals[:, 0]), np.asarray(replay[:, 0]))  # a permutation
    assert not np.array_equal(goals, np.asarray(replay))
