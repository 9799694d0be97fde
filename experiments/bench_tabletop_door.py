"""Throughput of tabletop and sawyer_door in the fused single-stream scan (one env, no vmap).

A jitted function resets the env and runs `lax.scan` over N uniform random actions; the second call is
timed (the first compiles). For the door a second number uses the scripted closing controller of
tests/test_sawyer_door.py, so the fingers are in contact with the door for most steps.

    PYTHONPATH=src:. python -c "import experiments.bench_tabletop_door as b; print(b.run())"
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp

import envs_mjx
from envs_mjx import sawyer_door

SECTION = "envs/tabletop_door"


def random_action_scan(env, num_steps: int):
    def rollout(key):
        key_reset, key_actions = jax.random.split(key)
        actions = jax.random.uniform(key_actions, (num_steps, env.action_size), minval=-1.0, maxval=1.0)

        def body(state, action):
            state = env.step(state, action)
            return state, state.obs

        state, observations = jax.lax.scan(body, env.reset(key_reset), actions)
        return state, observations  # the whole final state, so no part of the step is dead code

    return jax.jit(rollout)


def door_closing_scan(env, num_steps: int):
    """Pushes the leaf shut along its arc (a compact copy of the test's controller)."""

    def leaf_point(angle, front):
        cos, sin = jnp.cos(angle), jnp.sin(angle)
        x, y = 0.30, -front
        hinge = sawyer_door.HINGE
        return jnp.stack([hinge[0] + cos * x - sin * y, hinge[1] + sin * x + cos * y, jnp.asarray(0.18)])

    def body(carry, _):
        state, pushing = carry
        angle = sawyer_door.door_angle_of_handle(state.obs[4:7])
        approach, push = leaf_point(angle, 0.045), leaf_point(jnp.minimum(angle + 0.2, 0.0), 0.025)
        pushing = pushing | (jnp.linalg.norm(state.obs[0:3] - approach) < 0.015)
        target = jnp.where(pushing, push, approach)
        move = jnp.clip((target - state.obs[0:3]) / sawyer_door.MOCAP_STEP, -1.0, 1.0)
        state = env.step(state, jnp.concatenate([move, jnp.ones(1)]))
        return (state, pushing), state.obs

    def rollout(key):
        (state, _), observations = jax.lax.scan(
            body, (env.reset(key), jnp.array(False)), None, length=num_steps
        )
        return state, observations

    return jax.jit(rollout)


def time_scan(compiled, num_steps: int, repeats: int = 2) -> tuple[float, float, float]:
    """(compile + first call seconds, best wall-clock steps/s and best process-CPU steps/s over `repeats`
    further calls). CPU time is less sensitive than wall time to other processes sharing the cores."""
    start = time.perf_counter()
    jax.block_until_ready(compiled(jax.random.PRNGKey(0)))
    first = time.perf_counter() - start
    best_wall = best_cpu = float("inf")
    for i in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(jax.random.PRNGKey(i + 1)))
        best_wall = min(best_wall, time.perf_counter() - start)
        best_cpu = min(best_cpu, time.process_time() - start_cpu)
    return first, num_steps / best_wall, num_steps / best_cpu


def row(name: str, value: float, unit: str, note: str) -> dict:
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def run(quick: bool = False) -> list[dict]:
    rows = []
    cases = [("tabletop", random_action_scan, 2_000 if quick else 20_000, "random actions")]
    if not quick:  # the door's physics alone takes ~20 s to compile on this CPU
        cases += [
            ("sawyer_door", random_action_scan, 2_000, "random actions"),
            ("sawyer_door", door_closing_scan, 300, "scripted closing (contacts)"),
        ]
    for name, make_scan, num_steps, what in cases:
        env = envs_mjx.make(name)
        first, per_wall_s, per_cpu_s = time_scan(make_scan(env, num_steps), num_steps)
        note = f"fused single-stream lax.scan of {num_steps} steps, {what}; 2nd+ call, best of 2"
        kind = what.split()[0]
        rows.append(row(f"{name}/env_steps_per_s/{kind}", per_wall_s, "steps/s", note + ", wall clock"))
        rows.append(row(f"{name}/env_steps_per_cpu_s/{kind}", per_cpu_s, "steps/s", note + ", process CPU"))
        rows.append(row(f"{name}/compile_s/{kind}", first, "s", "compile + first call"))
    return rows


if __name__ == "__main__":
    for row in run():
        print(f"{row['name']:45s} {row['value']:12.1f} {row['unit']:8s} {row['note']}")
