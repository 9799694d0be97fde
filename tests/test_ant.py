"""Ant physics: standing still, the room's walls, and MJX against C MuJoCo."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from conftest import cached_env

from envs_mjx.ant import ROOM_HIGH, ROOM_LOW

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


def test_zero_action_stays_upright_in_the_room_for_500_steps():
    env = cached_env(ENV)
    obs = jax.jit(lambda key: _rollout(env, env.reset(key), jnp.zeros((500, 8))))(jax.random.PRNGKey(0))
    obs = np.asarray(obs)
    assert np.all(np.isfinite(obs))
    assert _up_z(obs[:, 3:7]).min() > 0.9, "the ant tipped over"
    assert obs[:, 2].min() > 0.2, "the torso sank into the floor"
    assert np.all((obs[:, :2] > ROOM_LOW) & (obs[:, :2] < ROOM_HIGH))
    assert np.abs(obs[-1, :2]).max() < 0.5, "with no action the ant should stay near its start"


def test_walls_stop_a_torso_pushed_toward_them():
    env = cached_env(ENV)

    def pushed(key, velocity):
        state = env.reset(key)
        data = state.pipeline_state
        data = data.replace(qpos=data.qpos.at[:2].set(jnp.array([3.5, 3.5])),
                            qvel=data.qvel.at[:2].set(velocity))
        return _rollout(env, state.replace(pipeline_state=data), jnp.zeros((40, 8)))

    run = jax.jit(pushed)
    for velocity in ([8.0, 0.0], [0.0, 8.0], [-8.0, 0.0], [0.0, -8.0]):
        xy = np.asarray(run(jax.random.PRNGKey(1), jnp.array(velocity))[:, :2])
        # The torso sphere (radius 0.25) may touch a wall but its centre never passes within 0.15 of it.
        assert xy.min() > ROOM_LOW + 0.15 and xy.max() < ROOM_HIGH - 0.15, (velocity, xy.min(), xy.max())
        assert np.abs(xy - 3.5).max() > 0.5 or velocity[0] < 0 or velocity[1] < 0, "the push did not move it"


def test_mjx_matches_c_mujoco_for_20_steps():
    """Each of 20 random-action steps, started from the same state in MJX and C MuJoCo, agrees.

    Stated tolerance: away from contact onsets the two agree to 1e-6 (we require most steps within
    1e-5); where a contact activates MJX's pyramidal-cone solve differs from C MuJoCo's by up to about
    2e-2 in one control step (measured), so every step must be within 3e-2."""
    env = cached_env(ENV)
    step = jax.jit(env.step)
    errors = []
    for seed in range(2):
        state = jax.jit(env.reset)(jax.random.PRNGKey(seed))
        actions = jax.random.uniform(jax.random.PRNGKey(10 + seed), (20, 8), minval=-1.0, maxval=1.0)
        for action in actions:
            c_data = mujoco.MjData(env.mj_model)
            c_data.qpos[:] = np.asarray(state.pipeline_state.qpos)
            c_data.qvel[:] = np.asarray(state.pipeline_state.qvel)
            c_data.ctrl[:] = 30.0 * np.asarray(action)
            for _ in range(env.frames_per_step):
                mujoco.mj_step(env.mj_model, c_data)
            state = step(state, action)
            errors.append(np.abs(np.asarray(state.pipeline_state.qpos) - c_data.qpos).max())
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
