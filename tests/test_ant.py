"""Ant physics: standing still, the room's walls, and MJX against C MuJoCo."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from conftest import cached_env

from envs_mjx.ant import GOAL_HIGH, GOAL_LOW, ROOM_HIGH, ROOM_LOW

ENV = "ant"


def _up_z(quaternion):
    """z component of the torso's up axis for a (w, x, y, z) quaternion."""
    w, x, y, z = quaternion[..., 0], quaternion[..., 1], quaternion[..., 2], quaternion[..., 3]
    return 1 - 2 * (x**2 + y**2) / (w**2 + x**2 + y**2 + z**2)


def _rollout(env, state, actions):
    def body(state, action):
        state = env.step(state, action)
        return state, state.obs

    return jax.lax.scan(body, state, actions)[1]


# The tests below share one compiled scan (the MJX step's compile dominates this file): STEPS steps from a
# reset, optionally with the torso moved and pushed, returning every state's qpos and qvel.
STEPS = 500


@functools.cache
def _trajectory_program():
    env = cached_env(ENV)

    def trajectory(key, pushed, xy, velocity, actions):
        """(first qpos, first qvel), then obs, qpos and qvel after each of the STEPS actions."""
        state = env.reset(key)
        data = state.pipeline_state
        moved = data.replace(qpos=data.qpos.at[:2].set(xy), qvel=data.qvel.at[:2].set(velocity))
        data = jax.tree.map(lambda m, d: jnp.where(pushed, m, d), moved, data)
        state = state.replace(pipeline_state=data)

        def body(state, action):
            state = env.step(state, action)
            return state, (state.obs, state.pipeline_state.qpos, state.pipeline_state.qvel)

        return (data.qpos, data.qvel), jax.lax.scan(body, state, actions)[1]

    return jax.jit(trajectory)


def _trajectory(seed, actions=None, pushed_from=None, velocity=(0.0, 0.0)):
    steps = np.zeros((STEPS, 8), np.float32)
    if actions is not None:
        steps[: len(actions)] = actions
    xy = (0.0, 0.0) if pushed_from is None else pushed_from
    return jax.device_get(_trajectory_program()(jax.random.PRNGKey(seed), pushed_from is not None,
                                                jnp.array(xy), jnp.array(velocity), jnp.asarray(steps)))


def test_zero_action_stays_upright_in_the_room_for_500_steps():
    _, (obs, _, _) = _trajectory(0)
    assert np.all(np.isfinite(obs))
    assert _up_z(obs[:, 3:7]).min() > 0.9, "the ant tipped over"
    assert obs[:, 2].min() > 0.2, "the torso sank into the floor"
    assert np.all((obs[:, :2] > ROOM_LOW) & (obs[:, :2] < ROOM_HIGH))
    assert np.abs(obs[-1, :2]).max() < 0.5, "with no action the ant should stay near its start"


def test_the_start_is_the_room_centre_and_the_goal_square_its_top_right_corner():
    """The paper: the ant starts at the centre (0, 0) of the square room; goals U(2, 3)^2, top-right."""
    assert ROOM_LOW == -ROOM_HIGH
    assert np.all(GOAL_LOW > 0) and np.all(GOAL_HIGH < ROOM_HIGH)
    assert np.all(GOAL_LOW - 0.0 > ROOM_HIGH - GOAL_HIGH)  # nearer the corner walls than the start


def test_walls_stop_a_torso_pushed_toward_them():
    for direction in ([1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]):
        start = (ROOM_HIGH - 1.5) * np.array(direction)  # 1.5 from the wall it is pushed at (a square room)
        xy = _trajectory(1, pushed_from=tuple(start), velocity=8.0 * np.array(direction))[1][0][:40, :2]
        # The torso sphere (radius 0.25) may touch a wall but its centre never passes within 0.15 of it.
        assert xy.min() > ROOM_LOW + 0.15 and xy.max() < ROOM_HIGH - 0.15, (direction, xy.min(), xy.max())
        assert np.abs(xy - start).max() > 0.5, "the push did not move it"


def test_mjx_matches_c_mujoco_for_20_steps():
    """Each of 20 random-action steps, started from the same state in MJX and C MuJoCo, agrees.

    Stated tolerance: away from contact onsets the two agree to 1e-6 (we require most steps within
    1e-5); where a contact activates MJX's pyramidal-cone solve differs from C MuJoCo's by up to about
    2e-2 in one control step (measured), so every step must be within 3e-2."""
    env = cached_env(ENV)
    errors = []
    for seed in range(2):
        actions = np.asarray(jax.random.uniform(jax.random.PRNGKey(10 + seed), (20, 8), minval=-1.0,
                                                maxval=1.0))
        (qpos, qvel), (_, qpos_after, qvel_after) = _trajectory(seed, actions)
        # each C step starts from MJX's state before that step
        starts_qpos = np.concatenate([qpos[None], qpos_after[: len(actions) - 1]])
        starts_qvel = np.concatenate([qvel[None], qvel_after[: len(actions) - 1]])
        for action, start_qpos, start_qvel, next_qpos in zip(actions, starts_qpos, starts_qvel,
                                                               qpos_after[: len(actions)], strict=True):
            c_data = mujoco.MjData(env.mj_model)
            c_data.qpos[:], c_data.qvel[:] = start_qpos, start_qvel
            c_data.ctrl[:] = 30.0 * action
            for _ in range(env.frames_per_step):
                mujoco.mj_step(env.mj_model, c_data)
            errors.append(np.abs(next_qpos - c_data.qpos).max())
    errors = np.asarray(errors)
    assert errors.max() < 3e-2, errors.max()
    assert np.mean(errors < 1e-5) > 0.6, np.sort(errors)


def test_elliptic_cone_matches_c_mujoco_closely():
    """With elliptic cones (an override) free-running trajectories agree to 1e-4 for 20 steps."""
    import envs_mjx

    env = envs_mjx.make(ENV, cone="elliptic")
    rest = env.initial_states(jax.random.PRNGKey(1))
    state = env.reset(jax.random.PRNGKey(0))
    state = state.replace(pipeline_state=state.pipeline_state.replace(qpos=rest[:15], qvel=rest[15:]))
    actions = 0.3 * jax.random.uniform(jax.random.PRNGKey(4), (20, 8), minval=-1.0, maxval=1.0)
    mjx_qpos = np.asarray(jax.jit(lambda s, a: _rollout(env, s, a))(state, actions))[:, :15]
    c_data = mujoco.MjData(env.mj_model)
    c_data.qpos[:], c_data.qvel[:] = np.asarray(rest[:15]), np.asarray(rest[15:])
    c_qpos = []
    for action in np.asarray(actions):
        c_data.ctrl[:] = 30.0 * action
        for _ in range(env.frames_per_step):
            mujoco.mj_step(env.mj_model, c_data)
        c_qpos.append(c_data.qpos.copy())
    np.testing.assert_allclose(mjx_qpos, np.asarray(c_qpos), atol=1e-4)
