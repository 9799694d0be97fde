"""MEDAL: its demonstrations in the buffers, the discriminator's reward, the stream it steers (the task goal
kept across backward segments, goal-distribution backward goals, the policy acting in the seed phase), a
whole run and exact resume after SIGKILL. The shared model-free machinery is tested in test_stream.py."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from envs_mjx.tabletop import INITIAL_STATE
from morefree_jax import driver
from morefree_jax.baselines.baseline_config import ModelFreeConfig
from morefree_jax.baselines.medal import demos as demo_files
from morefree_jax.baselines.medal.agent import MEDAL
from morefree_jax.baselines.sac import rewards
from morefree_jax.baselines.sac.buffer import init_buffer, sample_from
from morefree_jax.baselines.sac.stream import BACKWARD, FORWARD, StreamParts
from morefree_jax.compile import seed_slice
from morefree_jax.logger import read_metrics
from tests.run_helpers import (
    assert_same_run,
    assert_train_cli_error,
    debug_args,
    final_state,
    sigkilled_after,
)
from tests.test_stream import CHUNK, MF_ARGS, PREFILL, SWITCH, mf_config

ENV = "tabletop"  # run_helpers.RUN_ENV: the fast-compiling kinematic step


@functools.cache
def env():
    return envs_mjx.make(ENV)


def synthetic_demos(count: int = 20):
    """Forward and reverse DemoSets whose rows are recognisable: observation column 0 holds 100 + row
    (forward) or 200 + row (reverse)."""
    size, actions = env().observation_size, env().action_size

    def demo(offset):
        obs = np.zeros((count, size), np.float32)
        obs[:, 0] = offset + np.arange(count)
        terminals = np.zeros(count, np.float32)
        terminals[-1] = 1.0
        return demo_files.DemoSet(observations=obs, goals=obs + 1.0, actions=np.zeros((count, actions),
                                  np.float32), rewards=terminals.copy(), terminals=terminals,
                                  next_observations=obs + 0.5)

    return {"forward": demo(100), "reverse": demo(200)}


def test_buffers_start_with_the_demonstrations():
    medal = MEDAL(ModelFreeConfig(), env(), synthetic_demos())
    empty = tuple(init_buffer(100, env().observation_size, env().action_size) for _ in range(2))
    forward, backward = medal.fill_buffers(empty, jax.random.PRNGKey(0))
    assert int(forward.count) == 20 and int(backward.count) == 40 == medal.backward_demo_count
    assert np.array_equal(forward.obs[:20, 0], 100 + np.arange(20))
    assert np.array_equal(forward.goal[:20, 0], 101 + np.arange(20))  # forward demos keep their goal
    assert forward.reward[19] == 1.0 and forward.not_done[19] == 0.0 and forward.not_done[0] == 1.0
    assert np.array_equal(backward.obs[:40, 0], np.concatenate([100 + np.arange(20), 200 + np.arange(20)]))
    goals = np.asarray(backward.goal[:40])  # relabelled: draws of the goal distribution, not the demos'
    assert not np.any(np.isin(goals[:, 0], forward.goal[:20, 0]))
    draws = np.asarray(jax.vmap(env().eval_goals)(jax.random.split(jax.random.PRNGKey(1), 200)))
    low, high = draws.min(0) - 1e-6, draws.max(0) + 1e-6
    assert np.all((goals >= low) & (goals <= high))


def test_negatives_come_from_past_the_demonstrations():
    medal = MEDAL(ModelFreeConfig(), env(), synthetic_demos())
    empty = tuple(init_buffer(60, env().observation_size, env().action_size) for _ in range(2))
    backward = medal.fill_buffers(empty, jax.random.PRNGKey(0))[BACKWARD]
    visited = backward.replace(obs=backward.obs.at[40:50, 0].set(-7.0), count=jnp.asarray(50))
    drawn = sample_from(visited, jax.random.PRNGKey(2), 300, start=medal.backward_demo_count)
    assert set(np.asarray(drawn.obs[:, 0]).tolist()) == {-7.0}
    # One more write wraps the ring onto slot 0: the stream's now; slots 1-39 still hold demonstrations.
    wrapped = visited.replace(obs=visited.obs.at[0, 0].set(-3.0), count=jnp.asarray(61))
    drawn = np.asarray(sample_from(wrapped, jax.random.PRNGKey(2), 300, start=40).obs[:, 0])
    assert set(drawn.tolist()) == {-3.0, -7.0, 0.0}
    overwritten = wrapped.replace(count=jnp.asarray(100))  # all 40 demonstration slots written over
    drawn = np.asarray(sample_from(overwritten, jax.random.PRNGKey(2), 300, start=40).obs[:, 0])
    assert np.any(drawn > 0.0) and {-3.0, -7.0, 0.0} <= set(drawn.tolist())


def test_visitation_counts_the_stream_not_the_demonstrations():
    """The heatmap and task-relevant share are where the stream went: demonstration rows (task-relevant
    here) are left out, the forward ones written to both buffers not counted twice, until the ring wraps."""
    config = mf_config("medal", "steps=200")
    medal = MEDAL(ModelFreeConfig(), env(), synthetic_demos())
    assert medal.demo_rows == (20, 40)
    empty = tuple(init_buffer(60, env().observation_size, env().action_size) for _ in range(2))
    far = np.array([2.0, 2.0, 2.4, 2.4, INITIAL_STATE[4], INITIAL_STATE[5]], np.float32)
    assert not bool(env().task_relevant(jnp.asarray(far))) and bool(env().task_relevant(INITIAL_STATE))
    buffers = []
    for buffer, demos in zip(medal.fill_buffers(empty, jax.random.PRNGKey(0)), medal.demo_rows, strict=True):
        obs = buffer.obs.at[:demos].set(INITIAL_STATE).at[demos:demos + 10].set(far)
        buffers.append(buffer.replace(obs=obs, count=jnp.asarray(demos + 10)))
    parts = StreamParts(config, env(), medal)
    views = parts.visitation(tuple(buffers))
    assert float(views["task_relevant"]) == 0.0 and float(jnp.sum(views["xy"])) == 20.0  # 10 stream rows each
    # The ring wraps onto slot 0: it counts (its row is still task-relevant here), slots 1-39 do not yet.
    wrapped = (buffers[0], buffers[1].replace(count=jnp.asarray(61)))
    views = parts.visitation(wrapped)
    assert float(jnp.sum(views["xy"])) == 10 + 21 and float(views["task_relevant"]) == pytest.approx(1 / 31)
    overwritten = (buffers[0], buffers[1].replace(count=jnp.asarray(100)))  # every demonstration slot
    views = parts.visitation(overwritten)
    assert float(jnp.sum(views["xy"])) == 10 + 60 and float(views["task_relevant"]) == pytest.approx(40 / 70)


def test_discriminator_reward_rises_on_demonstration_states():
    config = ModelFreeConfig()
    medal = MEDAL(config, env(), synthetic_demos())
    empty = tuple(init_buffer(100, env().observation_size, env().action_size) for _ in range(2))
    forward, backward = medal.fill_buffers(empty, jax.random.PRNGKey(0))
    backward = backward.replace(obs=backward.obs.at[40:100, 0].set(-50.0), count=jnp.asarray(100))
    state = medal.init(jax.random.PRNGKey(3))
    update = jax.jit(medal.update_discriminator)
    for step in range(200):
        state, loss = update(state, backward, jax.random.PRNGKey(step))
    demo = synthetic_demos()["forward"]
    demo_input = jnp.concatenate([demo.observations, demo.goals], -1)
    visited = jnp.concatenate([backward.obs[40:60], backward.goal[40:60]], -1)
    reward = lambda x: rewards.classifier_reward(config.discriminator, state.discriminator, x)  # noqa: E731
    assert float(reward(demo_input).mean()) > 2.0 > 0.1 > float(reward(visited).mean())
    assert float(loss) < 0.6  # mixup keeps BCE above 0 even when separable


# ---- the stream, through the compiled run functions (one compiled group) ----------------------------

@functools.lru_cache(maxsize=1)
def medal_programs():
    return driver.build_programs(mf_config("medal", "steps=200"), 1)


def test_seed_phase_acts_with_the_policy_and_steers_medal_goals():
    programs = medal_programs()
    initial = programs.init(jax.random.PRNGKey(0)[None])
    start = jax.tree.map(np.array, seed_slice(initial, 0))  # copies: prefill donates its input
    state = programs.prefill(initial)
    forward, backward = seed_slice(state.replay, 0)
    loaded = demo_files.load_demos(ENV, env())
    forward_demos = len(loaded["forward"].actions)
    backward_demos = sum(len(demo.actions) for demo in loaded.values())
    seen_forward, seen_backward = int(forward.count) - forward_demos, int(backward.count) - backward_demos
    assert seen_forward + seen_backward == PREFILL and seen_backward > 0
    # The first seed-phase action is the untrained policy's sample under the step's key (run_fns.step).
    key_steps = jax.random.split(start.key)[1]
    key_act = jax.random.split(jax.random.split(key_steps, PREFILL)[0], 3)[0]
    obs_goal = jnp.concatenate([start.stream.env_state.obs, start.stream.goal])
    expected = programs.fns.agent.learner.act(start.agent, FORWARD, obs_goal, key_act)
    assert np.allclose(forward.action[forward_demos], expected, atol=1e-6)
    forward_goals = np.asarray(forward.goal[forward_demos:forward_demos + seen_forward])
    assert np.all(forward_goals == forward_goals[0])  # the task goal, kept across the backward segment
    stored = np.asarray(backward.not_done[backward_demos:int(backward.count)])
    ends = np.flatnonzero(stored == 0)
    assert np.all(np.diff(np.concatenate([[-1], ends])) <= SWITCH)
    initial_state = np.asarray(env().initial_states(jax.random.PRNGKey(0)))
    backward_goals = np.asarray(backward.goal[backward_demos:int(backward.count)])
    assert not np.allclose(backward_goals[0], initial_state)  # a goal-distribution draw, unlike r3l's


def test_medal_run_writes_every_file_and_resumes_after_sigkill_bit_exactly(tmp_path):
    full_dir, killed_dir = tmp_path / "full", tmp_path / "killed"
    three = PREFILL + 3 * CHUNK
    config = lambda d, n: mf_config("medal", f"run_dir={d}", f"steps={n}")  # noqa: E731
    driver.train(config(full_dir, three), programs=medal_programs(), progress="off")
    records = read_metrics(full_dir / "metrics.jsonl")
    last = [r for r in records if "train/updates" in r][-1]
    assert last["train/updates"] == 3 * CHUNK
    assert "medal/discriminator_loss" in last and last["medal/discriminator_loss"] > 0
    assert any("eval/success" in r for r in records) and list((full_dir / "tb").iterdir())
    assert str(three) in {p.name for p in (full_dir / "checkpoints").iterdir()}
    # A CLI run that would go on for 40 chunks is SIGKILLed once its checkpoint after chunk 1 is complete,
    # then resumed to three chunks: the same state and metrics, bit for bit.
    done = sigkilled_after([*debug_args("agent=medal", *MF_ARGS), f"steps={PREFILL + 40 * CHUNK}",
                            f"run_dir={killed_dir}"], killed_dir / "checkpoints", PREFILL + CHUNK)
    assert done < three, f"killed too late: step {done}"
    driver.train(config(killed_dir, three), programs=medal_programs(), progress="off")
    (step_a, state_a), (step_b, state_b) = (final_state(d, medal_programs()) for d in (full_dir, killed_dir))
    assert step_a == step_b == three
    assert_same_run(full_dir, state_a, killed_dir, state_b)


@pytest.mark.parametrize(("arguments", "message"), [
    (["env=ant"], "there are no demonstrations for ant (no MEDAL on Ant); tasks with demonstrations: "),
    (["env=tabletop", "baseline.discriminator.batch=7"],
     "baseline.discriminator.batch=7: batch must be even"),
    (["env=tabletop", "baseline.discriminator.train_every=0"],
     "baseline.discriminator.train_every=0: train_every must be > 0, got 0"),
    (["env=tabletop", "baseline.discriminator.mixup=maybe"],
     "baseline.discriminator.mixup expects bool, got 'maybe'"),
])
def test_bad_medal_input_is_one_line(arguments, message, capsys):

    assert_train_cli_error(capsys, ["agent=medal", "preset=debug", *arguments], message)
