"""One `train_step` of the agent as module-level functions over its modules (agent.AgentModules):

    world_model_part -> goal_conditioned_part (actor-critic + temporal distance) -> explore_part
    (Plan2Explore ensemble + exploration actor-critic)

`make_agent` binds them to its modules; benchmarks and notebooks may call each part on its own
(`agent.parts`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from morefree_jax.actor_critic import actor_critic_update, start_without_gradient
from morefree_jax.distance import distance_update, goal_projection
from morefree_jax.imagination import (
    SOURCE_EVAL,
    SOURCE_INITIAL,
    GoalPools,
    Trajectory,
    sample_imagination_goals,
)
from morefree_jax.networks import Latent
from morefree_jax.plan2explore import disagreement, ensemble_update
from morefree_jax.world_model import Batch, encode, world_model_update


def world_model_part(m, state, batch: Batch, key: jax.Array):
    """World-model update -> (wm state, posterior of the batch, metrics)."""
    return world_model_update(m.wm, m.wm_opt, state.wm, batch, key)


def imagination_starts(m, latent: Latent, obs, key):
    """Flattened posterior starts (N, ...), their replay row (N,), and the batch observations (T*B, O)."""
    length, batch_size = latent.deter.shape[:2]
    flat = jax.tree.map(lambda x: x.reshape(length * batch_size, *x.shape[2:]), latent)
    sequence_id = jnp.tile(jnp.arange(batch_size), length)
    replay_obs = jnp.swapaxes(obs, 0, 1).reshape(length * batch_size, -1)
    num = m.config.imag_starts
    if 0 < num < length * batch_size:
        index = jax.random.permutation(key, length * batch_size)[:num]
        flat, sequence_id = jax.tree.map(lambda x: x[index], flat), sequence_id[index]
    return flat, sequence_id, replay_obs


def _goal_reward_fn(m, state, wm_params, goal_embed):
    """The goal-conditioned reward -D(embed(feat), goal) of a trajectory, and the embeddings the distance
    trains on."""
    distance_projection = goal_projection(m.dist, state.distance.params, goal_embed)

    def embed(feat):
        return m.wm.embed_head.apply(wm_params["embed_head"], feat)

    def goal_reward(trajectory: Trajectory):
        # Reward on states 0..H-1; the distance trains on the embeddings of all H+1 states, and the last
        # one needs no gradient (it enters no reward).
        def reward_and_embed(feat):
            embeds = embed(feat)
            d = m.dist.net.apply(state.distance.params, embeds, distance_projection[None],
                                 method=m.dist.net.from_projection)[..., 0]
            return -d, embeds

        reward, embeds = start_without_gradient(reward_and_embed, trajectory.feat[:-1])
        last = embed(jax.lax.stop_gradient(trajectory.feat[-1:]))
        return reward, jnp.concatenate([embeds, last], 0)

    return goal_reward


def goal_conditioned_part(m, state, wm_params, posterior, batch: Batch, goals: GoalPools, key_starts, key):
    """Goal-conditioned actor-critic and temporal distance -> (gc actor, gc critic, distance, metrics).

    `key_starts` picks the imagination starts (shared with the exploration part, as in PEG)."""
    key_goals, key_gc, key_dist = jax.random.split(key, 3)
    starts, sequence_id, replay_obs = imagination_starts(m, posterior.latent, batch.obs, key_starts)
    goal_obs, source = sample_imagination_goals(key_goals, replay_obs, goals, m.config.alpha,
                                                sequence_id.shape[0])
    goal_embed = encode(m.wm, wm_params, goal_obs)
    goal_reward = _goal_reward_fn(m, state, wm_params, goal_embed)
    gc_actor, gc_critic, imagined, gc_metrics = actor_critic_update(
        m.gc, state.gc_actor, state.gc_critic, state.updates, m.wm.rssm, wm_params["rssm"], goal_reward,
        starts, goal_embed, key_gc, "gc")
    distance_state, distance_metrics = distance_update(m.dist, state.distance, imagined.reward_extras,
                                                       sequence_id, key_dist)
    metrics = {**gc_metrics, **distance_metrics, "gc/goal_eval_frac": jnp.mean(source == SOURCE_EVAL),
               "gc/goal_initial_frac": jnp.mean(source == SOURCE_INITIAL)}
    return gc_actor, gc_critic, distance_state, metrics


def explore_part(m, state, wm_params, posterior, batch: Batch, key_starts, key_expl):
    """Plan2Explore ensemble and exploration actor-critic -> (ensemble, actor, critic, metrics)."""
    starts, _, _ = imagination_starts(m, posterior.latent, batch.obs, key_starts)
    ensemble_state, ensemble_metrics = ensemble_update(m.ens, state.ensemble, posterior.latent,
                                                       jnp.swapaxes(batch.action, 0, 1))

    def explore_reward(trajectory: Trajectory):
        reward = start_without_gradient(partial(disagreement, m.ens, ensemble_state.params),
                                        trajectory.feat[:-1], trajectory.action[:-1])
        return reward, None

    explore_actor, explore_critic, _, explore_metrics = actor_critic_update(
        m.explore_ac, state.explore_actor, state.explore_critic, state.updates, m.wm.rssm, wm_params["rssm"],
        explore_reward, starts, None, key_expl, "explore")
    return ensemble_state, explore_actor, explore_critic, {**ensemble_metrics, **explore_metrics}


def train_step(m, state, batch: Batch, goals: GoalPools, key: jax.Array):
    """All five updates on one replay batch (B, T, ...) -> (state, metrics)."""
    key_wm, key_starts, key_gc, key_expl = jax.random.split(key, 4)
    wm_state, posterior, wm_metrics = world_model_part(m, state, batch, key_wm)
    gc_actor, gc_critic, distance_state, gc_metrics = goal_conditioned_part(
        m, state, wm_state.params, posterior, batch, goals, key_starts, key_gc)
    # The two imagination parts are independent and XLA may interleave them; the barrier makes the
    # exploration part wait for the goal-conditioned one, and the `paper` step runs faster so
    # (docs/performance.md).
    (gc_actor, gc_critic, distance_state), posterior = jax.lax.optimization_barrier(
        ((gc_actor, gc_critic, distance_state), posterior))
    ensemble_state, explore_actor, explore_critic, explore_metrics = explore_part(
        m, state, wm_state.params, posterior, batch, key_starts, key_expl)
    new_state = state.replace(wm=wm_state, gc_actor=gc_actor, gc_critic=gc_critic, distance=distance_state,
                              ensemble=ensemble_state, explore_actor=explore_actor,
                              explore_critic=explore_critic, updates=state.updates + 1)
    return new_state, {**wm_metrics, **gc_metrics, **explore_metrics}
