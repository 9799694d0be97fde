"""Shared fixtures: the CPU runtime, the compilation cache, one env instance per task, the task parameter."""

from __future__ import annotations

import functools

import jax
import pytest
from run_helpers import COMPILATION_CACHE

import envs_mjx
from morefree_jax import runtime

# The tuned CPU runtime the CLIs use (importing the library sets nothing); before any JAX computation.
runtime.configure()
# One persistent compilation cache for the test processes (both xdist workers) and the CLI runs they start:
# a CLI run loads the programs a test compiled in-process with the same config, and a worker loads what the
# other compiled (run_helpers.COMPILATION_CACHE). Programs under a second to compile are not written.
jax.config.update("jax_compilation_cache_dir", COMPILATION_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@functools.cache
def cached_env(name: str) -> envs_mjx.ResetFreeEnv:
    return envs_mjx.make(name)


@pytest.fixture(params=envs_mjx.ALL_ENVS)
def env_name(request) -> str:
    return request.param
