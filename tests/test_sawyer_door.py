"""Sawyer Door: scripted closing, the 60-degree stopper, the workspace box, and MJX against C MuJoCo.

All rollouts go through one jitted scan whose controller is picked by `mode` (lax.switch), so the
door's physics compiles once for the whole file."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from conftest import cached_env

from envs_mjx import sawyer_door as door
from envs_mjx import scripted

HORIZON = 300
CLOSE, PUSH_OPEN, CORNERS, RANDOM = range(4)
STOPPER_TOLERANCE = 0.01  # rad: the soft joint limit may be passed by this much
WORKSPACE_TOLERANCE = 0.015  # m: the hand lags its (clipped) mocap target by about a centimetre


def env() -> door.SawyerDoor:
    return cached_env("sawyer_door")


def close_controller(obs, phase, t, key):
    del t, key
    return scripted.close_door(obs, door.GOAL_STATE, phase)


def push_open_controller(obs, phase, t, key):
    del t, key
    return scripted.push_door_open(obs, door.GOAL_STATE, phase)


def corners_controller(obs, phase, t, key):
    """Full-speed pushes far outside the workspace, changing corner every 100 steps."""
    del obs, key
    corners = jnp.array([[1, -1, 1], [-1, 1, -1], [1, 1, 1]], jnp.float32)
    return scripted.with_fingers_closed(corners[(t // 100) % 3]), phase


def random_controller(obs, phase, t, key):
    del obs, t
    return scripted.with_fingers_closed(jax.random.uniform(key, (3,), minval=-1.0, maxval=1.0)), phase


@functools.cache
def compiled_rollout():
    controllers = [close_controller, push_open_controller, corners_controller, random_controller]

    def rollout(key, mode):
        """Returns per step: pre-step data, action, post-step obs, door angle and mocap (HORIZON, ...)."""
        key_reset, key_actions = jax.random.split(key)

        def body(carry, inputs):
            state, phase = carry
            t, key_t = inputs
            action, phase = jax.lax.switch(mode, controllers, state.obs, phase, t, key_t)  # fingers closed
            next_state = env().step(state, action)
            data = next_state.pipeline_state
            record = (state.pipeline_state, action, next_state.obs, env().door_angle(data), data.mocap_pos[0])
            return (next_state, phase), record

        inputs = (jnp.arange(HORIZON), jax.random.split(key_actions, HORIZON))
        _, records = jax.lax.scan(body, (env().reset(key_reset), jnp.array(0)), inputs)
        return records

    return jax.jit(rollout)


@functools.cache
def run(mode: int, seed: int = 0):
    return jax.device_get(compiled_rollout()(jax.random.PRNGKey(seed), mode))


def test_reset_matches_the_reference_initial_state():
    env_ = env()
    for seed in range(3):
        state = jax.jit(env_.reset)(jax.random.PRNGKey(seed))
        angle = float(env_.door_angle(state.pipeline_state))
        assert door.OPEN_ANGLE <= angle <= door.OPEN_ANGLE + door.INITIAL_NOISE
        obs = np.asarray(state.obs)
        np.testing.assert_allclose(obs[0:4], [0.00592, 0.39968, 0.19493, 1.0], atol=1e-5)
        np.testing.assert_allclose(obs[4:7], np.asarray(door.handle_position(angle)), atol=1e-5)
    # EARL's reference handle positions: 60 degrees open, and closed.
    np.testing.assert_allclose(
        np.asarray(door.handle_position(door.OPEN_ANGLE)), [0.01007, 0.47105, 0.10004], atol=2e-5
    )
    np.testing.assert_allclose(door.GOAL_HANDLE, [0.29072, 0.74286, 0.10004], atol=2e-5)
    # the goal is written in numpy (no JAX at import) and is the closed door's handle bit for bit
    np.testing.assert_array_equal(door.GOAL_HANDLE, np.asarray(door.handle_position(0.0)))


def test_scripted_controller_closes_the_door_within_300_steps():
    goal = door.GOAL_STATE
    for seed in range(2):
        _, _, obs, angle, _ = run(CLOSE, seed)
        success = np.asarray(jax.vmap(env().success, in_axes=(0, None))(obs, goal))
        assert not success[0] and success[-1], (seed, obs[-1])
        assert success[-50:].all(), "the door stays closed"
        assert np.abs(angle[-1]) < 0.02 and angle.max() < STOPPER_TOLERANCE
        assert obs[0, 3] > 0.99 and obs[-1, 3] < 0.45, "the fingers closed (opening 1.0 -> 0.4)"


def test_door_never_opens_beyond_the_stopper():
    _, _, obs, angle, _ = run(PUSH_OPEN)
    assert (
        obs[-1, 2] < 0.2 and np.linalg.norm(obs[-1, 4:6] - door.handle_position(door.OPEN_ANGLE)[:2]) < 0.01
    )
    assert angle.min() > door.OPEN_ANGLE - STOPPER_TOLERANCE
    assert angle.min() < door.OPEN_ANGLE + 0.01, "the controller did push the door into the stopper"
    for seed in range(2):
        assert run(RANDOM, seed)[3].min() > door.OPEN_ANGLE - STOPPER_TOLERANCE


def test_gripper_cannot_leave_its_workspace():
    _, _, obs, _, mocap = run(CORNERS)
    low, high = door.WORKSPACE_LOW, door.WORKSPACE_HIGH
    assert np.all((mocap >= low - 1e-6) & (mocap <= high + 1e-6))
    hand = obs[:, 0:3]
    outside = np.linalg.norm(hand - np.clip(hand, low, high), axis=-1)
    assert outside.max() < WORKSPACE_TOLERANCE
    # The corners were reached: the hand got within 2 cm of both extremes on every axis.
    assert np.all(hand.min(0) < low + 0.02) and np.all(hand.max(0) > high - 0.02)


def c_mujoco_rollout(env_, data, actions):
    """Steps C MuJoCo from the MJX `data` with the same mocap rule and controls. Returns qpos (T, nq)."""
    mj_data = reference_mj_data(env_, data)
    qpos = []
    for action in actions:
        mocap = mj_data.mocap_pos + door.MOCAP_STEP * action[0:3]
        mj_data.mocap_pos[:] = np.clip(mocap, door.WORKSPACE_LOW, door.WORKSPACE_HIGH)
        mj_data.ctrl[:] = [action[3], -action[3]]
        for _ in range(env_.frames_per_step):
            mujoco.mj_step(env_.mj_model, mj_data)
        qpos.append(mj_data.qpos.copy())
    return np.asarray(qpos)


def test_mjx_matches_c_mujoco():
    """Over 20 steps, free motion (the hand rising) agrees to 1e-4 (measured ~1e-7); while the fingers
    push the door (contacts) the door angle agrees within 0.015 rad (measured up to 0.008: the light door
    bounces off slightly different contact points) and hand and fingers within 1 mm (measured 1e-4)."""
    env_ = env()
    free = run(PUSH_OPEN)
    contact = run(CLOSE)
    contact_start = int(np.argmax(np.abs(contact[3] - contact[3][0]) > 1e-4)) - 2
    assert np.ptp(free[3][:21]) == 0.0 and contact[3][contact_start + 20] - contact[3][contact_start] > 0.1
    door_qpos = env_.mj_model.jnt_qposadr[env_.mj_model.joint("doorjoint").id]
    contact_tolerance = np.full(env_.mj_model.nq, 1e-3)
    contact_tolerance[door_qpos] = 0.015
    for (datas, actions, *_), start, tolerance in (
        (free, 0, 1e-4),
        (contact, contact_start, contact_tolerance),
    ):
        data = jax.tree.map(lambda x, s=start: x[s], datas)
        reference = c_mujoco_rollout(env_, data, actions[start : start + 20])
        error = np.abs(reference - datas.qpos[start + 1 : start + 21]).max(0)
        assert np.all(error < tolerance), (start, error)


def reference_mj_data(env, data):
    """A C MuJoCo MjData with the full dynamic state of `data` (qpos, qvel, mocap, ctrl, act, warmstart)."""
    mj_data = env.mj_data_from(data)
    mj_data.ctrl[:] = np.asarray(data.ctrl)
    mj_data.qacc_warmstart[:] = np.asarray(data.qacc_warmstart)
    return mj_data
