"""Agent: train_step traces once, keeps the state's structure, is deterministic, vmaps over seeds; act."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.agent import (
    MODE_DETERMINISTIC,
    MODE_EXPLORE,
    MODE_GOAL,
    EnvSpec,
    _acting_noise,
    acting_state,
    make_agent,
)
from morefree_jax.imagination import GoalPools
from morefree_jax.learner_config import preset
from tests.core_helpers import fixed_batch

TRACES = {"train_step": 0, "act": 0}


@functools.cache
def setup():
    cfg = preset("debug")
    batch = fixed_batch(cfg.replay.batch, cfg.replay.length)
    obs_size = batch.obs.shape[-1]
    agent = make_agent(cfg, EnvSpec(obs_size=obs_size, action_size=2, goal_dims=(0, 1)))

    def counted_train_step(*args):
        TRACES["train_step"] += 1
        return agent.train_step(*args)

    def counted_act(*args):
        TRACES["act"] += 1
        return agent.act(*args)

    pools = GoalPools(jnp.full((3, obs_size), 0.5), jnp.zeros((2, obs_size)))
    seeds_step = jax.jit(jax.vmap(counted_train_step, in_axes=(0, None, None, 0)))
    return agent, seeds_step, jax.jit(counted_act), batch, pools


def init_state(seed: int):
    """The agent's initial state, initialised by one compiled call (op by op it takes seconds)."""
    return _jitted_init()(jax.random.PRNGKey(seed))


@functools.cache
def _jitted_init():
    return jax.jit(setup()[0].init)


def test_train_step_traces_once_keeps_structure_is_deterministic_and_vmaps_over_seeds():
    # One compilation of jax.vmap(train_step) over 2 seeds serves every check (compile time dominates).
    agent, train_step, _, batch, pools = setup()
    state = jax.jit(jax.vmap(agent.init))(jax.random.split(jax.random.PRNGKey(0), 2))
    initial = state
    for i in range(3):
        state, metrics = train_step(state, batch, pools, jax.random.split(jax.random.PRNGKey(i), 2))
    assert TRACES["train_step"] == 1
    assert jax.tree.structure(state) == jax.tree.structure(initial)
    for new, old in zip(jax.tree.leaves(state), jax.tree.leaves(initial), strict=True):
        assert new.shape == old.shape and new.dtype == old.dtype
    np.testing.assert_array_equal(np.asarray(state.updates), [3, 3])
    for name in ["wm/loss", "gc/actor_loss", "gc/critic_loss", "distance/loss", "explore/ensemble_loss",
                 "explore/actor_loss", "explore/critic_loss", "explore/reward"]:
        assert metrics[name].shape == (2,) and np.all(np.isfinite(np.asarray(metrics[name]))), name
    assert float(metrics["wm/loss"][0]) != float(metrics["wm/loss"][1])  # the seeds differ
    # Same inputs and key -> same result; another key -> another result.
    keys = jax.random.split(jax.random.PRNGKey(9), 2)
    again_a, metrics_a = train_step(state, batch, pools, keys)
    again_b, metrics_b = train_step(state, batch, pools, keys)
    _, metrics_c = train_step(state, batch, pools, jax.random.split(jax.random.PRNGKey(10), 2))
    for a, b in zip(jax.tree.leaves(again_a), jax.tree.leaves(again_b), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    loss_a, loss_b = np.asarray(metrics_a["gc/actor_loss"]), np.asarray(metrics_b["gc/actor_loss"])
    np.testing.assert_array_equal(loss_a, loss_b)
    assert np.all(np.asarray(metrics_a["gc/actor_loss"]) != np.asarray(metrics_c["gc/actor_loss"]))
    assert TRACES["train_step"] == 1
    # The target critic is copied on update 0 only (target_every = 5 in debug): now it lags the critic.
    lag = jax.tree.leaves(jax.tree.map(lambda a, b: jnp.max(jnp.abs(a - b)), state.gc_critic.params,
                                       state.gc_critic.target))
    assert max(float(x) for x in lag) > 0


def test_act_single_env_and_vmapped_modes():
    agent, train_step, act, batch, pools = setup()
    state = init_state(3)
    obs_size = batch.obs.shape[-1]
    obs = jnp.zeros(obs_size).at[:2].set(jnp.array([0.1, 0.2]))
    goal = jnp.zeros(obs_size).at[:2].set(jnp.array([0.5, 0.5]))
    latent = agent.initial_latent(())
    prev = jnp.zeros(2)
    for mode in [MODE_GOAL, MODE_EXPLORE]:
        action, new_latent = act(state, latent, prev, obs, goal, jax.random.PRNGKey(0), jnp.int32(mode))
        assert action.shape == (2,) and new_latent.deter.shape == latent.deter.shape
        assert float(jnp.max(jnp.abs(action))) <= 1.0
    # Deterministic mode takes the actor's mode (the latent is still sampled, PEG eval_state_mean False).
    key = jax.random.PRNGKey(0)
    mode = jnp.int32(MODE_GOAL | MODE_DETERMINISTIC)
    det = [act(state, latent, prev, obs, goal, key, mode)[0] for _ in range(2)]
    np.testing.assert_array_equal(np.asarray(det[0]), np.asarray(det[1]))
    stochastic = act(state, latent, prev, obs, goal, key, jnp.int32(MODE_GOAL))[0]
    assert float(jnp.max(jnp.abs(stochastic - det[0]))) > 1e-4
    goal_act = act(state, latent, prev, obs, goal, jax.random.PRNGKey(0), jnp.int32(MODE_DETERMINISTIC))[0]
    explore_act = act(state, latent, prev, obs, goal, jax.random.PRNGKey(0), jnp.int32(3))[0]
    assert float(jnp.max(jnp.abs(goal_act - explore_act))) > 1e-4  # two different policies
    assert TRACES["act"] == 1  # mode is traced: one compilation serves all modes
    batched = jax.jit(jax.vmap(agent.act, in_axes=(None, 0, 0, 0, 0, 0, None)))
    actions, latents = batched(state, agent.initial_latent((5,)), jnp.zeros((5, 2)), jnp.tile(obs, (5, 1)),
                               jnp.tile(goal, (5, 1)), jax.random.split(jax.random.PRNGKey(0), 5),
                               jnp.int32(MODE_GOAL))
    assert actions.shape == (5, 2) and latents.stoch.shape == (5, preset("debug").wm.stoch)
    d = agent.goal_distance(state, new_latent, goal, obs=obs)
    assert d.shape == () and np.isfinite(float(d))
    # The slimmed acting state gives the same actions and latents with far fewer leaves to dispatch.
    slim = acting_state(state)
    assert len(jax.tree.leaves(slim)) < len(jax.tree.leaves(state)) / 3
    for mode in [MODE_GOAL, MODE_EXPLORE, MODE_GOAL | MODE_DETERMINISTIC]:
        full_out = act(state, latent, prev, obs, goal, key, jnp.int32(mode))
        slim_out = act(slim, latent, prev, obs, goal, key, jnp.int32(mode))
        for a, b in zip(jax.tree.leaves(full_out), jax.tree.leaves(slim_out), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_act_on_a_goal_context_matches_act_on_the_goal():
    agent, _, _, batch, _ = setup()
    act = jax.jit(agent.act)  # not the trace-counting one: this test traces its own variants
    state = acting_state(init_state(5))
    obs_size = batch.obs.shape[-1]
    obs, goal = jnp.full(obs_size, 0.1), jnp.full(obs_size, 0.7)
    latent, prev, key = agent.initial_latent(()), jnp.full(2, 0.3), jax.random.PRNGKey(1)
    context = jax.jit(agent.goal_context)(state, goal)
    for mode in [MODE_GOAL, MODE_GOAL | MODE_DETERMINISTIC, MODE_EXPLORE]:
        on_goal = act(state, latent, prev, obs, goal, key, jnp.int32(mode))
        on_context = act(state, latent, prev, obs, context, key, jnp.int32(mode))
        for a, b in zip(jax.tree.leaves(on_goal), jax.tree.leaves(on_context), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    # A different goal's context gives a different action: the context is what the policy reads.
    other = jax.jit(agent.goal_context)(state, jnp.full(obs_size, -0.7))
    mode = jnp.int32(MODE_GOAL | MODE_DETERMINISTIC)
    assert float(jnp.max(jnp.abs(act(state, latent, prev, obs, other, key, mode)[0]
                                 - act(state, latent, prev, obs, context, key, mode)[0]))) > 1e-4
    # Batched goals give batched contexts, usable under vmap.
    contexts = agent.goal_context(state, jnp.stack([goal, goal]))
    batched = jax.vmap(agent.act, in_axes=(None, 0, 0, 0, 0, 0, None))
    actions, _ = batched(state, agent.initial_latent((2,)), jnp.stack([prev, prev]), jnp.stack([obs, obs]),
                         contexts, jnp.stack([key, key]), MODE_GOAL)
    np.testing.assert_allclose(np.asarray(actions[0]), np.asarray(actions[1]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(actions[0]), np.asarray(act(state, latent, prev, obs, goal, key,
                                                                      jnp.int32(MODE_GOAL))[0]), atol=1e-5)


def test_acting_noise_is_standard_normal_and_uniform():
    normal, unit = jax.jit(_acting_noise, static_argnums=(1, 2, 3))(jax.random.PRNGKey(0), (4000,), 5, 3)
    assert normal.shape == (4000, 5) and unit.shape == (4000, 3)
    normal, unit = np.asarray(normal).ravel(), np.asarray(unit).ravel()
    assert np.all(np.isfinite(normal)) and np.all((unit >= 0) & (unit < 1))
    n = normal.size
    assert abs(normal.mean()) < 4 / np.sqrt(n) and abs(normal.std() - 1) < 4 / np.sqrt(2 * n)
    # Kolmogorov-Smirnov distance to the normal CDF and to U[0, 1): 1.63 / sqrt(n) is the 1% critical value.
    cdf = np.sort(np.asarray(jax.scipy.stats.norm.cdf(normal)))
    assert np.max(np.abs(cdf - (np.arange(n) + 0.5) / n)) < 1.63 / np.sqrt(n)
    ranks = np.sort(unit)
    assert np.max(np.abs(ranks - (np.arange(unit.size) + 0.5) / unit.size)) < 1.63 / np.sqrt(unit.size)


def test_planner_building_blocks_shapes():
    agent, _, _, batch, _ = setup()
    state = init_state(4)
    goals = jax.random.uniform(jax.random.PRNGKey(5), (6, batch.obs.shape[-1]))
    traj = jax.jit(agent.imagine_to_goals, static_argnums=3)(state, agent.initial_latent(()), goals, 7,
                                                           jax.random.PRNGKey(6))
    assert traj.feat.shape[:2] == (8, 6) and traj.action.shape == (8, 6, 2)
    reward, returns = agent.exploration_value(state, traj)
    assert reward.shape == (8, 6) and returns.shape == (7, 6)
    # Untrained members disagree once the state moves off the all-zero start (zero-initialised biases).
    assert float(jnp.min(reward[1:])) > 0
