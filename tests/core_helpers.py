"""Shared pieces of the learning-core tests: task data and compiled functions cached across test files."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import envs_mjx
from morefree_jax.world_model import Batch


def standin_point_mass_stream(key: jax.Array, num_steps: int) -> tuple[jax.Array, jax.Array]:
    """Random-action stream of a 2-D point mass in a walled box: obs (N, 4) = (x, y, vx, vy), actions (N, 2).

    Stand-in for point_umaze until that task is registered (same obs layout family: position + velocity).
    """
    actions = jax.random.uniform(key, (num_steps, 2), minval=-1.0, maxval=1.0)

    def step(state, action):
        pos, vel = state
        vel = 0.8 * vel + 0.5 * action
        pos = jnp.clip(pos + 0.1 * vel, -1.0, 1.0)
        return (pos, vel), jnp.concatenate([pos, vel])

    _, obs = jax.lax.scan(step, (jnp.zeros(2), jnp.zeros(2)), actions)
    return obs, actions


@functools.cache
def task_stream(num_steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
    """(obs (N, O), action (N, A), source) from point_umaze with random actions, or the stand-in."""
    key = jax.random.PRNGKey(seed)
    if "point_umaze" in envs_mjx.ALL_ENVS:
        env = envs_mjx.make("point_umaze")
        key_reset, key_act = jax.random.split(key)
        actions = jax.random.uniform(key_act, (num_steps, env.action_size), minval=-1.0, maxval=1.0)

        def body(state, action):
            state = env.step(state, action)
            return state, state.obs

        _, obs = jax.jit(lambda s, a: jax.lax.scan(body, s, a))(env.reset(key_reset), actions)
        return np.asarray(obs), np.asarray(actions), "point_umaze"
    obs, actions = standin_point_mass_stream(key, num_steps)
    return np.asarray(obs), np.asarray(actions), "standin"


def fixed_batch(batch: int, length: int) -> Batch:
    """B x T windows cut from one random-action stream; is_first at each window start."""
    obs, actions, _ = task_stream(batch * length)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    return Batch(
        jnp.asarray(obs.reshape(batch, length, -1)), jnp.asarray(actions.reshape(batch, length, -1)),
        jnp.asarray(is_first),
    )
