"""The ibc agent: hindsight relabelling on a hand-made replay, the curriculum's costs and matching against
hand-computed answers, IBC's segment switching, a whole two-chunk run through driver.train (two seeds in one
program), exact resume after SIGKILL, and bad input. The generalised SAC learner is in test_sac.py."""

from __future__ import annotations

import dataclasses
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from envs_mjx.tabletop import INITIAL_STATE
from morefree_jax import driver
from morefree_jax.baselines.baseline_config import IBCConfig
from morefree_jax.baselines.ibc import curriculum as curriculum_lib
from morefree_jax.baselines.ibc import her
from morefree_jax.baselines.ibc.curriculum import Curriculum
from morefree_jax.baselines.ibc.learner import BACKWARD, FORWARD, IBCLearner
from morefree_jax.baselines.ibc.segments import IBCParts
from morefree_jax.baselines.ibc.tasks import corridor_points, ibc_task
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.config import resolve_config
from morefree_jax.logger import read_metrics
from tests.run_helpers import (
    assert_same_run,
    assert_train_cli_error,
    callback_primitives,
    debug_args,
    final_state,
    sigkilled_after,
)

PREFILL, CHUNK, SEGMENT = 100, 50, 10
SEEDS = (0, 1)
# Tiny learners, pool and segments (tabletop's kinematic step compiles fast, run_helpers.RUN_ENV): 200 steps
# hold ~20 segments, enough for the matchings at forward segments 2, 3, 6, ...
IBC_ARGS = (f"prefill={PREFILL}", f"baseline.chunk_len={CHUNK}", "baseline.replay_capacity=1000",
            "baseline.ibc.sac.batch_size=32", "baseline.ibc.sac.hidden_dim=32",
            "baseline.ibc.sac.feature_dim=16",
            "baseline.ibc.pool_size=8", "baseline.ibc.slots=4", "baseline.ibc.match_first=2",
            "baseline.ibc.match_every=3", "baseline.ibc.value_samples=2", "baseline.ibc.random_steps=40",
            f"baseline.ibc.segment_length={SEGMENT}", "log_every=50", "eval_every=100", "checkpoint_every=50")


def ibc_config(*extra: str):
    return resolve_config(debug_args("agent=ibc", *IBC_ARGS, *extra), envs_mjx.ALL_ENVS)


@functools.lru_cache(maxsize=1)
def ibc_programs():
    return driver.build_programs(ibc_config("steps=200"), len(SEEDS))


# ---- IBC's SAC variant (sac.py's options) ---------------------------------------------------------

def test_ibc_sac_options_squash_log_std_and_skip_actor_and_target_on_odd_updates():
    cfg = dataclasses.replace(IBCConfig().sac, hidden_dim=16, feature_dim=8, batch_size=4)
    state = sac.init(cfg, 6, 2, jax.random.PRNGKey(0))
    assert len(state.actor.params["params"]["_Head_0"]) == 4  # 3 hidden layers + the output
    _, log_std = sac.policy(cfg, state.actor.params, 1e4 * jax.random.normal(jax.random.PRNGKey(1), (64, 6)))
    assert float(log_std.min()) >= -10.0 and float(log_std.max()) <= 2.0
    batch = sac.SACBatch(obs=jnp.ones((4, 6)), action=jnp.zeros((4, 2)), reward=-jnp.ones(4),
                         next_obs=jnp.ones((4, 6)), not_done=jnp.ones(4))
    update = jax.jit(functools.partial(sac.update, cfg))
    first, metrics = update(state, batch, jax.random.PRNGKey(2))  # update 0: critic, actor, alpha, target
    second, _ = update(first, batch, jax.random.PRNGKey(3))  # update 1: the critic only
    def changed(a, b):
        return any(bool(jnp.any(x != y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))

    assert changed(state.actor.params, first.actor.params)
    assert not changed(first.actor.params, second.actor.params)
    assert changed(state.critic.target, first.critic.target) and not changed(first.critic.target,
                                                                              second.critic.target)
    assert changed(first.critic.params, second.critic.params)
    # The plain clipped step from alpha 0.5: alpha - 1e-5 (entropy - target entropy), at most 0.5.
    expected = min(0.5 - 1e-5 * (float(metrics["sac/entropy"]) + 2.0), 0.5)  # target entropy -|A| = -2
    np.testing.assert_allclose(float(metrics["sac/alpha"]), expected, rtol=1e-6)
    loss_half = sac.critic_loss(dataclasses.replace(cfg, critic_loss_weight=0.5), state.critic.params, batch,
                                jnp.zeros(4))[0]
    loss_full = sac.critic_loss(cfg, state.critic.params, batch, jnp.zeros(4))[0]
    np.testing.assert_allclose(loss_full, 2 * loss_half, rtol=1e-6)


# ---- hindsight replay ------------------------------------------------------------------------------

def hand_made_buffer():
    """Segment A: obs x 0..3 -> next 1..4, goal x 100 (never reached), ended; segment B: next 11..13,
    still open."""
    buffer = her.init_segment_buffer(16, 2, 1)
    write = jax.jit(her.insert_where)
    for x in range(4):
        buffer = write(buffer, jnp.array([x, 0.0]), jnp.array([100.0, 7.0]), jnp.zeros(1),
                       jnp.array([x + 1.0, 0.0]), jnp.asarray(True))
    assert not bool(buffer.sampleable)  # nothing before its segment ends
    buffer = her.end_segment_where(buffer, jnp.asarray(True))
    for x in range(10, 13):
        buffer = write(buffer, jnp.array([x, 0.0]), jnp.array([100.0, 7.0]), jnp.zeros(1),
                       jnp.array([x + 1.0, 0.0]), jnp.asarray(True))
    return buffer


def test_her_relabels_with_strictly_later_goals_of_the_same_segment_and_keeps_a_fifth():
    buffer = hand_made_buffer()
    assert int(buffer.committed) == 4 and int(buffer.count) == 7 and buffer.segment_end[0] == 3
    success = lambda obs, goal: jnp.abs(obs[0] - goal[0]) < 0.5  # noqa: E731
    mask = jnp.array([1.0, 0.0])  # the agent sees goal x only
    batch = her.sample_her(buffer, jax.random.PRNGKey(0), 1000, 0.8, success, mask)
    obs_x, next_x, goal_x = (np.asarray(a) for a in (batch.obs[:, 0], batch.next_obs[:, 0], batch.obs[:, 2]))
    assert set(obs_x.tolist()) == {0.0, 1.0, 2.0, 3.0}  # segment B is still open: never drawn
    relabelled, original = slice(0, 800), slice(800, 1000)
    assert np.all(goal_x[original] == 100.0) and np.all(batch.reward[original] == -1.0)
    assert np.all(goal_x[relabelled] <= 4.0)
    np.testing.assert_array_equal(batch.reward, np.where(goal_x == next_x, 0.0, -1.0))
    np.testing.assert_array_equal(batch.obs[:, 3], 0.0)  # masked goal dim
    assert np.all(batch.not_done == 1.0)  # IBC never masks the bootstrap
    # IBC's "future" is a strictly later transition's next state: x + 2 .. 4 for x = 0..2; the segment's
    # last transition (x = 3) has none and takes its own next state.
    last = obs_x[relabelled] == 3.0
    assert np.all(goal_x[relabelled][~last] > next_x[relabelled][~last])
    assert np.all(goal_x[relabelled][last] == 4.0)
    assert set(goal_x[relabelled][obs_x[relabelled] == 0.0].tolist()) == {2.0, 3.0, 4.0}
    reached = np.mean(batch.reward[relabelled] == 0.0)
    assert 0.18 < reached < 0.32  # only the last transition reaches its relabelled goal: 1 / 4


# ---- the curriculum ------------------------------------------------------------------------------

def test_matching_picks_the_least_cost_assignment():
    cost = np.array([[4.0, 1.0, 3.0, 9.0], [2.0, 0.0, 5.0, 9.0], [3.0, 2.0, 2.0, 9.0]])
    # Greedy would take (1, 1) = 0 then pay 4 + 2; the optimum is 1 + 2 + 2 = 5.
    assert curriculum_lib.assignment(cost).tolist() == [1, 0, 2]
    from_jit = jax.jit(curriculum_lib.assign_on_host)(jnp.asarray(cost, jnp.float32))
    assert np.asarray(from_jit).tolist() == [1, 0, 2]
    big = np.random.default_rng(0).uniform(size=(50, 1000))
    start = time.perf_counter()
    columns = curriculum_lib.assignment(big)
    print(f"linear_sum_assignment 50 x 1000: {1e3 * (time.perf_counter() - start):.1f} ms")
    assert len(set(columns.tolist())) == 50


def test_point_umaze_targets_lie_on_ibc_corridor_points():
    env = envs_mjx.make("point_umaze")
    task = ibc_task(env)
    points = corridor_points(task)
    assert points.shape == (30, 2) and np.allclose(points[[0, -1]], [[0.0, 0.0], [0.0, 8.0]])
    gaps = np.linalg.norm(np.diff(points, axis=0), axis=1)  # even along the U (a chord cuts each corner)
    assert np.sum(np.isclose(gaps, 24.0 / 29)) >= 27 and np.all(gaps <= 24.0 / 29 + 1e-9)
    curriculum = Curriculum(env, task, IBCConfig(), 0.99)
    _, goals = curriculum.target_pairs(jax.random.PRNGKey(0))
    offsets = np.abs(np.asarray(goals)[:, None, :2] - points[None]).max(-1)  # (K, 30) inf-norm
    assert goals.shape == (50, env.observation_size) and np.all(offsets.min(1) <= 0.1 + 1e-6)
    assert len({int(i) for i in offsets.argmin(1)}) > 10  # spread over the corridor, not one point


def test_matching_costs_follow_the_formula_on_a_tiny_pool():
    # Two 1-D trajectories (the second only 2 steps long), one target: goal 3, initial proprio 0.
    goals = jnp.array([[[1.0], [2.0], [4.0]], [[3.0], [9.0], [9.0]]])
    values = jnp.array([[-10.0, -20.0, -5.0], [-50.0, 0.0, 0.0]])
    lengths, valid = jnp.array([3, 2]), jnp.array([True, True])
    first_proprio, target_goal = jnp.array([[0.5], [2.0]]), jnp.array([[3.0]])
    target_proprio = jnp.array([[0.0]])
    max_dis, discount, c, big_l = 10.0, 0.9, 3.0, 5.0
    cost, best_t = curriculum_lib.matching_costs(goals, lengths, first_proprio, valid, values, target_goal,
                                                 target_proprio, max_dis, discount, c, big_l)
    scale = max_dis * (1 - discount) / big_l  # 0.2
    by_hand_0 = min(2 + 10 * scale, 1 + 20 * scale, 1 + 5 * scale) + c * 0.5  # t = 2: 2.0 + 1.5
    # t = 0 reaches the goal but has a low value: t = 1 wins (t = 2 is past the trajectory's end)
    by_hand_1 = min(0 + 50 * scale, 6 + 0) + c * 2.0
    np.testing.assert_allclose(cost, [[by_hand_0, by_hand_1]], rtol=1e-6)
    assert best_t.tolist() == [[2, 1]]
    cost, _ = curriculum_lib.matching_costs(goals, lengths, first_proprio, jnp.array([True, False]), values,
                                            target_goal, target_proprio, max_dis, discount, c, big_l)
    assert float(cost[0, 1]) == curriculum_lib.NO_MATCH  # an empty pool row


# ---- segments and switching -------------------------------------------------------------------------

@functools.lru_cache(maxsize=1)
def tabletop_parts():
    config = ibc_config("steps=200")
    env = envs_mjx.make("tabletop")
    ibc = config.baseline.ibc
    task = ibc_task(env, ibc.segment_length)
    return IBCParts(config, env, IBCLearner(ibc, env, task), Curriculum(env, task, ibc, ibc.sac.discount))


SWITCH_CASES = [  # (direction, success, segment_step) -> (ends, next direction)
    ((FORWARD, True, 3), (True, FORWARD)),  # success: a new forward goal, no backward segment
    ((FORWARD, False, SEGMENT - 1), (True, BACKWARD)),  # failed forward: the backward agent runs
    ((FORWARD, False, 3), (False, FORWARD)),  # mid-segment
    ((BACKWARD, True, 3), (True, FORWARD)),
    ((BACKWARD, False, SEGMENT - 1), (True, FORWARD)),
]


def test_backward_runs_only_after_a_failed_forward_segment():
    parts = tabletop_parts()
    state = jax.jit(parts.init)(jax.random.PRNGKey(0))

    @jax.jit
    def switch(direction, success, segment_step):  # one compile serves every case
        stream = state.stream.replace(direction=direction, segment_step=segment_step)
        end, reset = parts.segment_end(stream, success)
        following = parts.next_segment(stream, state.curriculum, stream.env_state, success, end, reset,
                                       jax.random.PRNGKey(1))
        return end, following

    for (direction, success, segment_step), (ends, next_direction) in SWITCH_CASES:
        end, following = switch(jnp.asarray(direction, jnp.int32), jnp.asarray(success),
                                jnp.asarray(segment_step, jnp.int32))
        assert bool(end) == ends and int(following.direction) == next_direction
        assert int(following.segment_step) == (0 if ends else segment_step + 1)
        if ends and next_direction == BACKWARD:  # a slot's start; Tabletop's noise is on the mug, not xy
            starts = np.asarray(state.curriculum.backward_slots[:, :2])
            assert np.any(np.all(starts == np.asarray(following.goal[:2]), axis=1))


def test_forward_agent_samples_half_the_batch_and_backward_all_of_it(monkeypatch):
    """IBC's ForwardBackwardReplayBufferWrapper.sample: int(rl_batch_size / 2) forward, all of it backward."""
    env = envs_mjx.make("tabletop")
    config = IBCConfig(sac=dataclasses.replace(IBCConfig().sac, hidden_dim=8, feature_dim=4, batch_size=64))
    learner = IBCLearner(config, env, ibc_task(env))
    buffers = tuple(her.init_segment_buffer(16, env.observation_size, env.action_size) for _ in range(2))
    state = learner.init(jax.random.PRNGKey(0))
    seen = {}
    real_sample = her.sample_her

    def spy(buffer, key, batch, relabel, success_fn, goal_mask):
        seen["forward" if success_fn == env.success else "backward"] = batch  # the task's test: forward
        return real_sample(buffer, key, batch, relabel, success_fn, goal_mask)

    monkeypatch.setattr("morefree_jax.baselines.ibc.learner.sample_her", spy)
    jax.eval_shape(learner.update, state, buffers, jnp.asarray(FORWARD), jax.random.PRNGKey(1))
    assert seen == {"forward": 32, "backward": 64}


def curriculum_of(name: str, **config):
    env, ibc = envs_mjx.make(name), IBCConfig(**config)
    return Curriculum(env, ibc_task(env, ibc.segment_length), ibc, 0.99)


def many_backward_goals(curriculum, state, obs, count: int = 4000) -> np.ndarray:
    keys = jax.random.split(jax.random.PRNGKey(7), count)
    return np.asarray(jax.jit(jax.vmap(lambda k: curriculum.backward_goal(state, obs, k)))(keys))


def test_backward_goal_draws_its_own_slot_and_keeps_a_reached_second_draw():
    # Tabletop: the backward test reads the gripper xy [0:2]; the noise goes on the mug [2:4].
    curriculum = curriculum_of("tabletop", pool_size=4, slots=4)
    state = curriculum.init(jax.random.PRNGKey(0))
    grippers = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    state = state.replace(backward_slots=state.backward_slots.at[:, :2].set(grippers))
    far = jnp.array([-2.0, -2.0, 0.0, 0.0, -1.0, -1.0])
    chosen = many_backward_goals(curriculum, state, far)[:, :2]
    shares = [np.mean(np.all(chosen == g, axis=1)) for g in np.asarray(grippers)]
    assert all(0.2 < share < 0.3 for share in shares)  # uniform over all four slots, not one paired slot
    # The state already reaches slot 0: a first draw of it is drawn again, a second one stands (1/16).
    at_slot_0 = far.at[:2].set(0.0)
    chosen = many_backward_goals(curriculum, state, at_slot_0)[:, :2]
    kept = np.mean(np.all(chosen == 0.0, axis=1))
    assert 0.04 < kept < 0.09


def test_backward_goal_noise_is_gaussian_with_the_curriculum_std_on_the_task_dims():
    # point_umaze: N(0, 0.3) on the point xy (IBC's MatchSampler.add_noise), not uniform +-0.1.
    curriculum = curriculum_of("point_umaze", pool_size=4, slots=4)
    state = curriculum.init(jax.random.PRNGKey(0))
    start = jnp.array([4.0, 0.0, 0.5, 0.0, 0.0, 0.0])
    state = state.replace(backward_slots=jnp.broadcast_to(start, state.backward_slots.shape))
    goals = many_backward_goals(curriculum, state, jnp.array([0.0, 8.0, 0.0, 0.0, 0.0, 0.0]))
    offsets = goals - np.asarray(start)
    np.testing.assert_allclose(offsets[:, :2].std(axis=0), 0.3, rtol=0.1)
    assert np.all(offsets[:, 2:] == 0.0)
    # Tabletop: the mug entries get N(0, 0.1), the gripper entries none.
    curriculum = curriculum_of("tabletop", pool_size=4, slots=4)
    state = curriculum.init(jax.random.PRNGKey(0))
    start = jnp.array([0.5, 0.5, 1.0, 1.0, -1.0, -1.0])
    state = state.replace(backward_slots=jnp.broadcast_to(start, state.backward_slots.shape))
    offsets = many_backward_goals(curriculum, state, jnp.array([-2.0, -2.0, 0.0, 0.0, -1.0, -1.0])) - start
    np.testing.assert_allclose(offsets[:, 2:4].std(axis=0), 0.1, rtol=0.1)
    assert np.all(offsets[:, [0, 1, 4, 5]] == 0.0)


def test_noised_forward_goals_are_clipped_as_ibc_clips_them():
    # Tabletop, through the whole draw: the mug near two table edges, N(0, 0.1) noise, clipped to +-2.8.
    curriculum = curriculum_of("tabletop", pool_size=4, slots=4)
    state = curriculum.init(jax.random.PRNGKey(0))
    slot_goal = jnp.array([0.0, 0.0, 2.75, -2.75, -1.0, -1.0])
    state = state.replace(forward_slots=jnp.broadcast_to(slot_goal, state.forward_slots.shape))
    obs = jnp.asarray(INITIAL_STATE)  # far from the slot goal: the first draw stands
    keys = jax.random.split(jax.random.PRNGKey(7), 2000)
    mugs = np.asarray(jax.jit(jax.vmap(lambda k: curriculum.forward_goal(state, obs, k)))(keys))[:, 2:4]
    assert np.all(np.abs(mugs) <= 2.8 + 1e-6) and mugs.std(axis=0).min() > 0.03
    assert np.mean(np.isclose(mugs[:, 0], 2.8)) > 0.2 and np.mean(np.isclose(mugs[:, 1], -2.8)) > 0.2
    # push: the block into IBC's box and onto the table (clip_forward alone: no Fetch curriculum to build).
    env = envs_mjx.make("push")
    push = Curriculum(env, ibc_task(env), IBCConfig(), 0.99)
    outside = jnp.zeros(env.observation_size).at[3:6].set(jnp.array([1.6, 0.5, 0.47]))
    block = np.asarray(push.clip_forward(outside))[3:6]
    np.testing.assert_allclose(block, [1.49786948, 0.59894948, 0.43], atol=1e-6)


def test_target_initial_states_get_uniform_noise_once_or_per_matching_in_earl_tasks():
    curriculum = curriculum_of("point_umaze")
    state = curriculum.init(jax.random.PRNGKey(0))
    # initial states are U(-0.1, 0.1) poses with zero velocity; IBC adds U(-0.1, 0.1) once more, on all
    offsets = np.asarray(state.target_init[:, 3:])
    assert np.all(np.abs(offsets) <= 0.1 + 1e-6) and np.abs(offsets).max() > 0.05
    slot_init = curriculum.slot_initial_states(state, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(slot_init, state.target_init)  # K = slots = 50: fixed pairs
    curriculum = curriculum_of("tabletop")
    state = curriculum.init(jax.random.PRNGKey(0))
    first, second = (curriculum.slot_initial_states(state, jax.random.PRNGKey(k)) for k in (1, 2))
    initial = np.asarray(curriculum.env.initial_states(jax.random.PRNGKey(0)))
    assert first.shape == (50, 6) and not np.allclose(first, second)  # fresh per slot and matching
    assert np.all(np.abs(np.asarray(first) - initial) <= 0.05 + 1e-6)


def matched_with_one_trajectory(name: str, trajectory: np.ndarray, stored_dims):
    """A curriculum of pool 8 and 4 slots after a matching with `trajectory` (L, O) as its only entry, its
    achieved goals the entries `stored_dims`."""
    curriculum = curriculum_of(name, pool_size=8, slots=4, segment_length=len(trajectory))
    state = curriculum.init(jax.random.PRNGKey(0))
    stored = np.asarray(trajectory)[:, list(stored_dims)]
    state = state.replace(pool_goals=state.pool_goals.at[0].set(stored),
                          pool_lengths=state.pool_lengths.at[0].set(len(trajectory)),
                          pool_first=state.pool_first.at[0].set(trajectory[0]), pool_count=jnp.asarray(1))
    value_fn = lambda obs, goal, key: jnp.zeros(obs.shape[0])  # noqa: E731
    return curriculum, curriculum.match(state, value_fn, jax.random.PRNGKey(1))


def test_matching_pads_a_young_pool_so_one_trajectory_serves_every_slot():
    # point_umaze: the point walks (0, 0) -> (4, 0) in 5 steps.
    steps = np.linspace(0.0, 1.0, 5)[:, None]
    trajectory = np.concatenate([4.0 * steps, np.zeros((5, 5))], axis=1).astype(np.float32)
    _, state = matched_with_one_trajectory("point_umaze", trajectory, (0, 1))
    # IBC's TrajectoryPool.pad repeats the one trajectory: every slot's backward goal is its first state,
    # every forward goal one of its points (none falls back to a target pair).
    np.testing.assert_array_equal(state.backward_slots, np.broadcast_to(trajectory[0], (4, 6)))
    for goal in np.asarray(state.forward_slots)[:, :2]:
        assert np.any(np.all(np.isclose(trajectory[:, :2], goal), axis=1))


def tabletop_trajectory() -> np.ndarray:
    """The mug carried from (2.5, 0) to (0, 2.5) in 5 steps with the gripper holding it (entries 4, 5 = 0)."""
    steps = np.linspace(0.0, 1.0, 5)[:, None]
    mug = (1 - steps) * np.array([2.5, 0.0]) + steps * np.array([0.0, 2.5])
    return np.concatenate([mug, mug, np.zeros((5, 2))], axis=1).astype(np.float32)


def test_earl_goals_are_whole_states_in_both_agents_inputs_and_the_curriculum():
    """IBC's EARL observation is [state, goal state]: the forward agent sees every goal entry there
    (env_utils.py), only the desired goal's entries (env.goal_dims) on the other tasks. The backward agent
    too (IBC's HER keeps the whole desired goal in its input; proprioceptive_only changes only the reward
    there), but it sees the gripper alone on the Fetch tasks."""
    seen_by = {"tabletop": (range(6), range(6)), "sawyer_door": (range(7), range(7)),
               "push": ((3, 4, 5), (0, 1, 2))}
    for name, (forward, backward) in seen_by.items():
        env = envs_mjx.make(name)
        learner = IBCLearner(IBCConfig(), env, ibc_task(env))
        size = env.observation_size
        for direction, seen in ((FORWARD, forward), (BACKWARD, backward)):
            goal_part = learner.policy_input(direction, jnp.zeros(size), jnp.arange(1.0, size + 1))[size:]
            assert np.flatnonzero(np.asarray(goal_part)).tolist() == list(seen), (name, direction)
    # The curriculum keeps whole states too: Tabletop's matched goals carry the trajectory's attachment
    # entries (4, 5), which env.goal_dims leave out.
    _, state = matched_with_one_trajectory("tabletop", tabletop_trajectory(), range(6))
    np.testing.assert_array_equal(np.asarray(state.forward_slots)[:, 4:], 0.0)


def stream_directions(state) -> tuple[np.ndarray, np.ndarray]:
    """Per buffer (forward, backward): the segment lengths of the ended segments."""
    out = []
    for buffer in state.replay:
        segment_ids = np.asarray(buffer.segment[:int(buffer.committed)])
        out.append(np.bincount(segment_ids) if len(segment_ids) else np.zeros(0, int))
    return tuple(out)


# ---- whole runs ------------------------------------------------------------------------------------

def train(run_dir, total_steps: int):
    config = ibc_config(f"run_dir={run_dir}", f"steps={total_steps}")
    return driver.train(config, seeds=SEEDS, programs=ibc_programs(), progress="off")


def test_two_chunk_run_writes_every_file_and_keeps_the_stream_rules(tmp_path):
    steps = PREFILL + 2 * CHUNK
    programs = ibc_programs()
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in SEEDS])
    prefilled = programs.prefill(programs.init(keys))
    # The only host round trip is the matching's assignment (every match_every forward segments).
    assert callback_primitives(programs.collect.trace(prefilled).jaxpr.jaxpr) == {"pure_callback"}
    summaries = train(tmp_path, steps)
    assert [s.env_steps for s in summaries] == [steps] * len(SEEDS)
    assert programs.collect._cache_size() == 1
    for seed in SEEDS:
        run_dir = tmp_path / f"seed{seed}"
        config = json.loads((run_dir / "config.json").read_text())
        assert config["run"]["agent"] == "ibc" and config["baseline"]["ibc"]["sac"]["hidden_depth"] == 3
        records = read_metrics(run_dir / "metrics.jsonl")
        assert [r["step"] for r in records if "train/updates" in r] == [PREFILL + CHUNK, steps]
        last = [r for r in records if "train/updates" in r][-1]
        assert last["replay/size"] == steps and 0 < last["train/updates"] <= 2 * CHUNK
        assert last["curriculum/matches"] >= 2 and last["curriculum/pool"] > 0
        assert any("eval/success" in r and "eval/final_success" in r for r in records)
        assert any("visitation/task_relevant" in r for r in records)
        assert all(np.isfinite(v) for r in records for v in r.values())
        assert list((run_dir / "tb").glob("events.out.tfevents.*"))
        assert list((run_dir / "plots").glob("visitation_*.npy"))
        assert str(steps) in {p.name for p in (run_dir / "checkpoints").iterdir()}
    # The stream's rules in the first seed's replay: segments end at SEGMENT steps at most, and each
    # backward segment follows a failed forward one, so there are never more backward than forward segments.
    state = final_state(tmp_path / "seed0", ibc_programs(), SEEDS)[1]
    forward_lengths, backward_lengths = stream_directions(state)
    assert forward_lengths.max() <= SEGMENT and backward_lengths.max() <= SEGMENT
    failed_forward = int(np.sum(forward_lengths == SEGMENT))  # (or succeeded on the last step)
    assert 0 < len(backward_lengths) <= failed_forward


def test_resume_after_sigkill_is_bit_exact(tmp_path):
    full_dir, killed_dir = tmp_path / "full", tmp_path / "killed"
    three = PREFILL + 3 * CHUNK
    train(full_dir, three)
    group = [arg for arg in debug_args("agent=ibc", *IBC_ARGS) if not arg.startswith("seed=")] + ["seeds=0,1"]
    done = sigkilled_after([*group, f"steps={PREFILL + 40 * CHUNK}", f"run_dir={killed_dir}"],
                           killed_dir / f"seed{SEEDS[-1]}" / "checkpoints", PREFILL + CHUNK)
    assert done < three, f"killed too late: step {done}"
    train(killed_dir, three)
    for seed in SEEDS:
        a_dir, b_dir = full_dir / f"seed{seed}", killed_dir / f"seed{seed}"
        (step_a, state_a), (step_b, state_b) = (final_state(d, ibc_programs(), SEEDS) for d in (a_dir, b_dir))
        assert step_a == step_b == three
        assert int(state_a.curriculum.matches) >= 2  # the matching ran, and resumed alike
        assert_same_run(a_dir, state_a, b_dir, state_b)


@pytest.mark.parametrize(("arguments", "message"), [
    (["baseline.ibc.her_relabel=2"], "baseline.ibc.her_relabel=2: her_relabel must be in [0, 1], got 2.0"),
    (["baseline.ibc.pool_size=10"], "baseline.ibc.pool_size (10) must be >= baseline.ibc.slots (50)"),
    (["baseline.ibc.sac.weight_init=he"], "unknown weight_init 'he'; valid: xavier, orthogonal"),
    (["baseline.ibc.sac.actor_update_every=0"], "actor_update_every must be > 0, got 0"),
    (["baseline.ibc.segment_length=0"], "segment_length must be > 0, got 0"),
])
def test_bad_ibc_input_exits_2_with_one_line(arguments, message, capsys):
    assert_train_cli_error(capsys, ["env=tabletop", "agent=ibc", *arguments], message)
