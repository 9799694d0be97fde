"""Imagined rollouts in the world model and the imagination goal sampler (MoReFree's alpha mix).

`imagine` follows DreamerV2: the policy sees stop-gradient features, actions are reparameterised samples,
the prior step is reparameterised, so the actor's gradient flows through the dynamics. Only the recurrent
prior step and the policy run inside `lax.scan`; features are assembled once afterwards, and the policy's
distribution at every state is kept so the actor loss reuses it (no second actor pass for the entropy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from morefree_jax.networks import RSSM, Latent, TruncNormal, feature

SOURCE_REPLAY, SOURCE_EVAL, SOURCE_INITIAL = 0, 1, 2


class Trajectory(NamedTuple):
    """Time-major imagined rollout of H+1 states (start included) for N starts.

    latent (H+1, N, ...); feat (H+1, N, F); action (H+1, N, A) where action[t] led to state t and
    action[0] = 0 (DreamerV2); policy: the actor's distribution at states 0..H-1, (H, N, A).
    """

    latent: Latent
    feat: jax.Array
    action: jax.Array
    policy: TruncNormal


PolicyFn = Callable[[jax.Array], TruncNormal]  # stop-gradient feat (N, F) -> distribution


def imagine(rssm: RSSM, rssm_params, policy_fn: PolicyFn, start: Latent, horizon: int,
            key: jax.Array, unroll: int = 1) -> Trajectory:
    """Rolls `policy_fn` out in the prior for `horizon` steps from `start` (N, ...)."""
    key_noise, key_actions = jax.random.split(key)
    noise = jax.random.normal(key_noise, (horizon, *start.stoch.shape))
    action_keys = jax.random.split(key_actions, horizon)

    def step(latent: Latent, inputs):
        action_key, noise_t = inputs
        dist = policy_fn(jax.lax.stop_gradient(feature(latent)))
        action = dist.sample(action_key)
        latent, _ = rssm.apply(rssm_params, latent, action, noise_t, method=RSSM.img_step)
        return latent, (latent, action, dist)

    _, (latents, actions, dists) = jax.lax.scan(step, start, (action_keys, noise), unroll=unroll)
    latents = jax.tree.map(lambda s, x: jnp.concatenate([s[None], x], 0), start, latents)
    actions = jnp.concatenate([jnp.zeros_like(actions[:1]), actions], 0)
    return Trajectory(latents, feature(latents), actions, dists)


class GoalPools(NamedTuple):
    """Goal sources supplied by the task (sampled outside jit): eval goals (Pe, O), initial states (Pi, O)."""

    eval_goals: jax.Array
    initial_states: jax.Array


def sample_imagination_goals(key: jax.Array, replay_obs: jax.Array, pools: GoalPools, alpha: float,
                             num: int) -> tuple[jax.Array, jax.Array]:
    """MoReFree's imagination goal mix -> goals (num, O), source (num,) in {REPLAY, EVAL, INITIAL}.

    Each goal is an eval goal with probability alpha/2, an initial state with probability alpha/2, and
    otherwise a replay state; replay states are the batch observations `replay_obs` (M >= num, O) randomly
    permuted (PEG's `training_goals: batch`). alpha = 0 gives PEG (replay goals only).
    """
    key_perm, key_source, key_eval, key_init = jax.random.split(key, 4)
    replay = replay_obs[jax.random.permutation(key_perm, replay_obs.shape[0])[:num]]
    if alpha == 0.0:
        return replay, jnp.full((num,), SOURCE_REPLAY, jnp.int32)
    eval_goals = pools.eval_goals[jax.random.randint(key_eval, (num,), 0, pools.eval_goals.shape[0])]
    initial = pools.initial_states[jax.random.randint(key_init, (num,), 0, pools.initial_states.shape[0])]
    u = jax.random.uniform(key_source, (num,))
    source = jnp.where(u < alpha / 2, SOURCE_EVAL, jnp.where(u < alpha, SOURCE_INITIAL, SOURCE_REPLAY))
    goals = jnp.where((source == SOURCE_EVAL)[:, None], eval_goals,
                      jnp.where((source == SOURCE_INITIAL)[:, None], initial, replay))
    return goals, source.astype(jnp.int32)
