"""The update cadence (run.update_cadence): under "interleaved" the env steps of a chunk act with the
parameters of every update before them, one update per train_every steps; under "chunk" they all act with
the chunk's starting parameters and the updates follow the chunk."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from morefree_jax.agent import EnvSpec, make_agent
from morefree_jax.compile import jit_run_fns
from morefree_jax.config import ConfigError
from morefree_jax.run import make_run_fns
from tests.run_helpers import CHUNK, debug_config

PREFILL, TRAIN_EVERY = 20, 20  # run_helpers.DEBUG_ARGS: 10 updates per 200-step chunk


def update_counting(agent):
    """The agent with an act that writes the number of updates its parameters have had into the action,
    so the stored actions say which parameters acted at each step."""

    def act(state, latent, prev_action, obs, goal, key, mode):
        action, latent = agent.act(state, latent, prev_action, obs, goal, key, mode)
        return jnp.full_like(action, state.updates.astype(action.dtype)), latent

    return agent._replace(act=act)


@pytest.mark.parametrize("cadence", ["interleaved", "chunk"])
def test_the_act_at_step_t_uses_the_parameters_of_the_updates_before_it(cadence):
    config = debug_config("morefree", "steps=620", f"update_cadence={cadence}")
    env = envs_mjx.make(config.run.env)
    agent = update_counting(make_agent(config.agent, EnvSpec.from_env(env)))
    fns = jit_run_fns(make_run_fns(config, env, agent))
    assert fns.update_cadence == cadence and fns.updates_per_chunk == CHUNK // TRAIN_EVERY
    state = fns.prefill(fns.init(jax.random.PRNGKey(0)))
    t = np.arange(CHUNK)
    for chunk in range(2):
        state, _ = fns.collect(state)
        if cadence == "chunk":
            state, _ = fns.train_updates(state)
        first = PREFILL + chunk * CHUNK
        acted_with = np.asarray(state.replay.action[first:first + CHUNK, 0])
        before = chunk * fns.updates_per_chunk  # updates of the chunks before this one
        expected = before + (t // TRAIN_EVERY if cadence == "interleaved" else 0)
        np.testing.assert_array_equal(acted_with, expected)
        assert int(state.agent.updates) == before + fns.updates_per_chunk


def test_interleaved_needs_train_every_to_divide_the_chunk():
    config = debug_config("morefree", "train_every=30")
    with pytest.raises(ConfigError, match=r"run.train_every \(30\) must divide the chunk of 200 steps"):
        make_run_fns(config, envs_mjx.make(config.run.env))
    assert make_run_fns(debug_config("morefree", "train_every=30", "update_cadence=chunk"),
                        envs_mjx.make(config.run.env)).updates_per_chunk == 7
