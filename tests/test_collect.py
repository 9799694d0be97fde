"""The fused chunk collection: phases, early switch, hard resets, goal choice; compiled once, no callbacks.

Most tests drive collect_chunk with a scripted stand-in agent (known actions, a learned distance read from
its "parameters", a planner score with a known optimum) so the numbers are exact; the last ones compile the
real debug agent's chunk function of a run (shared with test_loop through run_helpers). The stream is
tabletop's (run_helpers.RUN_ENV): its kinematic step compiles in about a second, where point_umaze's MJX
physics costs ~20 s in each of the seven chunk programs here; the chunk logic is the same for every task.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs_mjx.tabletop import GOAL_STATES, INITIAL_STATE
from morefree_jax.agent import MODE_EXPLORE
from morefree_jax.collect import CollectConfig, collect_chunk, init_stream, peg_goal_scores
from morefree_jax.goal_schedule import GoalType, ScheduleConfig, init_schedule
from morefree_jax.planner import PlannerConfig, peg_score, start_search
from tests.conftest import cached_env
from tests.run_helpers import RUN_ENV, callback_primitives, debug_run, hlo_has_callback

GO_ACTION = np.array([0.5, 0.0, 0.0], np.float32)  # tabletop: gripper +0.1 in x per step, no grasp
EXPLORE_ACTION = np.array([-0.5, 0.1, 0.0], np.float32)
# Optimum of the stand-in planner score, inside tabletop's observation bounds (the goal search's box).
TARGET = np.array([1.5, -2.0, 1.0, 1.0, -0.5, -0.5], np.float32)


class ScriptedAgent(NamedTuple):
    """Stand-in for agent.Agent. latent = number of observations filtered since the last reset;
    goal_distance = agent_state["distance"]; planner score = -||candidate - TARGET||^2."""

    def initial_latent(self, batch_shape=()):
        return jnp.zeros(batch_shape, jnp.int32)

    def act(self, state, latent, prev_action, obs, goal, key, mode):
        explore = (jnp.asarray(mode) & MODE_EXPLORE) != 0
        return jnp.where(explore, EXPLORE_ACTION, GO_ACTION), latent + 1

    def goal_distance(self, state, latent, goal, obs=None):
        return state["distance"]

    def imagine_to_goals(self, state, start, goals, horizon, key):
        return goals  # (G, O), the "trajectory" handed to exploration_value

    def exploration_value(self, state, goals):
        score = -jnp.sum(jnp.square(goals - TARGET), axis=-1)
        return jnp.zeros((3, goals.shape[0])), jnp.broadcast_to(score, (2, goals.shape[0]))


AGENT = ScriptedAgent()
PLANNER = PlannerConfig(method="cem", num_candidates=200, iterations=6, init_std=3.0, horizon=2,
                        use_last_steps=None, init_mean="current")


@functools.cache
def compiled_chunk(cfg: CollectConfig, schedule_cfg: ScheduleConfig, planner_cfg: PlannerConfig = PLANNER):
    env = cached_env(RUN_ENV)
    return jax.jit(functools.partial(collect_chunk, env, AGENT, cfg, planner_cfg, schedule_cfg))


def fresh(schedule_cfg: ScheduleConfig):
    env = cached_env(RUN_ENV)
    return (init_stream(env, AGENT, jax.random.PRNGKey(1)), init_schedule(env.observation_size),
            start_search(PLANNER, jnp.zeros(env.observation_size)))


MAIN = CollectConfig(go_steps=50, explore_steps=50, subgoal_threshold=5.0, hard_reset_every=37)
BACK_AND_FORTH = ScheduleConfig(kind="back_and_forth", alpha=0.2)


def run_chunk(distance: float, cfg=MAIN, schedule_cfg=BACK_AND_FORTH, start=None, key=0, planner_cfg=PLANNER):
    stream, schedule, planner = start or fresh(schedule_cfg)
    return compiled_chunk(cfg, schedule_cfg, planner_cfg)({"distance": jnp.float32(distance)}, stream,
                                                          schedule, planner, jax.random.PRNGKey(key))


def test_go_phase_lasts_h_g_steps_when_the_learned_distance_stays_above_threshold():
    stream, _, _, transitions, metrics = run_chunk(distance=10.0)
    actions, resets = np.asarray(transitions.action), np.asarray(transitions.reset)
    assert metrics["go/steps"] == 50 and metrics["go/active_at_end"] == 0
    assert np.flatnonzero(resets).tolist() == [0, 37, 74]  # stream positions 0, 37, 74
    moved = ~resets
    assert np.all(actions[:50][moved[:50]] == GO_ACTION)
    assert np.all(actions[50:][moved[50:]] == EXPLORE_ACTION)
    assert np.all(actions[resets] == 0.0)
    assert int(stream.steps) == 100 and int(stream.latent) == 100 - 75  # filtered since the reset at 74


def test_go_phase_switches_on_the_first_checked_step_below_threshold():
    _, _, _, transitions, metrics = run_chunk(distance=1.0)
    # step 0 is the hard reset (no check), step 1 is checked and switches
    assert metrics["go/steps"] == 2
    assert np.all(np.asarray(transitions.action)[2:][~np.asarray(transitions.reset)[2:]] == EXPLORE_ACTION)


def test_replay_transitions_are_the_stream_observations_and_reset_starts_at_an_initial_state():
    stream, _, _, transitions, _ = run_chunk(distance=10.0)
    obs = np.asarray(transitions.obs)
    assert np.allclose(obs[-1], np.asarray(stream.env_state.obs))
    env = cached_env(RUN_ENV)
    np.testing.assert_array_equal(obs[[0, 37, 74]], np.tile(INITIAL_STATE, (3, 1)))  # resets land on it
    assert bool(env.task_relevant(jnp.asarray(obs[37])))


def test_planner_chunk_goal_comes_from_the_search():
    schedule_cfg = ScheduleConfig(kind="planner")
    stream, schedule, planner, _, metrics = run_chunk(10.0, schedule_cfg=schedule_cfg)
    assert metrics["goal/searched"] == 1 and metrics["goal/type"] == GoalType.PLANNER
    np.testing.assert_allclose(np.asarray(planner.mean), TARGET, atol=0.3)
    np.testing.assert_allclose(np.asarray(stream.goal)[:2], TARGET[:2], atol=1.0)


@pytest.mark.parametrize("schedule_cfg", [ScheduleConfig(kind="planner"), BACK_AND_FORTH],
                         ids=["rf_peg", "morefree"])
def test_every_planner_chunk_runs_a_fresh_search(schedule_cfg):
    """Reset-free PEG optimises the goal distribution every H_G + H_E steps (paper appendix); MoReFree
    keeps that for its planner chunks. Counted by the planner state over 12 chunks."""
    start, types = fresh(schedule_cfg), []
    for key in range(12):
        outputs = run_chunk(10.0, schedule_cfg=schedule_cfg, start=start, key=key)
        start, planner, metrics = outputs[:3], outputs[2], outputs[4]
        types.append(int(metrics["goal/type"]))
        assert metrics["goal/searched"] == (types[-1] == GoalType.PLANNER)
        # A fresh search starts from N(current obs, 3) and needs its iterations: first-round score is low.
        if types[-1] == GoalType.PLANNER:
            assert float(metrics["planner/score_first"]) < float(metrics["planner/score"]) - 1.0
    planner_chunks = int(np.sum(np.array(types) == GoalType.PLANNER))
    assert int(planner.searches) == planner_chunks > 0
    if schedule_cfg.kind == "planner":
        assert planner_chunks == 12


def test_a_hard_reset_due_on_the_first_step_comes_before_the_goal_choice():
    """With a near-zero search spread around the current observation, the planner goal is the state the
    goal was chosen from: it must be the reset state, not where the previous chunk ended."""
    cfg = CollectConfig(go_steps=50, explore_steps=50, subgoal_threshold=5.0, hard_reset_every=100)
    schedule_cfg = ScheduleConfig(kind="planner")
    pinned = PlannerConfig(method="cem", num_candidates=8, iterations=1, init_std=1e-4, horizon=2,
                           use_last_steps=None, init_mean="current")
    first = run_chunk(10.0, cfg, schedule_cfg, planner_cfg=pinned)
    end_of_first = np.asarray(first[0].env_state.obs)
    assert int(first[0].steps) == 100 and np.linalg.norm(end_of_first - INITIAL_STATE) > 2.0  # far from it
    stream, _, _, transitions, metrics = run_chunk(10.0, cfg, schedule_cfg, start=first[:3], key=1,
                                                   planner_cfg=pinned)
    reset_obs = np.asarray(transitions.obs[0])
    assert bool(transitions.reset[0]) and not np.any(np.asarray(transitions.reset[1:]))  # reset once
    np.testing.assert_array_equal(reset_obs, INITIAL_STATE)
    np.testing.assert_allclose(np.asarray(stream.goal), reset_obs, atol=0.01)
    assert metrics["collect/hard_resets"] == 1


def test_episodic_goal_and_phases_span_the_hard_reset_segment():
    cfg = CollectConfig(go_steps=50, explore_steps=50, subgoal_threshold=5.0, hard_reset_every=200,
                        episodic=True)
    schedule_cfg = ScheduleConfig(kind="episodic_planner")
    start, goals, go_steps = fresh(schedule_cfg), [], []
    for key in range(3):
        stream, schedule, planner, _, metrics = run_chunk(10.0, cfg, schedule_cfg, start, key=key)
        start = (stream, schedule, planner)
        goals.append(np.asarray(stream.goal))
        go_steps.append(float(metrics["go/steps"]))
    assert go_steps == [100.0, 0.0, 100.0]  # first half of each 200-step segment goes
    np.testing.assert_array_equal(goals[0], goals[1])
    assert not np.array_equal(goals[1], goals[2])  # a new segment, a new goal


def test_episodic_segment_starting_inside_a_chunk_takes_its_goal_at_the_next_chunk():
    """sawyer_door's case: hard resets (every 250 here) that chunks (100) do not line up with. The reset at
    250 falls inside the third chunk, which explores on; the fourth (from 300) chooses the new segment's goal
    and goes until the segment's midpoint, 375."""
    cfg = CollectConfig(go_steps=50, explore_steps=50, subgoal_threshold=5.0, hard_reset_every=250,
                        episodic=True)
    schedule_cfg = ScheduleConfig(kind="episodic_planner")
    start, goals, go_steps, resets = fresh(schedule_cfg), [], [], []
    for key in range(5):
        stream, schedule, planner, transitions, metrics = run_chunk(10.0, cfg, schedule_cfg, start, key=key)
        start = (stream, schedule, planner)
        goals.append(np.asarray(stream.goal))
        go_steps.append(float(metrics["go/steps"]))
        resets.append(np.flatnonzero(np.asarray(transitions.reset)).tolist())
    assert resets == [[0], [], [50], [], []]  # stream positions 0 and 250
    assert go_steps == [100.0, 25.0, 0.0, 75.0, 0.0]
    assert all(np.array_equal(goals[0], g) for g in goals[1:3])
    assert not np.array_equal(goals[2], goals[3]) and np.array_equal(goals[3], goals[4])


def test_eval_only_without_explore_goes_the_whole_chunk_to_the_eval_goal():
    cfg = CollectConfig(go_steps=100, explore_steps=0, subgoal_threshold=5.0, hard_reset_every=10**6,
                        explore=False)
    schedule_cfg = ScheduleConfig(kind="eval_only")
    stream, _, _, transitions, metrics = run_chunk(0.0, cfg, schedule_cfg)
    assert metrics["go/steps"] == 100 and metrics["goal/type"] == GoalType.EVAL
    assert any(np.array_equal(np.asarray(stream.goal), goal) for goal in GOAL_STATES)  # one of the 4 pads
    assert np.all(np.asarray(transitions.action)[1:] == GO_ACTION)


# ---- the real agent's chunk function (debug preset) ------------------------------------------------

def test_callback_detector_sees_a_debug_callback():
    def noisy(x):
        def body(c, _):
            jax.debug.callback(lambda v: None, c)
            return c + 1, None
        return jax.lax.scan(body, x, None, length=3)[0]

    assert callback_primitives(jax.make_jaxpr(noisy)(1.0).jaxpr)
    assert hlo_has_callback(jax.jit(noisy), 1.0)


def test_chunk_function_compiles_once_and_has_no_host_callback():
    programs, state = debug_run("morefree")
    jaxpr = jax.make_jaxpr(programs.fns.collect)(jax.tree.map(lambda x: x[0], state))
    assert not callback_primitives(jaxpr.jaxpr)
    assert not hlo_has_callback(programs.collect, state)
    for _ in range(2):
        state, metrics = programs.collect(state)
    assert programs.collect._cache_size() == 1  # also after the restored runs of test_loop (same entry)
    assert all(np.isfinite(np.asarray(v)).all() for v in metrics.values())


def test_goal_scores_on_the_last_steps_equal_the_full_computation():
    programs, state = debug_run("morefree")
    state = jax.tree.map(lambda x: x[0], state)
    agent = programs.fns.agent
    candidates = jax.random.uniform(jax.random.PRNGKey(3), (6, 6), minval=0.0, maxval=8.0)
    config = PlannerConfig(horizon=12, use_last_steps=4)

    @jax.jit
    def both(agent_state, key):
        start = agent.initial_latent()
        trajectory = agent.imagine_to_goals(agent_state, start, candidates, config.horizon, key)
        reward, returns = agent.exploration_value(agent_state, trajectory)
        full = peg_score(reward, returns, config.use_last_steps)
        return full, peg_goal_scores(agent, agent_state, start, candidates, config, key)

    full, trimmed = both(state.agent, jax.random.PRNGKey(4))
    assert np.all(np.isfinite(np.asarray(full))) and float(jnp.std(full)) > 0
    np.testing.assert_allclose(np.asarray(trimmed), np.asarray(full), rtol=1e-5, atol=1e-5)
