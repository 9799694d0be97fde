"""Benchmark of the training system: fused collection throughput, goal-search time, time per chunk.

    PYTHONPATH=src:. python -c "import experiments.benchmarks.loop as b; print(b.run())"
    PYTHONPATH=src:. python experiments/benchmarks/loop.py [quick=1]

Rows {"section", "name", "value", "unit", "note"}:
  collect/<task>_steps_per_s  env steps/s of the fused collection (goal policy + learned-distance check +
                              env step; explore policy after H_G) with the `paper`-size agent, untrained,
                              threshold ~0 so that every go step is checked (worst case). Bar: >= 2,000
                              on point_umaze. Reference (TF2 original, this machine): <= ~370 steps/s.
  planner/<task>_search_s     one PEG goal search with the task's planner config and the paper-size agent,
                              compiled once (the trace count is checked); ant: 500 candidates, horizon 250,
                              5 iterations. Bar: <= 20 s. Reference: 39-43 s per call at PEG's horizon 150.
  chunk/*                     one chunk of the `cpu`-preset run on point_umaze: collect with a goal search
                              (rf_peg: every chunk), collect without one (task goals), train (chunk_len /
                              train_every updates); the search's share of a morefree chunk (a search on
                              the 2/3 of chunks that pursue planner goals) and of an rf_peg chunk.
  goal_box/*                  where the goal search's candidates lie: the share of all candidates of every
                              iteration (rf_peg searches on point_umaze, cpu preset) inside the range of
                              observations the replay has visited, and inside its 1-99% quantile box, with
                              the task's observation bounds as the search box (before) and with the
                              visited range (after; what the runs use). `goal_box_rows(run_dir)` measures
                              on a run's newest checkpoint, default a fresh run after its prefill.
quick=True: the point_umaze collection row only (about 20 s).
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs_mjx
from morefree_jax.agent import EnvSpec, make_agent
from morefree_jax.collect import CollectConfig, collect_chunk, init_stream, peg_goal_scores
from morefree_jax.compile import jit_run_fns
from morefree_jax.config import resolve_config
from morefree_jax.goal_schedule import ScheduleConfig, init_schedule
from morefree_jax.learner_config import preset
from morefree_jax.planner import plan_goal, start_search
from morefree_jax.registry import make_run_fns

SECTION = "loop"
REFERENCE_STEPS_PER_S = 370.0  # TF2 original: policy 1.1-1.6 ms + distance check 1.1 ms per env step
REFERENCE_SEARCH_S = 41.0  # TF2 original, PEG's ant-maze config (horizon 150): 39-43 s per call, another day


def _row(name, value, unit, note=""):
    return {"section": SECTION, "name": name, "value": float(value), "unit": unit, "note": note}


def _median_time(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def planner_config(task: str, preset_name: str = "paper"):
    """The task's resolved planner config (its default_config under the preset)."""
    arguments = [f"env={task}", f"preset={preset_name}", "run_dir=/nonexistent"]
    return resolve_config(arguments, envs_mjx.ALL_ENVS).planner


def collection_rows(task: str, chunks: int = 5) -> list[dict]:
    """Fused collection steps/s of an untrained paper-size agent (eval goals; the search is timed apart)."""
    env = envs_mjx.make(task)
    agent = make_agent(preset("paper"), EnvSpec.from_env(env))
    half = env.eval_episode_length // 2
    cfg = CollectConfig(half, env.eval_episode_length - half, subgoal_threshold=1e-9,
                        hard_reset_every=env.hard_reset_every)
    schedule_cfg = ScheduleConfig(kind="eval_only")
    planner_cfg = planner_config(task)
    chunk = jax.jit(functools.partial(collect_chunk, env, agent, cfg, planner_cfg, schedule_cfg))
    key_agent, key_stream = jax.random.split(jax.random.PRNGKey(0))
    agent_state = jax.jit(agent.init)(key_agent)
    carry = [init_stream(env, agent, key_stream), init_schedule(env.observation_size),
             start_search(planner_cfg, jnp.zeros(env.observation_size))]

    key_chunk = jax.random.PRNGKey(1)

    def one_chunk():
        carry[0], carry[1], carry[2], transitions, metrics = chunk(agent_state, *carry, key_chunk)
        return transitions

    start = time.perf_counter()
    jax.block_until_ready(one_chunk())
    compile_s = time.perf_counter() - start
    seconds = _median_time(one_chunk, chunks)
    steps_per_s = cfg.chunk_len / seconds
    note = (f"paper-size agent, chunk {cfg.chunk_len} steps (H_G {cfg.go_steps} with distance check), "
            f"{steps_per_s / REFERENCE_STEPS_PER_S:.1f}x the TF2 bound; compile {compile_s:.1f} s")
    return [_row(f"collect/{task}_steps_per_s", steps_per_s, "steps/s", note)]


def search_rows(task: str, reps: int = 3) -> list[dict]:
    """Seconds per PEG goal search (paper-size agent, the task's planner config), compiled once."""
    env = envs_mjx.make(task)
    agent = make_agent(preset("paper"), EnvSpec.from_env(env))
    config = planner_config(task)
    low, high = (jnp.asarray(b, jnp.float32) for b in env.observation_bounds)
    traces = []

    @jax.jit
    def search(agent_state, start_latent, init_mean, key):
        traces.append(1)

        def score_fn(candidates, key_score):
            return peg_goal_scores(agent, agent_state, start_latent, candidates, config, key_score)

        return plan_goal(score_fn, start_search(config, init_mean), low, high, key, config)

    agent_state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    latent = agent.initial_latent()
    init_mean = env.initial_states(jax.random.PRNGKey(1))
    start = time.perf_counter()
    jax.block_until_ready(search(agent_state, latent, init_mean, jax.random.PRNGKey(2)))
    first_s = time.perf_counter() - start
    keys = iter(jax.random.split(jax.random.PRNGKey(3), reps))
    seconds = _median_time(lambda: search(agent_state, latent, init_mean, next(keys)), reps)
    note = (f"{config.method}, {config.num_candidates} candidates, horizon {config.horizon}, "
            f"{config.iterations} iterations, paper-size agent; first call (compile) {first_s:.1f} s; "
            f"traced {len(traces)}x")
    if task == "ant":
        note += (f"; CONSTANT for context, not measured in this run: TF2 original {REFERENCE_SEARCH_S:.0f} s "
                 "at PEG's ant-maze horizon 150")
    return [_row(f"planner/{task}_search_s", seconds, "s", note)]


def jitted_run_fns(config):
    return jit_run_fns(make_run_fns(config, envs_mjx.make(config.run.env)))


def _chunk_times(agent: str, chunks: int) -> tuple[float, float, object]:
    """(fastest collect s, fastest train s, RunFns) of `chunks` chunks of a cpu-preset point_umaze run."""
    config = resolve_config(["env=point_umaze", f"agent={agent}", "preset=cpu", "update_cadence=chunk"],
                            envs_mjx.ALL_ENVS)  # the chunk cadence keeps collect and train apart
    run = jitted_run_fns(config)
    state = run.prefill(run.init(jax.random.PRNGKey(0)))
    state, _ = jax.block_until_ready(run.collect(state))  # compiles
    state, _ = jax.block_until_ready(run.train_updates(state))  # compiles
    collect_s, train_s = [], []
    for _ in range(chunks):
        start = time.perf_counter()
        state, _ = jax.block_until_ready(run.collect(state))
        collect_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        state, _ = jax.block_until_ready(run.train_updates(state))
        train_s.append(time.perf_counter() - start)
    return min(collect_s), min(train_s), run


def chunk_rows(chunks: int = 3) -> list[dict]:
    """Time of one chunk of the cpu-preset point_umaze run and the goal search's share of it: rf_peg
    searches on every chunk, mf_task_only never (same steps and updates), so their collect times differ
    by one search. A morefree chunk searches with probability (1 - alpha) / (1 + alpha) = 2/3."""
    search_collect, train, run = _chunk_times("rf_peg", chunks)
    plain_collect, _, _ = _chunk_times("mf_task_only", chunks)
    search = max(search_collect - plain_collect, 0.0)
    planner_share = 1 - ScheduleConfig(kind="back_and_forth", alpha=0.2).task_chunk_share()
    morefree = train + plain_collect + planner_share * search
    rf_peg = train + search_collect
    planner = run.config.planner
    note = (f"cpu preset, point_umaze, {run.chunk_len} env steps + {run.updates_per_chunk} updates/chunk; "
            f"search {planner.method}, {planner.num_candidates} candidates, {planner.iterations} iterations, "
            f"horizon {planner.horizon}")
    return [
        _row("chunk/point_umaze_cpu_search_s", search, "s", note),
        _row("chunk/point_umaze_cpu_collect_s", plain_collect, "s", "collect without a search"),
        _row("chunk/point_umaze_cpu_train_s", train, "s", "train updates of one chunk"),
        _row("chunk/point_umaze_cpu_morefree_s", morefree, "s", "expected chunk: search on 2/3 of chunks"),
        _row("chunk/point_umaze_cpu_morefree_search_share", 100 * planner_share * search / morefree, "%",
             "share of the goal search in a morefree chunk"),
        _row("chunk/point_umaze_cpu_rf_peg_search_share", 100 * search / rf_peg, "%",
             "share of the goal search in an rf_peg chunk (search every chunk)"),
        _row("chunk/point_umaze_cpu_morefree_steps_per_s", run.chunk_len / morefree, "steps/s",
             "collect + train, morefree"),
    ]


def _candidate_recorder(agent, store: list):
    """The agent with imagine_to_goals wrapped to hand every batch of candidates to `store` (host)."""
    def imagine_to_goals(agent_state, start, goals, horizon, key):
        jax.debug.callback(lambda g: store.append(np.asarray(g)), goals)
        return agent.imagine_to_goals(agent_state, start, goals, horizon, key)

    return agent._replace(imagine_to_goals=imagine_to_goals)


def goal_box_rows(run_dir: str | None = None, searches: int = 10) -> list[dict]:
    """Shares of goal-search candidates inside the replay's visited range, with the task box vs the
    visited range as the search box (rf_peg's search from the stream's current state)."""
    from morefree_jax import replay as replay_lib
    from morefree_jax.collect import choose_goal
    from morefree_jax.driver import restore_run

    if run_dir is None:
        config = resolve_config(["env=point_umaze", "agent=rf_peg", "preset=cpu"], envs_mjx.ALL_ENVS)
        run = jitted_run_fns(config)
        state = run.prefill(run.init(jax.random.PRNGKey(0)))
        where = f"after the {config.run.prefill}-step prefill"
    else:
        fns, state, step = restore_run(run_dir)
        run = jit_run_fns(fns)
        where = f"{run_dir} at step {step}"
    env, replay = run.env, state.replay
    observations = np.asarray(replay.obs[:min(int(replay.count), replay.obs.shape[0])])
    visited = (observations.min(axis=0), observations.max(axis=0))
    quantiles = (np.quantile(observations, 0.01, axis=0), np.quantile(observations, 0.99, axis=0))
    task_box = tuple(jnp.asarray(b, jnp.float32) for b in env.observation_bounds)
    boxes = {"task_box": task_box, "visited_range": replay_lib.visited_range(replay, *task_box)}
    rows = []
    for name, box in boxes.items():
        store: list = []
        agent = _candidate_recorder(run.agent, store)
        schedule_cfg = ScheduleConfig(kind="planner")
        search = jax.jit(lambda agent_state, stream, key, box=box, agent=agent, schedule_cfg=schedule_cfg:
                         choose_goal(env, agent, run.config.planner, schedule_cfg, agent_state, stream,
                                     state.schedule, state.planner, key, box)[0])
        for index in range(searches):
            jax.block_until_ready(search(state.agent, state.stream, jax.random.PRNGKey(index)))
        candidates = np.concatenate(store)

        def share(low, high, dims=slice(None), candidates=candidates):
            picked = candidates[:, dims]
            return 100 * np.mean(np.all((picked >= low[dims]) & (picked <= high[dims]), axis=-1))

        note = f"{len(candidates)} candidates of {searches} searches, {where}"
        rows += [_row(f"goal_box/{name}_in_visited_range", share(*visited), "%", note),
                 _row(f"goal_box/{name}_in_quantile_box", share(*quantiles), "%", "1-99% of the replay")]
        for dim in range(env.observation_size):
            inside = share(*quantiles, slice(dim, dim + 1))
            rows.append(_row(f"goal_box/{name}_dim{dim}_in_quantile_box", inside, "%",
                             f"replay 1-99%: [{quantiles[0][dim]:.3g}, {quantiles[1][dim]:.3g}]"))
    return rows


def run(quick: bool = False, show=None) -> list[dict]:
    """All rows; `show(row)` is called as each row is measured (the CLI prints them)."""
    if quick:
        parts = [functools.partial(collection_rows, "point_umaze", chunks=3)]
    else:
        # point_umaze first (the bars), then the search at the ant config, then every other task
        others = [task for task in envs_mjx.ALL_ENVS if task != "point_umaze"]
        partial = functools.partial
        parts = [partial(collection_rows, "point_umaze"), partial(search_rows, "point_umaze"), chunk_rows,
                 partial(search_rows, "ant")]
        parts += [partial(collection_rows, task) for task in others]
    rows = []
    for part in parts:
        for row in part():
            rows.append(row)
            if show is not None:
                show(row)
    return rows


if __name__ == "__main__":
    import sys

    from experiments.cli import parse_keys
    from morefree_jax import runtime

    runtime.configure()  # before any JAX computation
    run(parse_keys(sys.argv[1:], {"quick": False})["quick"],
        show=lambda row: print(f"{row['name']:<36} {row['value']:>10.3f} {row['unit']:<8} {row['note']}",
                               flush=True))
