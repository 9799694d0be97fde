"""Shared pieces of the run tests: tiny debug runs (compiled once per variant per session) and the
host-callback detectors."""

from __future__ import annotations

import functools
import os
import pathlib
import re
import tempfile

import jax
from jax.experimental.compilation_cache import compilation_cache

import envs_mjx
from morefree_jax.config_run import resolve_config

# A persistent compilation cache shared with the CLI subprocesses of test_loop, so that they load the
# executables this process compiled (identical HLO -> identical executable) instead of compiling again.
COMPILATION_CACHE = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(
    pathlib.Path(tempfile.gettempdir()) / f"morefree_jax_test_cache_{os.getuid()}")
if not jax.config.jax_compilation_cache_dir:
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    compilation_cache.set_cache_dir(COMPILATION_CACHE)
    compilation_cache.reset_cache()

CHUNK = 100  # point_umaze: H_G + H_E = its 100-step evaluation episode

# Small, fast settings shared by every debug run (and by the CLI runs of test_loop, so that the
# persistent compilation cache can serve them): 5 updates per chunk, a small goal search.
DEBUG_ARGS = (
    "env=point_umaze", "preset=debug", "seed=0", "prefill=20", "train_every=20", "pretrain=5",
    "planner.num_candidates=16", "planner.iterations=2", "planner.horizon=5", "eval_episodes=4",
    "log_every=100", "eval_every=200", "checkpoint_every=100", "visitation_bins=8",
)


def debug_config(agent: str, *extra: str):
    return resolve_config([*DEBUG_ARGS, f"agent={agent}", *extra], envs_mjx.ALL_ENVS)


@functools.cache
def _debug_run(agent: str):
    from morefree_jax.loop import prepare_run

    return prepare_run(debug_config(agent, "steps=200", "run_dir=/nonexistent"))


def debug_run(agent: str):
    """(Run, a fresh prefilled RunState): the Run and its compiled functions are shared per variant."""
    run = _debug_run(agent)
    return run, run.prefill(run.init(jax.random.PRNGKey(0)))


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
