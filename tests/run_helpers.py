"""Shared pieces of the run tests: tiny debug runs (compiled programs shared per variant and seed count)
the host-callback detectors, and the comparisons of exact resume."""

from __future__ import annotations

import fcntl
import functools
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs_mjx
from morefree_jax.checkpoint import latest_valid
from morefree_jax.compile import seed_slice
from morefree_jax.config import resolve_config
from morefree_jax.logger import read_metrics

# The persistent compilation cache of the test processes (conftest) and of the CLI runs they start: the
# first to compile a program writes it, the others load it (docs/testing.md).
COMPILATION_CACHE = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(
    pathlib.Path(tempfile.gettempdir()) / f"morefree_jax_test_cache_{os.getuid()}")

REPO = pathlib.Path(__file__).resolve().parents[1]


def cli_env(**extra: str) -> dict:
    """A CLI subprocess's environment: the repository importable from any working directory, and the
    tests' compilation cache with every program in it."""
    return {**os.environ, "PYTHONPATH": f"{REPO / 'src'}:{REPO}",
            "JAX_COMPILATION_CACHE_DIR": COMPILATION_CACHE, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            **extra}


def start_train_cli(arguments) -> subprocess.Popen:
    """`python -m experiments.train *arguments` in the repository (stderr kept for sigkill_once_written)."""
    return subprocess.Popen([sys.executable, "-m", "experiments.train", *arguments], cwd=REPO, env=cli_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


# The run tests use tabletop, whose kinematic step compiles in ~1 s, where point_umaze's MJX physics
# (RK4 with contacts) takes ~15 s in each of prefill, collect and evaluate (measured, debug preset): the
# run infrastructure is the same for every task, and the physics has its own tests.
RUN_ENV = "tabletop"
CHUNK = 200  # tabletop: H_G + H_E = its 200-step evaluation episode

# Small, fast settings shared by every debug run (and by the CLI runs of test_loop, so that the
# persistent compilation cache can serve them): 10 updates per chunk, a small goal search, every
# program compiled unoptimised (codegen=fast: compiling is most of a debug run's time), float32 (the
# default precision depends on the CPU; pinned, the suite computes the same on every machine, and
# test_precision.py covers bf16).
DEBUG_ARGS = (
    f"env={RUN_ENV}", "preset=debug", "seed=0", "prefill=20", "train_every=20", "pretrain=5",
    "planner.num_candidates=16", "planner.iterations=2", "planner.horizon=5", "eval_episodes=4",
    "log_every=100", "eval_every=200", "checkpoint_every=100", "visitation_bins=8", "codegen=fast",
    "agent.precision=f32",
)


def debug_args(*extra: str) -> list[str]:
    """DEBUG_ARGS with the keys `extra` sets replaced by extra's values (a key given twice is an error)."""
    keys = {argument.split("=")[0] for argument in extra}
    return [argument for argument in DEBUG_ARGS if argument.split("=")[0] not in keys] + list(extra)


def debug_config(agent: str, *extra: str):
    return resolve_config(debug_args(f"agent={agent}", *extra), envs_mjx.ALL_ENVS)


@functools.lru_cache(maxsize=1)
def debug_programs(agent: str, num_seeds: int = 1):
    """One variant's programs at a time: switching variants drops the previous ones and JAX's executables.
    With the MJX physics in the collect program, XLA aborted compiling or loading a variant's collect in a
    process that held the executables of five other variants (tests/test_loop.py, 2026-11-29)."""
    from morefree_jax.driver import build_programs

    jax.clear_caches()
    return build_programs(debug_config(agent, "steps=200"), num_seeds)


def debug_run(agent: str, seeds: tuple[int, ...] = (0,)):
    """(Programs, a fresh prefilled RunState with a leading seed axis) of the debug config."""
    programs = debug_programs(agent, len(seeds))
    keys = jax.numpy.stack([jax.random.PRNGKey(seed) for seed in seeds])
    return programs, programs.prefill(programs.init(keys))


def callback_primitives(jaxpr) -> set[str]:
    """Names of host-callback primitives anywhere in a jaxpr, sub-jaxprs (scan, cond, pjit) included."""
    found = set()
    for eqn in jaxpr.eqns:
        if "callback" in eqn.primitive.name:
            found.add(eqn.primitive.name)
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found |= callback_primitives(inner)
    return found


def hlo_has_callback(jitted, *args) -> bool:
    """Whether the compiled HLO calls back into Python: a custom call whose target is a Python callback
    (only the targets are searched: op metadata names source functions, which may say "callback")."""
    text = jitted.lower(*args).compile().as_text()
    return any("callback" in target.lower() for target in re.findall(r'custom_call_target="([^"]+)"', text))


def sigkill_once_written(process: subprocess.Popen, path, timeout_s: float = 600,
                         group: bool = False) -> None:
    """SIGKILLs a running CLI process as soon as `path` exists (e.g. a checkpoint's files.json); fails with
    the process's stderr if it ended first. group: kill its whole process group (a process started with
    start_new_session=True and its children) and wait until every member is gone."""
    deadline = time.monotonic() + timeout_s
    while not path.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert process.poll() is None, process.stderr.read().decode()[-2000:]
    if not group:
        process.send_signal(signal.SIGKILL)
        process.wait()
        return
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    while time.monotonic() < deadline + 60:  # a dying child still holds its run dir's lock
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)
    raise AssertionError(f"process group {process.pid} still alive after SIGKILL")


def wait_until_unlocked(run_dir, timeout_s: float = 60) -> None:
    """Waits until no process holds run_dir's lock (a killed run's process may take a moment to die). A
    bare flock probe, not RunDirLock: that would empty the lock file on release, where a killed run leaves
    its owner in it for the resume."""
    deadline = time.monotonic() + timeout_s
    with open(pathlib.Path(run_dir) / ".lock", "a") as lock:
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(lock, fcntl.LOCK_UN)
                return
            except BlockingIOError:
                assert time.monotonic() < deadline, f"{run_dir}'s lock still held after its process died"
                time.sleep(0.05)


def unequal_leaves(a, b) -> list[str]:
    """Paths of the state arrays of `a` and `b` (same structure) whose bytes differ."""
    paths = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(a)[0]]
    return [path for path, x, y in zip(paths, jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
            if np.asarray(x).tobytes() != np.asarray(y).tobytes()]


def records_without_time(run_dir) -> list[dict]:
    """metrics.jsonl without its wall-clock entries: what an exact resume must reproduce."""
    return [{k: v for k, v in r.items() if not k.startswith("time/")}
            for r in read_metrics(pathlib.Path(run_dir) / "metrics.jsonl")]


def assert_same_run(dir_a, state_a, dir_b, state_b) -> None:
    """Two runs ended in bit-identical states and wrote the same metrics."""
    unequal = unequal_leaves(state_a, state_b)
    assert not unequal, f"{len(unequal)} state arrays differ: {unequal[:5]}"
    assert records_without_time(dir_a) == records_without_time(dir_b)


def sigkilled_after(arguments, checkpoints, step: int) -> int:
    """Starts a train CLI with `arguments`, SIGKILLs it as soon as its checkpoint at `step` is complete in
    the `checkpoints` dir (a group's: its last seed's, which the group writes last) and returns the newest
    step checkpointed there."""
    sigkill_once_written(start_train_cli(arguments), checkpoints / str(step) / "files.json")
    return max(int(p.name) for p in checkpoints.iterdir() if p.name.isdigit())


def final_state(run_dir, programs, seeds=(0,)):
    """(step, state) of run_dir's newest valid checkpoint, read with a template made by `programs`
    (compiled for `seeds`)."""
    template = seed_slice(programs.init(jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])), 0)
    config_dict = json.loads((pathlib.Path(run_dir) / "config.json").read_text())
    restored = latest_valid(run_dir, template, config_dict)
    return restored.step, restored.state


def assert_train_cli_error(capsys, arguments, message: str) -> None:
    """`train` with bad `arguments` exits 2 with one line on stderr that contains `message`."""
    from experiments import train as train_cli

    assert train_cli.main(arguments) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
