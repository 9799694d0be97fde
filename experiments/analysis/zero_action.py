"""The chance level of a task's evaluation: the success of a policy that never acts.

    reference = zero_action_reference("push_hard", episodes=1000)   # {"task", "episodes", "success", ...}
    write_reference(reference, "results/data")                      # results/data/push_hard/zero_action.json
    read_reference("results/data", "push_hard")                     # None where none was written

Episodes as evaluate.evaluate_policy runs them (a fresh reset, a goal from the task's evaluation goals, the
task's episode length, success at any step and at the last), with a zero action at every step. On the Fetch
tasks goals are drawn around the block's start, so some are met before the robot moves (a goal within the
success threshold of the start); a learning curve means something above this level.
"""

from __future__ import annotations

import json
import pathlib

import jax
import jax.numpy as jnp

import envs_mjx
from morefree_jax.provenance import code_version

FILE_NAME = "zero_action.json"
EPISODES = 1000
BATCH = 200  # episodes per compiled call (zero_action_reference says why)


def zero_action_rollout(env, key: jax.Array, episodes: int) -> tuple[jax.Array, jax.Array]:
    """(success at any step, success at the last step), each (episodes,) bool, of zero-action episodes."""
    key_reset, key_goal = jax.random.split(key)
    states = jax.vmap(env.reset)(jax.random.split(key_reset, episodes))
    goals = env.evaluation_goals(key_goal, episodes)
    action = jnp.zeros((episodes, env.action_size))

    def step(carry, _):
        states, reached = carry
        states = jax.vmap(env.step)(states, action)
        return (states, reached | jax.vmap(env.success)(states.obs, goals)), None

    (states, reached), _ = jax.lax.scan(step, (states, jnp.zeros(episodes, bool)), None,
                                        length=env.eval_episode_length)
    return reached, jax.vmap(env.success)(states.obs, goals)


def zero_action_reference(task: str, episodes: int = EPISODES, seed: int = 0) -> dict:
    """The chance level of `task` over `episodes` episodes, run BATCH episodes per call: 1,000 MJX episodes
    in one call stalled XLA's CPU runtime (no progress, threads idle) when it had two cores to itself, not
    when pinned to one; 200 per call ran on either."""
    env = envs_mjx.make(task)
    rollout = jax.jit(zero_action_rollout, static_argnums=(0, 2))
    keys = jax.random.split(jax.random.PRNGKey(seed), -(-episodes // BATCH))
    counts = [min(BATCH, episodes - i * BATCH) for i in range(len(keys))]
    reached, final = zip(*(rollout(env, key, count) for key, count in zip(keys, counts, strict=True)),
                         strict=True)
    return {"task": task, "episodes": episodes, "seed": seed,
            "success": float(jnp.mean(jnp.concatenate(reached))),
            "final_success": float(jnp.mean(jnp.concatenate(final))), "commit": code_version()["commit"]}


def reference_path(data_root, task: str) -> pathlib.Path:
    return pathlib.Path(data_root) / task / FILE_NAME


def write_reference(reference: dict, data_root) -> pathlib.Path:
    path = reference_path(data_root, reference["task"])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(reference, indent=1) + "\n")
    return path


def read_reference(data_root, task: str) -> dict | None:
    path = reference_path(data_root, task)
    return json.loads(path.read_text()) if path.exists() else None


def markdown_line(reference: dict) -> str:
    return (f"Chance level: a policy that never acts succeeds in {reference['success']:.3f} of "
            f"{reference['episodes']:,} episodes at any step and {reference['final_success']:.3f} at the "
            f"last step ({FILE_NAME}, commit {(reference['commit'] or 'unknown')[:7]}).")
