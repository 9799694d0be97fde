"""Episodic evaluation on fresh env instances and the replay's visitation statistics.

    result = evaluate_policy(env, agent, agent_state, key, num_episodes=10)   # jit at the caller
    metrics = evaluation_metrics(result)
    views = visitation(env, replay, bins=50)   # {"task_relevant", "xy"} (+ {"in_air", "xz"}: side view)

Evaluation follows PEG (docs/training.md, "Evaluation"): every episode starts from a fresh reset (the task's
initial-state distribution) with a goal from the task's `evaluation_goals` (independent eval_goals draws, or
the task's order); the goal-conditioned policy acts deterministically (its mode), the latent is filtered from
is_first; success is the task's `success` at ANY step of the episode (PEG's max over the episode), and we
also report success at the last step and the final distance to the goal.
Episodes are vmapped; the env steps run inside one lax.scan.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.agent import MODE_DETERMINISTIC, MODE_GOAL


class EvalResult(NamedTuple):
    """Per episode (E,): success at any step, success at the last step, final and smallest distance to the
    goal; goals and final_obs, the last observations (E, O). pipeline_states: the episodes' states over
    time (T, E, ...) when kept, else None."""

    success: jax.Array
    final_success: jax.Array
    final_distance: jax.Array
    min_distance: jax.Array
    goals: jax.Array
    final_obs: jax.Array
    pipeline_states: object = None


def evaluate_policy(env, agent, agent_state, key: jax.Array, num_episodes: int,
                    episode_length: int | None = None, keep_states: bool = False) -> EvalResult:
    """num_episodes vmapped episodes of `episode_length` (default: the task's) steps -> EvalResult."""
    length = episode_length or env.eval_episode_length
    key_reset, key_goal, key_act = jax.random.split(key, 3)
    env_states = jax.vmap(env.reset)(jax.random.split(key_reset, num_episodes))
    goals = env.evaluation_goals(key_goal, num_episodes)
    contexts = agent.goal_context(agent_state, goals)  # the goals are fixed for the episode: encode them once
    act = jax.vmap(agent.act, in_axes=(None, 0, 0, 0, 0, 0, None))
    mode = MODE_GOAL | MODE_DETERMINISTIC
    carry = (env_states, agent.initial_latent((num_episodes,)), jnp.zeros((num_episodes, env.action_size)),
             jnp.zeros(num_episodes, bool), jnp.full(num_episodes, jnp.inf))

    def step(carry, key_step):
        env_states, latent, prev_action, reached, closest = carry
        action, latent = act(agent_state, latent, prev_action, env_states.obs, contexts,
                             jax.random.split(key_step, num_episodes), mode)
        env_states = jax.vmap(env.step)(env_states, action)
        reached = reached | jax.vmap(env.success)(env_states.obs, goals)
        closest = jnp.minimum(closest, jax.vmap(env.goal_distance)(env_states.obs, goals))
        kept = env_states.pipeline_state if keep_states else None
        return (env_states, latent, action, reached, closest), kept

    final, states = jax.lax.scan(step, carry, jax.random.split(key_act, length))
    env_states, _, _, reached, closest = final
    return EvalResult(
        success=reached, final_success=jax.vmap(env.success)(env_states.obs, goals),
        final_distance=jax.vmap(env.goal_distance)(env_states.obs, goals), min_distance=closest, goals=goals,
        final_obs=env_states.obs, pipeline_states=states,
    )


def evaluation_metrics(result: EvalResult) -> dict:
    """eval/success (PEG: any step), eval/final_success, eval/final_distance: means over episodes."""
    return {
        "eval/success": jnp.mean(result.success.astype(jnp.float32)),
        "eval/final_success": jnp.mean(result.final_success.astype(jnp.float32)),
        "eval/final_distance": jnp.mean(result.final_distance),
        "eval/min_distance": jnp.mean(result.min_distance),
    }


def success_per_goal(result: EvalResult, goal_dims) -> list[dict]:
    """Groups episodes by their goal (on goal_dims, rounded to 1e-4) -> [{goal, episodes, success,
    final_success, final_distance}], for tasks with a few fixed goals (PointUMaze: 1, Tabletop: 4)."""
    goals = np.round(np.asarray(result.goals)[:, list(goal_dims)], 4)
    rows = []
    for goal in np.unique(goals, axis=0):
        mask = np.all(goals == goal, axis=1)
        rows.append({
            "goal": goal.tolist(), "episodes": int(mask.sum()),
            "success": float(np.asarray(result.success)[mask].mean()),
            "final_success": float(np.asarray(result.final_success)[mask].mean()),
            "final_distance": float(np.asarray(result.final_distance)[mask].mean()),
        })
    return rows


def visited_rows(replay, skip_rows: int = 0) -> jax.Array:
    """(capacity,) the filled rows the stream visited. skip_rows: leading rows it did not (MEDAL's
    demonstrations, written first); once the ring wraps it overwrites them from row 0 on, and each
    overwritten row counts."""
    capacity = replay.obs.shape[0]
    rows = jnp.arange(capacity)
    rewritten = rows < replay.count - capacity  # written again after the ring wrapped
    return ((rows >= skip_rows) | rewritten) & (rows < jnp.minimum(replay.count, capacity))


def visitation(env, replay, bins: int, skip_rows: int = 0) -> dict[str, jax.Array]:
    """Over the visited transitions in the replay (visited_rows): "task_relevant", the fraction near an
    initial state or an evaluation goal, and "xy", a (bins, bins) histogram of env.xy over the task's
    observation bounds. Tasks with a side view (env.side_view_dims) add "xz", the histogram of
    env.side_view (horizontal, height), and "in_air", the fraction above env.air_height."""
    weights = visited_rows(replay, skip_rows).astype(jnp.float32)
    total = jnp.maximum(jnp.sum(weights), 1.0)
    relevant = jax.vmap(env.task_relevant)(replay.obs)
    views = {"task_relevant": jnp.sum(relevant * weights) / total,
             "xy": _histogram(env.xy, env, replay.obs, weights, bins)}
    if env.side_view_dims is not None:
        height = jax.vmap(env.side_view)(replay.obs)[:, 1]
        views["in_air"] = jnp.sum((height > env.air_height) * weights) / total
        views["xz"] = _histogram(env.side_view, env, replay.obs, weights, bins)
    return views


def _histogram(view, env, obs, weights, bins: int) -> jax.Array:
    """(bins, bins) weighted histogram of view(obs) (2-D points) over the view of the observation bounds."""
    points = jax.vmap(view)(obs)
    with jax.ensure_compile_time_eval():  # constants of the task, also when traced
        low, high = (np.asarray(view(jnp.asarray(b, jnp.float32))) for b in env.observation_bounds)
    box = [[low[0], high[0]], [low[1], high[1]]]
    histogram, _, _ = jnp.histogram2d(points[:, 0], points[:, 1], bins=bins, range=box, weights=weights)
    return histogram


def render_episode(env, pipeline_states, episode: int = 0, width: int = 320, height: int = 240) -> np.ndarray:
    """RGB frames (T, H, W, 3) of one episode of `EvalResult.pipeline_states` (T, E, ...), rendered by C
    MuJoCo on the CPU (set MUJOCO_GL=egl on a headless machine)."""
    states = jax.device_get(pipeline_states)
    length = jax.tree.leaves(states)[0].shape[0]
    steps = (jax.tree.map(lambda x, t=t: x[t, episode], states) for t in range(length))
    return env.render_frames(steps, width=width, height=height)


def write_video(frames: np.ndarray, path, fps: int = 20) -> str:
    """Writes frames (T, H, W, 3): .mp4 when imageio is installed, an animated .gif with Pillow, else
    .npy. Returns the path written (its suffix may differ from the one asked for)."""
    import importlib.util
    import pathlib

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".mp4" and importlib.util.find_spec("imageio") is not None:
        import imageio

        imageio.mimwrite(path, list(frames), fps=fps)
        return str(path)
    if path.suffix in (".mp4", ".gif") and importlib.util.find_spec("PIL") is not None:
        from PIL import Image

        path = path.with_suffix(".gif")
        images = [Image.fromarray(frame) for frame in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
        return str(path)
    path = path.with_suffix(".npy")
    np.save(path, frames)
    return str(path)
