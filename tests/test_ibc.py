"""The ibc agent: hindsight relabelling on a hand-made replay, the curriculum's costs and matching against
hand-computed answers, IBC's segment switching, a whole two-chunk run through loop.train (two seeds in one
program), exact resume after SIGKILL, and bad input. The generalised SAC learner is in test_sac.py."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pathlib
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from experiments import train as train_cli
from morefree_jax import loop
from morefree_jax.baselines import curriculum as curriculum_lib
from morefree_jax.baselines import her, sac
from morefree_jax.baselines.config import IBCConfig
from morefree_jax.baselines.curriculum import Curriculum
from morefree_jax.baselines.ibc import BACKWARD, FORWARD, IBCLearner
from morefree_jax.baselines.ibc_run import IBCParts
from morefree_jax.baselines.ibc_tasks import corridor_points, ibc_task
from morefree_jax.checkpoint import latest_valid
from morefree_jax.config_run import resolve_config
from morefree_jax.logger import read_metrics
from morefree_jax.programs import seed_slice
from tests.loop_helpers import (
    COMPILATION_CACHE,
    assert_same_run,
    callback_primitives,
    debug_args,
    sigkill_once_written,
)

REPO = pathlib.Path(__file__).resolve().parents[1]
PREFILL, CHUNK, SEGMENT = 100, 50, 10
SEEDS = (0, 1)
# Tiny learners, pool and segments (tabletop's kinematic step compiles fast, loop_helpers.RUN_ENV): 200 steps
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
    return loop.build_programs(ibc_config("steps=200"), len(SEEDS))


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


def test_her_relabels_with_future_goals_of_the_same_segment_and_keeps_a_fifth():
    buffer = hand_made_buffer()
    assert int(buffer.committed) == 4 and int(buffer.count) == 7 and buffer.segment_end[0] == 3
    success = lambda obs, goal: jnp.abs(obs[0] - goal[0]) < 0.5  # noqa: E731
    mask = jnp.array([1.0, 0.0])  # the agent sees goal x only
    batch = her.sample_her(buffer, jax.random.PRNGKey(0), 1000, 0.8, success, mask)
    obs_x, next_x, goal_x = (np.asarray(a) for a in (batch.obs[:, 0], batch.next_obs[:, 0], batch.obs[:, 2]))
    assert set(obs_x.tolist()) == {0.0, 1.0, 2.0, 3.0}  # segment B is still open: never drawn
    relabelled, original = slice(0, 800), slice(800, 1000)
    assert np.all(goal_x[original] == 100.0) and np.all(batch.reward[original] == -1.0)
    assert np.all(goal_x[relabelled] >= next_x[relabelled]) and np.all(goal_x[relabelled] <= 4.0)
    np.testing.assert_array_equal(batch.reward, np.where(goal_x == next_x, 0.0, -1.0))
    np.testing.assert_array_equal(batch.obs[:, 3], 0.0)  # masked goal dim
    assert np.all(batch.not_done == 1.0)  # IBC never masks the bootstrap
    # A transition at x = 3 (the segment's last) can only be relabelled with its own next state.
    assert np.all(goal_x[relabelled][obs_x[relabelled] == 3.0] == 4.0)
    reached = np.mean(batch.reward[relabelled] == 0.0)
    assert 0.35 < reached < 0.65  # E[1 / (4 - x)] over x = 0..3 = 0.52


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
        following, _ = parts.next_segment(stream, state.curriculum, stream.env_state, success, end, reset,
                                          jax.random.PRNGKey(1))
        return end, following

    for (direction, success, segment_step), (ends, next_direction) in SWITCH_CASES:
        end, following = switch(jnp.asarray(direction, jnp.int32), jnp.asarray(success),
                                jnp.asarray(segment_step, jnp.int32))
        assert bool(end) == ends and int(following.direction) == next_direction
        assert int(following.segment_step) == (0 if ends else segment_step + 1)
        if ends and next_direction == BACKWARD:  # a proprioceptive goal near the slot's start: gripper xy
            start = state.curriculum.backward_slots[state.curriculum.slot]
            noise = parts.curriculum.task.backward_noise
            assert np.all(np.abs(following.goal[:2] - start[:2]) <= noise + 1e-6)


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
    return loop.train(config, seeds=SEEDS, programs=ibc_programs(), progress="off")


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
    state = _final_state(tmp_path / "seed0")[1]
    forward_lengths, backward_lengths = stream_directions(state)
    assert forward_lengths.max() <= SEGMENT and backward_lengths.max() <= SEGMENT
    failed_forward = int(np.sum(forward_lengths == SEGMENT))  # (or succeeded on the last step)
    assert 0 < len(backward_lengths) <= failed_forward


def _final_state(run_dir):
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in SEEDS])
    template = seed_slice(ibc_programs().init(keys), 0)
    config_dict = json.loads((pathlib.Path(run_dir) / "config.json").read_text())
    restored = latest_valid(run_dir, template, config_dict)
    return restored.step, restored.state


def test_resume_after_sigkill_is_bit_exact(tmp_path):
    full_dir, killed_dir = tmp_path / "full", tmp_path / "killed"
    three = PREFILL + 3 * CHUNK
    train(full_dir, three)
    env = {**os.environ, "PYTHONPATH": "src:.", "JAX_COMPILATION_CACHE_DIR": COMPILATION_CACHE,
           "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
    group = [arg for arg in debug_args("agent=ibc", *IBC_ARGS) if not arg.startswith("seed=")] + ["seeds=0,1"]
    command = [sys.executable, "-m", "experiments.train", *group,
               f"steps={PREFILL + 40 * CHUNK}", f"run_dir={killed_dir}"]
    process = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    last_seed = killed_dir / f"seed{SEEDS[-1]}"  # the group's checkpoint is complete once it has it
    sigkill_once_written(process, last_seed / "checkpoints" / str(PREFILL + CHUNK) / "files.json")
    done = max(int(p.name) for p in (last_seed / "checkpoints").iterdir() if p.name.isdigit())
    assert done < three, f"killed too late: step {done}"
    train(killed_dir, three)
    for seed in SEEDS:
        a_dir, b_dir = full_dir / f"seed{seed}", killed_dir / f"seed{seed}"
        (step_a, state_a), (step_b, state_b) = _final_state(a_dir), _final_state(b_dir)
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
    assert train_cli.main(["env=tabletop", "agent=ibc", *arguments]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
