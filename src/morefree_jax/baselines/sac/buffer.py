"""The model-free baselines' replay: a ring of single transitions on the device.

    buffer = init_buffer(capacity, obs_size, action_size)
    buffer = insert(buffer, Stored(obs, goal, action, reward, next_obs, not_done))  # one step, in a scan
    stored = sample(buffer, key, 256)                                # uniform, with replacement

`obs` holds the env's raw observations (the goal is kept apart and concatenated when a batch is built), so
evaluate.visitation reads the buffer like the world model's replay (it needs `.obs` and `.count`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct


class Stored(NamedTuple):
    """One transition (or a batch of them along a leading axis)."""

    obs: jax.Array
    goal: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    not_done: jax.Array  # 0 on the last step of an episode or segment: no bootstrap across it


class Ring:
    """capacity and size of a ring buffer whose rows are `obs` and whose `count` counts every write (also
    the ibc agent's segment replay, baselines/ibc/her.py)."""

    @property
    def capacity(self) -> int:
        return self.obs.shape[0]

    @property
    def size(self) -> jax.Array:
        return jnp.minimum(self.count, self.capacity)


@struct.dataclass
class TransitionBuffer(Ring):
    obs: jax.Array
    goal: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    not_done: jax.Array
    count: jax.Array  # transitions ever inserted (the ring keeps the newest `capacity`)


def init_buffer(capacity: int, obs_size: int, action_size: int) -> TransitionBuffer:
    def zeros(*shape):
        return jnp.zeros((capacity, *shape), jnp.float32)

    return TransitionBuffer(obs=zeros(obs_size), goal=zeros(obs_size), action=zeros(action_size),
                            reward=zeros(), next_obs=zeros(obs_size), not_done=zeros(),
                            count=jnp.zeros((), jnp.int32))


def insert(buffer: TransitionBuffer, transition: Stored) -> TransitionBuffer:
    """Writes one transition over the oldest slot."""
    slot = buffer.count % buffer.capacity
    fields = {name: getattr(buffer, name).at[slot].set(jnp.asarray(value, jnp.float32))
              for name, value in transition._asdict().items()}
    return buffer.replace(count=buffer.count + 1, **fields)


def sample(buffer: TransitionBuffer, key: jax.Array, batch: int) -> Stored:
    """`batch` transitions drawn uniformly with replacement from the filled slots (MEDAL's
    with_replacement); the buffer must hold at least one."""
    index = jax.random.randint(key, (batch,), 0, jnp.maximum(buffer.size, 1))
    return Stored(*(getattr(buffer, name)[index] for name in Stored._fields))


def sample_from(buffer: TransitionBuffer, key: jax.Array, batch: int, start: int) -> Stored:
    """Like sample(), from the slots written after the first `start` rows (e.g. past demonstrations
    written first). Once the ring wraps it writes over those rows from slot 0 on: the rewritten ones are
    drawn too, the rest skipped. A buffer holding no more than `start` rows gives its last row."""
    rewritten = jnp.clip(buffer.count - buffer.capacity, 0, start)
    unwrapped_skip = jnp.clip(buffer.size - 1, 0, start)
    skipped = jnp.where(buffer.count > buffer.capacity, start - rewritten, unwrapped_skip)
    drawn = jax.random.randint(key, (batch,), 0, jnp.maximum(buffer.size - skipped, 1))
    index = jnp.where(drawn < rewritten, drawn, drawn + skipped)  # past the rows still skipped
    return Stored(*(getattr(buffer, name)[index] for name in Stored._fields))


def write_rows(buffer: TransitionBuffer, rows: Stored) -> TransitionBuffer:
    """An empty buffer with `rows` (a leading batch axis) in its first slots, e.g. demonstrations."""
    count = rows.action.shape[0]
    if count > buffer.capacity:
        raise ValueError(f"{count} rows do not fit a buffer of capacity {buffer.capacity}")
    fields = {name: getattr(buffer, name).at[:count].set(jnp.asarray(value, jnp.float32))
              for name, value in rows._asdict().items()}
    return buffer.replace(count=jnp.asarray(count, jnp.int32), **fields)


def insert_where(buffer: TransitionBuffer, transition: Stored, flag: jax.Array) -> TransitionBuffer:
    """insert() when `flag`, else the buffer unchanged; written in place (the slot's old row is written
    back) so that a scan can feed one of several buffers per step without copying any of them."""
    slot = buffer.count % buffer.capacity
    fields = {}
    for name, value in transition._asdict().items():
        array = getattr(buffer, name)
        fields[name] = array.at[slot].set(jnp.where(flag, jnp.asarray(value, jnp.float32), array[slot]))
    return buffer.replace(count=buffer.count + flag.astype(jnp.int32), **fields)
