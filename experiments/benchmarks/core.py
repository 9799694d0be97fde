"""Benchmark of the learning core: compile time, ms per train_step and per component, ms per act,
achieved FLOP/s of train_step (XLA cost analysis) next to a matmul peak measured in the same run.

    PYTHONPATH=src:. python -c "import experiments.benchmarks.core as b; print(b.run())"
    PYTHONPATH=src:. python experiments/benchmarks/core.py [presets=paper,cpu] [precisions=f32,bf16] [reps=3]

Shapes: `paper` with ant shapes (obs 29, action 8, batch 45 x 50, the reference TF2 measurement);
`cpu` with PointUMaze shapes (obs 7, action 2). Each preset at each precision (agent.precision; rows
`<preset>_<precision>/...`); the paper rows come from one child process per precision in the `large`
runtime that precision uses (morefree_jax.runtime), each with its own matmul peak. Rows: {"section", "name",
"value", "unit", "note"}.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp

from experiments.cli import parse_keys
from morefree_jax import runtime
from morefree_jax.agent import MODE_GOAL, EnvSpec, acting_state, make_agent
from morefree_jax.imagination import GoalPools
from morefree_jax.learner_config import preset
from morefree_jax.world_model import Batch

SECTION = "core"
SHAPES = {"paper": EnvSpec(29, 8, (0, 1)), "cpu": EnvSpec(7, 2, (0, 1)), "debug": EnvSpec(7, 2, (0, 1))}
# Original TF2 agent, paper config, ant shapes, measured on another day (issue 3). Printed as a labelled
# constant only: on a slower day here the same step took 1.5x longer, so a ratio to it means nothing.
REFERENCE_TRAIN_S = 6.85


def _row(name, value, unit, note=""):
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def _time(fn, *args, reps: int) -> float:
    """Median seconds per call of an already compiled function."""
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def matmul_peak(n: int = 2048, reps: int = 5) -> float:
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n))
    f = jax.jit(lambda x: x @ x)
    jax.block_until_ready(f(a))
    return 2 * n**3 / _time(f, a, reps=reps)


def layer_chains_rate(n: int = 256, layers: int = 100, reps: int = 3) -> float:
    """FLOP/s of two independent chains of tanh(x @ w) layers (n x n x n) in one compiled loop: the rate a
    learner's n-row, n-wide layers reach here when both threads have independent work."""
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    x, y, w, v = (0.05 * jax.random.normal(k, (n, n)) for k in keys)
    step = lambda i, c: (jnp.tanh(c[0] @ w), jnp.tanh(c[1] @ v))  # noqa: E731
    chains = jax.jit(lambda x, y: jax.lax.fori_loop(0, layers, step, (x, y)))
    jax.block_until_ready(chains(x, y))
    return 2 * layers * 2 * n**3 / _time(chains, x, y, reps=reps)


def _inputs(name: str, precision: str = "f32"):
    cfg, spec = dataclasses.replace(preset(name), precision=precision), SHAPES[name]
    agent = make_agent(cfg, spec)
    b, t = cfg.replay.batch, cfg.replay.length
    key_obs, key_act = jax.random.split(jax.random.PRNGKey(1))
    batch = Batch(jax.random.normal(key_obs, (b, t, spec.obs_size)),
                  jax.random.uniform(key_act, (b, t, spec.action_size), minval=-1, maxval=1),
                  jnp.zeros((b, t), bool).at[:, 0].set(True))
    pools = GoalPools(jnp.ones((4, spec.obs_size)), jnp.zeros((1, spec.obs_size)))
    return agent, agent.init(jax.random.PRNGKey(0)), batch, pools


def unrolled(config):
    """The same config with every scan fully unrolled: XLA's cost analysis counts a loop body once."""
    wm = dataclasses.replace(config.wm, unroll=config.replay.length)
    gc = dataclasses.replace(config.gc, unroll=config.gc.horizon)
    explore_ac = dataclasses.replace(config.explore.ac, unroll=config.explore.ac.horizon)
    explore = dataclasses.replace(config.explore, ac=explore_ac)
    return dataclasses.replace(config, wm=wm, gc=gc, explore=explore)


def train_step_flops(config, spec, state, batch, pools, key) -> float:
    """FLOPs of one train_step from the HLO cost analysis of the fully unrolled program (no compile)."""
    agent = make_agent(unrolled(config), spec)
    return float(jax.jit(agent.train_step).lower(state, batch, pools, key).cost_analysis()["flops"])


def bench_train(name: str, reps: int, peak: float, precision: str = "f32") -> list[dict]:
    agent, state, batch, pools = _inputs(name, precision)
    key = jax.random.PRNGKey(2)
    start = time.perf_counter()
    compiled = jax.jit(agent.train_step).lower(state, batch, pools, key).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(state, batch, pools, key))  # warm-up, finished before timing starts
    step_s = _time(compiled, state, batch, pools, key, reps=reps)
    flops = train_step_flops(agent.config, agent.spec, state, batch, pools, key)
    label = f"{name}_{precision}"
    rows = [
        _row(f"{label}/train_step_compile", compile_s, "s"),
        _row(f"{label}/train_step", step_s * 1e3, "ms", "all five learners"),
        _row(f"{label}/train_step_gflop", flops / 1e9, "GFLOP", "XLA cost analysis"),
        _row(f"{label}/train_step_flops", flops / step_s / 1e9, "GFLOP/s",
             f"{flops / step_s / peak:.0%} of the f32 matmul peak"),
    ]
    if name == "paper":  # a constant from another day, not a ratio: this machine's speed varies by ~2x
        rows.append(_row("paper/tf2_train_step_constant", REFERENCE_TRAIN_S, "s",
                         "CONSTANT, not measured in this run: TF2 original, paper config (issue 3)"))
    return rows + bench_components(label, agent, state, batch, pools, reps)


def bench_components(name, agent, state, batch, pools, reps) -> list[dict]:
    parts = agent.parts
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    wm_part = jax.jit(parts.world_model_part)
    wm_state, posterior, _ = wm_part(state, batch, keys[0])
    gc_part = jax.jit(parts.goal_conditioned_part)
    explore_part = jax.jit(parts.explore_part)
    gc_args = (state, wm_state.params, posterior, batch, pools, keys[1], keys[2])
    explore_args = (state, wm_state.params, posterior, batch, keys[1], keys[3])
    jax.block_until_ready(gc_part(*gc_args))
    jax.block_until_ready(explore_part(*explore_args))
    explore_s = _time(explore_part, *explore_args, reps=reps)
    return [
        _row(f"{name}/world_model", _time(wm_part, state, batch, keys[0], reps=reps) * 1e3, "ms"),
        _row(f"{name}/gc_actor_critic+distance", _time(gc_part, *gc_args, reps=reps) * 1e3, "ms"),
        _row(f"{name}/ensemble+explore_actor_critic", explore_s * 1e3, "ms"),
    ]


def bench_act(name: str, steps: int = 1000) -> list[dict]:
    """One jitted single-env act call, and the per-step cost inside a lax.scan (the fused collection)."""
    agent, full_state, _, _ = _inputs(name)
    state, spec = acting_state(full_state), agent.spec
    obs, goal = jnp.ones(spec.obs_size), jnp.zeros(spec.obs_size)
    latent, prev = agent.initial_latent(()), jnp.zeros(spec.action_size)
    act = jax.jit(agent.act, static_argnums=6)
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(act(state, latent, prev, obs, goal, key, MODE_GOAL))
    call_s = _time(act, state, latent, prev, obs, goal, key, MODE_GOAL, reps=200)
    call_row = _row(f"{name}/act_call", call_s * 1e3, "ms", "one jitted call on acting_state, incl. dispatch")
    context = jax.jit(agent.goal_context)(state, goal)
    jax.block_until_ready(act(state, latent, prev, obs, context, key, MODE_GOAL))
    context_s = _time(act, state, latent, prev, obs, context, key, MODE_GOAL, reps=200)
    context_row = _row(f"{name}/act_call_goal_context", context_s * 1e3, "ms",
                       "the same call given agent.goal_context(state, goal) instead of the goal")
    if steps == 0:
        return [call_row, context_row]

    @jax.jit
    def rollout(state, key):
        def body(carry, key):
            latent, prev = carry
            action, latent = agent.act(state, latent, prev, obs + prev.sum(), goal, key, MODE_GOAL)
            return (latent, action), action

        return jax.lax.scan(body, (latent, prev), jax.random.split(key, steps))[1]

    jax.block_until_ready(rollout(state, key))
    scan_s = _time(rollout, state, key, reps=3) / steps
    return [call_row, context_row,
            _row(f"{name}/act_in_scan", scan_s * 1e3, "ms", f"per step of a {steps}-step lax.scan")]


def _paper_in_large_runtime(reps: int, precision: str) -> list[dict]:
    """The paper rows of one precision from a child process in MOREFREE_JAX_RUNTIME=large on jemalloc where
    installed (what `make train PRESET=paper` uses; the allocator and XLA flags, which depend on the
    precision, are fixed when a process starts, see morefree_jax.runtime)."""
    env = {**os.environ, runtime.MODE_VARIABLE: "large", **runtime.allocator_env()}
    command = [sys.executable, "-m", "experiments.benchmarks.core", "presets=paper", f"reps={reps}", "json=1",
               f"precisions={precision}"]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"the paper benchmark's child process failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(quick: bool = False, presets: tuple[str, ...] = ("paper", "cpu"), reps: int = 3,
        precisions: tuple[str, ...] = ("f32", "bf16")) -> list[dict]:
    if quick:  # smoke test: the matmul peak and one act call of the debug preset
        peak = matmul_peak(1024, reps=3)
        peak_row = _row("matmul_peak_1024", peak / 1e9, "GFLOP/s", "f32 1024^3 under jit")
        return [peak_row, *bench_act("debug", 0)]
    mode = runtime.runtime_mode()
    rows = []
    if "paper" in presets and mode != "large":
        for precision in precisions:
            rows += _paper_in_large_runtime(reps, precision)
        presets = tuple(name for name in presets if name != "paper")
    peak = matmul_peak()
    allocator = runtime.settings()["allocator"]
    flags = " ".join(runtime.settings()["xla_flags"]) or "none"
    rows.append(_row("matmul_peak_2048", peak / 1e9, "GFLOP/s",
                     f"f32 2048^3 under jit, runtime {mode}, allocator {allocator}, XLA flags {flags}"))
    for name in presets:
        rows += bench_act(name)
        for precision in precisions:
            rows += bench_train(name, reps, peak, precision)
    return rows


def main(argv: list[str]) -> int:
    args = parse_keys(argv, {"presets": "paper,cpu", "reps": 3, "quick": False, "json": False,
                             "precisions": "f32,bf16"})
    precisions = tuple(args["precisions"].split(","))
    # before any JAX computation; a single precision picks its XLA flags (the paper child processes)
    runtime.configure(precision=precisions[0] if len(precisions) == 1 else "auto")
    rows = run(args["quick"], tuple(args["presets"].split(",")), args["reps"], precisions)
    if args["json"]:
        print(json.dumps(rows))
        return 0
    for row in rows:
        print(f"{row['name']:40s} {row['value']:12.3f} {row['unit']:8s} {row['note']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
