"""Where a run's goal policy misses its goal, and what its learned reward says there.

    python -m experiments.analysis.goal_probe run_dir=runs/point_umaze/morefree/seed2 [episodes=10]
                                              [points=9] [seed=0] [out=probe.json]
    make probe RUN_DIR=runs/point_umaze/morefree/seed2

Loads the run dir's newest good checkpoint (read-only, safe beside a live run), runs the evaluation
episodes (as evaluate_checkpoint does) and takes the goal of the first episode. It prints where the
episodes with that goal end, and the learned temporal distance to the goal (in env steps, what the go phase
compares with its early-switch threshold) at `points` positions on the line from the goal to the episodes'
mean end. Positions are in the task's goal coordinates; every other observation entry is the goal's own.

The world-model agents' goal policy maximises minus the learned distance (docs/learner.md), so a minimum
of the distance away from the goal is a place the policy is rewarded for stopping at: a seed whose episodes
end there misses the goal because of its learned reward, not for want of exploration or of an actor that
reaches the place it is rewarded for. Bad input exits with code 2 and one line.
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

from experiments.cli import REQUIRED, parse_keys

MIN_POINTS = 2


def parse(argv: list[str]) -> dict:
    values = parse_keys(argv, {"run_dir": REQUIRED, "episodes": 10, "points": 9, "seed": 0, "out": None})
    if values["episodes"] <= 0:
        raise ValueError(f"episodes must be > 0, got {values['episodes']}")
    if values["points"] < MIN_POINTS:
        raise ValueError(f"points must be >= {MIN_POINTS} (the goal and the mean end), "
                         f"got {values['points']}")
    return values


def line_positions(start: np.ndarray, end: np.ndarray, points: int) -> np.ndarray:
    """`points` positions evenly spaced from `start` to `end`, both included: (points, D)."""
    fractions = np.linspace(0.0, 1.0, points)[:, None]
    return start[None] + fractions * (end - start)[None]


def probe_observations(goal: np.ndarray, goal_dims, positions: np.ndarray) -> np.ndarray:
    """The goal observation (task units) with its goal coordinates set to each position: (P, O)."""
    probes = np.repeat(goal[None].astype(np.float32), len(positions), axis=0)
    probes[:, list(goal_dims)] = positions
    return probes


def goal_episodes(goals: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Mask of the episodes whose goal is `goal` (tasks with several evaluation goals mix them)."""
    return np.all(np.isclose(goals, goal[None], atol=1e-5), axis=-1)


def learned_distance_line(run, agent_state, goal_task: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """The agent's learned distance (env steps) from each position to the goal, both in task units: (P,)."""
    import jax
    import jax.numpy as jnp

    from envs_mjx.normalise import NormalisedObservations

    to_env = run.env.normalise if isinstance(run.env, NormalisedObservations) else (lambda x: x)
    probes = to_env(jnp.asarray(probe_observations(goal_task, run.env.goal_dims, positions)))
    goals = jnp.broadcast_to(to_env(jnp.asarray(goal_task, jnp.float32)), probes.shape)
    latent = run.agent.initial_latent((len(positions),))  # unused: the probes are embedded from observations
    distance = jax.jit(lambda state: run.agent.goal_distance(state, latent, goals, obs=probes))(agent_state)
    return np.asarray(distance)


def probe(run, agent_state, key, episodes: int, points: int) -> dict:
    """The evaluation episodes of the first episode's goal and the learned distance on the line to where
    they end (module docstring)."""
    import jax

    from envs_mjx.normalise import in_task_units
    from morefree_jax.compile import compiler_options
    from morefree_jax.evaluate import evaluate_policy

    evaluate = jax.jit(lambda state, k: evaluate_policy(run.env, run.agent, state, k, episodes),
                       compiler_options=compiler_options(run))
    result = evaluate(agent_state, key)
    goals = np.asarray(in_task_units(run.env, result.goals))
    ends = np.asarray(in_task_units(run.env, result.final_obs))[:, list(run.env.goal_dims)]
    same = goal_episodes(goals, goals[0])
    goal_position = goals[0, list(run.env.goal_dims)]
    mean_end = ends[same].mean(axis=0)
    positions = line_positions(goal_position, mean_end, points)
    distances = learned_distance_line(run, agent_state, goals[0], positions)
    return {"goal": goal_position.tolist(), "goal_observation": goals[0].tolist(),
            "episodes": int(same.sum()), "success": int(np.asarray(result.success)[same].sum()),
            "final_success": int(np.asarray(result.final_success)[same].sum()),
            "ends": ends[same].tolist(), "mean_end": mean_end.tolist(),
            "final_distance": float(np.asarray(result.final_distance)[same].mean()),
            "line": [{"position": p.tolist(), "learned_distance": float(d)}
                     for p, d in zip(positions, distances, strict=True)]}


def _point(values) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in values) + ")"


def report(found: dict) -> list[str]:
    """The probe as printed lines: the episodes, the line's table and where its minimum lies."""
    distances = [row["learned_distance"] for row in found["line"]]
    lowest = int(np.argmin(distances))
    fraction = lowest / (len(distances) - 1)
    lines = [f"goal {_point(found['goal'])}: {found['success']}/{found['episodes']} episodes reach it, "
             f"{found['final_success']} end on it; mean end {_point(found['mean_end'])}, "
             f"mean final distance {found['final_distance']:.2f}",
             "learned distance to the goal (env steps) on the line from the goal to the mean end:"]
    for i, row in enumerate(found["line"]):
        mark = " <- goal" if i == 0 else " <- mean end" if i == len(distances) - 1 else ""
        lines.append(f"  {_point(row['position']):>24} {row['learned_distance']:8.2f}{mark}")
    lines.append(f"minimum {distances[lowest]:.2f} at {fraction:.2f} of the way from the goal to the mean "
                 f"end (at the goal: {distances[0]:.2f})")
    return lines


def probe_run(run_dir, episodes: int = 10, points: int = 9, seed: int = 0) -> dict:
    """The probe of a run dir's newest good checkpoint, with the run's task, agent, commits and step.
    Raises ValueError (or the checkpoint's and config's errors) for what cannot be probed."""
    import jax

    from experiments.analysis.run_record import read_starts, short_commits
    from morefree_jax.driver import restore_run

    run, state, step = restore_run(run_dir)
    if not hasattr(run.agent, "goal_distance"):
        raise ValueError(f"goal_probe needs a world-model agent (it reads the learned distance); "
                         f"{run.config.run.agent} has none")
    found = probe(run, state.agent, jax.random.PRNGKey(seed), episodes, points)
    return {"run_dir": str(run_dir), "task": run.config.run.env, "agent": run.config.run.agent,
            "commits": list(short_commits(read_starts(pathlib.Path(run_dir)))),
            "checkpoint_step": int(step), "seed": seed, **found}


def main(argv: list[str]) -> int:
    from morefree_jax import runtime

    runtime.configure()  # before any JAX computation
    from morefree_jax.checkpoint import CheckpointError, ConfigMismatchError
    from morefree_jax.config import ConfigError

    try:
        args = parse(argv)
        found = probe_run(args["run_dir"], args["episodes"], args["points"], args["seed"])
    except (ValueError, ConfigError, ConfigMismatchError, CheckpointError) as error:
        print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"{found['agent']} on {found['task']} (code {', '.join(found['commits'])}), checkpoint step "
          f"{found['checkpoint_step']}, {args['episodes']} episodes")
    print("\n".join(report(found)))
    if args["out"]:
        pathlib.Path(args["out"]).write_text(json.dumps(found, indent=1) + "\n")
        print(f"written: {args['out']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
