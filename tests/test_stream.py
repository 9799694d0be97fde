"""The model-free stream (baselines/sac/stream.py) with its oracle_sac and r3l learners: the replay, the
streams each agent steers, whole runs through driver.train, exact resume after SIGKILL, and bad input.
The SAC learner itself is tested in test_sac.py."""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from morefree_jax import driver
from morefree_jax.baselines.baseline_config import ClassifierConfig, RNDConfig
from morefree_jax.baselines.oracle_sac.agent import OracleSAC
from morefree_jax.baselines.r3l.agent import R3L
from morefree_jax.baselines.sac import rewards
from morefree_jax.baselines.sac.buffer import Stored, init_buffer, insert_where, sample
from morefree_jax.baselines.sac.stream import FORWARD, StreamParts
from morefree_jax.compile import seed_slice
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

PREFILL, CHUNK, SWITCH = 100, 50, 30
# Tiny learners and buffers; tabletop (run_helpers.RUN_ENV) for its fast-compiling kinematic step.
MF_ARGS = (f"prefill={PREFILL}", f"baseline.chunk_len={CHUNK}", "baseline.replay_capacity=1000",
           "baseline.sac.batch_size=32", "baseline.sac.hidden_dim=32", "baseline.classifier.batch=32",
           f"baseline.switch_every={SWITCH}", "log_every=50", "eval_every=100", "checkpoint_every=50")


def mf_config(agent: str, *extra: str):
    return resolve_config(debug_args(f"agent={agent}", *MF_ARGS, *extra), envs_mjx.ALL_ENVS)


# One compiled group per agent, shared by every test here: r3l with two seeds in one program (the multi-seed
# path), oracle_sac with one.
SEEDS = {"oracle_sac": (0,), "r3l": (0, 1)}


@functools.lru_cache(maxsize=2)
def mf_programs(agent: str):
    return driver.build_programs(mf_config(agent, "steps=200"), len(SEEDS[agent]))


def prefilled(agent: str):
    """(programs, a fresh state after the seed phase, with the seed axis)."""
    programs = mf_programs(agent)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in SEEDS[agent]])
    return programs, programs.prefill(programs.init(keys))


# ---- the replay and the learned rewards ------------------------------------------------------------

def test_buffer_writes_only_flagged_transitions_and_wraps():
    buffer = init_buffer(3, 2, 1)
    for value in range(5):
        row = Stored(*(jnp.full(shape, float(value)) for shape in ((2,), (2,), (1,), (), (2,), ())))
        buffer = insert_where(buffer, row, jnp.asarray(value != 2))  # value 2 is not this buffer's
    assert int(buffer.count) == 4 and int(buffer.size) == 3
    assert buffer.reward.tolist() == [4.0, 1.0, 3.0]  # 0, 1, 3 fill the ring of 3; 4 replaces 0
    drawn = sample(buffer, jax.random.PRNGKey(0), 200)
    assert set(np.asarray(drawn.reward).tolist()) == {1.0, 3.0, 4.0}
    assert np.array_equal(drawn.obs[:, 0], drawn.reward)  # rows stay whole


def test_mixup_mixes_inputs_and_labels_with_the_same_weight():
    inputs, labels = jnp.array([[0.0], [10.0], [0.0], [10.0]]), jnp.array([0.0, 1.0, 0.0, 1.0])
    mixed, mixed_labels = rewards.mixup(inputs, labels, jax.random.PRNGKey(3))
    assert np.allclose(mixed[:, 0] / 10.0, mixed_labels) and not np.allclose(mixed_labels, labels)


def test_classifier_reward_rises_on_goal_examples():
    cfg = ClassifierConfig(batch=64)
    state = rewards.init_classifier(cfg, 2, jax.random.PRNGKey(0))
    goals = jnp.array([3.0, 3.0]) + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (32, 2))
    visited = jnp.array([-3.0, 0.0]) + 0.5 * jax.random.normal(jax.random.PRNGKey(2), (32, 2))
    before = rewards.classifier_reward(cfg, state, jnp.array([[3.0, 3.0], [-3.0, 0.0]]))
    update = jax.jit(rewards.update_classifier, static_argnums=0)
    for step in range(300):
        state, loss = update(cfg, state, goals, visited, jax.random.PRNGKey(step))
    after = rewards.classifier_reward(cfg, state, jnp.array([[3.0, 3.0], [-3.0, 0.0]]))
    assert after[0] > 2.0 > 0.1 > after[1] and after[0] > before[0]
    assert bool(jnp.all(after >= 0.0))  # -log(1 - p) >= 0


def test_rnd_reward_is_high_on_novel_states_and_in_unit_range():
    cfg = RNDConfig()
    state = rewards.init_rnd(cfg, 3, jax.random.PRNGKey(0))
    seen = jax.random.normal(jax.random.PRNGKey(1), (64, 3))
    novel = 4.0 + jax.random.normal(jax.random.PRNGKey(2), (64, 3))
    observe, update = jax.jit(rewards.observe), jax.jit(rewards.update_rnd, static_argnums=0)
    for obs in jnp.concatenate([seen, novel]):  # whitening statistics of everything visited
        state = observe(state, obs)
    for _ in range(400):
        state, loss = update(cfg, state, seen)
    reward = rewards.rnd_reward(cfg, state, jnp.concatenate([seen[:16], novel[:16]]))
    assert float(reward.min()) == 0.0 and float(reward.max()) == pytest.approx(1.0)
    # DI-engine's networks end in a ReLU, so features at zero for both networks carry no novelty and the
    # contrast is far smaller than without it (docs/baselines.md, "R3L's choices": measured over init keys).
    assert float(reward[16:].mean()) > 2 * float(reward[:16].mean())


def test_reward_networks_start_as_pytorch_linears_and_rnd_features_pass_a_final_relu():
    """MEDAL's discriminator and DI-engine's RND networks are PyTorch modules at their default init;
    DI-engine's FCEncoder applies its ReLU after the last layer too."""
    rnd = rewards.init_rnd(RNDConfig(hidden=(64, 64, 128)), 3, jax.random.PRNGKey(0))
    classifier = rewards.init_classifier(ClassifierConfig(hidden=128), 3, jax.random.PRNGKey(1))
    for params in (rnd.target, rnd.predictor.params, classifier.params):
        for layer in params["params"].values():
            limit = 1.0 / np.sqrt(layer["kernel"].shape[0])
            for leaf in (layer["kernel"], layer["bias"]):
                assert 0.0 < float(jnp.abs(leaf).max()) <= limit  # a PyTorch bias starts nonzero
                if leaf.size >= 64:  # uniform draws fill the interval
                    assert float(jnp.abs(leaf).max()) > 0.9 * limit
    obs = jax.random.normal(jax.random.PRNGKey(2), (256, 3))
    features = rewards._MLP((64, 64, 128), relu_output=True).apply(rnd.target, obs)
    assert features.shape == (256, 128) and float(features.min()) == 0.0 and float(features.max()) > 0.0
    logits = rewards.classifier_logits(ClassifierConfig(hidden=128), classifier.params, obs)
    assert float(logits.min()) < 0.0 < float(logits.max())  # the classifier's output stays a free logit


def test_running_statistics_match_numpy():
    state = rewards.init_rnd(RNDConfig(), 2, jax.random.PRNGKey(0))
    data = np.random.default_rng(0).normal(2.0, 3.0, (500, 2)).astype(np.float32)
    observe = jax.jit(rewards.observe)
    for obs in data:
        state = observe(state, jnp.asarray(obs))
    assert np.allclose(state.mean, data.mean(0), atol=1e-3) and np.allclose(state.var, data.var(0), rtol=1e-2)


# ---- the fused chunk and the streams ---------------------------------------------------------------

@pytest.mark.parametrize("agent", ["oracle_sac", "r3l"])
def test_fused_chunk_compiles_once_without_host_callbacks(agent):
    programs, state = prefilled(agent)
    assert programs.train_updates is None  # the chunk is the whole training step
    assert not callback_primitives(programs.collect.trace(state).jaxpr.jaxpr)
    for _ in range(2):
        state, metrics = programs.collect(state)
    assert programs.collect._cache_size() == 1
    agent_state = state.agent
    updates = agent_state.updates if agent == "oracle_sac" else (
        agent_state.forward.updates + agent_state.backward.updates)
    assert np.all(updates == 2 * CHUNK) and np.all(metrics["train/updates"] == updates)  # UTD 1 per seed
    assert all(np.all(np.isfinite(value)) for value in metrics.values())


def loop_body_instructions(hlo: str) -> list[str]:
    """The instructions of every while-loop body computation in compiled HLO text."""
    bodies = set(re.findall(r"body=%?([\w.-]+)", hlo))
    blocks = re.split(r"\n(?=\S)", hlo)  # a computation starts at column 0, its instructions are indented
    return [line for block in blocks if block.split(" ", 1)[0].lstrip("%") in bodies
            for line in block.splitlines()[1:]]


@pytest.mark.parametrize("agent", ["oracle_sac", "r3l"])
def test_fused_chunk_never_copies_the_replay_per_step(agent):
    """Each step stores into the replay and samples from it; XLA's default copy insertion copied a replay
    field twice per step for that (a 1e6-row replay: 24 MB a step). The runtime's region analysis
    (morefree_jax.runtime) writes it in place: no loop body of the compiled chunk copies a replay-sized
    array."""
    programs, state = prefilled(agent)
    capacity = state.replay[0].obs.shape[1]  # (seeds, capacity, obs)
    body = loop_body_instructions(programs.collect.lower(state).compile().as_text())
    assert any(" copy(" in line for line in body)  # the parse found the loop bodies (they copy small things)
    copies = [line for line in body if re.search(rf"= f32\[[\d,]*\b{capacity}\b[\d,]*\]\S* copy\(", line)]
    assert not copies, copies[:3]


@dataclasses.dataclass(frozen=True)
class ReplaySizeSpy:
    """An Oracle learner whose update reports the replay size it was given instead of learning."""

    inner: Any

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def update(self, state, buffers, direction, step, key):
        return state, {"sac/seen": buffers[0].count.astype(jnp.float32)}


def test_update_precedes_the_env_step_and_chunks_store_their_last_transition():
    """MEDAL's order: step i of a chunk updates on the replay before its own transition is stored."""
    config = mf_config("oracle_sac", "steps=200")
    env = envs_mjx.make(config.run.env)
    spy = ReplaySizeSpy(OracleSAC(config.baseline, env))
    parts = StreamParts(config, env, spy)
    state = jax.jit(parts.prefill)(parts.init(jax.random.PRNGKey(0)))
    run_chunk = jax.jit(lambda s: parts.run_steps(s, CHUNK, learn=True))
    for chunk in range(2):
        state, records = run_chunk(state)
        first = PREFILL + chunk * CHUNK
        np.testing.assert_array_equal(records["sac/seen"], first + np.arange(CHUNK))
        assert int(state.replay[0].count) == first + CHUNK  # the chunk's last transition is in


def test_oracle_episodes_end_on_success_or_timeout_without_bootstrap():
    programs, state = prefilled("oracle_sac")
    buffer = seed_slice(state.replay[0], 0)
    ends = np.flatnonzero(np.asarray(buffer.not_done[:PREFILL]) == 0)
    successes = np.flatnonzero(np.asarray(buffer.reward[:PREFILL]) == 1)
    assert set(successes) <= set(ends)  # the sparse reward ends its episode
    lengths = np.diff(np.concatenate([[-1], ends]))
    assert np.all(lengths <= programs.fns.env.eval_episode_length)
    goals = np.asarray(buffer.goal[:PREFILL])
    starts = np.concatenate([[0], ends + 1])[:-1] if len(ends) else [0]
    for start, end in zip(starts, [*ends, PREFILL - 1], strict=False):  # one goal per episode
        assert np.all(goals[start:end + 1] == goals[start])


@pytest.mark.parametrize("agent", ["oracle_sac", "r3l"])
def test_seed_phase_acts_uniformly_for_the_oracle_and_with_the_untrained_policy_for_r3l(agent):
    """MEDAL's oracle.py draws uniform actions in its seed frames; fbrl.py, r3l's template, acts with its
    untrained policies."""
    programs = mf_programs(agent)
    initial = programs.init(jnp.stack([jax.random.PRNGKey(seed) for seed in SEEDS[agent]]))
    start = jax.tree.map(np.array, seed_slice(initial, 0))  # copies: prefill donates its input
    forward = seed_slice(programs.prefill(initial).replay, 0)[0]
    # The first seed-phase action under the step's key (run_fns.step), as test_medal checks for medal.
    key_steps = jax.random.split(start.key)[1]
    key_act = jax.random.split(jax.random.split(key_steps, PREFILL)[0], 3)[0]
    obs_goal = jnp.concatenate([start.stream.env_state.obs, start.stream.goal])
    policy = programs.fns.agent.learner.act(start.agent, FORWARD, obs_goal, key_act)
    uniform = jax.random.uniform(key_act, policy.shape, minval=-1.0, maxval=1.0)
    expected, other = (policy, uniform) if agent == "r3l" else (uniform, policy)
    assert np.allclose(forward.action[0], expected, atol=1e-6)
    assert not np.allclose(forward.action[0], other, atol=1e-3)


def test_r3l_alternates_forward_and_backward_segments():
    programs, state = prefilled("r3l")
    forward, backward = seed_slice(state.replay, 0)
    assert int(forward.count) + int(backward.count) == PREFILL
    assert float(backward.reward[:int(backward.count)].sum()) == 0.0  # the backward policy has no success
    # Segments of SWITCH steps (R3L acts on no success), alternating, forward first: 100 steps are forward
    # 0-29, backward 30-59, forward 60-89, backward 90-99.
    assert int(forward.count) == 2 * SWITCH
    for buffer in (forward, backward):
        ends = np.flatnonzero(np.asarray(buffer.not_done[:int(buffer.count)]) == 0)
        assert np.all(np.diff(np.concatenate([[-1], ends])) == SWITCH)
    initial = np.asarray(programs.fns.env.initial_states(jax.random.PRNGKey(0)))
    assert np.allclose(backward.goal[0], initial)  # tabletop has one initial state: the backward goal


@dataclasses.dataclass(frozen=True)
class FixedSuccess:
    """The env with its success test replaced by a constant."""

    inner: Any
    value: bool

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def success(self, obs, goal):
        return jnp.asarray(self.value)


def test_r3l_switches_without_the_tasks_success():
    """R3L sees no reward or success: with the env's success test always False, or always True (which would
    end every forward segment at once were it acted on), its segments, switches and learners are the same."""
    config = mf_config("r3l", "steps=200")
    env = envs_mjx.make(config.run.env)
    runs = []
    for tested in (env, FixedSuccess(env, False), FixedSuccess(env, True)):
        parts = StreamParts(config, tested, R3L(config.baseline, env))
        state = jax.jit(parts.prefill)(parts.init(jax.random.PRNGKey(0)))
        state, records = jax.jit(lambda s, parts=parts: parts.run_steps(s, 2 * SWITCH, learn=True))(state)
        runs.append((state, records))
    (state, records), *others = runs
    for other_state, other_records in others:
        for name in ("direction", "end"):
            np.testing.assert_array_equal(records[name], other_records[name])
        assert jax.tree.all(jax.tree.map(np.array_equal, state.agent, other_state.agent))
    assert np.asarray(records["end"]).sum() == 2  # one segment of SWITCH steps each way
    assert np.asarray(runs[2][1]["success"]).any()  # the always-True test was seen and not acted on


# ---- whole runs --------------------------------------------------------------------------------------

def train(agent: str, run_dir, total_steps: int):
    """Several seeds write <run_dir>/seed<k>; one seed writes the run_dir as given."""
    config = mf_config(agent, f"run_dir={run_dir}", f"steps={total_steps}")
    return driver.train(config, seeds=SEEDS[agent], programs=mf_programs(agent), progress="off")


def seed_dir(agent: str, run_dir, seed: int = 0) -> pathlib.Path:
    return pathlib.Path(run_dir) / f"seed{seed}" if len(SEEDS[agent]) > 1 else pathlib.Path(run_dir)


@pytest.mark.parametrize("agent", ["oracle_sac", "r3l"])
def test_two_chunk_run_writes_every_file(agent, tmp_path):
    steps, seeds = PREFILL + 2 * CHUNK, SEEDS[agent]
    summaries = train(agent, tmp_path, steps)
    assert [s.env_steps for s in summaries] == [steps] * len(seeds)
    for seed in seeds:
        run_dir = seed_dir(agent, tmp_path, seed)
        config = json.loads((run_dir / "config.json").read_text())
        assert config["run"]["agent"] == agent and config["run"]["seed"] == seed
        records = read_metrics(run_dir / "metrics.jsonl")
        assert [r["step"] for r in records if "train/updates" in r] == [PREFILL + CHUNK, steps]
        last = [r for r in records if "train/updates" in r][-1]
        assert last["train/updates"] == 2 * CHUNK and last["replay/size"] == steps
        assert any("eval/success" in r for r in records)
        assert any("visitation/task_relevant" in r for r in records)
        assert all(np.isfinite(v) for r in records for v in r.values())
        assert list((run_dir / "tb").glob("events.out.tfevents.*"))
        assert list((run_dir / "plots").glob("visitation_*.npy"))
        assert str(steps) in {p.name for p in (run_dir / "checkpoints").iterdir()}
    if len(seeds) > 1:  # each seed its own stream
        first, second = ([r for r in read_metrics(tmp_path / f"seed{seed}" / "metrics.jsonl")
                          if "train/updates" in r][-1] for seed in seeds)
        assert first["forward/critic_loss"] != second["forward/critic_loss"]


def test_r3l_resume_after_sigkill_is_bit_exact(tmp_path):
    full_dir, killed_dir = tmp_path / "full", tmp_path / "killed"
    three = PREFILL + 3 * CHUNK
    train("r3l", full_dir, three)
    group = [arg for arg in debug_args("agent=r3l", *MF_ARGS) if not arg.startswith("seed=")] + ["seeds=0,1"]
    done = sigkilled_after([*group, f"steps={PREFILL + 40 * CHUNK}", f"run_dir={killed_dir}"],
                           killed_dir / f"seed{SEEDS['r3l'][-1]}" / "checkpoints", PREFILL + CHUNK)
    assert done < three, f"killed too late: step {done}"
    train("r3l", killed_dir, three)
    full_dir, killed_dir = seed_dir("r3l", full_dir, 1), seed_dir("r3l", killed_dir, 1)
    (step_a, state_a), (step_b, state_b) = (final_state(d, mf_programs("r3l"), SEEDS["r3l"])
                                            for d in (full_dir, killed_dir))
    assert step_a == step_b == three
    assert_same_run(full_dir, state_a, killed_dir, state_b)


@pytest.mark.parametrize(("arguments", "message"), [
    (["agent=sac"], "unknown agent 'sac'; valid agents: morefree, rf_peg, peg, dreamer_gc, mf_no_bfge, "
                    "mf_no_imag, mf_task_only, oracle_sac, r3l, medal, ibc"),
    (["agent=r3l", "baseline.sac.lr=-1"], "baseline.sac.lr=-1: lr must be > 0, got -1.0"),
    (["agent=r3l", "baseline.chunk_len=0"], "baseline.chunk_len=0: chunk_len must be > 0, got 0"),
    (["agent=r3l", "baseline.classifier.batch=7"], "batch must be even"),
    (["agent=oracle_sac", "baseline.sac.discount=2"], "discount must be in [0, 1], got 2.0"),
    (["agent=r3l", "baseline.rnd.hidden=64,0"], "hidden must be positive widths"),
])
def test_bad_model_free_input_exits_2_with_one_line(arguments, message, capsys):
    assert_train_cli_error(capsys, ["env=tabletop", *arguments], message)
