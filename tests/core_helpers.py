"""Shared pieces of the learning-core tests: task data and compiled functions cached across test files."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.world_model import Batch


@functools.cache
def task_stream(num_steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(obs (N, 4), actions (N, 2)): a random-action stream of a 2-D point mass in a walled box, obs =
    (x, y, vx, vy), PointUMaze's layout family (position + velocity).

    A stand-in, not point_umaze itself: its MJX step costs seconds of compile in every test process that
    builds a batch, and the learning-core tests need only a smooth stream with a 2-D position (the task's
    physics has its own tests)."""
    actions = jax.random.uniform(jax.random.PRNGKey(seed), (num_steps, 2), minval=-1.0, maxval=1.0)

    def step(state, action):
        pos, vel = state
        vel = 0.8 * vel + 0.5 * action
        pos = jnp.clip(pos + 0.1 * vel, -1.0, 1.0)
        return (pos, vel), jnp.concatenate([pos, vel])

    _, obs = jax.lax.scan(step, (jnp.zeros(2), jnp.zeros(2)), actions)
    return np.asarray(obs), np.asarray(actions)


def fixed_batch(batch: int, length: int) -> Batch:
    """B x T windows cut from one random-action stream; is_first at each window start."""
    obs, actions = task_stream(batch * length)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    return Batch(
        jnp.asarray(obs.reshape(batch, length, -1)), jnp.asarray(actions.reshape(batch, length, -1)),
        jnp.asarray(is_first),
    )
