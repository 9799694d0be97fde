"""IBC's hindsight replay (docs/baselines.md, "Hindsight relabelling") as a device ring of transitions grouped
in segments.

    buffer = init_segment_buffer(capacity, obs_size, action_size)
    buffer = insert_where(buffer, obs, goal, action, next_obs, flag)   # one step of a segment, in a scan
    buffer = end_segment_where(buffer, flag)                            # the segment ended: now sampleable
    batch = sample_her(buffer, key, 512, relabel=0.8, success_fn)      # SACBatch, reward in {-1, 0}

IBC hands a segment to its replay only when the segment ends. Here every step is written at once (no
segment-sized staging copy in the scan carry) and a transition becomes sampleable when `committed`, the
count at the last segment end, passes it. Each transition carries the id of its segment; a table indexed
by segment id holds where that segment ended (absolute positions), so drawing "a future achieved goal of
the same segment" costs two gathers. Ids of live transitions span fewer than `capacity` segments, so the
table (one int per slot) never holds two live segments in one row.

Rewards are not stored: HER recomputes them for every drawn goal with the direction's success test
(r = success - 1, IBC's {-1, 0}), so original and relabelled goals are rewarded alike. The TD target never
masks by done (IBC's consider_done_true_in_critic false): not_done is 1 throughout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.baselines.sac.buffer import Ring
from morefree_jax.baselines.sac.learner import SACBatch


@struct.dataclass
class SegmentBuffer(Ring):
    obs: jax.Array  # (N, O)
    goal: jax.Array  # (N, O) the goal the segment pursued, a full observation vector
    action: jax.Array  # (N, A)
    next_obs: jax.Array  # (N, O)
    segment: jax.Array  # (N,) id of the transition's segment
    segment_end: jax.Array  # (N,) absolute position of the last transition of segment id % N
    count: jax.Array  # transitions ever written
    committed: jax.Array  # count at the last segment end: positions below it are sampleable
    segments: jax.Array  # segments ended so far (the id of the open one)

    @property
    def oldest(self) -> jax.Array:
        """The absolute position of the oldest transition still in the ring."""
        return jnp.maximum(self.count - self.capacity, 0)

    @property
    def sampleable(self) -> jax.Array:
        return self.committed > self.oldest


def init_segment_buffer(capacity: int, obs_size: int, action_size: int) -> SegmentBuffer:
    def zeros(*shape, dtype=jnp.float32):
        return jnp.zeros(shape, dtype)

    return SegmentBuffer(obs=zeros(capacity, obs_size), goal=zeros(capacity, obs_size),
                         action=zeros(capacity, action_size), next_obs=zeros(capacity, obs_size),
                         segment=zeros(capacity, dtype=jnp.int32),
                         segment_end=zeros(capacity, dtype=jnp.int32),
                         count=zeros(dtype=jnp.int32), committed=zeros(dtype=jnp.int32),
                         segments=zeros(dtype=jnp.int32))


def insert_where(buffer: SegmentBuffer, obs, goal, action, next_obs, flag) -> SegmentBuffer:
    """Writes one transition of the open segment when `flag`; in place otherwise (the slot's old row is
    written back), so a scan can feed one of two buffers per step without copying either."""
    slot = buffer.count % buffer.capacity

    def write(array, value):
        return array.at[slot].set(jnp.where(flag, jnp.asarray(value, array.dtype), array[slot]))

    return buffer.replace(obs=write(buffer.obs, obs), goal=write(buffer.goal, goal),
                          action=write(buffer.action, action), next_obs=write(buffer.next_obs, next_obs),
                          segment=write(buffer.segment, buffer.segments),
                          count=buffer.count + flag.astype(jnp.int32))


def end_segment_where(buffer: SegmentBuffer, flag) -> SegmentBuffer:
    """Closes the open segment when `flag` (and it has a transition): its transitions become sampleable."""
    flag = flag & (buffer.count > buffer.committed)
    row = buffer.segments % buffer.capacity
    end = jnp.where(flag, buffer.count - 1, buffer.segment_end[row])
    return buffer.replace(segment_end=buffer.segment_end.at[row].set(end),
                          committed=jnp.where(flag, buffer.count, buffer.committed),
                          segments=buffer.segments + flag.astype(jnp.int32))


def future_positions(position, end, key) -> jax.Array:
    """Per transition at `position` of a segment ending at `end`: a uniform draw from position + 1 .. end,
    or position itself when it is the segment's last (IBC's HindsightExperienceReplayWrapperVer2 maps each
    transition to the indices after it and falls back to its own next observation when there are none)."""
    later = end - position
    offset = 1 + jnp.floor(jax.random.uniform(key, position.shape) * later).astype(jnp.int32)
    # A uniform draw of exactly 1.0 is impossible, float rounding up to `later + 1` is not.
    return jnp.where(later > 0, jnp.minimum(position + offset, end), position)


def sample_her(buffer: SegmentBuffer, key: jax.Array, batch: int, relabel: float, success_fn,
               goal_mask: jax.Array) -> SACBatch:
    """`batch` committed transitions drawn uniformly with replacement; the first round(relabel * batch)
    get the next observation of a uniformly drawn strictly later transition of their segment as goal
    (HER's "future"; a segment's last transition, which has none, takes its own), the rest keep theirs.
    reward = success_fn(next_obs, goal) - 1. The networks see obs ++ goal * goal_mask (the goal's relevant
    dims only)."""
    key_index, key_future = jax.random.split(key)
    low = buffer.oldest
    position = low + jax.random.randint(key_index, (batch,), 0, jnp.maximum(buffer.committed - low, 1))
    slot = position % buffer.capacity
    end = buffer.segment_end[buffer.segment[slot] % buffer.capacity]
    future = future_positions(position, end, key_future)
    relabelled = jnp.arange(batch) < round(relabel * batch)
    goal = jnp.where(relabelled[:, None], buffer.next_obs[future % buffer.capacity], buffer.goal[slot])
    next_obs = buffer.next_obs[slot]
    reward = jax.vmap(success_fn)(next_obs, goal).astype(jnp.float32) - 1.0
    masked = goal * goal_mask
    return SACBatch(obs=jnp.concatenate([buffer.obs[slot], masked], -1), action=buffer.action[slot],
                    reward=reward, next_obs=jnp.concatenate([next_obs, masked], -1),
                    not_done=jnp.ones((batch,), jnp.float32))
