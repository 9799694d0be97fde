"""Physics and task checks of the four Fetch tasks (push, pick_place, push_hard, pick_place_hard).

Every check of a task reads one compiled, vmapped rollout of SCENARIOS scripted scenarios (500 steps each,
controllers from envs_mjx.scripted, in jnp inside the scan), so each task compiles once:
  0-3   a sampled evaluation goal, pushed (push tasks) or picked and carried (pick-and-place tasks)
  4-7   pushing the block towards a point 0.6 m beyond each wall / confinement side (+x, -x, +y, -y)
  8     zero action (the block must rest)
  9-12  constant actions driving the gripper into the workspace corners
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import envs_mjx
from envs_mjx import fetch
from envs_mjx.scripted import pick_action, push_action

FETCH_TASKS = ("push", "pick_place", "push_hard", "pick_place_hard")
NUM_STEPS = 500
PUSH, PICK, FIXED = 0, 1, 2
GOAL_SCENARIOS = range(0, 4)
WALL_SCENARIOS = range(4, 8)
REST_SCENARIO = 8
CORNER_ACTIONS = np.array([[1, 1, 1, 0], [-1, -1, -1, 0], [1, -1, 1, 0], [-1, 1, -1, 0]], np.float32)
CORNER_SCENARIOS = range(9, 13)
WALL_DIRECTIONS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], np.float32)
def scripted_rollout(env, state, goal, mode, fixed_action):
    """One scenario from `state`: (qpos (T, nq), qvel (T, nv), obs (T, 25)) after each of NUM_STEPS steps."""

    def body(carry, _):
        state, phase = carry
        pick, next_phase = pick_action(state.obs, goal, phase)
        scripted = jnp.where(mode == PUSH, push_action(state.obs, goal), pick)
        action = jnp.where(mode == FIXED, fixed_action, scripted)
        state = env.step(state, action)
        data = state.pipeline_state
        return (state, jnp.where(mode == PICK, next_phase, 0)), (data.qpos, data.qvel, state.obs)

    _, trajectory = jax.lax.scan(body, (state, jnp.zeros((), jnp.int32)), None, length=NUM_STEPS)
    return trajectory


def all_scenarios(env, carries: bool):
    """Start observation (25,), scenario goals (S, 3) and trajectories (S, T, ...), S = 13 scenarios."""
    start = env.reset(jax.random.PRNGKey(0))
    goal_keys = jax.random.split(jax.random.PRNGKey(7), len(GOAL_SCENARIOS))
    eval_goals = jax.vmap(env.eval_goals)(goal_keys)[:, 3:6]
    wall_goals = start.obs[3:6] + jnp.pad(0.6 * WALL_DIRECTIONS, ((0, 0), (0, 1)))
    rest_goals = jnp.tile(start.obs[3:6], (1 + len(CORNER_SCENARIOS), 1))
    goals = jnp.concatenate([eval_goals, wall_goals, rest_goals])
    modes = jnp.array([PICK if carries else PUSH] * 4 + [PUSH] * 4 + [FIXED] * 5)
    fixed = jnp.concatenate([jnp.zeros((9, 4)), CORNER_ACTIONS])
    # lax.map (sequential) compiles faster than vmap here, which matters more than run time.
    trajectories = jax.lax.map(lambda x: scripted_rollout(env, start, *x), (goals, modes, fixed))
    return start.obs, goals, trajectories


class Rollouts(NamedTuple):
    env: envs_mjx.ResetFreeEnv
    start: np.ndarray  # (25,) observation every scenario starts from
    goals: np.ndarray  # (S, 3) block goal of each scenario
    qpos: np.ndarray  # (S, T, nq)
    qvel: np.ndarray  # (S, T, nv)
    obs: np.ndarray  # (S, T, 25)


@functools.cache
def task_rollouts(name: str) -> Rollouts:
    """The scenarios of one task, compiled once and run once."""
    env = envs_mjx.make(name)
    run = jax.jit(functools.partial(all_scenarios, env, name.startswith("pick_place")))
    start, goals, (qpos, qvel, obs) = jax.device_get(run())
    return Rollouts(env, start, goals, qpos, qvel, obs)


@pytest.fixture(params=FETCH_TASKS)
def task(request):
    return request.param


def test_scripted_controller_reaches_sampled_goals_within_episode(task):
    env, _, goals, _, _, obs = task_rollouts(task)
    episode = env.eval_episode_length
    for i in GOAL_SCENARIOS:
        distance = np.linalg.norm(obs[i, :, 3:6] - goals[i], axis=-1)
        assert distance[:episode].min() < env.success_threshold, f"goal {i} {goals[i]} never reached"
        assert distance[episode - 1] < env.success_threshold, f"goal {i}: not at the goal at step {episode}"


def test_pick_place_hard_lifts_into_air_box_and_holds():
    env, _, goals, _, _, obs = task_rollouts("pick_place_hard")
    for i in GOAL_SCENARIOS:
        block = obs[i, env.eval_episode_length - 1 :, 3:6]  # from the end of the episode on
        assert np.all(block >= env.goal_low - 0.01) and np.all(block <= env.goal_high + 0.01)
        held_distance = np.linalg.norm(block - goals[i], axis=-1)
        assert held_distance.max() < 0.02, f"goal {i}: drifted {held_distance.max():.3f} m while held"


@pytest.mark.parametrize("name", ["push_hard", "pick_place_hard"])
def test_walls_keep_block_on_table(name):
    """Tolerance: the block centre may pass the rigid-wall position by < 1 cm at impact (one 0.01 s
    substep of travel) and by < 3 mm while the gripper keeps squeezing it into the wall."""
    _, _, _, _, _, obs = task_rollouts(name)
    inner_low = fetch.TABLE_LOW + 0.025  # block centre against a wall
    inner_high = fetch.TABLE_HIGH - 0.025
    for i, direction in zip(WALL_SCENARIOS, WALL_DIRECTIONS, strict=True):
        block_xy = obs[i, :, 3:5]
        assert np.all(block_xy >= inner_low - 0.01) and np.all(block_xy <= inner_high + 0.01)
        squeezed = block_xy[-100:]
        assert np.all(squeezed >= inner_low - 0.003) and np.all(squeezed <= inner_high + 0.003)
        assert np.all(obs[i, :, 5] > 0.4), "the block went through the table"
        # It really was driven into the wall it was pushed towards (within 1 cm of touching it).
        axis, sign = int(np.argmax(np.abs(direction))), direction.sum()
        wall = inner_high[axis] if sign > 0 else inner_low[axis]
        assert np.abs(block_xy[-100:, axis] - wall).max() < 0.01


@pytest.mark.parametrize("name", ["push", "pick_place"])
def test_block_stays_in_ibc_confinement_box(name):
    env, _, _, _, _, obs = task_rollouts(name)
    center = env.block_center[:2]
    for i, direction in zip(WALL_SCENARIOS, WALL_DIRECTIONS, strict=True):
        offset = obs[i, :, 3:5] - center
        assert np.all(np.abs(offset) <= fetch.IBC_CONFINEMENT + 0.01), np.abs(offset).max()
        axis = int(np.argmax(np.abs(direction)))
        reached = (offset[:, axis] * direction[axis]).max()
        assert reached > fetch.IBC_CONFINEMENT - 0.01, f"block pushed only to {reached:.3f} m"


def test_gripper_cannot_leave_workspace(task):
    env, _, _, _, _, obs = task_rollouts(task)
    grip = obs[:, :, 0:3]
    low, high = env.workspace_low, env.workspace_high
    assert np.all(grip >= low - 0.003) and np.all(grip <= high + 0.003), (grip.min((0, 1)), grip.max((0, 1)))
    # Finger bottoms (1.5 cm below the grip site) above the table; fingers inside the walls / table edges.
    assert low[2] - 0.015 > 0.4 and np.all(low[:2] - 0.0135 >= fetch.TABLE_LOW - 1e-9)
    assert np.all(high[:2] + 0.0135 <= fetch.TABLE_HIGH + 1e-9)
    for i, action in zip(CORNER_SCENARIOS, CORNER_ACTIONS, strict=True):
        corner = np.where(action[:3] > 0, high, low)
        assert np.abs(grip[i, -1] - corner).max() < 0.005, "the gripper did not reach its corner"


def test_block_rests_under_zero_action_for_500_steps(task):
    """Tolerance over 500 steps (20 s): drift < 1 mm, rotation < 0.01 rad; after 10 settling steps,
    jitter < 2.5 mm/s (1e-4 m per step) linear and < 0.025 rad/s (1e-3 rad per step) angular."""
    _, start, _, _, _, obs = task_rollouts(task)
    rest = obs[REST_SCENARIO]
    assert np.abs(rest[:, 3:6] - start[3:6]).max() < 1e-3
    assert np.abs(rest[:, 11:14]).max() < 0.01
    assert np.abs(rest[10:, 14:17]).max() < 1e-4 and np.abs(rest[10:, 17:20]).max() < 1e-3
    assert np.abs(rest[:, 0:3] - start[0:3]).max() < 1e-3, "the gripper drifted"


@pytest.mark.parametrize("name", ["pick_place", "push_hard"])
def test_observation_matches_c_mujoco_sites(name):
    """Block Euler angles and site velocities x dt agree with C MuJoCo on moving states."""
    env, _, _, qpos, qvel, obs = task_rollouts(name)
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    grip_site, block_site = model.site("grip").id, model.site("object0").id
    velocity = np.zeros(6)
    moving = 0
    for t in range(1, 60):  # every step of the first 60
        data.qpos[:], data.qvel[:] = qpos[0, t], qvel[0, t]
        mujoco.mj_forward(model, data)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, grip_site, velocity, 0)
        grip_vel = velocity[3:].copy()
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, block_site, velocity, 0)
        expected = np.concatenate([
            data.site_xpos[grip_site], data.site_xpos[block_site],
            Rotation.from_matrix(data.site_xmat[block_site].reshape(3, 3)).as_euler("xyz"),
            (velocity[3:] - grip_vel) * env.dt, velocity[:3] * env.dt, grip_vel * env.dt,
        ])
        actual = np.concatenate([obs[0, t, 0:6], obs[0, t, 11:23]])
        np.testing.assert_allclose(actual, expected, atol=2e-4)
        moving += np.abs(grip_vel).max() > 0.05
    assert moving > 3, "the checked states should include a moving gripper"


class _Replay(NamedTuple):
    obs: jax.Array
    count: jax.Array


def test_side_view_counts_the_lifted_block_in_the_air_and_the_pushed_one_not():
    """The paper's XZ heatmap of Pick&Place (hard): blocks held at the air goals are above the air line;
    blocks pushed into the walls (tipping included) or at rest are not; unfilled rows count nowhere."""
    from envs_mjx.normalise import NormalisedObservations
    from morefree_jax.evaluate import visitation

    env, _, _, _, _, obs = task_rollouts("pick_place_hard")
    lifted = obs[list(GOAL_SCENARIOS), -50:].reshape(-1, obs.shape[-1])
    on_table = obs[[*WALL_SCENARIOS, REST_SCENARIO]].reshape(-1, obs.shape[-1])
    rows = np.concatenate([lifted, on_table])
    unfilled = np.full((7, obs.shape[-1]), 0.5, np.float32)
    unfilled[:, 5] = 1.0  # would be in the air if it counted
    replay = _Replay(jnp.asarray(np.concatenate([rows, unfilled])), jnp.asarray(len(rows)))
    views = visitation(env, replay, bins=10)
    assert float(views["in_air"]) == pytest.approx(len(lifted) / len(rows))
    assert float(views["xz"].sum()) == len(rows) and float(views["xy"].sum()) == len(rows)
    normalised = NormalisedObservations(env)
    same = visitation(normalised, replay._replace(obs=normalised.normalise(replay.obs)), bins=10)
    assert float(same["in_air"]) == pytest.approx(float(views["in_air"]))
    np.testing.assert_allclose(same["xz"], views["xz"])
    no_side_view = visitation(envs_mjx.make("push_hard"), replay, bins=10)
    assert set(no_side_view) == {"task_relevant", "xy"}
