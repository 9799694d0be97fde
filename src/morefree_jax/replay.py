"""Replay: one fixed-capacity ring buffer over the single reset-free stream, as a pytree of device arrays.

Transition t stores obs_t, the action that led to it (zeros after a hard reset, DreamerV2 convention) and
`reset_t` = True on the first transition after a hard reset. `sample` draws B windows of T consecutive
transitions uniformly among the valid ones: all T still in the buffer and no hard reset after the window's
first step (a window may start at a reset). `is_first` is True at each window's first step; since windows
never cross a reset, that is also where the hard resets are. add/sample are pure and jittable.

The buffer also keeps the per-dimension range of every observation ever added (`visited_range`): the
goal search draws its candidates inside it (collect.py), so they are states the stream has been in.
The range never shrinks when old transitions are overwritten (budgets up to 8e5 steps fit the default
capacity of 1e6, so nothing is overwritten in the paper's runs).
"""

from __future__ import annotations

import os

import flax
import jax
import jax.numpy as jnp

from morefree_jax.batching import lazy_cond
from morefree_jax.learner_config import ReplayConfig
from morefree_jax.world_model import Batch

# sample_windows' draws per window: with half the starts invalid, 1 call in ~4,000 falls back to the pass.
WINDOW_TRIES = 16


@flax.struct.dataclass
class ReplayState:
    obs: jax.Array  # (C, O)
    action: jax.Array  # (C, A)
    reset: jax.Array  # (C,) bool
    count: jax.Array  # transitions added so far (int32; the stream position of the next write)
    obs_low: jax.Array  # (O,) smallest value of each observation entry added so far (+inf when empty)
    obs_high: jax.Array  # (O,) largest (-inf when empty)


def replay_bytes(capacity: int, obs_size: int, action_size: int) -> int:
    return capacity * (4 * (obs_size + action_size) + 1)


def _available_memory() -> int:
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return 2**62


def init_replay(cfg: ReplayConfig, obs_size: int, action_size: int) -> ReplayState:
    """An empty buffer; a capacity whose arrays exceed `cfg.max_bytes` or free memory is a clear error."""
    if cfg.capacity < cfg.length:
        raise ValueError(f"replay capacity {cfg.capacity} is smaller than the sequence length {cfg.length}")
    need = replay_bytes(cfg.capacity, obs_size, action_size)
    limit = min(cfg.max_bytes, _available_memory())
    if need > limit:
        raise ValueError(
            f"replay capacity {cfg.capacity} needs {need / 2**30:.2f} GiB "
            f"(obs {obs_size}, action {action_size}) "
            f"but only {limit / 2**30:.2f} GiB are allowed/free; lower replay.capacity to at most "
            f"{limit // replay_bytes(1, obs_size, action_size)}"
        )
    return ReplayState(
        obs=jnp.zeros((cfg.capacity, obs_size), jnp.float32),
        action=jnp.zeros((cfg.capacity, action_size), jnp.float32),
        reset=jnp.zeros((cfg.capacity,), bool),
        count=jnp.zeros((), jnp.int32),
        obs_low=jnp.full((obs_size,), jnp.inf, jnp.float32),
        obs_high=jnp.full((obs_size,), -jnp.inf, jnp.float32),
    )


def add(state: ReplayState, obs: jax.Array, action: jax.Array, reset: jax.Array) -> ReplayState:
    """Appends a chunk of N transitions: obs (N, O), action (N, A), reset (N,); N <= capacity."""
    capacity = state.obs.shape[0]
    index = (state.count + jnp.arange(obs.shape[0])) % capacity
    return ReplayState(
        obs=state.obs.at[index].set(obs),
        action=state.action.at[index].set(action),
        reset=state.reset.at[index].set(reset),
        count=state.count + obs.shape[0],
        obs_low=jnp.minimum(state.obs_low, jnp.min(obs, axis=0)),
        obs_high=jnp.maximum(state.obs_high, jnp.max(obs, axis=0)),
    )


def visited_range(state: ReplayState, low: jax.Array, high: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The per-dimension range of the observations added so far, clipped to the box [low, high] (O,);
    the box itself while the buffer is empty."""
    empty = state.count == 0
    return (jnp.where(empty, low, jnp.clip(state.obs_low, low, high)),
            jnp.where(empty, high, jnp.clip(state.obs_high, low, high)))


def valid_starts(state: ReplayState, length: int) -> jax.Array:
    """(C,) bool over buffer slots: a window of `length` starting at that slot is valid."""
    capacity = state.reset.shape[0]
    oldest = jnp.maximum(state.count - capacity, 0)
    # Stream position of every slot, then: in buffer, window inside the written part, no inner reset.
    slot = jnp.arange(capacity)
    position = oldest + (slot - oldest) % capacity
    inside = (position >= oldest) & (position + length <= state.count)
    # Resets per stream position, in stream order, to count inner resets with one cumulative sum.
    in_order = jnp.roll(state.reset, -(oldest % capacity)).astype(jnp.int32)
    cumulative = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum(in_order)])
    rank = position - oldest  # order index of the slot
    inner = cumulative[jnp.minimum(rank + length, capacity)] - cumulative[jnp.minimum(rank + 1, capacity)]
    return inside & (inner == 0)


def sample(state: ReplayState, key: jax.Array, batch: int, length: int) -> Batch:
    """B windows of T steps, uniform over valid windows -> Batch (B, T, ...). Needs >= 1 valid window.
    O(C): one pass over the buffer, shared by every window of the call (see sample_windows)."""
    return _windows(state, _exact_starts(state, key, batch, length), length)


def sample_windows(state: ReplayState, key: jax.Array, batch: int, length: int) -> Batch:
    """What `sample` draws (uniform over valid windows), in O(B T) instead of O(C): each window's start is
    the first valid one of WINDOW_TRIES uniform draws over the buffer; only if some window finds none (a
    hard reset every few windows, as episodic PEG's) does the call fall back to `sample`'s pass. The first
    accepted draw is uniform over the valid windows, so the mixture is too. For one update at a time (the
    interleaved cadence), where a pass over a 1e6 buffer per update would cost a third of the update."""
    key_tries, key_exact = jax.random.split(key)
    capacity = state.obs.shape[0]
    oldest = jnp.maximum(state.count - capacity, 0)
    candidates = jnp.maximum(state.count - length - oldest + 1, 1)
    position = oldest + jax.random.randint(key_tries, (WINDOW_TRIES, batch), 0, candidates)
    inner = (position[..., None] + jnp.arange(1, length)) % capacity  # a reset there would cut the window
    valid = ~jnp.any(state.reset[inner], axis=-1)
    start = position[jnp.argmax(valid, axis=0), jnp.arange(batch)] % capacity
    start = lazy_cond(~jnp.all(jnp.any(valid, axis=0)),
                      lambda: _exact_starts(state, key_exact, batch, length), lambda: start)
    return _windows(state, start, length)


def _exact_starts(state: ReplayState, key: jax.Array, batch: int, length: int) -> jax.Array:
    """(B,) buffer slots, uniform over valid window starts."""
    # The k-th valid slot for k uniform in [0, #valid): a cumulative sum and a binary search, O(C + B log C).
    cumulative = jnp.cumsum(valid_starts(state, length).astype(jnp.int32))
    k = jax.random.randint(key, (batch,), 0, jnp.maximum(cumulative[-1], 1))
    return jnp.searchsorted(cumulative, k, side="right")


def _windows(state: ReplayState, start: jax.Array, length: int) -> Batch:
    """The windows of `length` steps from buffer slots `start` (B,) -> Batch (B, T, ...)."""
    index = (start[:, None] + jnp.arange(length)[None]) % state.obs.shape[0]
    is_first = jnp.zeros((start.shape[0], length), bool).at[:, 0].set(True)
    return Batch(state.obs[index], state.action[index], is_first)


