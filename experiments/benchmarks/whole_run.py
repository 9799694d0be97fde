"""Profile of whole training runs (`make bench`, section `whole_run`): per-seed env steps/s of a `cpu` run and
the share of each part of it, per task, agent, precision and update cadence, all in one process (ratios
compare figures of this same run only).

    python -m experiments.benchmarks only=whole_run
    python -m experiments.benchmarks.whole_run tasks=tabletop,push agents=morefree precisions=f32,bf16
    python -m experiments.benchmarks.whole_run tasks=point_umaze agents=morefree cadences=interleaved,chunk

Each measurement builds the run's compiled programs (one seed, the task's default config at the `cpu`
preset), prefills, compiles every program with one warm-up call, then times `chunks` chunks of the driver's
loop: collect (the goal search included on the chunks that search), train updates, and the host between
and around the two calls (fetching the chunk's metrics). One goal search (the run's own, from the stream's
state) is timed on its own, warm, and charged to the share of measured chunks that searched (morefree
searches on about 2/3 of its chunks, rf_peg on every one); collect is the rest. Evaluation (evaluate +
visitation), a checkpoint of the whole state and a log record are timed once each, warm, and amortised at
the task's configured cadence (eval_every, checkpoint_every, log_every). Under the interleaved cadence the
updates run inside the collect call, so its share is "collect+train". Rows:

  whole_run/<task>_<agent>_<precision>_<cadence>_steps_per_s   per-seed env steps/s at the configured
                                                               cadence; the note gives each part's share
  whole_run/<task>_<agent>_<cadence>_bf16_over_f32             the two precisions' ratio
  whole_run/<task>_<agent>_<precision>_interleaved_over_chunk  the two cadences' ratio
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time

import jax
import jax.numpy as jnp

import envs_mjx
from experiments.benchmarks.seeds import _timed
from experiments.cli import parse_keys
from morefree_jax import replay as replay_lib
from morefree_jax.checkpoint import RunCheckpointer
from morefree_jax.collect import choose_goal
from morefree_jax.compile import seed_slice
from morefree_jax.config import config_to_dict, resolve_config
from morefree_jax.driver import build_programs, eval_keys
from morefree_jax.goal_schedule import ScheduleConfig
from morefree_jax.logger import RunLogger

SECTION = "whole_run"
TASKS = ("point_umaze", "tabletop", "push", "push_hard", "ant")
AGENTS = ("morefree", "rf_peg")
PRECISIONS = ("f32", "bf16")
CADENCES = ("interleaved",)  # the default; cadences=interleaved,chunk compares the two
PARTS = ("collect", "search", "train", "collect+train", "host", "evaluate", "checkpoint", "log")


def _row(name, value, unit, note=""):
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def _chunks(programs, state, chunks: int):
    """(state, [(collect_s, train_s, host_s, searched)], the last chunk's metrics) of `chunks` chunks of the
    driver's loop."""
    times, record = [], {}
    for _ in range(chunks):
        searches = int(state.planner.searches[0])
        start = time.perf_counter()
        state, collect_metrics = jax.block_until_ready(programs.collect(state))
        collected = time.perf_counter()
        train_metrics = {}
        if programs.fns.update_cadence == "chunk":  # else collect ran the updates
            state, train_metrics = jax.block_until_ready(programs.train_updates(state))
        trained = time.perf_counter()
        record = jax.device_get({**collect_metrics, **train_metrics})  # what the driver fetches to log
        searched = int(state.planner.searches[0]) > searches
        times.append((collected - start, trained - collected, time.perf_counter() - trained, searched))
    return state, times, seed_slice(record, 0)


def _search_seconds(programs, state, reps: int = 3) -> float:
    """Median seconds of one goal search of the run (its planner config, agent and stream state), warm."""
    fns, single = programs.fns, seed_slice(state, 0)
    task_box = tuple(jnp.asarray(b, jnp.float32) for b in fns.env.observation_bounds)
    box = replay_lib.visited_range(single.replay, *task_box)
    planner_only = ScheduleConfig(kind="planner")
    search = jax.jit(lambda agent_state, stream, key: choose_goal(
        fns.env, fns.agent, fns.config.planner, planner_only, agent_state, stream, single.schedule,
        single.planner, key, box)[0])
    jax.block_until_ready(search(single.agent, single.stream, jax.random.PRNGKey(0)))
    times = [_timed(search, single.agent, single.stream, jax.random.PRNGKey(k))[1] for k in range(reps)]
    return statistics.median(times)


def _occasional(programs, config, state, record, run_dir) -> dict:
    """Seconds of one warm evaluation, checkpoint and log record (each called once before, to compile)."""
    def evaluate():
        metrics, _ = programs.evaluate(state.agent, eval_keys((0,), 1))
        return metrics, programs.visitation(state.replay)

    config_dict = config_to_dict(config)
    checkpointer = RunCheckpointer(run_dir, config_dict, config.run.checkpoint_every, keep=1)
    logger = RunLogger(run_dir, config_dict, config.run.total_steps, progress="off")
    try:
        seconds = {}
        for step in (1, 2):  # the first call compiles (evaluate) or creates files (checkpoint, log)
            _, seconds["evaluate"] = _timed(evaluate)
            start = time.perf_counter()
            checkpointer.save(step, seed_slice(state, 0), {"env_steps": step}, force=True)
            seconds["checkpoint"] = time.perf_counter() - start
            start = time.perf_counter()
            logger.log(step, {key: float(value) for key, value in record.items()})
            logger.flush()
            seconds["log"] = time.perf_counter() - start
    finally:
        logger.close()
        checkpointer.close()
    return seconds


def measure(task: str, agent: str, precision: str, chunks: int = 4, cadence: str = "interleaved") -> dict:
    """The parts' seconds and the cadence of one cpu run (module docstring)."""
    with tempfile.TemporaryDirectory() as run_dir:
        arguments = [f"env={task}", f"agent={agent}", "preset=cpu", f"agent.precision={precision}",
                     f"update_cadence={cadence}", f"run_dir={run_dir}"]
        config = resolve_config(arguments, envs_mjx.ALL_ENVS)
        programs = build_programs(config, 1)
        state, _ = _timed(lambda: programs.prefill(programs.init(jax.random.PRNGKey(0)[None])))
        state, warm, _ = _chunks(programs, state, 1)  # compiles collect and train_updates
        state, times, record = _chunks(programs, state, chunks)
        occasional = _occasional(programs, config, state, record, run_dir)
        search_s = _search_seconds(programs, state) if config.schedule.kind != "eval_only" else 0.0
    jax.clear_caches()
    run = config.run
    return {"task": task, "agent": agent, "precision": precision, "cadence": cadence,
            "chunk_len": programs.fns.chunk_len,
            "updates": programs.fns.updates_per_chunk, "times": times, "compile_s": sum(warm[0][:2]),
            "eval_every": run.eval_every, "checkpoint_every": run.checkpoint_every,
            "log_every": run.log_every, "search": search_s, **occasional}


def seconds_per_step(result: dict) -> dict:
    """Each part's seconds per env step at the run's cadence (search: its share of collect)."""
    times, length = result["times"], result["chunk_len"]
    searched = sum(t[3] for t in times) / len(times)
    collect = statistics.mean(t[0] for t in times)
    search = min(searched * result["search"], collect)
    steps = {"collect": (collect - search) / length, "train": statistics.mean(t[1] for t in times) / length}
    if result["cadence"] == "interleaved":  # one call did both
        steps = {"collect+train": steps["collect"]}
    return {**steps, "search": search / length,
            "host": statistics.mean(t[2] for t in times) / length,
            "evaluate": result["evaluate"] / result["eval_every"],
            "checkpoint": result["checkpoint"] / result["checkpoint_every"],
            "log": result["log"] / result["log_every"]}


def rows_of(results: list[dict]) -> list[dict]:
    rows, speed = [], {}
    for result in results:
        parts = seconds_per_step(result)
        total = sum(parts.values())
        key = (result["task"], result["agent"], result["precision"], result["cadence"])
        speed[key] = 1.0 / total
        shares = ", ".join(f"{name} {100 * parts[name] / total:.1f}%" for name in PARTS if name in parts)
        searched = sum(t[3] for t in result["times"])
        note = (f"chunk {result['chunk_len']} steps + {result['updates']} updates, {len(result['times'])} "
                f"chunks ({searched} searched, {result['search']:.2f} s a search); {shares}; compile "
                f"{result['compile_s']:.0f} s")
        rows.append(_row(f"{SECTION}/{'_'.join(key)}_steps_per_s", speed[key], "steps/s", note))
    for (task, agent, precision, cadence), value in speed.items():
        if precision == "bf16" and (task, agent, "f32", cadence) in speed:
            rows.append(_row(f"{SECTION}/{task}_{agent}_{cadence}_bf16_over_f32",
                             value / speed[(task, agent, "f32", cadence)], "x",
                             "per-seed env steps/s, bf16 / f32, this run"))
        if cadence == "interleaved" and (task, agent, precision, "chunk") in speed:
            rows.append(_row(f"{SECTION}/{task}_{agent}_{precision}_interleaved_over_chunk",
                             value / speed[(task, agent, precision, "chunk")], "x",
                             "per-seed env steps/s, interleaved / chunk cadence, this run"))
    return rows


def run(quick: bool = False, tasks=TASKS, agents=AGENTS, precisions=PRECISIONS, chunks: int = 4,
        show=None, cadences=CADENCES) -> list[dict]:
    if quick:  # checks the section runs: one short measurement
        tasks, agents, precisions, chunks, cadences = ("tabletop",), ("morefree",), ("f32",), 2, ("chunk",)
    results = []
    for task in tasks:
        for agent in agents:
            for precision in precisions:
                for cadence in cadences:
                    results.append(measure(task, agent, precision, chunks, cadence))
                    if show is not None:
                        show(rows_of(results[-1:])[0])
    return rows_of(results)


def main(argv: list[str]) -> int:
    from morefree_jax import runtime

    args = parse_keys(argv, {"tasks": ",".join(TASKS), "agents": ",".join(AGENTS),
                             "precisions": ",".join(PRECISIONS), "cadences": ",".join(CADENCES), "chunks": 4,
                             "quick": False})
    runtime.configure()  # before any JAX computation
    show = lambda row: print(f"{row['name']:<44} {row['value']:9.2f} {row['unit']:<8} {row['note']}",  # noqa: E731
                             flush=True)
    rows = run(args["quick"], args["tasks"].split(","), args["agents"].split(","),
               args["precisions"].split(","), args["chunks"], show=show, cadences=args["cadences"].split(","))
    for row in rows:
        show(row)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
