"""Generate MEDAL's demonstrations with the scripted controllers (envs_mjx/scripted.py).

    python -m experiments.make_demos env=push      # or env=all (every task with demonstrations)

Rolls out each task's candidates with a fixed key (deterministic on CPU), keeps the first N successful
episodes in key order, writes envs_mjx/demos/<task>.npz and updates envs_mjx/demos/checksums.json. Prints
one line per task and direction: episodes kept / tried, mean length. Bad input exits with code 2 and one
line; a task whose controller succeeds too rarely exits with code 1 and writes nothing for it.
"""

from __future__ import annotations

import sys
import time

from experiments.cli import parse_keys

SEED = 0


def parse(argv: list[str]) -> tuple[str, ...]:
    from morefree_jax.baselines.medal.demos import demo_path, tasks_with_demos

    values = parse_keys(argv, {"env": "all"})  # env=<task> or env=all
    if values["env"] == "all":
        return tasks_with_demos()
    demo_path(values["env"])  # raises for ant and unknown tasks
    return (values["env"],)


def generate(task: str) -> bool:
    """Rolls out, checks and writes one task; False when the controller fell short."""
    import jax

    import envs_mjx
    from morefree_jax.baselines.medal import demo_rollouts, demos

    env, started = envs_mjx.make(task), time.perf_counter()
    key = jax.random.fold_in(jax.random.PRNGKey(SEED), demos.tasks_with_demos().index(task))
    episodes = demo_rollouts.candidate_episodes(env, task, key, demo_rollouts.NUM_CANDIDATES[task])
    try:
        selected, stats = demo_rollouts.select_demos(episodes, demos.DEMO_COUNTS[task])
    except ValueError as error:
        print(f"{task}: FAILED {error}")
        return False
    for direction, demo in selected.items():
        problems = demos.episode_problems(demo, env.goal_dims, env.success_threshold)
        if problems:
            print(f"{task} {direction}: FAILED the stored-episode check: {'; '.join(problems)}")
            return False
    path = demos.write_demos(task, selected)
    seconds = time.perf_counter() - started
    for direction, (kept, tried, mean_length, rate) in stats.items():
        print(f"{task} {direction}: kept {kept} / tried {tried} episodes (success rate {rate:.2f} over "
              f"{demo_rollouts.NUM_CANDIDATES[task]} candidates), mean length {mean_length:.1f} steps")
    print(f"{task}: wrote {demos.shown(path)} ({path.stat().st_size / 1024:.0f} KiB) in {seconds:.0f} s")
    return True


def main(argv: list[str]) -> int:
    from morefree_jax import runtime

    runtime.configure()  # before any JAX computation
    try:
        tasks = parse(argv)
    except ValueError as error:
        print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 2
    results = [generate(task) for task in tasks]
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
