"""Whole-run-state checkpoints: bit-exact round trip, keep-last-k, corruption fallback, config refusal,
kill during a write."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from morefree_jax import checkpoint

CONFIG = {"env": "point_umaze", "agent": {"alpha": 0.2, "sizes": (64, 64)}, "seed": 0}


@struct.dataclass
class Inner:
    params: dict
    key: jax.Array


@struct.dataclass
class RunState:
    agent: Inner
    counters: dict
    replay_obs: jax.Array
    flags: jax.Array


def make_state(step: int) -> RunState:
    key = jax.random.PRNGKey(step)
    return RunState(
        agent=Inner(params={"w": jax.random.normal(key, (17, 5)), "b": jnp.full((5,), step / 3.0)},
                    key=jax.random.split(key)[1]),
        counters={"env_steps": jnp.asarray(step * 1000, jnp.int32), "updates": jnp.asarray(step, jnp.uint32)},
        replay_obs=jnp.arange(4000, dtype=jnp.float32).reshape(400, 10) * (step + 1),
        flags=jnp.arange(7) % (step + 2) == 0,
    )


def assert_trees_equal(a, b):
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def saved_run(tmp_path, steps, keep=3, every=10):
    checkpointer = checkpoint.RunCheckpointer(tmp_path, CONFIG, every_steps=every, keep=keep)
    for step in steps:
        checkpointer.save(step, make_state(step), {"env_steps": step, "chunk": step // 10})
    return checkpointer


def largest_file(step_dir: pathlib.Path) -> pathlib.Path:
    files = [p for p in step_dir.rglob("*") if p.is_file() and p.name != checkpoint.FILE_MANIFEST]
    return max(files, key=lambda p: p.stat().st_size)


def test_round_trip_is_bit_exact_and_keeps_last_k(tmp_path):
    checkpointer = saved_run(tmp_path, [0, 10, 20, 30, 40], keep=3)
    assert checkpointer.all_steps() == [20, 30, 40]
    assert not checkpointer.save(45, make_state(45))  # not a multiple of every_steps
    assert not checkpointer.save(40, make_state(40), force=True)  # already saved at this step
    restored = checkpointer.latest_valid(make_state(0))
    assert restored.step == 40 and restored.metadata == {"env_steps": 40, "chunk": 4}
    assert_trees_equal(restored.state, make_state(40))
    assert restored.state.agent.key.dtype == jnp.uint32
    assert checkpointer.save(47, make_state(47), {"env_steps": 47}, force=True)  # the exit save
    assert checkpointer.all_steps() == [30, 40, 47]
    checkpointer.close()
    # A fresh process-like reopen (module-level, read-only) sees the same newest state.
    again = checkpoint.latest_valid(tmp_path, make_state(0), CONFIG)
    assert again.step == 47
    assert_trees_equal(again.state, make_state(47))


def test_fresh_run_dir_has_nothing_to_restore(tmp_path):
    checkpointer = checkpoint.RunCheckpointer(tmp_path, CONFIG, every_steps=10)
    assert checkpointer.latest_valid(make_state(0)) is None


@pytest.mark.parametrize("damage", ["truncate", "flip_byte", "flip_byte_no_manifest"])
def test_damaged_newest_falls_back_to_previous_naming_it(tmp_path, damage):
    checkpointer = saved_run(tmp_path, [10, 20, 30])
    newest = tmp_path / "checkpoints" / "30"
    target = largest_file(newest)
    data = bytearray(target.read_bytes())
    if damage == "truncate":
        target.write_bytes(data[: len(data) // 2])
    else:
        data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))
    if damage == "flip_byte_no_manifest":  # e.g. killed between orbax's rename and files.json
        (newest / checkpoint.FILE_MANIFEST).unlink()
    with pytest.warns(checkpoint.CheckpointWarning) as record:
        restored = checkpointer.latest_valid(make_state(0))
    assert restored.step == 20
    assert_trees_equal(restored.state, make_state(20))
    message = str(record[0].message)
    assert str(newest) in message and "using checkpoint 20" in message
    if damage != "flip_byte_no_manifest":
        assert str(target) in message  # the exact file is named
    # The bad one is moved aside, not deleted, and the run continues saving at its step.
    assert (tmp_path / checkpoint.QUARANTINE_DIR / "30").is_dir()
    assert checkpointer.all_steps() == [10, 20]
    assert checkpointer.save(30, make_state(30))
    assert checkpointer.latest_valid(make_state(0)).step == 30


def test_no_good_checkpoint_is_a_one_line_error(tmp_path):
    checkpointer = saved_run(tmp_path, [10, 20])
    for step in (10, 20):
        target = largest_file(tmp_path / "checkpoints" / str(step))
        target.write_bytes(target.read_bytes()[:3])
    with pytest.raises(checkpoint.CheckpointError) as error:
        checkpointer.latest_valid(make_state(0))
    text = str(error.value)
    assert "\n" not in text and "no valid checkpoint" in text
    assert str(tmp_path / "checkpoints" / "10") in text and str(tmp_path / "checkpoints" / "20") in text
    assert (tmp_path / "checkpoints" / "20").is_dir()  # nothing moved or destroyed


def test_config_mismatch_is_refused_naming_keys(tmp_path):
    saved_run(tmp_path, [10]).close()
    changed = {**CONFIG, "agent": {"alpha": 0.5, "sizes": [64, 64]}, "seed": 1}
    with pytest.raises(checkpoint.ConfigMismatchError, match=r"agent\.alpha: 0\.2 -> 0\.5, seed: 0 -> 1"):
        checkpoint.RunCheckpointer(tmp_path, changed, every_steps=10).latest_valid(make_state(0))
    # Tuples and lists compare equal (config.json holds lists); ignored keys may change.
    same = checkpoint.RunCheckpointer(tmp_path, {**CONFIG, "seed": 1}, every_steps=10,
                                      ignore_config_keys=("seed",))
    assert same.latest_valid(make_state(0)).step == 10
    (tmp_path / "config.json").write_text(json.dumps(CONFIG))
    checkpoint.check_run_dir_config(tmp_path, CONFIG)
    with pytest.raises(checkpoint.ConfigMismatchError, match=r"env: 'point_umaze' -> 'ant'"):
        checkpoint.check_run_dir_config(tmp_path, {**CONFIG, "env": "ant"})


def test_a_run_dir_from_before_a_config_key_existed_compares_with_the_value_it_ran_with(tmp_path):
    """Run dirs written before agent.precision and run.update_cadence existed ran f32 and the chunk
    cadence."""
    old = {"run": {"env": "point_umaze"}, "agent": {"alpha": 0.2}}
    (tmp_path / "config.json").write_text(json.dumps(old))
    as_run = {"run": {"env": "point_umaze", "update_cadence": "chunk"},
              "agent": {"alpha": 0.2, "precision": "f32"}}
    checkpoint.check_run_dir_config(tmp_path, as_run)
    interleaved = {**as_run, "run": {"env": "point_umaze", "update_cadence": "interleaved"}}
    with pytest.raises(checkpoint.ConfigMismatchError, match=r"run\.update_cadence: 'chunk' -> 'interl"):
        checkpoint.check_run_dir_config(tmp_path, interleaved)


def test_unfinished_write_is_ignored_and_cleaned(tmp_path):
    saved_run(tmp_path, [10]).close()
    partial = tmp_path / "checkpoints" / "20.orbax-checkpoint-tmp-1234567"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "junk").write_bytes(b"\x00" * 100)
    checkpointer = checkpoint.RunCheckpointer(tmp_path, CONFIG, every_steps=10)
    assert checkpointer.all_steps() == [10]
    assert checkpointer.latest_valid(make_state(0)).step == 10
    # orbax removes leftover tmp dirs in the background and waits for that before its next save.
    assert checkpointer.save(20, make_state(20)) and not partial.exists()
    assert checkpointer.latest_valid(make_state(0)).step == 20


WRITER = textwrap.dedent("""
    import sys, jax.numpy as jnp
    from morefree_jax import checkpoint
    run_dir = sys.argv[1]
    checkpointer = checkpoint.RunCheckpointer(run_dir, {"x": 1}, every_steps=1, keep=2)
    step = 1
    while True:  # killed by the parent at some point during these writes
        state = {"big": jnp.full((3_000_000,), float(step)), "step": jnp.asarray(step, jnp.int32)}
        checkpointer.save(step, state, {"step": step})
        step += 1
""")


def test_sigkill_during_writes_leaves_a_valid_checkpoint(tmp_path):
    env = {**os.environ, "PYTHONPATH": f"src{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    process = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = tmp_path / "checkpoints" / "1" / checkpoint.FILE_MANIFEST
    deadline = time.time() + 120
    while not first.exists() and time.time() < deadline and process.poll() is None:
        time.sleep(0.05)
    assert first.exists(), "writer did not save its first checkpoint"
    time.sleep(0.7)  # somewhere inside a later write (each 12 MB write takes a fraction of a second)
    process.send_signal(signal.SIGKILL)
    process.wait()
    template = {"big": jnp.zeros((3_000_000,)), "step": jnp.asarray(0, jnp.int32)}
    restored = checkpoint.RunCheckpointer(tmp_path, {"x": 1}, every_steps=1).latest_valid(template)
    assert restored.step >= 1 and int(restored.state["step"]) == restored.step
    assert float(restored.state["big"].min()) == float(restored.state["big"].max()) == restored.step


def test_ctrl_c_during_a_save_finishes_the_save_first(tmp_path):
    checkpointer = checkpoint.RunCheckpointer(tmp_path, CONFIG, every_steps=10)
    original_save = checkpointer.manager.save

    def save_interrupted_midway(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # arrives while orbax is writing
        return original_save(*args, **kwargs)

    checkpointer.manager.save = save_interrupted_midway
    with pytest.raises(KeyboardInterrupt):
        checkpointer.save(10, make_state(10))
    checkpointer.manager.save = original_save
    restored = checkpointer.latest_valid(make_state(0))
    assert restored.step == 10 and (tmp_path / "checkpoints" / "10" / checkpoint.FILE_MANIFEST).exists()
    assert_trees_equal(restored.state, make_state(10))
