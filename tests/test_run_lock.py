"""A run dir nothing can corrupt: one writer (the lock), bad values refused before anything is written,
a full disk reported in one line. (Resume after SIGKILL with a second writer, lock takeover and TensorBoard,
and a moved run dir: tests/test_loop.py.)"""

from __future__ import annotations

import errno
import json
import multiprocessing
import types

import pytest

from experiments import train as train_cli
from morefree_jax import driver, run_lock
from morefree_jax.run_lock import RunDirError, RunDirLock, RunDirLockedError
from tests.run_helpers import DEBUG_ARGS, assert_train_cli_error


def test_a_second_lock_on_a_run_dir_is_refused_naming_the_owner(tmp_path):
    with RunDirLock(tmp_path / "run"), pytest.raises(RunDirLockedError, match=r"is in use by pid \d+ on "):
        RunDirLock(tmp_path / "run").acquire()
    RunDirLock(tmp_path / "run").acquire().release()  # released: free again, with no takeover message
    assert (tmp_path / "run" / run_lock.LOCK_FILE).read_text() == ""


def _hold_lock_and_die(run_dir):
    RunDirLock(run_dir).acquire()
    # exits without releasing: like a SIGKILL, the kernel drops the flock, the owner's name stays


def test_the_lock_of_a_dead_process_is_taken_over_with_a_message(tmp_path, capsys):
    context = multiprocessing.get_context("spawn")
    process = context.Process(target=_hold_lock_and_die, args=(tmp_path,))
    process.start()
    process.join(60)
    lock = RunDirLock(tmp_path).acquire()
    assert f"taking over the lock of {tmp_path} from pid {process.pid}" in capsys.readouterr().err
    assert json.loads((tmp_path / run_lock.LOCK_FILE).read_text())["pid"] != process.pid
    lock.release()


def test_an_unwritable_run_dir_is_one_line(tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(run_lock.pathlib.Path, "mkdir", refuse)
    with pytest.raises(RunDirError, match=r"cannot write to run dir .*/ro \(Permission denied\)"):
        RunDirLock(tmp_path / "ro").acquire()


@pytest.mark.parametrize("value, message", [
    ("wm.deter=-3", "agent.wm.deter=-3: deter must be > 0, got -3"),
    ("wm.deter=0", "agent.wm.deter=0: deter must be > 0, got 0"),
    ("replay.batch=0", "agent.replay.batch=0: batch must be > 0, got 0"),
    ("wm.opt.lr=-1", "agent.wm.opt.lr=-1: lr must be > 0, got -1.0"),
    ("wm.encoder_layers=32,0", "encoder_layers must be > 0 (every entry), got (32, 0)"),
    ("gc.discount=1.5", "discount must be in [0.0, 1.0], got 1.5"),
    ("explore.members=1", "members must be >= 2, got 1"),
    ("steps=10", "steps (10) must be larger than the prefill (20 random steps before learning)"),
    ("wm.deter=16", "agent.wm.deter is given twice (wm.deter=64 and wm.deter=16)"),
    ("seed=1", "run.seed is given twice (seed=0 and seed=1)"),
])
def test_bad_values_exit_2_with_one_line_and_leave_no_run_dir(value, message, tmp_path, capsys):
    arguments = [*DEBUG_ARGS, f"run_dir={tmp_path / 'run'}", value]
    if value.startswith("wm.deter=16"):
        arguments.insert(-1, "wm.deter=64")
    assert_train_cli_error(capsys, arguments, message)
    assert not (tmp_path / "run").exists()


def test_a_seed_beyond_32_bits_is_refused(capsys):
    arguments = [argument for argument in DEBUG_ARGS if not argument.startswith("seed=")]
    assert train_cli.main([*arguments, "seed=4294967296"]) == 2
    assert "run.seed must be in 0..4294967295 (JAX keys keep 32 bits)" in capsys.readouterr().err


def test_a_failed_write_is_one_line_with_the_free_space(tmp_path):
    error = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "metrics.jsonl"))
    line = train_cli.disk_error_line(error)
    assert line.startswith(f"could not write {tmp_path}/run/metrics.jsonl (No space left on device); ")
    assert "MiB free there; checkpoints already written are kept" in line and "\n" not in line


def test_a_disk_full_at_start_is_one_line_and_leaves_no_run_dir(tmp_path, monkeypatch):
    class FullDisk:  # the owner record cannot be written
        loads = staticmethod(json.loads)

        @staticmethod
        def dumps(value):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_lock, "json", FullDisk)
    lock = RunDirLock(tmp_path / "run")
    expected = r"cannot write to run dir .*/run \(No space left on device; [\d.]+ MiB"
    with pytest.raises(RunDirError, match=expected):
        lock.acquire()
    lock.remove_if_unused()
    assert not (tmp_path / "run").exists()


def test_a_second_ctrl_c_ends_with_one_line_and_no_traceback(tmp_path, monkeypatch, capsys):
    def interrupted_twice(*args, **kwargs):
        raise KeyboardInterrupt  # what _StopFlag raises on the second Ctrl-C

    programs = types.SimpleNamespace(fns=types.SimpleNamespace(chunk_len=200, updates_per_chunk=10))
    monkeypatch.setattr(driver, "build_programs", lambda config, num_seeds: programs)  # nothing compiles
    monkeypatch.setattr(driver, "train", interrupted_twice)
    assert train_cli.main([*DEBUG_ARGS, f"run_dir={tmp_path / 'run'}"]) == 130
    err = capsys.readouterr().err.strip()
    assert err == "interrupted; re-run the same command to resume from the last checkpoint"
