"""PointUMaze physics: the manual wall rule, a scripted solution, and containment."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from conftest import cached_env

from envs_mjx.point_umaze import LAYOUT, cell_center, collide_with_walls, wall_faces

ENV = "point_umaze"


def test_reflection_matches_hand_computed_bounce():
    faces = jnp.asarray(wall_faces())
    # The inner wall's lower face, inflated by 0.4, is the line y = 1.6 for x in [-2.4, 6.4].
    new = collide_with_walls(faces, jnp.array([0.0, 0.0]), jnp.array([0.0, 2.6]))
    # Hit at (0, 1.6); the end mirrors to (0, 0.6); 0.8 of the remainder from the hit point: (0, 0.8).
    np.testing.assert_allclose(np.asarray(new), [0.0, 0.8], atol=1e-5)
    free_move = collide_with_walls(faces, jnp.array([0.0, 0.0]), jnp.array([0.5, 0.5]))
    np.testing.assert_allclose(np.asarray(free_move), [0.5, 0.5], atol=1e-6)


# The three drives below share one compiled scan (the MJX step's compile dominates this file): a
# 10,000-step drive with the controller chosen by an argument; each test reads its prefix.
DRIVE_STEPS = 10_000
PUSH_FORWARD, WAYPOINTS, RANDOM = 0, 1, 2


@functools.cache
def _drive_program():
    env = cached_env(ENV)

    def drive(controller, heading0, key):
        """DRIVE_STEPS of `controller`: from the pose (0, 0, heading0) at rest, or for RANDOM from a reset
        with `key`. Returns the observations (DRIVE_STEPS, obs size)."""
        key_reset, key_actions = jax.random.split(key)
        reset = env.reset(key_reset)
        data = reset.pipeline_state.replace(qpos=jnp.array([0.0, 0.0, heading0]), qvel=jnp.zeros(3))
        posed = reset.replace(pipeline_state=data, obs=jnp.concatenate([data.qpos, data.qvel]))
        state = jax.tree.map(lambda r, p: jnp.where(controller == RANDOM, r, p), reset, posed)
        random_actions = jax.random.uniform(key_actions, (DRIVE_STEPS, env.action_size), minval=-1.0,
                                            maxval=1.0)
        controllers = (lambda obs, a: jnp.array([1.0, 0.0]), lambda obs, a: waypoint_controller(obs),
                       lambda obs, a: a)

        def body(state, random_action):
            state = env.step(state, jax.lax.switch(controller, controllers, state.obs, random_action))
            return state, state.obs

        return jax.lax.scan(body, state, random_actions)[1]

    return jax.jit(drive)


def _drive(controller: int, heading0: float = 0.0, seed: int = 0):
    return _drive_program()(controller, heading0, jax.random.PRNGKey(seed))


def test_driving_into_inner_wall_never_crosses_it():
    obs = _drive(PUSH_FORWARD, jnp.pi / 2)[:50]
    y = np.asarray(obs[:, 1])
    assert y.max() <= 1.6 + 1e-4, "the point entered the inflated inner wall"
    assert y.max() > 1.0, "the point should have driven up to the wall"


def waypoint_controller(obs):
    """Follows the U: right along the bottom corridor, up the right side, then left to the goal."""
    x, y = obs[0], obs[1]
    up_right = jnp.where(y < 7.5, jnp.array([8.0, 8.0]), jnp.array([0.0, 8.0]))
    target = jnp.where((y < 7.5) & (x < 7.5), jnp.array([8.0, 0.0]), up_right)
    delta = target - obs[:2]
    error = jnp.arctan2(delta[1], delta[0]) - obs[2]
    error = (error + jnp.pi) % (2 * jnp.pi) - jnp.pi
    turn = jnp.clip(error / 0.25, -1.0, 1.0)
    aligned = jnp.abs(error) < 0.25
    forward = jnp.where(aligned, jnp.minimum(jnp.linalg.norm(delta), 1.0), 0.0)
    return jnp.array([forward, turn])


def test_scripted_controller_reaches_goal_within_episode():
    env = cached_env(ENV)
    obs = _drive(WAYPOINTS)[: env.eval_episode_length]
    goal = env.eval_goals(jax.random.PRNGKey(0))
    successes = np.asarray(jax.vmap(env.success, in_axes=(0, None))(obs, goal))
    assert successes.any(), f"closest approach {float(jnp.min(env.goal_distance(obs, goal))):.2f}"
    assert bool(successes[-1]), "the controller should stay at the goal"


@functools.cache
def _wall_blocks():
    blocks = [(i, j) for i, row in enumerate(LAYOUT) for j, c in enumerate(row) if c == "1"]
    return np.array([cell_center(i, j) for i, j in blocks])


def test_random_actions_for_10000_steps_stay_in_the_maze():
    obs = _drive(RANDOM, seed=7)
    xy = np.asarray(obs[:, :2])
    assert xy.min() >= -2.0 and xy.max() <= 10.0
    # Never inside a wall block (blocks are 4 x 4, centred on their cell).
    offsets = np.abs(xy[:, None, :] - _wall_blocks()[None])
    inside = np.all(offsets < 2.0, axis=-1)
    assert not inside.any()
    assert np.ptp(xy[:, 0]) > 4.0, "random exploration should move through the corridor"
