"""Whole runs (debug preset, tabletop: see run_helpers.RUN_ENV): files, every variant, exact resume after
SIGKILL, bad checkpoints, config refusal, Ctrl-C, bad CLI input.

Runs share compiled programs through run_helpers.debug_programs (driver.train(..., programs=...) reuses
them across run dirs and budgets); the CLI subprocesses share a persistent compilation cache.
"""

from __future__ import annotations

import collections
import errno
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from morefree_jax import checkpoint, driver
from morefree_jax.checkpoint import ConfigMismatchError
from morefree_jax.logger import read_metrics
from morefree_jax.run import keep_if_finite
from morefree_jax.tb_events import event_files, read_records
from morefree_jax.variants import VARIANTS
from tests.run_helpers import (
    CHUNK,
    COMPILATION_CACHE,
    assert_same_run,
    assert_train_cli_error,
    debug_args,
    debug_config,
    debug_programs,
    final_state,
    records_without_time,
    sigkill_once_written,
    start_train_cli,
)

REPO = pathlib.Path(__file__).resolve().parents[1]
PREFILL = 20  # run_helpers.DEBUG_ARGS: prefill=20, then chunks of CHUNK steps
TWO_CHUNKS, THREE_CHUNKS = PREFILL + 2 * CHUNK, PREFILL + 3 * CHUNK


def train(agent: str, run_dir, total_steps: int, **changes):
    programs = debug_programs(agent)
    extra = [f"{key}={value}" for key, value in changes.items()]
    config = debug_config(agent, f"run_dir={run_dir}", f"steps={total_steps}", *extra)
    return driver.train(config, programs=programs, progress="off")[0]


# Whole runs (~55 s of compiles each) of morefree and rf_peg stay in the fast suite; the others are in the
# slow suite. The ablations combine code paths the paper agents already run (mf_no_bfge: rf_peg's schedule
# with the imagination mix; mf_no_imag and mf_task_only: morefree's schedule with alpha 0 or 1); peg's
# episodic goal and dreamer_gc's eval-only chunk are checked chunk by chunk in test_collect.py
# (test_episodic_goal_and_phases_span_the_hard_reset_segment, test_eval_only_without_explore_...), and the
# driver around them is the same. Their settings are in test_variants.py.
COMBINED_PATHS = ("peg", "dreamer_gc", "mf_no_bfge", "mf_no_imag", "mf_task_only")
# morefree last: the tests after this one run morefree, and debug_programs keeps one variant compiled.
RUN_ORDER = sorted(VARIANTS, key=lambda agent: agent == "morefree")


@pytest.mark.parametrize("agent", [pytest.param(agent, marks=pytest.mark.slow) if agent in COMBINED_PATHS
                                   else agent for agent in RUN_ORDER])
def test_two_chunk_run_writes_every_file_with_finite_metrics(agent, tmp_path):
    summary = train(agent, tmp_path, TWO_CHUNKS)
    assert summary.env_steps == TWO_CHUNKS and not summary.interrupted
    config = json.loads((tmp_path / "config.json").read_text())
    assert config["run"]["agent"] == agent and config["schedule"]["kind"] == VARIANTS[agent].schedule_kind
    records = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["step"] for r in records if "wm/loss" in r] == [PREFILL + CHUNK, TWO_CHUNKS]
    assert any("eval/success" in r for r in records) and any("visitation/task_relevant" in r for r in records)
    assert all(np.isfinite(v) for r in records for v in r.values())
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    assert list((tmp_path / "plots").glob("visitation_*.npy"))
    assert sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit()) == [
        PREFILL + CHUNK, TWO_CHUNKS]
    step, state = final_state(tmp_path, debug_programs(agent))
    assert step == TWO_CHUNKS and int(state.stream.steps) == TWO_CHUNKS == int(state.replay.count)
    # pretrain: 5 updates rounded up to one chunk's CHUNK / train_every 20 = 10, then 2 chunks of 10
    assert int(state.agent.updates) == 3 * (CHUNK // 20)
    assert [r["train/dropped_share"] for r in records if "wm/loss" in r] == [0.0, 0.0]  # every update tried


def test_the_dropped_share_counts_updates_dropped_since_the_run_began(tmp_path, capsys):
    """The second chunk's updates all dropped (as keep_if_finite drops a non-finite one: the agent state,
    its update counter included, stays as it was): 10 of the 30 updates tried (10 of pretraining, 10 per
    chunk) are lost, which the log says once."""
    programs, calls = debug_programs("morefree"), []
    assert programs.fns.update_cadence == "interleaved"  # the chunk's updates run inside collect

    def second_chunk_dropped(state):
        calls.append(len(calls))
        before = jax.tree.map(jnp.copy, state.agent)  # collect donates its input
        new_state, metrics = programs.collect(state)
        if len(calls) == 2:
            updates = before.updates.astype(jnp.float32)
            new_state, metrics = new_state.replace(agent=before), {**metrics, "train/updates": updates}
        return new_state, metrics

    config = debug_config("morefree", f"run_dir={tmp_path}", f"steps={TWO_CHUNKS}")
    driver.train(config, programs=programs._replace(collect=second_chunk_dropped), progress="lines")
    shares = [r["train/dropped_share"] for r in read_metrics(tmp_path / "metrics.jsonl") if "wm/loss" in r]
    assert shares == [0.0, pytest.approx(1 / 3)]
    assert capsys.readouterr().out.count("warning: 33.3% of this run's updates so far were non-finite") == 1


def _start_cli(run_dir, steps: int) -> subprocess.Popen:
    return start_train_cli([*debug_args(f"checkpoint_every={2 * CHUNK}"), "agent=morefree", f"steps={steps}",
                            f"run_dir={run_dir}"])


def _second_writer_is_refused(first: subprocess.Popen, run_dir) -> None:
    """A second CLI process on the live run dir exits 2 with one line naming the first one's pid."""
    lock = run_dir / ".lock"
    while first.poll() is None and not (lock.exists() and lock.read_text()):
        time.sleep(0.05)
    second = _start_cli(run_dir, PREFILL + 10 * CHUNK)
    _, err = second.communicate(timeout=300)
    lines = err.decode().strip().splitlines()
    assert second.returncode == 2 and lines[-1].startswith(f"error: run dir {run_dir} is in use by pid "
                                                           f"{first.pid} on "), lines[-3:]


def _every_metric_is_in_tensorboard(run_dir) -> None:
    """TensorBoard holds exactly what metrics.jsonl holds: each (step, tag) of each line, once per line
    (time/* tags come with every line, so a step can carry them more than once in both)."""
    logged = collections.Counter((r["step"], name) for r in read_metrics(run_dir / "metrics.jsonl")
                                 for name in r if name not in ("step", "time/wall"))
    events = collections.Counter((event.step, value.tag) for path in event_files(run_dir / "tb")
                                 for event, _ in read_records(path) for value in event.summary.value)
    assert events == logged, f"missing {list(logged - events)[:5]}, extra {list(events - logged)[:5]}"


def test_resume_after_sigkill_continues_bit_for_bit(tmp_path, capsys):
    full_dir, killed_dir = tmp_path / "full", tmp_path / "killed"
    train("morefree", full_dir, THREE_CHUNKS, checkpoint_every=2 * CHUNK)
    # A CLI run that would go on for 10 chunks is SIGKILLed once its checkpoint after chunk 2 is complete.
    process = _start_cli(killed_dir, PREFILL + 10 * CHUNK)
    _second_writer_is_refused(process, killed_dir)
    sigkill_once_written(process, killed_dir / "checkpoints" / str(TWO_CHUNKS) / "files.json")
    steps = sorted(int(p.name) for p in (killed_dir / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [TWO_CHUNKS], f"killed too late: {steps}"
    # Resume (same config, a shorter budget: allowed and recorded) and run one more chunk.
    summary = train("morefree", killed_dir, THREE_CHUNKS, checkpoint_every=2 * CHUNK)
    assert summary.env_steps == THREE_CHUNKS
    out, err = capsys.readouterr()
    assert f"taking over the lock of {killed_dir} from pid {process.pid}" in err
    assert f"resuming from step {TWO_CHUNKS} (checkpoint {killed_dir}/checkpoints/{TWO_CHUNKS})" in out
    starts = [json.loads(line) for line in (killed_dir / "provenance.jsonl").read_text().splitlines()]
    assert [s["start_step"] for s in starts] == [0, TWO_CHUNKS]
    assert starts[1]["changed"] == {"run.total_steps": [PREFILL + 10 * CHUNK, THREE_CHUNKS]}
    _every_metric_is_in_tensorboard(killed_dir)
    step_a, state_a = final_state(full_dir, debug_programs("morefree"))
    step_b, state_b = final_state(killed_dir, debug_programs("morefree"))
    assert step_a == step_b == THREE_CHUNKS
    assert_same_run(full_dir, state_a, killed_dir, state_b)


def test_a_moved_run_dir_resumes_bit_for_bit(tmp_path):
    """The location is not part of a run's identity: a copy elsewhere, named with a trailing slash,
    resumes as the original would have continued."""
    full_dir, first_dir, moved_dir = tmp_path / "full", tmp_path / "first", tmp_path / "else" / "moved"
    train("morefree", full_dir, THREE_CHUNKS)
    train("morefree", first_dir, TWO_CHUNKS)
    shutil.copytree(first_dir, moved_dir)  # like cp -a
    train("morefree", f"{moved_dir}/", THREE_CHUNKS)
    step_a, state_a = final_state(full_dir, debug_programs("morefree"))
    step_b, state_b = final_state(moved_dir, debug_programs("morefree"))
    assert step_a == step_b == THREE_CHUNKS
    assert all(np.asarray(a).tobytes() == np.asarray(b).tobytes()
               for a, b in zip(jax.tree.leaves(state_a), jax.tree.leaves(state_b), strict=True))
    assert records_without_time(full_dir) == records_without_time(moved_dir)
    changed = json.loads((moved_dir / "provenance.jsonl").read_text().splitlines()[-1])["changed"]
    assert changed["run.run_dir"] == [str(first_dir), f"{moved_dir}/"]


def test_a_full_disk_stops_with_the_last_checkpoint_intact(tmp_path, monkeypatch):
    """The checkpoint after the first finds no space (disk_usage patched): one OSError naming the step's
    dir, no partial checkpoint or temporary file left, the previous checkpoint loads."""
    real_usage = checkpoint.shutil.disk_usage
    saves = []

    def full_after_first_save(path):
        saves.append(path)
        usage = real_usage(path)
        return usage._replace(free=0) if len(saves) > 1 else usage

    monkeypatch.setattr(checkpoint.shutil, "disk_usage", full_after_first_save)
    with pytest.raises(OSError) as error:
        train("morefree", tmp_path, THREE_CHUNKS)
    assert error.value.errno == errno.ENOSPC and error.value.filename.endswith(f"checkpoints/{TWO_CHUNKS}")
    monkeypatch.undo()
    assert not [p for p in tmp_path.rglob("*") if "tmp" in p.name], "temporary files left"
    # the checkpoint before the failed one
    assert final_state(tmp_path, debug_programs("morefree"))[0] == PREFILL + CHUNK


def test_corrupted_checkpoint_is_named_and_the_previous_one_used(tmp_path, capsys):
    train("morefree", tmp_path, TWO_CHUNKS)
    bad_dir = tmp_path / "checkpoints" / str(TWO_CHUNKS)
    biggest = max((p for p in bad_dir.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    biggest.write_bytes(biggest.read_bytes()[: biggest.stat().st_size // 2])  # truncated on disk
    summary = train("morefree", tmp_path, TWO_CHUNKS + CHUNK)
    err = capsys.readouterr().err
    assert str(biggest) in err and f"using checkpoint {PREFILL + CHUNK} instead" in err
    assert (tmp_path / "checkpoints_bad" / str(TWO_CHUNKS)).exists()
    assert summary.env_steps == TWO_CHUNKS + CHUNK  # continued from the first chunk: two more
    assert [r["step"] for r in read_metrics(tmp_path / "metrics.jsonl") if "wm/loss" in r] == [
        PREFILL + CHUNK, TWO_CHUNKS, TWO_CHUNKS + CHUNK]


def test_run_dir_with_a_different_config_is_refused(tmp_path):
    train("morefree", tmp_path, PREFILL + CHUNK)
    before = (tmp_path / "metrics.jsonl").read_text()
    other = debug_config("morefree", "wm.deter=16", f"run_dir={tmp_path}", "steps=220")
    with pytest.raises(ConfigMismatchError, match=r"agent\.wm\.deter: 32 -> 16"):
        driver.train(other, progress="off")
    assert (tmp_path / "metrics.jsonl").read_text() == before  # nothing destroyed


def test_ctrl_c_finishes_the_chunk_saves_and_stops(tmp_path):
    metrics = tmp_path / "metrics.jsonl"

    def interrupt_after_first_log():
        while not (metrics.exists() and metrics.read_text()):
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt_after_first_log, daemon=True).start()
    summary = train("morefree", tmp_path, PREFILL + 5000)
    assert summary.interrupted and summary.env_steps < PREFILL + 5000
    assert (tmp_path / "checkpoints" / str(summary.env_steps)).exists()


@pytest.mark.parametrize("arguments, message", [
    (["env=maze"], "unknown env 'maze'; valid envs: point_umaze"),
    (["agent=sac"], "unknown agent 'sac'; valid agents: morefree, rf_peg, peg, dreamer_gc"),
    (["preset=huge"], "unknown preset 'huge'; valid presets: paper, cpu, debug"),
    (["wm.detr=3"], "unknown key 'agent.wm.detr'; valid keys at 'agent.wm': deter"),
    (["steps=many"], "steps expects int, got 'many'"),
    (["steps=-5"], "steps must be > 0"),
    (["planner.iterations=x"], "planner.iterations expects int"),
])
def test_bad_cli_input_exits_2_with_one_line(arguments, message, capsys):
    given = {argument.split("=")[0] for argument in arguments}  # a key given twice is its own error
    base = [arg for arg in ("env=point_umaze", "agent=morefree") if arg.split("=")[0] not in given]
    assert_train_cli_error(capsys, [*base, *arguments], message)


def test_bad_cli_input_exit_code_in_a_subprocess():
    command = [sys.executable, "-m", "experiments.train", "env=point_umaze", "steps=0"]
    result = subprocess.run(command, cwd=REPO, env={**os.environ, "PYTHONPATH": "src:."}, capture_output=True,
                            text=True)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == "error: steps must be > 0, got 0"


def test_evaluate_cli_prints_success_per_goal_and_writes_a_video(tmp_path):
    train("morefree", tmp_path, PREFILL + CHUNK)
    video = tmp_path / "episode.gif"
    command = [sys.executable, "-m", "experiments.evaluate_checkpoint", f"run_dir={tmp_path}", "episodes=3",
               f"video={video}"]
    env = {**os.environ, "PYTHONPATH": "src:.", "MUJOCO_GL": "egl",
           "JAX_COMPILATION_CACHE_DIR": COMPILATION_CACHE}
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"checkpoint step {PREFILL + CHUNK}, 3 episodes" in result.stdout
    lines = result.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:2] == ["goal", "episodes"])
    overall = next(i for i, line in enumerate(lines) if line.startswith("overall success"))
    goal_rows = lines[header + 1:overall]
    assert goal_rows and sum(int(row.split()[-4]) for row in goal_rows) == 3  # episodes over the goals
    written = pathlib.Path(result.stdout.split("video: ")[1].split()[0])
    assert written.exists() and written.stat().st_size > 1000
    bad = subprocess.run([sys.executable, "-m", "experiments.evaluate_checkpoint",
                          f"run_dir={tmp_path / 'nope'}"], cwd=REPO, env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and "is not a run dir" in bad.stderr


def test_a_non_finite_update_is_dropped():
    old = {"a": jnp.zeros(2), "w": jnp.ones(3), "count": jnp.asarray(4, jnp.int32)}
    good = {"a": jnp.full(2, 3.0), "w": jnp.full(3, 2.0), "count": jnp.asarray(5, jnp.int32)}
    kept, finite = jax.jit(keep_if_finite)(good, old)
    assert bool(finite) and float(kept["w"][0]) == 2.0 and int(kept["count"]) == 5
    for leaf, value in (("a", jnp.inf), ("w", jnp.nan)):  # the first leaf and a later one
        bad = {**good, leaf: good[leaf].at[1].set(value)}
        kept, finite = jax.jit(keep_if_finite)(bad, old)
        assert not bool(finite) and jax.tree.all(jax.tree.map(jnp.array_equal, kept, old))
    # Per seed under vmap (the seed group's "vmap" mode): only the seed with the NaN keeps its old state.
    bad = {**good, "w": good["w"].at[1].set(jnp.nan)}
    stacked = lambda *trees: jax.tree.map(lambda *xs: jnp.stack(xs), *trees)  # noqa: E731
    kept, finite = jax.jit(jax.vmap(keep_if_finite))(stacked(good, bad), stacked(old, old))
    assert finite.tolist() == [True, False]
    assert jax.tree.all(jax.tree.map(jnp.array_equal, kept, stacked(good, old)))
