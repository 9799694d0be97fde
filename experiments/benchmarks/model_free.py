"""Benchmark of the model-free baselines: the fused chunk per task and the SAC update against PyTorch.

    PYTHONPATH=src:. python -m experiments.benchmarks only=model_free [quick=1]

Rows {"section", "name", "value", "unit", "note"}:
  <task>_<agent>_steps_per_s   env steps/s of the fused chunk (policy, one SAC update, env step and
                               replay insert per step, MEDAL's sizes: batch 256, 2 x 256 heads) of
                               oracle_sac on every task, r3l, medal and ibc (3 x 512 heads, batch 512)
                               on point_umaze and tabletop; 1,000-step chunks, median of 3 after the
                               compile, with the compile time in the note.
  ibc_matching_s               one curriculum matching of ibc at its sizes on push (pool 1,000 x 50 steps,
                               10 actions valued by the 3 x 512 critic, 50 slots), compiled; it runs once
                               per 20 forward segments.
  sac_update_ms                one SAC update alone (point_umaze shapes: input 12, action 2), 200 updates in
                               one scan, with its FLOP/s (XLA cost analysis) against a 2048^3 matmul peak
                               measured in the same run.
  sac_update_at_layer_rate_ms  the update's FLOPs at the rate two independent chains of 256 x 256 x 256
                               layers reach in one program in the same run: about the fastest the update's
                               matmuls run on this CPU (17 of its 59 matmuls have that shape: 570 of their
                               692 MFLOP, counted on its jaxpr).
  torch_sac_update_ms          the same update in PyTorch (benchmarks/torch_sac_reference.py), run by the
                               Python in $TORCH_PYTHON (a throwaway venv with torch; not a dependency).
  fused_step_vs_torch_update   PyTorch's update time over the fused chunk's time per env step on
                               point_umaze (oracle_sac). Bar: >= 3.
The point_umaze oracle_sac row and the bar's rows (the update, PyTorch, the ratio) come first, measured back
to back; the other chunk rows and the matching follow.
quick=True: tabletop oracle_sac with 100-step chunks and the update row, no PyTorch.

The bar's rows alone, with no other chunk row (a few minutes; `make bench-bar`):

    TORCH_PYTHON=/tmp/torchvenv/bin/python PYTHONPATH=src:. python -m experiments.benchmarks.model_free
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import envs_mjx
from experiments.benchmarks.core import layer_chains_rate, matmul_peak
from experiments.cli import KeyValueError, parse_keys
from morefree_jax import registry
from morefree_jax.baselines.ibc.curriculum import Curriculum
from morefree_jax.baselines.ibc.learner import IBCLearner
from morefree_jax.baselines.ibc.tasks import ibc_task
from morefree_jax.baselines.oracle_sac import agent as oracle_sac
from morefree_jax.baselines.sac import learner as sac
from morefree_jax.compile import jit_run_fns
from morefree_jax.config import resolve_config
from morefree_jax.registry import make_run_fns

SECTION = "model_free"
BAR_VS_TORCH = 3.0
ORACLE = oracle_sac.AGENT.name  # the speed bar's agent: the one plain SAC learner, on every task
# The other model-free agents of the registry (their learners read config sections `baseline.*`) run on these.
OTHER_AGENTS = tuple(name for name, entry in registry.AGENTS.items()
                     if name != ORACLE and entry.config_sections[0].startswith("baseline"))
OTHER_AGENTS_TASKS = ("point_umaze", "tabletop")


def _row(name, value, unit, note=""):
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def chunk_rate(task: str, agent: str, chunk: int, reps: int = 3) -> tuple[float, float, str]:
    """(env steps/s of the fused chunk, compile + first call seconds, the learner's sizes)."""
    config = resolve_config([f"env={task}", f"agent={agent}", "prefill=300", f"baseline.chunk_len={chunk}",
                             "baseline.replay_capacity=100000"], envs_mjx.ALL_ENVS)
    fns = jit_run_fns(make_run_fns(config, envs_mjx.make(task)))
    state = jax.block_until_ready(fns.prefill(fns.init(jax.random.PRNGKey(0))))
    start = time.perf_counter()
    state, _ = jax.block_until_ready(fns.collect(state))
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        state, _ = jax.block_until_ready(fns.collect(state))
        times.append(time.perf_counter() - start)
    own_sac = "baseline.ibc" in registry.entry(agent).config_sections  # IBC's SAC variant
    learner = config.baseline.ibc.sac if own_sac else config.baseline.sac
    sizes = f"batch {learner.batch_size}, {learner.hidden_depth} x {learner.hidden_dim} heads"
    return chunk / sorted(times)[len(times) // 2], compile_s, sizes


def update_rows(obs_size: int = 12, action_size: int = 2, updates: int = 200) -> tuple[list[dict], float]:
    """The SAC update alone in JAX (rows, ms per update)."""
    config = sac.SACConfig()
    keys = jax.random.split(jax.random.PRNGKey(0), 6)
    batch = sac.SACBatch(jax.random.normal(keys[0], (256, obs_size)),
                         jax.random.uniform(keys[1], (256, action_size), minval=-1, maxval=1),
                         jax.random.uniform(keys[2], (256,)), jax.random.normal(keys[3], (256, obs_size)),
                         jnp.ones(256))
    state = sac.init(config, obs_size, action_size, keys[4])

    def many(state, key):
        step = lambda s, k: (sac.update(config, s, batch, k)[0], None)  # noqa: E731
        return jax.lax.scan(step, state, jax.random.split(key, updates))[0]

    compiled = jax.jit(many).lower(state, keys[5]).compile()
    # XLA's cost analysis counts a loop body once: take the FLOPs of one update compiled on its own
    single = jax.jit(lambda s, k: sac.update(config, s, batch, k)).lower(state, keys[5]).compile()
    flops = (single.cost_analysis() or {}).get("flops", float("nan"))
    jax.block_until_ready(compiled(state, keys[5]))
    start = time.perf_counter()
    jax.block_until_ready(compiled(state, keys[5]))
    seconds = (time.perf_counter() - start) / updates
    peak, layers = matmul_peak(), layer_chains_rate()
    note = (f"{flops / 1e6:.0f} MFLOP per update, {flops / seconds / 1e9:.0f} GFLOP/s = "
            f"{flops / seconds / peak:.0%} of the matmul peak ({peak / 1e9:.0f} GFLOP/s, same run)")
    layer_note = f"{flops / 1e6:.0f} MFLOP at {layers / 1e9:.0f} GFLOP/s (two chains of 256^3 layers)"
    return [_row("sac_update_ms", 1e3 * seconds, "ms", note),
            _row("sac_update_at_layer_rate_ms", 1e3 * flops / layers, "ms", layer_note)], 1e3 * seconds


def matching_row(task: str = "push") -> dict:
    """The time of one ibc curriculum matching on a full pool of random trajectories."""
    config = resolve_config([f"env={task}", "agent=ibc"], envs_mjx.ALL_ENVS).baseline.ibc
    env = envs_mjx.make(task)
    curriculum_task = ibc_task(env)
    learner = IBCLearner(config, env, curriculum_task)
    curriculum = Curriculum(env, curriculum_task, config, config.sac.discount)
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    agent, state = learner.init(keys[0]), curriculum.init(keys[1])
    state = state.replace(pool_goals=jax.random.normal(keys[2], state.pool_goals.shape),
                          pool_lengths=jnp.full_like(state.pool_lengths, curriculum_task.segment_length),
                          pool_count=jnp.asarray(config.pool_size, jnp.int32))

    def match(state, agent, key):
        return curriculum.match(state, lambda o, g, k: learner.forward_value(agent, o, g, k), key)

    compiled = jax.jit(match).lower(state, agent, keys[3]).compile()
    jax.block_until_ready(compiled(state, agent, keys[3]))
    start = time.perf_counter()
    jax.block_until_ready(compiled(state, agent, keys[3]))
    seconds = time.perf_counter() - start
    note = (f"{task}: pool {config.pool_size} x {curriculum_task.segment_length} steps, "
            f"{config.value_samples} actions, {config.slots} slots; "
            f"once per {config.match_every} forward segments")
    return _row("ibc_matching_s", seconds, "s", note)


def torch_update_ms(obs_size: int = 12, action_size: int = 2) -> dict | None:
    """The PyTorch reference's JSON, or None without $TORCH_PYTHON."""
    python = os.environ.get("TORCH_PYTHON")
    if not python:
        return None
    script = Path(__file__).with_name("torch_sac_reference.py")
    out = subprocess.run([python, str(script), f"obs={obs_size}", f"action={action_size}"],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _chunk_row(task: str, agent: str) -> tuple[dict, float]:
    rate, compile_s, sizes = chunk_rate(task, agent, 1000)
    row = _row(f"{task}_{agent}_steps_per_s", rate, "steps/s",
               f"UTD 1, {sizes}; compile + first chunk {compile_s:.0f} s")
    print(row, file=sys.stderr, flush=True)
    return row, rate


def bar_rows(point_umaze_rate: float) -> list[dict]:
    """The update alone, then with $TORCH_PYTHON PyTorch's update and its ratio to the fused env step."""
    update, _ = update_rows()
    reference = torch_update_ms()
    if reference is None:
        return update
    per_step_ms = 1e3 / point_umaze_rate
    ratio = reference["update_ms"] / per_step_ms
    verdict = "meets" if ratio >= BAR_VS_TORCH else "misses"
    at_layer_rate_ms = next(r["value"] for r in update if r["name"] == "sac_update_at_layer_rate_ms")
    return [*update,
            _row("torch_sac_update_ms", reference["update_ms"], "ms",
                 f"torch {reference['torch']}, {reference['threads']} threads, same shapes"),
            _row("fused_step_vs_torch_update", ratio, "x",
                 f"{verdict} the bar >= {BAR_VS_TORCH:g}: PyTorch update "
                 f"{reference['update_ms']:.2f} ms vs fused env step {per_step_ms:.2f} ms "
                 f"(point_umaze oracle_sac); an update at the layer rate and a free env step: "
                 f"{reference['update_ms'] / at_layer_rate_ms:.1f}x")]


def bar_section() -> list[dict]:
    """point_umaze's oracle_sac chunk, then the update alone, PyTorch's update and the ratio, back to back."""
    first, rate = _chunk_row("point_umaze", ORACLE)
    rows = [first, *bar_rows(rate)]
    for row in rows[1:]:
        print(row, file=sys.stderr, flush=True)
    return rows


def run(quick: bool = False) -> list[dict]:
    if quick:
        rate, compile_s, _ = chunk_rate("tabletop", ORACLE, 100, reps=1)
        return [_row(f"tabletop_{ORACLE}_steps_per_s", rate, "steps/s", f"compile {compile_s:.0f} s"),
                *update_rows(updates=20)[0]]
    # The bar's rows first and back to back: this CPU's speed drifts over the section's half hour
    rows = bar_section()
    runs = [(task, ORACLE) for task in envs_mjx.ALL_ENVS if task != "point_umaze"]
    runs += [(task, agent) for agent in OTHER_AGENTS for task in OTHER_AGENTS_TASKS]
    rows += [_chunk_row(task, agent)[0] for task, agent in runs]
    rows.append(matching_row())
    print(rows[-1], file=sys.stderr, flush=True)
    return rows


def main(argv=None) -> int:
    """The bar's rows alone (module docstring), printed as `make bench` prints a section."""
    from experiments.benchmarks.bench import format_table
    from morefree_jax import runtime

    try:
        parse_keys(list(argv or []), {})  # takes no argument: $TORCH_PYTHON names the PyTorch side
    except KeyValueError as error:
        print(f"model_free bench: {error}", file=sys.stderr)
        return 2
    runtime.configure()  # before any JAX computation, as `make bench`
    if not os.environ.get("TORCH_PYTHON"):
        print("model_free bench: TORCH_PYTHON is not set, so no PyTorch row and no ratio "
              "(see experiments/benchmarks/torch_sac_reference.py)", file=sys.stderr)
    print(format_table(bar_section()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
