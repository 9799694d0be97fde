"""Env throughput of every registered task in the reset-free setting (one stream, random actions).

Three ways of stepping the same task, measured in one run:
  fused scan   reset + N steps inside one jitted lax.scan (how the training loop steps the stream)
  python loop  a jitted `step` called from Python once per step (shows the dispatch cost)
  C MuJoCo     the task's MJCF stepped by mujoco.mj_step, frames_per_step substeps per env step
"""

from __future__ import annotations

import functools
import time

import jax
import mujoco
import numpy as np

import envs_mjx

# Issue bars for the fused scan on the 2-core CPU (env steps per second); point_umaze steps MJX physics
# since the original's physics was ported (bar 2,000).
BARS = {"point_umaze": 2_000, "tabletop": 20_000}
DEFAULT_BAR = 1_000


def _row(name: str, value: float, unit: str, note: str = "") -> dict:
    return {"section": "envs", "name": name, "value": float(value), "unit": unit, "note": note}


def _fused_rollout(env, key, num_steps: int):
    key_reset, key_actions = jax.random.split(key)
    actions = jax.random.uniform(key_actions, (num_steps, env.action_size), minval=-1.0, maxval=1.0)

    def body(state, action):
        state = env.step(state, action)
        return state, None

    final, _ = jax.lax.scan(body, env.reset(key_reset), actions)
    return final  # the whole state: returning only obs would let XLA drop unused pipeline_state work


def time_call(fn, *args) -> float:
    started = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - started


def fused_scan(env, num_steps: int) -> tuple[float, float]:
    """(compile + first call seconds, steady-state env steps per second)."""
    rollout = jax.jit(functools.partial(_fused_rollout, env, num_steps=num_steps))
    compile_s = time_call(rollout, jax.random.PRNGKey(0))
    run_s = min(time_call(rollout, jax.random.PRNGKey(i)) for i in (1, 2))
    return compile_s, num_steps / run_s


def python_loop(env, num_steps: int) -> float:
    step = jax.jit(env.step)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    actions = np.random.default_rng(0).uniform(-1, 1, (num_steps + 1, env.action_size)).astype(np.float32)
    state = jax.block_until_ready(step(state, actions[0]))  # compile
    started = time.perf_counter()
    for action in actions[1:]:
        state = step(state, action)
    jax.block_until_ready(state)
    return num_steps / (time.perf_counter() - started)


def c_mujoco(env, num_steps: int) -> float:
    model = env.mj_model
    data = env.mj_data_from(jax.jit(env.reset)(jax.random.PRNGKey(0)).pipeline_state)
    low, high = model.actuator_ctrlrange.T if model.nu else (np.zeros(0), np.zeros(0))
    controls = np.random.default_rng(0).uniform(low, high, (num_steps, model.nu))
    started = time.perf_counter()
    for ctrl in controls:
        data.ctrl[:] = ctrl
        for _ in range(env.frames_per_step):
            mujoco.mj_step(model, data)
    return num_steps / (time.perf_counter() - started)


def steps_for(name: str, quick: bool) -> tuple[int, int]:
    """(fused-scan steps, python-loop and C steps) sized to take a few seconds each."""
    bar = BARS.get(name, DEFAULT_BAR)
    if quick:
        return (2_000, 50) if bar >= 20_000 else (100, 10)
    if bar >= 20_000:
        return 200_000, 2_000
    return (20_000, 1_000) if bar >= 2_000 else (5_000, 300)


def run(quick: bool = False, names=None) -> list[dict]:
    rows = []
    for name in names or envs_mjx.ALL_ENVS:
        env = envs_mjx.make(name)
        fused_steps, loop_steps = steps_for(name, quick)
        compile_s, fused = fused_scan(env, fused_steps)
        bar = BARS.get(name, DEFAULT_BAR)
        verdict = "meets" if fused >= bar else "BELOW"
        rows.append(_row(f"{name}/fused_scan", fused, "steps/s", f"bar {bar}: {verdict}"))
        rows.append(_row(f"{name}/python_loop_jitted_step", python_loop(env, loop_steps), "steps/s"))
        rows.append(_row(f"{name}/c_mujoco_mj_step", c_mujoco(env, loop_steps), "steps/s", "same MJCF"))
        rows.append(_row(f"{name}/compile_fused_scan", compile_s, "s", f"{fused_steps} steps"))
    return rows
