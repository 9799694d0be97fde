"""Throughput of the four Fetch tasks in the fused single-stream scan (the reset-free training pattern).

For each task: jit(reset, then lax.scan of N uniform random-action steps), compile it once, then time
further calls with new keys. Reports steps/s (best of the repeats, wall clock and process CPU time; on a
shared machine the CPU-time figure is the less load-dependent one) and the compile time.

    PYTHONPATH=src:. python -c "import experiments.bench_fetch as b; print(b.run())"
"""

from __future__ import annotations

import functools
import time

import jax

import envs_mjx

TASKS = ("push", "pick_place", "push_hard", "pick_place_hard")


def random_action_stream(env: envs_mjx.ResetFreeEnv, key: jax.Array, num_steps: int) -> jax.Array:
    """Reset, then `num_steps` uniform random actions in one lax.scan; returns the final observation."""
    key_reset, key_actions = jax.random.split(key)
    actions = jax.random.uniform(key_actions, (num_steps, env.action_size), minval=-1.0, maxval=1.0)

    def body(state, action):
        return env.step(state, action), None

    final, _ = jax.lax.scan(body, env.reset(key_reset), actions)
    return final.obs


def measure_task(name: str, num_steps: int, repeats: int) -> list[dict]:
    env = envs_mjx.make(name)
    stream = jax.jit(functools.partial(random_action_stream, env, num_steps=num_steps))
    start = time.perf_counter()
    jax.block_until_ready(stream(jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - start
    wall, cpu = [], []
    for repeat in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(stream(jax.random.PRNGKey(repeat + 1)))
        wall.append(num_steps / (time.perf_counter() - start_wall))
        cpu.append(num_steps / (time.process_time() - start_cpu))
    note = f"fused reset + lax.scan of {num_steps} random-action steps, best of {repeats}"
    return [
        {"section": "fetch", "name": f"{name}/scan_steps_per_s", "value": max(wall), "unit": "steps/s",
         "note": note + " (wall clock)"},
        {"section": "fetch", "name": f"{name}/scan_steps_per_cpu_s", "value": max(cpu), "unit": "steps/s",
         "note": note + " (process CPU time: less sensitive to other load)"},
        {"section": "fetch", "name": f"{name}/compile_s", "value": compile_s, "unit": "s",
         "note": "first call, compile + one run"},
    ]


def run(quick: bool = False) -> list[dict]:
    """All four tasks (2,000 steps, 3 repeats); quick: push only, 100 steps, 1 repeat (compile-bound)."""
    if quick:
        return measure_task("push", num_steps=100, repeats=1)
    return [row for name in TASKS for row in measure_task(name, num_steps=2000, repeats=3)]


if __name__ == "__main__":
    for row in run():
        print(f"{row['name']:<32} {row['value']:>10.1f} {row['unit']:<8} {row['note']}")
