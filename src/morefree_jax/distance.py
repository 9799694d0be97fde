"""Learned temporal ("dynamical") distance of PEG: D(state_embed, goal_embed) ~ steps-to-go / H.

Trained by regression on the goal-conditioned policy's own imagined trajectories of the same update:
positives (i, j) with 0 <= i <= j <= H-1 drawn uniformly from the grid of all such pairs over all
trajectories, label (j - i) / H; negatives (neg_factor * num_pairs of them) pair states of trajectories
started from different replay sequences, label (H + 1) / H. Deviation from PEG: pairs are drawn fresh
every update (PEG drew them once at trace time).
The goal-conditioned reward is r = -D(embed_head(feat), goal_embed).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from morefree_jax.learner_config import DistanceConfig
from morefree_jax.networks import ContextMLP, NetState, gradient_update, init_net_state, make_optimizer


class Distance(NamedTuple):
    net: ContextMLP
    config: DistanceConfig
    optimizer: optax.GradientTransformation


def make_distance(cfg: DistanceConfig, precision: str = "f32") -> Distance:
    return Distance(ContextMLP(cfg.layers, 1, precision=precision), cfg, make_optimizer(cfg.opt))


def init_distance(dist: Distance, key: jax.Array, embed_size: int) -> NetState:
    x = jnp.zeros((1, embed_size))
    return init_net_state(dist.net.clone(input_size=2 * embed_size).init(key, x, x), dist.optimizer)


def goal_projection(dist: Distance, params, goal_embed: jax.Array) -> jax.Array:
    """The goal's share of D's first layer, computed once per goal (..., hidden)."""
    return dist.net.apply(params, goal_embed, method=ContextMLP.project)


def distance_from_projection(dist: Distance, params, state_embed: jax.Array, projection: jax.Array):
    """D(state, goal) (...,) in units of the imagination horizon."""
    return dist.net.apply(params, state_embed, projection, method=ContextMLP.from_projection)[..., 0]


def distance(dist: Distance, params, state_embed: jax.Array, goal_embed: jax.Array) -> jax.Array:
    return distance_from_projection(dist, params, state_embed, goal_projection(dist, params, goal_embed))


class Pairs(NamedTuple):
    """Training pairs: trajectory and time indices of state and goal, and the regression label."""

    state_traj: jax.Array
    state_time: jax.Array
    goal_traj: jax.Array
    goal_time: jax.Array
    label: jax.Array


def positive_grid(horizon: int) -> np.ndarray:
    """All (i, j) with 0 <= i <= j <= horizon-1, (horizon*(horizon+1)/2, 2)."""
    return np.array([(i, j) for i in range(horizon) for j in range(i, horizon)], np.int32)


def sample_pairs(key: jax.Array, cfg: DistanceConfig, horizon: int, sequence_id: jax.Array) -> Pairs:
    """Positive and negative pairs over N trajectories; sequence_id (N,) names each start's replay row."""
    key_traj, key_pair, key_neg_traj, key_neg_goal, key_neg_time = jax.random.split(key, 5)
    num_traj = sequence_id.shape[0]
    grid = jnp.asarray(positive_grid(horizon))
    traj = jax.random.randint(key_traj, (cfg.num_pairs,), 0, num_traj)
    ij = grid[jax.random.randint(key_pair, (cfg.num_pairs,), 0, grid.shape[0])]
    positives = Pairs(traj, ij[:, 0], traj, ij[:, 1], (ij[:, 1] - ij[:, 0]) / horizon)
    num_neg = int(cfg.neg_factor * cfg.num_pairs)
    if num_neg == 0:
        return positives
    state_traj = jax.random.randint(key_neg_traj, (num_neg,), 0, num_traj)
    # Goal trajectory from another replay sequence: first of 8 uniform candidates that qualifies
    # (uniform over the qualifying ones; all 8 failing has probability (1/B)^8).
    candidates = jax.random.randint(key_neg_goal, (num_neg, 8), 0, num_traj)
    other = sequence_id[candidates] != sequence_id[state_traj][:, None]
    goal_traj = candidates[jnp.arange(num_neg), jnp.argmax(other, 1)]
    times = jax.random.randint(key_neg_time, (2, num_neg), 0, horizon + 1)
    label = jnp.full((num_neg,), (horizon + 1) / horizon)
    negatives = Pairs(state_traj, times[0], goal_traj, times[1], label)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), positives, negatives)


def distance_loss(dist: Distance, params, embeds: jax.Array, pairs: Pairs, num_pos: int):
    """MSE on positives + MSE on negatives; embeds (H+1, N, E) are stop-gradient imagined embeddings."""
    pred = distance(dist, params, embeds[pairs.state_time, pairs.state_traj],
                    embeds[pairs.goal_time, pairs.goal_traj])
    sq = jnp.square(pred - pairs.label)
    loss = jnp.mean(sq[:num_pos])
    if sq.shape[0] > num_pos:
        loss = loss + jnp.mean(sq[num_pos:])
    return loss, {"distance/loss": loss, "distance/pred_mean": jnp.mean(pred[:num_pos])}


def distance_update(dist: Distance, state: NetState, embeds: jax.Array, sequence_id: jax.Array,
                    key: jax.Array) -> tuple[NetState, dict]:
    """One step on fresh pairs from the imagined embeddings (H+1, N, E)."""
    pairs = sample_pairs(key, dist.config, embeds.shape[0] - 1, sequence_id)
    state, metrics, grad_norm = gradient_update(
        state, lambda p: distance_loss(dist, p, embeds, pairs, dist.config.num_pairs), dist.optimizer)
    return state, {**metrics, "distance/grad_norm": grad_norm}
