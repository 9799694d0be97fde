"""Temporal distance trained on straight-line (constant-speed) trajectories ranks pairs by |j - i|."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from morefree_jax.distance import (
    distance,
    distance_update,
    init_distance,
    make_distance,
    positive_grid,
    sample_pairs,
)
from morefree_jax.learner_config import DistanceConfig, OptimizerConfig

H, N, E = 10, 32, 6


def straight_lines(key):
    key_start, key_dir = jax.random.split(key)
    start = jax.random.normal(key_start, (N, E))
    direction = jax.random.normal(key_dir, (N, E))
    direction = 0.3 * direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)  # constant speed
    return start[None] + jnp.arange(H + 1)[:, None, None] * direction[None]  # (H+1, N, E)


def test_distance_ranks_pairs_by_time_gap():
    # Positives only (point maze's neg_factor 0): negatives between random lines are label noise here.
    cfg = DistanceConfig(layers=(128, 128, 128), num_pairs=128, neg_factor=0.0, opt=OptimizerConfig(lr=2e-3))
    dist = make_distance(cfg)
    state = init_distance(dist, jax.random.PRNGKey(0), E)
    sequence_id = jnp.arange(N) % 8

    @jax.jit
    def train(state, key):
        def body(state, key):
            key_data, key_pairs = jax.random.split(key)
            return distance_update(dist, state, straight_lines(key_data), sequence_id, key_pairs)

        return jax.lax.scan(body, state, jax.random.split(key, 1000))

    state, metrics = train(state, jax.random.PRNGKey(1))
    losses = np.asarray(metrics["distance/loss"])
    assert losses[-20:].mean() < 0.5 * losses[:20].mean()
    embeds = straight_lines(jax.random.PRNGKey(99))  # held-out lines
    grid = positive_grid(H)
    pred = distance(dist, state.params, embeds[grid[:, 0]], embeds[grid[:, 1]])  # (pairs, N)
    gap = np.broadcast_to((grid[:, 1] - grid[:, 0])[:, None], pred.shape)
    rho = stats.spearmanr(np.asarray(pred).ravel(), gap.ravel()).statistic
    assert rho > 0.9, rho


def test_pairs_labels_and_negatives_from_other_sequences():
    cfg = DistanceConfig(num_pairs=256, neg_factor=0.25)
    sequence_id = jnp.arange(40) % 5
    pairs = sample_pairs(jax.random.PRNGKey(0), cfg, 15, sequence_id)
    pos = jax.tree.map(lambda x: np.asarray(x[:256]), pairs)
    neg = jax.tree.map(lambda x: np.asarray(x[256:]), pairs)
    assert len(neg.label) == 64
    assert np.all(pos.state_traj == pos.goal_traj) and np.all(pos.goal_time >= pos.state_time)
    assert pos.goal_time.max() <= 14
    np.testing.assert_allclose(pos.label, (pos.goal_time - pos.state_time) / 15)
    np.testing.assert_allclose(neg.label, 16 / 15)
    assert np.all(np.asarray(sequence_id)[neg.state_traj] != np.asarray(sequence_id)[neg.goal_traj])
    assert neg.state_time.max() <= 15
