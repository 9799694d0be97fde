"""Seeds in one program (`make bench`, section `seeds`): env steps/s of a whole `cpu` run at 1, 2 and 4 seeds
(all the program's seeds together), against two single-seed processes sharing the machine; compile times;
the `paper` train step at 1 and 2 seeds; achieved FLOP/s next to a matmul peak measured in the same run.

    python -m experiments.benchmarks only=seeds
    python -m experiments.benchmarks.seeds run=2,map,8   # one measurement (2 seeds, lax.map, 8 chunks), JSON
    python -m experiments.benchmarks.seeds paper_rows=1  # only the paper train step rows

Every ratio divides two figures of this same run (the machine's speed varies from day to day).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp

import envs_mjx
from experiments.benchmarks.core import _inputs, matmul_peak, train_step_flops
from morefree_jax.compile import compile_programs
from morefree_jax.config import resolve_config
from morefree_jax.registry import make_run_fns

SECTION = "seeds"


def _row(name, value, unit, note=""):
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def _timed(fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def run_throughput(num_seeds: int, seed_axis: str, chunks: int, precision: str = "auto") -> dict:
    """Compile seconds (collect + train) and mean chunk seconds of a cpu-preset morefree point_umaze run of
    `num_seeds` seeds in one program, after its prefill and one warm-up chunk."""
    # The chunk cadence keeps collection and updates in two calls, timed apart.
    arguments = ["env=point_umaze", "agent=morefree", "preset=cpu", f"agent.precision={precision}",
                 "update_cadence=chunk"]
    config = resolve_config(arguments, envs_mjx.ALL_ENVS)
    fns = make_run_fns(config, envs_mjx.make("point_umaze"))
    programs = compile_programs(fns, num_seeds, seed_axis=seed_axis)
    state = programs.prefill(programs.init(jnp.stack([jax.random.PRNGKey(s) for s in range(num_seeds)])))
    compile_s = 0.0
    compiled = {}
    for name in ("collect", "train_updates"):
        start = time.perf_counter()
        compiled[name] = getattr(programs, name).lower(state).compile()
        compile_s += time.perf_counter() - start
        state, _ = compiled[name](state)  # warm-up chunk
    collect_s = train_s = 0.0
    for _ in range(chunks):
        (state, _), seconds = _timed(compiled["collect"], state)
        collect_s += seconds
        (state, _), seconds = _timed(compiled["train_updates"], state)
        train_s += seconds
    searches = jax.device_get(state.planner.searches).tolist()
    return {"seeds": num_seeds, "compile_s": compile_s, "collect_s": collect_s / chunks,
            "train_s": train_s / chunks, "chunk_len": fns.chunk_len, "updates": fns.updates_per_chunk,
            "searches": searches, "chunks": chunks}


def _steps_per_s(result: dict) -> float:
    """Env steps per second of all the program's seeds together (each seed runs at this over the seeds)."""
    return result["seeds"] * result["chunk_len"] / (result["collect_s"] + result["train_s"])


def _child(*arguments: str) -> subprocess.Popen:
    """A measurement in a fresh process (its own memory and compile caches); it prints one JSON line."""
    command = [sys.executable, "-m", "experiments.benchmarks.seeds", *arguments]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=os.environ.copy())


def _result(child: subprocess.Popen):
    out, err = child.communicate()
    if child.returncode != 0:
        tail = err.strip()[-300:]
        raise RuntimeError(f"bench child {child.args[3:]} failed (exit {child.returncode}): {tail}")
    return json.loads(out.strip().splitlines()[-1])


def _two_processes(chunks: int) -> float:
    """Env steps/s of two single-seed processes running at the same time on this machine, together."""
    children = [_child(f"run=1,map,{chunks}") for _ in range(2)]
    return sum(_steps_per_s(_result(child)) for child in children)


def _cpu_flops_per_update() -> float:
    agent, state, batch, pools = _inputs("cpu")
    return train_step_flops(agent.config, agent.spec, state, batch, pools, jax.random.PRNGKey(2))


def run_rows(chunks: int, peak: float, seed_counts=(1, 2, 4), modes=("map", "vmap"),
             processes: bool = True, show=None) -> list[dict]:
    flops = _cpu_flops_per_update()
    rows, base = [], None
    for seed_axis in modes:
        for num_seeds in seed_counts:
            if seed_axis == "vmap" and num_seeds == 1:
                continue  # one seed runs the same unbatched program in both modes
            try:
                result = _result(_child(f"run={num_seeds},{seed_axis},{chunks}"))
            except RuntimeError as error:  # e.g. out of memory: the row says so, the others still run
                rows.append(_row(f"cpu_run/{seed_axis}_{num_seeds}_seeds_failed", 0.0, "", str(error)))
                continue
            together = _steps_per_s(result)
            if show is not None:
                show(result)
            base = together if num_seeds == 1 else base
            achieved = flops * result["updates"] * num_seeds / result["train_s"]
            name = f"cpu_run/{seed_axis}_{num_seeds}_seeds"
            rows += [
                _row(f"{name}_steps_per_s", together, "steps/s",
                     f"all seeds together, {together / base:.2f}x of one seed alone; {chunks} morefree "
                     "chunks, searches per seed "
                     f"{result['searches']}; collect {result['collect_s']:.2f} s, "
                     f"train {result['train_s']:.2f} s"),
                _row(f"{name}_compile_s", result["compile_s"], "s", "collect + train_updates, all seeds"),
                _row(f"{name}_train_flops", achieved / 1e9, "GFLOP/s",
                     f"{achieved / peak:.0%} of the matmul peak"),
            ]
    if not processes:
        return rows
    separate = _two_processes(chunks)
    rows.append(_row("cpu_run/two_processes_steps_per_s", separate, "steps/s",
                     f"{separate / base:.2f}x of one seed alone: both of two single-seed processes at once"))
    return rows


PAPER_CASES = ("1_seed", "vmap_2_seeds", "map_2_seeds")


def paper_case(label: str) -> dict:
    """One case of the paper-size train step on one batch per seed: compile s, best of 2 s per seed."""
    agent, state, batch, pools = _inputs("paper")
    flops = train_step_flops(agent.config, agent.spec, state, batch, pools, jax.random.PRNGKey(2))

    def mapped(*args):
        return jax.lax.map(lambda per_seed: agent.train_step(*per_seed), args)

    steps = {"1_seed": (1, agent.train_step), "vmap_2_seeds": (2, jax.vmap(agent.train_step)),
             "map_2_seeds": (2, mapped)}
    num_seeds, step = steps[label]
    if num_seeds == 1:
        args = (state, batch, pools, jax.random.PRNGKey(2))
    else:
        stacked = jax.tree.map(lambda x: jnp.stack([x] * num_seeds), (state, batch, pools))
        args = (*stacked, jax.random.split(jax.random.PRNGKey(2), num_seeds))
    start = time.perf_counter()
    compiled = jax.jit(step).lower(*args).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(*args))
    seconds = min(_timed(compiled, *args)[1] for _ in range(2))
    return {"seeds": num_seeds, "seconds": seconds, "compile_s": compile_s, "flops_per_seed": flops}


def paper_rows(peak: float) -> list[dict]:
    """The paper-size train step for 1 and 2 seeds (vmap and map), each case in its own process (the
    2-seed cases may not fit in memory here: that case becomes a row saying so)."""
    rows, base = [], None
    for label in PAPER_CASES:
        try:
            result = _result(_child(f"paper={label}"))
        except RuntimeError as error:
            rows.append(_row(f"paper/train_step_{label}_failed", 0.0, "", str(error)))
            continue
        per_seed = result["seconds"] / result["seeds"]
        base = per_seed if result["seeds"] == 1 else base
        speed = f"{base / per_seed:.2f}x the per-seed throughput of one seed; " if base else ""
        achieved = result["flops_per_seed"] * result["seeds"] / result["seconds"]
        rows += [_row(f"paper/train_step_{label}_per_seed_s", per_seed, "s",
                      f"{speed}compile {result['compile_s']:.0f} s"),
                 _row(f"paper/train_step_{label}_flops", achieved / 1e9, "GFLOP/s",
                      f"{achieved / peak:.0%} of the matmul peak")]
    return rows


def run(quick: bool = False) -> list[dict]:
    peak = matmul_peak(1024 if quick else 2048)
    rows = [_row("matmul_peak", peak / 1e9, "GFLOP/s", "this run's reference for the FLOP/s rows")]
    if quick:
        return rows + run_rows(chunks=1, peak=peak, seed_counts=(1,), modes=("map",), processes=False)
    return rows + run_rows(chunks=8, peak=peak) + paper_rows(peak)


if __name__ == "__main__":
    from experiments.cli import parse_keys
    from morefree_jax import runtime

    runtime.configure()  # before any JAX computation
    # run=SEEDS,AXIS,CHUNKS: one measurement of run_throughput as JSON; paper=<case>: one case of the paper
    # train step as JSON (PAPER_CASES); paper_rows=1: only the paper rows.
    args = parse_keys(sys.argv[1:], {"run": "", "paper": "", "paper_rows": False})
    if args["paper"]:
        print(json.dumps(paper_case(args["paper"])))
    elif args["paper_rows"]:
        peak = matmul_peak()
        for row in [_row("matmul_peak", peak / 1e9, "GFLOP/s", "")] + paper_rows(peak):
            print(f"{row['name']:52} {row['value']:10.3f} {row['unit']:8} {row['note']}", flush=True)
    elif args["run"]:
        seeds, axis, chunks = args["run"].split(",")
        print(json.dumps(run_throughput(int(seeds), axis, int(chunks))))
    else:
        peak = matmul_peak()
        print(f"matmul peak {peak / 1e9:.0f} GFLOP/s", flush=True)
        for row in run_rows(chunks=4, peak=peak, show=lambda result: print(json.dumps(result), flush=True)):
            print(f"{row['name']:52} {row['value']:10.3f} {row['unit']:8} {row['note']}", flush=True)
