"""Back-trajectory starts: the 100 locations before each successful back chunk, kept in a device ring and
saved by a run as plots/back_starts.npz."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import envs_mjx
from morefree_jax import driver
from morefree_jax.back_starts import (
    BACK_START_SLOTS,
    BACK_START_STEPS,
    init_back_starts,
    record_back_start,
    stored_back_starts,
)
from morefree_jax.compile import compile_programs
from morefree_jax.learner_config import ReplayConfig
from morefree_jax.logger import RunLogger, read_metrics
from morefree_jax.registry import make_run_fns
from morefree_jax.replay import add, init_replay
from tests.run_helpers import CHUNK, debug_config


class _Task:
    """A task whose location is the first two observation entries (hashable: a static jit argument)."""

    @staticmethod
    def xy(obs):
        return obs[:2]


ENV = _Task()


def stream_replay(num_steps: int, capacity: int = 400):
    """A replay holding stream steps 0..num_steps-1 whose obs are (t, -t, 0)."""
    replay = init_replay(ReplayConfig(capacity=capacity, length=4), 3, 1)
    t = jnp.arange(num_steps, dtype=jnp.float32)
    obs = jnp.stack([t, -t, jnp.zeros_like(t)], axis=1)
    for start in range(0, num_steps, 100):
        stop = min(start + 100, num_steps)
        replay = add(replay, obs[start:stop], jnp.zeros((stop - start, 1)), jnp.zeros(stop - start, bool))
    return replay


def test_records_the_last_100_locations_only_on_a_successful_back_chunk():
    replay = stream_replay(650)  # capacity 400: the ring has wrapped
    starts = jax.jit(record_back_start, static_argnums=1)(init_back_starts(), ENV, replay, jnp.asarray(True))
    xy, steps = stored_back_starts(starts)
    assert xy.shape == (1, BACK_START_STEPS, 2) and steps.tolist() == [650]
    np.testing.assert_array_equal(xy[0, :, 0], np.arange(550, 650))
    np.testing.assert_array_equal(xy[0, :, 1], -np.arange(550, 650))
    unchanged = record_back_start(starts, ENV, stream_replay(700), jnp.asarray(False))
    assert int(unchanged.count) == 1
    np.testing.assert_array_equal(np.asarray(unchanged.xy), np.asarray(starts.xy))


def test_locations_before_the_stream_start_are_nan():
    starts = record_back_start(init_back_starts(), ENV, stream_replay(30), jnp.asarray(True))
    xy, _ = stored_back_starts(starts)
    assert np.isnan(xy[0, :70]).all()
    np.testing.assert_array_equal(xy[0, 70:, 0], np.arange(30))


def test_the_ring_keeps_the_newest_in_stream_order():
    replay = stream_replay(120)
    starts, record = init_back_starts(), jax.jit(record_back_start, static_argnums=1)
    for step in range(BACK_START_SLOTS + 5):  # 5 more than fit: the 5 oldest are overwritten
        starts = record(starts, ENV, replay.replace(count=jnp.asarray(100 + step)), jnp.asarray(True))
    _, steps = stored_back_starts(starts)
    assert steps.tolist() == list(range(105, 100 + BACK_START_SLOTS + 5))


def test_the_logger_writes_them_atomically(tmp_path):
    starts = record_back_start(init_back_starts(), ENV, stream_replay(200), jnp.asarray(True))
    logger = RunLogger(tmp_path, {"seed": 0}, total_steps=1000, progress="off")
    logger.log_back_starts(500, *stored_back_starts(starts))
    logger.close()
    files = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert files == ["back_starts.npz"]
    with np.load(tmp_path / "plots" / "back_starts.npz") as data:
        assert data["xy"].shape == (1, BACK_START_STEPS, 2) and data["stream_step"].tolist() == [200]
        assert int(data["step"]) == 500


class _EveryGoalReachedTabletop(envs_mjx.env_class("tabletop")):
    """Tabletop on which every go phase reaches its goal, so that every back chunk is a successful one."""

    def __init__(self):
        super().__init__(success_threshold=1e3)


def test_a_debug_run_saves_the_starts_of_every_successful_back_chunk(tmp_path):
    # mf_task_only (alpha 1) alternates forth and back chunks: chunks 2 and 4 of four are back chunks.
    chunks, steps = 4, 20 + 4 * CHUNK  # after the debug prefill of 20 steps
    # The run saves them at each evaluation: one, at the end.
    config = debug_config("mf_task_only", f"run_dir={tmp_path}", f"steps={steps}", f"eval_every={steps}",
                          "checkpoint_every=10000")
    programs = compile_programs(make_run_fns(config, _EveryGoalReachedTabletop()), 1)
    driver.train(config, programs=programs, progress="off")
    saved = np.load(tmp_path / "plots" / "back_starts.npz")
    assert saved["xy"].shape == (chunks // 2, BACK_START_STEPS, 2)
    # Each back chunk starts where its forth chunk ended: stream steps prefill + CHUNK and + 3 CHUNK.
    assert saved["stream_step"].tolist() == [20 + CHUNK, 20 + 3 * CHUNK]
    assert int(saved["step"]) == steps
    assert np.isfinite(saved["xy"]).all()  # 100 stream steps precede each, none before the stream start
    records = [r for r in read_metrics(tmp_path / "metrics.jsonl") if "go/reach_rate_initial" in r]
    assert records[-1]["go/reach_rate_initial"] == 1.0
