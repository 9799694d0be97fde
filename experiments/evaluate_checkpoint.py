"""Evaluate a run's newest good checkpoint: success per goal over N episodes, optionally a video.

    python -m experiments.evaluate_checkpoint run_dir=runs/point_umaze/morefree/seed0 [episodes=10] [seed=0]
                                   [video=eval.gif] [video_episode=0]

Episodes start from the task's initial states with goals from its evaluation distribution; the policy is
deterministic (as in training-time evaluation). The video is rendered with C MuJoCo on the CPU (EGL);
it is an .mp4 when imageio is installed, else an animated .gif (Pillow), else frames in an .npy file.
Read-only: safe to run beside a live training run. Bad input exits with code 2 and one line.
"""

from __future__ import annotations

import os
import sys

from experiments.cli import REQUIRED, parse_keys


def parse(argv: list[str]) -> dict:
    values = parse_keys(argv, {"run_dir": REQUIRED, "episodes": 10, "seed": 0, "video": None,
                               "video_episode": 0})
    if values["episodes"] <= 0 or not 0 <= values["video_episode"] < values["episodes"]:
        raise ValueError("episodes must be > 0 and 0 <= video_episode < episodes")
    return values


def main(argv: list[str]) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; before anything imports mujoco
    from morefree_jax import runtime

    runtime.configure()  # before any JAX computation
    from morefree_jax.checkpoint import CheckpointError, ConfigMismatchError
    from morefree_jax.config import ConfigError

    try:
        args = parse(argv)
        import jax

        from envs_mjx.normalise import in_task_units
        from morefree_jax.compile import compiler_options
        from morefree_jax.driver import restore_run
        from morefree_jax.evaluate import evaluate_policy, render_episode, success_per_goal, write_video

        run, state, step = restore_run(args["run_dir"])
    except (ValueError, ConfigError, ConfigMismatchError, CheckpointError) as error:
        print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 2
    keep = args["video"] is not None
    evaluate = jax.jit(lambda agent_state, key: evaluate_policy(
        run.env, run.agent, agent_state, key, args["episodes"], keep_states=keep),
        compiler_options=compiler_options(run))
    result = evaluate(state.agent, jax.random.PRNGKey(args["seed"]))
    names = f"{run.config.run.agent} on {run.config.run.env}"
    print(f"{names}, checkpoint step {step}, {args['episodes']} episodes")
    print(f"{'goal':>24} {'episodes':>8} {'success':>8} {'final':>8} {'distance':>9}")
    task_goals = result._replace(goals=in_task_units(run.env, result.goals))  # printed in the task's units
    for row in success_per_goal(task_goals, run.env.goal_dims):
        goal = ", ".join(f"{g:.2f}" for g in row["goal"])
        print(f"{goal:>24} {row['episodes']:>8} {row['success']:>8.2f} {row['final_success']:>8.2f} "
              f"{row['final_distance']:>9.3f}")
    print(f"overall success {float(result.success.mean()):.2f}")
    if keep:
        frames = render_episode(run.env, result.pipeline_states, args["video_episode"])
        print(f"video: {write_video(frames, args['video'])} ({len(frames)} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
