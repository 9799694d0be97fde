"""Shared fixtures: one env instance and its compiled rollout per task, reused across tests."""

from __future__ import annotations

import functools

import jax
import pytest
from loop_helpers import COMPILATION_CACHE

import envs_mjx
from morefree_jax import runtime

# The tuned CPU runtime the CLIs use (importing the library sets nothing); before any JAX computation.
runtime.configure()
# One persistent compilation cache for the test processes (both xdist workers) and the CLI runs they start:
# a CLI run loads the programs a test compiled in-process with the same config, and a worker loads what the
# other compiled (loop_helpers.COMPILATION_CACHE). Programs under a second to compile are not written.
jax.config.update("jax_compilation_cache_dir", COMPILATION_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@functools.cache
def cached_env(name: str) -> envs_mjx.ResetFreeEnv:
    return envs_mjx.make(name)


def random_rollout(env: envs_mjx.ResetFreeEnv, key: jax.Array, num_steps: int):
    """Resets with `key` and takes `num_steps` uniform random actions in one lax.scan.

    Returns (initial state, final state, observations (num_steps, obs_size))."""
    key_reset, key_actions = jax.random.split(key)
    state0 = env.reset(key_reset)
    actions = jax.random.uniform(key_actions, (num_steps, env.action_size), minval=-1.0, maxval=1.0)

    def body(state, action):
        state = env.step(state, action)
        return state, state.obs

    final, observations = jax.lax.scan(body, state0, actions)
    return state0, final, observations


@functools.cache
def compiled_rollout(name: str, num_steps: int):
    env = cached_env(name)
    return jax.jit(functools.partial(random_rollout, env, num_steps=num_steps))


@pytest.fixture(params=envs_mjx.ALL_ENVS)
def env_name(request) -> str:
    return request.param
