"""Where successful "back" trajectories start: the data of the paper's back-trajectory figure.

The paper (section 6, fig:backward) analyses MoReFree's replay buffer and plots, for every "back" chunk
(Back-and-Forth Go-Explore's chunk to an initial-state goal) that reached its goal, the xy locations of the
agent / object over the 100 steps before that chunk, shaded by how long it rested there. The run keeps
those locations on the device as it goes (a ring of the newest `BACK_START_SLOTS` successful back chunks,
part of RunState, so it resumes exactly); the driver writes them to `plots/back_starts.npz` at each
evaluation and `experiments/plots.py` draws them.

    starts = init_back_starts()
    starts = record_back_start(starts, env, replay_before_chunk, successful_back)   # in collect, jittable
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

BACK_START_STEPS = 100  # the paper's window: "up to 100 timesteps before a successful Back trajectory"
# Newest successful back chunks kept. Back chunks are ~1/6 of the chunks at alpha 0.2, so 256 keeps all of
# them for ~1,500 chunks (point_umaze 1.5e5 steps, tabletop 3e5); longer runs keep the newest 256.
BACK_START_SLOTS = 256


@struct.dataclass
class BackStarts:
    """xy (K, 100, 2): locations (env.xy) over the 100 stream steps before each successful back chunk, NaN
    before the stream's start; stream_step (K,): stream position where that chunk began; count: successful
    back chunks so far (slot = count % K)."""

    xy: jax.Array
    stream_step: jax.Array
    count: jax.Array


def init_back_starts() -> BackStarts:
    return BackStarts(xy=jnp.full((BACK_START_SLOTS, BACK_START_STEPS, 2), jnp.nan, jnp.float32),
                      stream_step=jnp.full((BACK_START_SLOTS,), -1, jnp.int32),
                      count=jnp.zeros((), jnp.int32))


def record_back_start(starts: BackStarts, env, replay, successful_back: jax.Array) -> BackStarts:
    """Stores the last 100 locations of the stream (the replay before the back chunk is added) when
    `successful_back`; else returns `starts` unchanged."""
    capacity = replay.obs.shape[0]
    position = replay.count - BACK_START_STEPS + jnp.arange(BACK_START_STEPS)
    xy = jax.vmap(env.xy)(replay.obs[position % capacity])
    xy = jnp.where((position >= 0)[:, None], xy, jnp.nan)
    slot = starts.count % BACK_START_SLOTS
    recorded = BackStarts(xy=starts.xy.at[slot].set(xy),
                          stream_step=starts.stream_step.at[slot].set(replay.count), count=starts.count + 1)
    return jax.tree.map(lambda new, old: jnp.where(successful_back, new, old), recorded, starts)


def stored_back_starts(starts: BackStarts) -> tuple[np.ndarray, np.ndarray]:
    """(xy (n, 100, 2), stream_step (n,)) of the stored back chunks, oldest first (host numpy)."""
    xy, steps, count = (np.asarray(x) for x in jax.device_get((starts.xy, starts.stream_step, starts.count)))
    kept = min(int(count), BACK_START_SLOTS)
    order = np.argsort(steps[steps >= 0], kind="stable")[:kept]
    valid = np.flatnonzero(steps >= 0)[order]
    return xy[valid], steps[valid]
