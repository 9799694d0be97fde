"""Replay ring buffer: no window crosses a hard reset, wrap-around, uniform sampling, memory check."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from morefree_jax.learner_config import ReplayConfig
from morefree_jax.replay import add, init_replay, sample, sample_windows, valid_starts

LENGTH = 4


def stream(start: int, n: int, resets=()):
    """Transitions whose obs is their stream position, so windows can be read back."""
    pos = np.arange(start, start + n, dtype=np.float32)
    reset = np.isin(np.arange(start, start + n), resets)
    return jnp.asarray(pos[:, None]), jnp.asarray(pos[:, None] * 0.5), jnp.asarray(reset)


SAMPLERS = {"sample": sample, "sample_windows": sample_windows}  # one pass over the buffer; rejection


@functools.cache
def jitted(sampler: str = "sample"):
    return (jax.jit(add), jax.jit(SAMPLERS[sampler], static_argnums=(2, 3)),
            jax.jit(valid_starts, static_argnums=1))


def filled(capacity: int, total: int, resets=(), chunk: int = 7):
    add_fn, _, _ = jitted()
    state = init_replay(ReplayConfig(capacity=capacity, batch=2, length=LENGTH), 1, 1)
    for begin in range(0, total, chunk):
        state = add_fn(state, *stream(begin, min(chunk, total - begin), resets))
    return state


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_windows_never_cross_a_hard_reset_and_are_consecutive(sampler):
    resets = (0, 13, 14, 30)
    state = filled(capacity=64, total=40, resets=resets)
    _, sample_fn, _ = jitted(sampler)
    batch = sample_fn(state, jax.random.PRNGKey(0), 512, LENGTH)
    pos = np.asarray(batch.obs[..., 0]).astype(int)
    assert np.all(np.diff(pos, axis=1) == 1)
    for row in pos:
        assert not set(row[1:]) & set(resets), row
    np.testing.assert_array_equal(np.asarray(batch.is_first), np.arange(LENGTH)[None].repeat(512, 0) == 0)
    np.testing.assert_allclose(np.asarray(batch.action), np.asarray(batch.obs) * 0.5)
    # Valid starts: 0..36 minus those whose next 3 steps hit 13, 14 or 30.
    expected = [s for s in range(37) if not {s + 1, s + 2, s + 3} & set(resets)]
    assert sorted(set(pos[:, 0])) == expected
    assert int(jnp.sum(valid_starts(state, LENGTH))) == len(expected)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_wrap_around_keeps_the_latest_capacity_transitions(sampler):
    state = filled(capacity=16, total=45)  # positions 29..44 remain
    assert int(state.count) == 45
    np.testing.assert_array_equal(np.sort(np.asarray(state.obs[:, 0])), np.arange(29, 45))
    _, sample_fn, _ = jitted(sampler)
    pos = np.asarray(sample_fn(state, jax.random.PRNGKey(1), 1024, LENGTH).obs[..., 0]).astype(int)
    assert np.all(np.diff(pos, axis=1) == 1)  # windows are consecutive across the physical wrap
    assert pos.min() == 29 and pos.max() == 44
    assert sorted(set(pos[:, 0])) == list(range(29, 42))


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_sampling_is_uniform_over_valid_windows_chi_square(sampler):
    state = filled(capacity=32, total=50, resets=(40,))
    _, sample_fn, _ = jitted(sampler)
    starts = np.asarray(sample_fn(state, jax.random.PRNGKey(2), 20_000, LENGTH).obs[:, 0, 0]).astype(int)
    valid = [s for s in range(18, 47) if not {s + 1, s + 2, s + 3} & {40}]
    counts = np.array([np.sum(starts == s) for s in valid])
    assert counts.sum() == starts.size
    _, p_value = stats.chisquare(counts)
    assert p_value > 1e-3, (p_value, counts)


def test_sample_windows_falls_back_to_the_pass_when_valid_windows_are_rare():
    """One valid start among 61: rejection draws find it for few windows, so the call takes sample's pass."""
    resets = [p for p in range(64) if p not in (11, 12, 13)]
    state = filled(capacity=64, total=64, resets=resets)
    _, sample_fn, _ = jitted("sample_windows")
    pos = np.asarray(sample_fn(state, jax.random.PRNGKey(3), 64, LENGTH).obs[..., 0]).astype(int)
    assert np.all(pos == np.arange(10, 14))


def test_capacity_that_does_not_fit_is_a_clear_error():
    with pytest.raises(ValueError, match="replay capacity"):
        init_replay(ReplayConfig(capacity=10**9, max_bytes=2**30), 29, 8)
