"""Goal schedules over many simulated chunks: shares, forth -> back pairing, re-planning cadence."""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from morefree_jax.go_explore import (
    GOAL_TYPE_NAMES,
    GoalType,
    ScheduleConfig,
    choose_goal_type,
    commit_goal,
    init_schedule,
    next_chunk_goal,
    pair_start_probability,
    schedule_metrics,
)
from morefree_jax.planner import PlannerState

NUM_CHUNKS = 10_000
GOAL_SIZE = 3


@functools.cache
def simulate(config: ScheduleConfig, num_chunks: int = NUM_CHUNKS):
    """Runs the schedule for num_chunks chunks in one lax.scan. Goals are tagged by construction:
    eval goals are (1, i, 0), initial goals (2, i, 0), planner goals (0, i, 0) for chunk i."""

    @jax.jit
    def run(key):
        def chunk(state, key_chunk):
            index = state.chunk.astype(jnp.float32)
            choice = choose_goal_type(config, state, key_chunk)
            goal, state = commit_goal(
                config, state, choice,
                eval_goal=jnp.array([1.0, index, 0.0]),
                initial_goal=jnp.array([2.0, index, 0.0]),
                planner_goal=jnp.array([0.0, index, 0.0]),
            )
            return state, (choice.goal_type, choice.replan, goal)

        return jax.lax.scan(chunk, init_schedule(GOAL_SIZE, config), jax.random.split(key, num_chunks))

    final, (types, replans, goals) = run(jax.random.PRNGKey(0))
    return final, np.asarray(types), np.asarray(replans), np.asarray(goals)


def test_back_and_forth_shares_and_pairing():
    config = ScheduleConfig(kind="back_and_forth", alpha=0.2)
    final, types, _, goals = simulate(config)
    forth, back = types == GoalType.EVAL, types == GoalType.INITIAL
    # alpha/2 = 0.1 of the chunks go forth, 0.1 back, 0.8 plan. Pairs start on free chunks with p = 1/9:
    # about 1000 pairs, sd ~ sqrt(9000 * 1/9 * 8/9) ~ 30 -> share sd 0.003; tolerance 4 sd.
    assert abs(forth.mean() - 0.1) < 0.012, forth.mean()
    assert abs(back.mean() - 0.1) < 0.012, back.mean()
    assert abs((types == GoalType.PLANNER).mean() - 0.8) < 0.024
    # Every forth chunk is followed by a back chunk, and every back chunk follows a forth chunk.
    forth_index = np.flatnonzero(forth[:-1])
    assert np.all(back[forth_index + 1])
    assert np.all(forth[np.flatnonzero(back) - 1])
    # Goals match their types; the back goal is the initial state sampled with its forth chunk.
    np.testing.assert_array_equal(goals[:, 0], types.astype(np.float32))
    np.testing.assert_array_equal(goals[forth_index + 1, 1], goals[forth_index, 1])
    np.testing.assert_array_equal(np.asarray(final.type_counts), np.bincount(types, minlength=3))


def test_pair_probability_reading_of_alpha():
    assert pair_start_probability(0.2) == pytest.approx(1 / 9)
    assert pair_start_probability(0.0) == 0.0 and pair_start_probability(1.0) == 1.0
    _, types, replans, _ = simulate(ScheduleConfig(kind="back_and_forth", alpha=1.0), 200)
    np.testing.assert_array_equal(types, np.tile([GoalType.EVAL, GoalType.INITIAL], 100))
    assert not replans.any()


@pytest.mark.parametrize("config", [
    ScheduleConfig(kind="planner", alpha=0.2),  # rf_peg ignores alpha
    ScheduleConfig(kind="back_and_forth", alpha=0.0),  # mf_no_bfge
    ScheduleConfig(kind="episodic_planner"),
], ids=["rf_peg", "bfge_alpha0", "episodic_peg"])
def test_planner_schedules_never_use_task_goals(config):
    _, types, replans, goals = simulate(config)
    assert np.all(types == GoalType.PLANNER) and np.all(goals[:, 0] == 0.0)
    # Re-optimise at the first chunk and then every goal_update_every (50) chunks: 200 searches.
    np.testing.assert_array_equal(np.flatnonzero(replans), np.arange(0, NUM_CHUNKS, 50))


def test_replanning_counts_all_chunks_and_waits_for_a_planner_chunk():
    _, types, replans, _ = simulate(ScheduleConfig(kind="back_and_forth", alpha=0.2, goal_update_every=5))
    assert np.all(types[replans] == GoalType.PLANNER)
    replan_index = np.flatnonzero(replans)
    assert replan_index[0] == np.flatnonzero(types == GoalType.PLANNER)[0]
    assert np.all(np.diff(replan_index) >= 5)
    # Between searches a and b, no planner chunk at least 5 chunks after a goes without a search.
    for a, b in zip(replan_index[:-1], replan_index[1:], strict=True):
        assert not np.any(types[a + 5:b] == GoalType.PLANNER), (a, b)
    # 80% of chunks are planner chunks, so a search is rarely delayed much beyond 5 chunks.
    assert 5.0 < np.diff(replan_index).mean() < 7.0


def test_eval_only_always_uses_eval_goals():
    _, types, replans, goals = simulate(ScheduleConfig(kind="eval_only"), 500)
    assert np.all(types == GoalType.EVAL) and not replans.any() and np.all(goals[:, 0] == 1.0)


def test_phase_lengths_metrics_and_validation():
    assert ScheduleConfig().phase_lengths(eval_episode_length=101, hard_reset_every=200_000) == (50, 51)
    episodic = ScheduleConfig(kind="episodic_planner")
    assert episodic.resets_every_chunk and episodic.phase_lengths(100, 400) == (200, 200)
    config = ScheduleConfig()
    state = init_schedule(GOAL_SIZE, config)
    choice = choose_goal_type(config, state, jax.random.PRNGKey(0))
    _, state = commit_goal(config, state, choice, jnp.ones(3), 2 * jnp.ones(3), jnp.zeros(3))
    metrics = schedule_metrics(choice, state)
    assert set(metrics) == {"goal/type", "goal/replanned"} | {f"goal/share_{n}" for n in GOAL_TYPE_NAMES}
    assert float(sum(metrics[f"goal/share_{n}"] for n in GOAL_TYPE_NAMES)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="schedule kind must be one of"):
        ScheduleConfig(kind="random")
    with pytest.raises(ValueError, match="alpha"):
        ScheduleConfig(alpha=1.5)


def test_next_chunk_goal_searches_only_when_due_and_compiles_once():
    config = ScheduleConfig(kind="planner", goal_update_every=3)
    low, high = -jnp.ones(GOAL_SIZE) * 100, jnp.ones(GOAL_SIZE) * 100

    def fake_search(planner_state, key):
        # A "search" moves the Gaussian's mean by +1 and returns a goal tagged 50 + new mean.
        new_state = planner_state.replace(mean=planner_state.mean + 1.0)
        return new_state.mean + 50.0, new_state, {"planner/score": jnp.float32(7.0)}

    @chex.assert_max_traces(n=1)
    def step(schedule_state, planner_state, key):
        return next_chunk_goal(config, schedule_state, planner_state, key, jnp.ones(GOAL_SIZE),
                               2 * jnp.ones(GOAL_SIZE), fake_search, low, high)

    step = jax.jit(step)
    schedule_state = init_schedule(GOAL_SIZE, config)
    planner_state = PlannerState(mean=jnp.zeros(GOAL_SIZE), std=jnp.zeros(GOAL_SIZE), score=jnp.zeros(()))
    goals, scores = [], []
    for index in range(7):
        goal, choice, schedule_state, planner_state, metrics = step(
            schedule_state, planner_state, jax.random.PRNGKey(index))
        goals.append(float(goal[0]))
        scores.append(float(metrics["planner/score"]))
    # Searches at chunks 0, 3, 6 (goal 50 + mean); in between, samples of the stored Gaussian (std 0: mean).
    assert goals == [51.0, 1.0, 1.0, 52.0, 2.0, 2.0, 53.0]
    assert scores == [7.0, 0.0, 0.0, 7.0, 0.0, 0.0, 7.0]
    assert int(schedule_state.type_counts[GoalType.PLANNER]) == 7
