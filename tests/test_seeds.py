"""Several seeds in one program (debug preset, tabletop: see run_helpers.RUN_ENV): per-seed run dirs,
equality with single-seed runs, exact resume of a group after SIGKILL, vmap with one trace, sharding over
2 forced CPU devices, bad seed lists.

Tolerances: with seed_axis "map" (the CPU default) seed k runs the single-seed computation itself, so the
test asks for bit-equal states and metrics. Batched (vmap) or sharded programs round differently (XLA's
batched and partitioned kernels, ~1e-7 relative), and a contact-rich stream (PointUMaze, measured)
amplifies that within tens of steps, so those are compared before the first chunk of collection: initial
state, prefill, a chunk of updates, to 1e-5.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import train as train_cli
from morefree_jax import driver
from morefree_jax.checkpoint import RunCheckpointer, latest_valid
from morefree_jax.compile import compile_programs, seed_slice
from morefree_jax.config import ConfigError
from morefree_jax.driver import restore_group
from morefree_jax.logger import read_metrics
from morefree_jax.seeds import parse_seeds
from tests.run_helpers import (
    CHUNK,
    assert_same_run,
    assert_train_cli_error,
    cli_env,
    debug_args,
    debug_config,
    debug_programs,
    records_without_time,
    sigkill_once_written,
    unequal_leaves,
)

REPO = pathlib.Path(__file__).resolve().parents[1]
PREFILL = 20  # run_helpers.DEBUG_ARGS
THREE_CHUNKS = PREFILL + 3 * CHUNK
SEEDS = (0, 1)


def _cli(run_dir, steps: int, *extra: str) -> list[str]:
    arguments = [arg for arg in debug_args(f"checkpoint_every={2 * CHUNK}", *extra)
                 if not arg.startswith("seed=")]
    return [sys.executable, "-m", "experiments.train", *arguments, "agent=morefree", "seeds=0,1",
            f"steps={steps}", f"run_dir={run_dir}"]


def _checkpoint(run_dir, template):
    config_dict = json.loads((pathlib.Path(run_dir) / "config.json").read_text())
    restored = latest_valid(run_dir, template, config_dict)
    return restored.step, restored.state


def _template():
    return seed_slice(debug_programs("morefree").init(jax.random.PRNGKey(0)[None]), 0)




@pytest.fixture(scope="module")
def two_seed_run(tmp_path_factory):
    """A 3-chunk CLI run of seeds 0 and 1 in one program (it compiles; later CLI runs load its cache)."""
    run_dir = tmp_path_factory.mktemp("two_seeds")
    result = subprocess.run(_cli(run_dir, THREE_CHUNKS), cwd=REPO, env=cli_env(), capture_output=True,
                            text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-2000:]
    return run_dir


def test_each_seed_writes_its_own_run_dir(two_seed_run):
    for seed in SEEDS:
        seed_dir = two_seed_run / f"seed{seed}"
        config = json.loads((seed_dir / "config.json").read_text())
        assert config["run"]["seed"] == seed and config["run"]["run_dir"] == str(seed_dir)
        records = read_metrics(seed_dir / "metrics.jsonl")
        assert any("eval/success" in r for r in records) and list((seed_dir / "tb").iterdir())
        assert sorted(int(p.name) for p in (seed_dir / "checkpoints").iterdir() if p.name.isdigit()) == [
            PREFILL + 2 * CHUNK, THREE_CHUNKS]
    assert records_without_time(two_seed_run / "seed0") != records_without_time(two_seed_run / "seed1")


def test_seed_one_of_a_group_equals_the_single_seed_run(two_seed_run, tmp_path):
    config = debug_config("morefree", "seed=1", f"steps={THREE_CHUNKS}", f"checkpoint_every={2 * CHUNK}",
                          f"run_dir={tmp_path}")
    driver.train(config, programs=debug_programs("morefree"), progress="off")
    step_group, state_group = _checkpoint(two_seed_run / "seed1", _template())
    step_single, state_single = _checkpoint(tmp_path, _template())
    assert step_group == step_single == THREE_CHUNKS
    assert not unequal_leaves(state_group, state_single)  # bit-equal: seed_axis "map" on CPU
    assert records_without_time(two_seed_run / "seed1") == records_without_time(tmp_path)


def test_sigkill_during_a_two_seed_run_resumes_bit_exact_for_both(two_seed_run, tmp_path):
    process = subprocess.Popen(_cli(tmp_path, PREFILL + 10 * CHUNK), cwd=REPO, env=cli_env(),
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    checkpoint = tmp_path / "seed1" / "checkpoints" / str(PREFILL + 2 * CHUNK)
    sigkill_once_written(process, checkpoint / "files.json")
    resumed = subprocess.run(_cli(tmp_path, THREE_CHUNKS), cwd=REPO, env=cli_env(), capture_output=True,
                             text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    for seed in SEEDS:
        step_a, state_a = _checkpoint(two_seed_run / f"seed{seed}", _template())
        step_b, state_b = _checkpoint(tmp_path / f"seed{seed}", _template())
        assert step_a == step_b == THREE_CHUNKS
        assert_same_run(two_seed_run / f"seed{seed}", state_a, tmp_path / f"seed{seed}", state_b)


def _first_updates(programs, seeds):
    """State after init, prefill and one chunk of updates (no collection: see the module docstring)."""
    state = programs.prefill(programs.init(jnp.stack([jax.random.PRNGKey(s) for s in seeds])))
    return programs.train_updates(state)[0]


def _assert_close_to_single_seed_runs(state, tolerance: float = 1e-5):
    single = debug_programs("morefree")
    for index, seed in enumerate(SEEDS):
        expected = seed_slice(_first_updates(single, (seed,)), 0)
        got = seed_slice(state, index)
        for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
            np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                       rtol=tolerance, atol=tolerance)


def test_run_functions_vmap_over_two_seeds_with_one_trace():
    programs = compile_programs(debug_programs("morefree").fns, len(SEEDS), seed_axis="vmap")
    state = _first_updates(programs, SEEDS)
    _assert_close_to_single_seed_runs(state)
    for _ in range(2):
        state, metrics = programs.collect(state)  # the interleaved cadence: the chunk's updates included
    for name in ("init", "prefill", "collect", "train_updates"):
        assert getattr(programs, name)._cache_size() == 1, name
    assert all(np.asarray(v).shape[0] == 2 and np.isfinite(np.asarray(v)).all() for v in metrics.values())


def test_a_group_killed_between_its_seeds_saves_resumes_at_the_common_step(tmp_path):
    template = {"w": np.zeros(3, np.float32)}
    checkpointers = [RunCheckpointer(tmp_path / f"seed{seed}", {"seed": seed}, 100) for seed in SEEDS]
    for step in (100, 200):
        for seed, checkpointer in zip(SEEDS, checkpointers, strict=True):
            if not (seed == 1 and step == 200):  # killed after seed 0's save of step 200
                checkpointer.save(step, {"w": np.full(3, step + seed, np.float32)})
    states, step = restore_group(checkpointers, [template, template])
    assert step == 100 and [float(s["w"][0]) for s in states] == [100.0, 101.0]
    for checkpointer in checkpointers:
        checkpointer.close()


SHARDED_SCRIPT = """
import sys
import jax, jax.numpy as jnp, numpy as np
from morefree_jax import runtime
runtime.configure()
from morefree_jax.compile import compile_programs, seed_sharding
from tests.run_helpers import debug_programs
assert len(jax.devices()) == 2, jax.devices()
sharding = seed_sharding(2)
programs = compile_programs(debug_programs("morefree").fns, 2, sharding)
state = programs.prefill(programs.init(jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)])))
state, _ = programs.train_updates(state)
leaf = jax.tree.leaves(state.agent)[0]
assert leaf.sharding.is_equivalent_to(sharding, leaf.ndim) and len(leaf.addressable_shards) == 2
np.savez(sys.argv[1], *[np.asarray(x) for x in jax.tree.leaves(state)])
"""


def test_two_seeds_sharded_over_two_cpu_devices_match_one_device(tmp_path):
    output = tmp_path / "sharded.npz"
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    result = subprocess.run([sys.executable, "-c", SHARDED_SCRIPT, str(output)], cwd=REPO,
                            env=cli_env(XLA_FLAGS=flags), capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-2000:]
    with np.load(output) as stored:
        leaves = [stored[f"arr_{i}"] for i in range(len(stored.files))]
    template = _first_updates(debug_programs("morefree"), (0,))
    _assert_close_to_single_seed_runs(jax.tree.unflatten(jax.tree.structure(template), leaves))


@pytest.mark.parametrize("text, message", [
    ("", "seeds is empty"),
    ("0,0", "seeds must be distinct, got [0, 0]"),
    ("0,-1", "seeds must be integers in 0..4294967295, got [0, -1]"),
    ("0,4294967296", "seeds must be integers in 0..4294967295, got [0, 4294967296]"),
    ("0,x", "seeds must be comma-separated integers >= 0"),
    ("1.5", "seeds must be comma-separated integers >= 0"),
])
def test_bad_seed_lists_get_one_line_errors(text, message, capsys):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        parse_seeds(text)
    assert_train_cli_error(capsys, ["env=point_umaze", f"seeds={text}"], message)
    assert train_cli.main(["env=point_umaze", "seed=1", "seeds=0,1"]) == 2
