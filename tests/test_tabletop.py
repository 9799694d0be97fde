"""Tabletop: the original's kinematic rule step by step, and a scripted tour over all four goals."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from conftest import cached_env

from envs_mjx import tabletop
from envs_mjx.scripted import CLOSE, OPEN, tabletop_waypoint_action

STEPS_PER_WAYPOINT = 30  # the longest leg is 5 per axis, i.e. 25 steps of 0.2
MUG_START = (2.5, 0.0)


def env():
    return cached_env("tabletop")


@functools.cache
def reset():
    return jax.jit(env().reset)(jax.random.PRNGKey(0))


NUM_ACTIONS = 20  # every scripted sequence is padded to this length, so take_actions compiles once


@functools.cache
def compiled_take_actions():
    def take_actions(state, actions):
        def body(state, action):
            state = env().step(state, action)
            return state, state.obs

        return jax.lax.scan(body, state, actions)

    return jax.jit(take_actions)


def take_actions(state, actions, padding):
    """Runs `actions` then `padding` up to NUM_ACTIONS steps. Returns (final state, observations)."""
    actions = list(actions) + [padding] * (NUM_ACTIONS - len(actions))
    return compiled_take_actions()(state, jnp.asarray(actions, jnp.float32))


def test_grasp_threshold_move_and_clip_follow_the_original():
    state = reset()
    # Gripper walks to x = 2.0: 0.5 from the mug; grasping there fails, 0.2 closer it succeeds.
    actions = [[1.0, 0.0, OPEN]] * 10 + [[0.0, 0.0, CLOSE]] + [[1.0, 0.0, CLOSE]] * 2
    _, obs = take_actions(state, actions, padding=[0.0, 0.0, CLOSE])
    obs = np.asarray(obs)
    np.testing.assert_allclose(obs[9], [2.0, 0.0, 2.5, 0.0, -1.0, -1.0], atol=1e-5)
    np.testing.assert_allclose(obs[10], [2.0, 0.0, 2.5, 0.0, -1.0, -1.0], atol=1e-5)  # 0.5 > 0.4
    # Next step the gripper (0.5 away before moving) still fails, then the one after attaches at 0.3.
    np.testing.assert_allclose(obs[11], [2.2, 0.0, 2.5, 0.0, -1.0, -1.0], atol=1e-5)
    # Attached while moving: the mug moves with the realised gripper displacement.
    np.testing.assert_allclose(obs[12], [2.4, 0.0, 2.7, 0.0, 0.0, 0.0], atol=1e-5)


def test_held_mug_is_clipped_at_the_table_edge_and_released_on_open():
    state = reset()
    actions = [[1.0, 0.0, OPEN]] * 12 + [[0.0, 0.0, CLOSE]]  # gripper at 2.4, 0.1 from the mug
    actions += [[1.0, 0.5, CLOSE]] * 5  # pushes gripper and mug into the x edge
    actions += [[-1.0, 0.0, OPEN]] * 2  # release: the mug stays
    _, obs = take_actions(state, actions, padding=[-1.0, 0.0, OPEN])
    obs = np.asarray(obs)
    np.testing.assert_allclose(obs[12], [2.4, 0.0, 2.5, 0.0, 0.0, 0.0], atol=1e-5)
    # Gripper x: 2.4 -> 2.6 -> 2.8 (clipped); mug x: 2.5 -> 2.7 -> 2.8 (clipped) -> 2.8.
    np.testing.assert_allclose(obs[13], [2.6, 0.1, 2.7, 0.1, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(obs[14], [2.8, 0.2, 2.8, 0.2, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(obs[17], [2.8, 0.5, 2.8, 0.5, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(obs[19], [2.4, 0.5, 2.8, 0.5, -1.0, -1.0], atol=1e-5)
    assert np.all(np.abs(obs[:, 0:4]) <= 2.8 + 1e-6)


def tour_waypoints() -> np.ndarray:
    """(W, 3) gripper xy targets and grasp flags: for each goal, fetch the mug from its start, deliver it,
    park the gripper at the origin; then carry the mug back to its start and park again."""
    waypoints = []
    for mug_goal in tabletop.MUG_GOALS:
        waypoints += [
            (*MUG_START, OPEN), (*MUG_START, CLOSE), (*mug_goal, CLOSE), (*mug_goal, OPEN), (0, 0, OPEN),
            (*mug_goal, OPEN), (*mug_goal, CLOSE), (*MUG_START, CLOSE), (*MUG_START, OPEN), (0, 0, OPEN),
        ]  # fmt: skip
    return np.asarray(waypoints, np.float32)


@functools.cache
def scripted_tour():
    """Runs the tour in one scan. Returns observations (W, STEPS_PER_WAYPOINT, 6)."""

    def leg(state, waypoint):
        def body(state, _):
            state = env().step(state, tabletop_waypoint_action(state.obs, waypoint))
            return state, state.obs

        return jax.lax.scan(body, state, None, length=STEPS_PER_WAYPOINT)

    def tour(key):
        _, obs = jax.lax.scan(leg, env().reset(key), jnp.asarray(tour_waypoints()))
        return obs

    return np.asarray(jax.jit(tour)(jax.random.PRNGKey(0)))


def test_scripted_tour_reaches_every_goal_and_returns_the_mug():
    obs = scripted_tour()
    final = obs[:, -1]  # the observation at the end of each leg
    goals, initial = tabletop.GOAL_STATES, tabletop.INITIAL_STATE
    for g in range(4):
        delivered, returned = final[10 * g + 4], final[10 * g + 9]
        assert bool(env().success(delivered, goals[g])), (g, delivered)
        for other in set(range(4)) - {g}:
            assert not bool(env().success(delivered, goals[other]))
        np.testing.assert_allclose(delivered, goals[g], atol=1e-4)
        np.testing.assert_allclose(returned, initial, atol=1e-4)
        assert bool(env().success(returned, initial)) and not bool(env().success(returned, goals[g]))
    # While carried the mug is held; the mug never leaves the table.
    assert np.all(final[[10 * g + 2 for g in range(4)], 4:6] == 0.0)
    assert np.all(np.abs(obs[..., 2:4]) <= tabletop.TABLE_LIMIT + 1e-6)


def test_pipeline_state_holds_qpos_and_kinematics():
    env_ = env()
    state = reset()
    state, _ = take_actions(state, [[-1.0, 0.5, OPEN]] * 3, padding=[0.0, 0.0, OPEN])
    data = state.pipeline_state
    np.testing.assert_allclose(np.asarray(data.qpos), [-0.6, 0.3, 2.5, 0.0], atol=1e-5)
    mug = env_.mj_model.body("mug").id
    np.testing.assert_allclose(np.asarray(data.xpos[mug, 0:2]), [2.5, 0.0], atol=1e-5)


def test_an_evaluation_takes_the_four_goals_in_turn_from_a_drawn_one():
    firsts = set()
    for key in range(12):
        goals = np.asarray(env().evaluation_goals(jax.random.PRNGKey(key), 10))
        first = int(np.flatnonzero((np.asarray(tabletop.GOAL_STATES) == goals[0]).all(axis=1))[0])
        turn = (first + np.arange(10)) % 4
        np.testing.assert_array_equal(goals, np.asarray(tabletop.GOAL_STATES)[turn])
        firsts.add(first)
    assert firsts == {0, 1, 2, 3}  # every goal leads some evaluation: over a run the goals weigh the same
