"""Goal schedules over many simulated chunks: shares, forth -> back pairs, a search on every planner chunk."""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from morefree_jax.goal_schedule import (
    GOAL_TYPE_NAMES,
    GoalType,
    ScheduleConfig,
    choose_goal_type,
    commit_goal,
    init_schedule,
    next_chunk_goal,
    schedule_metrics,
)
from morefree_jax.planner import PlannerState

NUM_CHUNKS = 10_000
NUM_DECISIONS = 30_000
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
            return state, (choice.goal_type, choice.search, goal)

        return jax.lax.scan(chunk, init_schedule(GOAL_SIZE), jax.random.split(key, num_chunks))

    final, (types, searches, goals) = run(jax.random.PRNGKey(0))
    return final, np.asarray(types), np.asarray(searches), np.asarray(goals)


def test_back_and_forth_follows_the_paper_algorithm_literally():
    config = ScheduleConfig(kind="back_and_forth", alpha=0.2)
    # 30,000 decisions yield ~36,000 chunks (a decision is a forth + back pair with probability 0.2).
    final, types, searches, goals = simulate(config, 37_000)
    forth, back = types == GoalType.EVAL, types == GoalType.INITIAL
    decisions = np.flatnonzero(~back)  # every chunk that is not the back half of a pair draws r
    end = decisions[NUM_DECISIONS]  # the first chunk of decision 30,001
    forth, back, planner_chunks = forth[:end], back[:end], types[:end] == GoalType.PLANNER
    # Alg. alg:bfge: P(pair) = alpha per decision, so the task share is 2 alpha / (1 + alpha) = 1/3
    # (forth 1/6, back 1/6). Pairs ~ Binomial(30000, 0.2): sd 69 pairs -> task-share sd ~0.0014; bar 0.01.
    task_share = (forth.sum() + back.sum()) / end
    assert abs(task_share - 1 / 3) < 0.01, task_share
    assert config.task_chunk_share() == pytest.approx(1 / 3)
    assert abs(forth.sum() / NUM_DECISIONS - 0.2) < 0.01  # the draw itself: alpha per decision
    # Every forth chunk is followed by a back chunk, and every back chunk follows a forth chunk.
    forth_index = np.flatnonzero(forth[:-1])
    assert np.all(back[forth_index + 1])
    assert np.all(forth[np.flatnonzero(back) - 1])
    # Goals match their types; the back goal is the initial state sampled with its forth chunk.
    np.testing.assert_array_equal(goals[:, 0], types.astype(np.float32))
    np.testing.assert_array_equal(goals[forth_index + 1, 1], goals[forth_index, 1])
    np.testing.assert_array_equal(np.asarray(final.type_counts), np.bincount(types, minlength=3))
    # The goal search runs on every planner chunk and on no task chunk.
    np.testing.assert_array_equal(searches[:end], planner_chunks)


def test_alpha_one_only_goes_back_and_forth():
    _, types, searches, _ = simulate(ScheduleConfig(kind="back_and_forth", alpha=1.0), 200)
    np.testing.assert_array_equal(types, np.tile([GoalType.EVAL, GoalType.INITIAL], 100))
    assert not searches.any()


@pytest.mark.parametrize("config", [
    ScheduleConfig(kind="planner", alpha=0.2),  # rf_peg ignores alpha
    ScheduleConfig(kind="back_and_forth", alpha=0.0),  # mf_no_bfge
    ScheduleConfig(kind="episodic_planner"),
], ids=["rf_peg", "bfge_alpha0", "episodic_peg"])
def test_planner_schedules_never_use_task_goals_and_search_every_chunk(config):
    _, types, searches, goals = simulate(config)
    assert np.all(types == GoalType.PLANNER) and np.all(goals[:, 0] == 0.0)
    assert searches.all()  # a fresh search on every chunk (episodic PEG makes one choice per segment)
    assert config.task_chunk_share() == 0.0


def test_eval_only_always_uses_eval_goals():
    _, types, replans, goals = simulate(ScheduleConfig(kind="eval_only"), 500)
    assert np.all(types == GoalType.EVAL) and not replans.any() and np.all(goals[:, 0] == 1.0)


def test_phase_lengths_metrics_and_validation():
    assert ScheduleConfig().phase_lengths(eval_episode_length=101, hard_reset_every=200_000) == (50, 51)
    episodic = ScheduleConfig(kind="episodic_planner")
    assert episodic.resets_every_chunk and episodic.phase_lengths(100, 400) == (200, 200)
    config = ScheduleConfig()
    state = init_schedule(GOAL_SIZE)
    choice = choose_goal_type(config, state, jax.random.PRNGKey(0))
    _, state = commit_goal(config, state, choice, jnp.ones(3), 2 * jnp.ones(3), jnp.zeros(3))
    metrics = schedule_metrics(choice, state)
    assert set(metrics) == {"goal/type", "goal/searched"} | {f"goal/share_{n}" for n in GOAL_TYPE_NAMES}
    assert float(sum(metrics[f"goal/share_{n}"] for n in GOAL_TYPE_NAMES)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="schedule kind must be one of"):
        ScheduleConfig(kind="random")
    with pytest.raises(ValueError, match="alpha"):
        ScheduleConfig(alpha=1.5)


def test_next_chunk_goal_searches_on_every_planner_chunk_and_compiles_once():
    config = ScheduleConfig(kind="back_and_forth", alpha=0.5)

    def fake_search(planner_state, key):
        # A "search" moves the Gaussian's mean by +1 and returns a goal tagged 50 + new mean.
        new_state = planner_state.replace(mean=planner_state.mean + 1.0)
        return new_state.mean + 50.0, new_state, {"planner/score": jnp.float32(7.0)}

    @chex.assert_max_traces(n=1)
    def step(schedule_state, planner_state, key):
        return next_chunk_goal(config, schedule_state, planner_state, key, jnp.ones(GOAL_SIZE),
                               2 * jnp.ones(GOAL_SIZE), fake_search)

    step = jax.jit(step)
    schedule_state = init_schedule(GOAL_SIZE)
    planner_state = PlannerState(mean=jnp.zeros(GOAL_SIZE), std=jnp.zeros(GOAL_SIZE), score=jnp.zeros(()))
    types, goals, scores = [], [], []
    for index in range(12):
        goal, choice, schedule_state, planner_state, metrics = step(
            schedule_state, planner_state, jax.random.PRNGKey(index))
        types.append(int(choice.goal_type))
        goals.append(float(goal[0]))
        scores.append(float(metrics["planner/score"]))
    types = np.array(types)
    planner_chunks = types == GoalType.PLANNER
    assert 0 < planner_chunks.sum() < 12, types  # both kinds occur with these keys
    # The k-th planner chunk gets the k-th search's goal (50 + k); task chunks their eval / initial goal.
    goals = np.array(goals)
    np.testing.assert_array_equal(goals[planner_chunks], 50.0 + np.arange(1, planner_chunks.sum() + 1))
    np.testing.assert_array_equal(goals[~planner_chunks], types[~planner_chunks].astype(float))
    np.testing.assert_array_equal(np.array(scores), np.where(planner_chunks, 7.0, 0.0))
    assert int(planner_state.searches) == planner_chunks.sum()
