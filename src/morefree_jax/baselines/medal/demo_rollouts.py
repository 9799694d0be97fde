"""Rolling out the scripted controllers (envs_mjx.scripted) into MEDAL's demonstrations.

A forward episode starts at `env.reset(key)` and drives towards a goal from `env.eval_goals(key)`; a
reverse episode starts where its forward episode ended (the task solved) and drives back to a state from
`env.initial_states(key)`. Both last at most `env.eval_episode_length` steps and end on the first step
whose next observation is a success. All candidates of a task (forward, then reverse from their final
states) run in one compiled call: a `lax.scan` over steps, vmapped over episodes. The first N successful
candidates in key order are kept, so a fixed key gives the same demonstrations every time (on CPU).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs_mjx import scripted
from morefree_jax.baselines.medal import demos

# Candidates rolled out per task: a margin over the counts for controllers that sometimes fail.
NUM_CANDIDATES = {"point_umaze": 40, "tabletop": 16, "sawyer_door": 8, "push": 40, "pick_place": 40,
                  "push_hard": 40, "pick_place_hard": 40}

class Episodes(NamedTuple):
    """Candidate episodes, padded to the episode length T; E episodes."""

    goals: np.ndarray  # (E, O)
    observations: np.ndarray  # (E, T, O)
    actions: np.ndarray  # (E, T, A)
    next_observations: np.ndarray  # (E, T, O)
    active: np.ndarray  # (E, T) bool: the step belongs to the episode (no success before it)
    solved: np.ndarray  # (E, T) bool: the step's next observation is the first success


def run_episode(env, controller, state, goal):
    """One episode of `controller` from `state` (frozen after its first success). Returns the per-step
    records (time-major) and the final env state."""

    def body(carry, _):
        state, phase, done = carry
        action, next_phase = controller(state.obs, goal, phase)
        action = jnp.asarray(action, jnp.float32)
        next_state = env.step(state, action)
        solved = env.success(next_state.obs, goal) & ~done
        record = (state.obs, action, next_state.obs, ~done, solved)
        # After the success the state stays where the episode ended: the reverse episode starts there.
        state = jax.tree.map(lambda old, new: jnp.where(done, old, new), state, next_state)
        return (state, next_phase, done | solved), record

    start = (state, jnp.zeros((), jnp.int32), jnp.zeros((), bool))
    (final, _, _), records = jax.lax.scan(body, start, None, length=env.eval_episode_length)
    return records, final


def candidate_episodes(env, task: str, key: jax.Array, num_candidates: int) -> dict:
    """{direction: Episodes} of `num_candidates` forward (and reverse, where the task has them) candidates."""
    directions = demos.DEMO_COUNTS[task]
    key_forward, key_reverse = jax.random.split(key)

    def forward(key):
        key_reset, key_goal = jax.random.split(key)
        goal = env.eval_goals(key_goal)
        records, final = run_episode(env, scripted.CONTROLLERS[task, "forward"], env.reset(key_reset), goal)
        return (goal, *records), final

    def reverse(state, key):
        goal = env.initial_states(key)
        records, _ = run_episode(env, scripted.CONTROLLERS[task, "reverse"], state, goal)
        return (goal, *records)

    def run_all(key_forward, key_reverse):
        forward_records, finals = jax.vmap(forward)(jax.random.split(key_forward, num_candidates))
        result = {"forward": forward_records}
        if "reverse" in directions:
            result["reverse"] = jax.vmap(reverse)(finals, jax.random.split(key_reverse, num_candidates))
        return result

    records = jax.device_get(jax.jit(run_all)(key_forward, key_reverse))
    return {direction: Episodes(*values) for direction, values in records.items()}


def successful(episodes: Episodes) -> np.ndarray:
    return episodes.solved.any(axis=1)


def keep_first(episodes: Episodes, indices: np.ndarray) -> demos.DemoSet:
    """The flat transitions of the episodes at `indices`, in that order."""
    parts = []
    for i in indices:
        steps = episodes.active[i]
        length = int(steps.sum())
        goals = np.repeat(episodes.goals[i][None], length, axis=0)
        solved = episodes.solved[i][steps].astype(np.float32)
        parts.append((episodes.observations[i][steps], goals, episodes.actions[i][steps], solved, solved,
                      episodes.next_observations[i][steps]))
    return demos.DemoSet(*(np.concatenate(column).astype(np.float32) for column in zip(*parts, strict=True)))


def select_demos(episodes: dict[str, Episodes], counts: dict[str, int]) -> tuple[dict, dict]:
    """Keeps the first counts[direction] successful episodes of each direction in key order; a reverse
    candidate counts only when its forward episode succeeded (else it did not start from a solved task).

    Returns ({direction: DemoSet}, {direction: (kept, tried, mean length)}); raises ValueError when too
    few candidates succeeded."""
    forward_ok = successful(episodes["forward"])
    selected, stats = {}, {}
    for direction, count in counts.items():
        ok = successful(episodes[direction]) & forward_ok
        indices = np.flatnonzero(ok)[:count]
        tried = len(ok) if len(indices) < count else int(indices[-1]) + 1
        if len(indices) < count:
            message = f"only {len(indices)} of {tried} candidates succeeded, {count} needed"
            raise ValueError(f"{direction}: {message}")
        selected[direction] = keep_first(episodes[direction], indices)
        mean_length = float(episodes[direction].active[indices].sum(axis=1).mean())
        stats[direction] = (count, tried, mean_length, float(ok.mean()))
    return selected, stats
