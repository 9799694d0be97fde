"""PEG goal search on known score functions (no networks): convergence, clipping, one compilation."""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import cached_env

import envs_mjx
from morefree_jax import planner
from morefree_jax.config import resolve_config

LOW = jnp.array([-2.0, -2.0, -1.0])
HIGH = jnp.array([10.0, 10.0, 1.0])
OPTIMUM = jnp.array([6.5, 1.5, 0.3])


def quadratic_bowl(candidates, key):
    del key
    return -jnp.sum(jnp.square(candidates - OPTIMUM), axis=-1)


def outside_bowl(candidates, key):
    """Optimum (12, -5, 0) lies outside the box: the best reachable goal is the face point (10, -2, 0)."""
    del key
    return -jnp.sum(jnp.square(candidates - jnp.array([12.0, -5.0, 0.0])), axis=-1)


@functools.cache
def compiled_plan(score_fn, config):
    return jax.jit(functools.partial(planner.plan_goal, score_fn, config=config))


def task_planner(task: str, *overrides: str) -> planner.PlannerConfig:
    """The planner config a run on `task` resolves to (the task's default_config), with overrides."""
    return resolve_config([f"env={task}", *overrides], envs_mjx.ALL_ENVS).planner


CONFIGS = {
    # The per-task configurations the runs use (PEG point maze CEM, PEG ant-maze MPPI temperature).
    "cem": task_planner("point_umaze"),
    "mppi": task_planner("ant", "planner.init_std=4.0"),
}


@pytest.mark.parametrize("method", ["cem", "mppi"])
def test_converges_to_bowl_optimum_within_configured_iterations(method):
    config = CONFIGS[method]
    assert config.method == method and config.iterations == 5
    plan = compiled_plan(quadratic_bowl, config)
    start = planner.start_search(config, jnp.array([0.0, 0.0, 0.0]))
    for seed in range(3):
        goal, state, metrics = plan(start, LOW, HIGH, jax.random.PRNGKey(seed))
        # Start: 6.7 away from the optimum with std 4; after 5 rounds the mean is within 0.2 and the
        # sampled goal (std ~0.06 CEM, ~0.23 MPPI) within 1.0.
        assert float(jnp.linalg.norm(state.mean - OPTIMUM)) < 0.2, (method, seed, state.mean)
        assert float(jnp.linalg.norm(goal - OPTIMUM)) < 1.0, (method, seed, goal)
        assert float(jnp.max(state.std)) < 0.5
        assert float(metrics["planner/score"]) > float(metrics["planner/score_first"]) + 10.0
        assert float(metrics["planner/nonfinite_scores"]) == 0.0


@pytest.mark.parametrize("method", ["cem", "mppi"])
def test_clipping_to_bounds(method):
    config = CONFIGS[method]
    plan = compiled_plan(outside_bowl, config)
    goal, state, _ = plan(planner.start_search(config, jnp.zeros(3)), LOW, HIGH, jax.random.PRNGKey(1))
    assert bool(jnp.all((goal >= LOW) & (goal <= HIGH)))
    assert bool(jnp.all((state.mean >= LOW) & (state.mean <= HIGH)))
    # Every candidate has y clipped onto its low bound; x climbs towards its high bound (start 0).
    assert abs(float(state.mean[1]) + 2.0) < 0.1 and float(state.mean[0]) > 8.0, state.mean
    wide = planner.PlannerState(mean=jnp.zeros(3), std=jnp.full(3, 50.0), score=jnp.zeros(()))
    candidates = planner.sample_candidates(wide, LOW, HIGH, jax.random.PRNGKey(2), 1000)
    assert candidates.shape == (1000, 3)
    assert bool(jnp.all((candidates >= LOW) & (candidates <= HIGH)))
    # With std 50, P(N(0, 50) > 10) = 42% of draws land beyond x's high bound and are clipped onto it.
    assert 0.37 < float(jnp.mean(candidates[:, 0] == HIGH[0])) < 0.47
    stored = jax.vmap(lambda k: planner.sample_stored_goal(wide, LOW, HIGH, k))(
        jax.random.split(jax.random.PRNGKey(3), 100))
    assert bool(jnp.all((stored >= LOW) & (stored <= HIGH)))


def test_compiles_once_over_calls():
    config = planner.PlannerConfig(method="mppi", num_candidates=64, iterations=3, init_std=2.0)

    @chex.assert_max_traces(n=1)
    def traced_plan(state, low, high, key):
        return planner.plan_goal(quadratic_bowl, state, low, high, key, config)

    plan = jax.jit(traced_plan)
    state = planner.start_search(config, jnp.zeros(3))
    for seed in range(3):
        goal, state, _ = plan(state, LOW, HIGH, jax.random.PRNGKey(seed))
        planner.sample_stored_goal(state, LOW, HIGH, jax.random.PRNGKey(seed))
    assert goal.shape == (3,)


def test_nonfinite_scores_are_ignored():
    """A NaN score (e.g. a diverged imagined rollout) gets zero weight instead of poisoning the Gaussian."""
    def bowl_with_nans(candidates, key):
        scores = quadratic_bowl(candidates, key)
        return jnp.where(candidates[:, 0] < 3.0, jnp.nan, scores)

    for method in ("cem", "mppi"):
        config = CONFIGS[method]
        goal, state, metrics = compiled_plan(bowl_with_nans, config)(
            planner.start_search(config, jnp.array([5.0, 0.0, 0.0])), LOW, HIGH, jax.random.PRNGKey(0))
        assert bool(jnp.all(jnp.isfinite(state.mean))) and bool(jnp.all(jnp.isfinite(goal)))
        assert float(jnp.linalg.norm(state.mean - OPTIMUM)) < 0.3
        assert 0.0 < float(metrics["planner/nonfinite_scores"]) < 1.0


def test_peg_score_sums_last_steps():
    horizon, goals = 15, 4
    reward = jnp.arange(horizon * goals, dtype=jnp.float32).reshape(horizon, goals)
    returns = 2.0 * reward
    np.testing.assert_allclose(planner.peg_score(reward, returns, None), returns.sum(0))
    # last 10 of 15 steps: rows 5..14 of 2*(4t + g): 2 * (4 * sum(5..14) + 10 g) = 760 + 20 g.
    np.testing.assert_allclose(planner.peg_score(reward, returns, 10), 760.0 + 20.0 * jnp.arange(4))
    rewards_only = planner.peg_score(reward, returns, 10, use_value=False)
    np.testing.assert_allclose(rewards_only, 380.0 + 10.0 * jnp.arange(4))


def test_config_validation_and_task_defaults():
    with pytest.raises(ValueError, match="method"):
        planner.PlannerConfig(method="random")
    with pytest.raises(ValueError, match="cem_elite_fraction"):
        planner.PlannerConfig(cem_elite_fraction=0.0)
    assert planner.PlannerConfig(num_candidates=500).num_elites == 100
    ant = task_planner("ant")
    assert (ant.method, ant.mppi_temperature, ant.horizon, ant.init_std, ant.use_last_steps) == (
        "mppi", 2.0, 250, 10.0, 10)  # horizon = MoReFree's H_G, half the 500-step episode
    assert task_planner("point_umaze", "planner.iterations=3").iterations == 3


@pytest.mark.parametrize("task", envs_mjx.ALL_ENVS)
def test_every_registered_task_sets_its_planner(task):
    defaults = envs_mjx.env_class(task).default_config()
    assert {"planner.method", "planner.horizon", "planner.init_std"} <= set(defaults)
    assert task_planner(task).horizon == defaults["planner.horizon"]
    # PEG imagines a candidate goal's pursuit for as long as the go phase will pursue it: H_G, which for
    # MoReFree is half the evaluation episode (paper section 5).
    assert defaults["planner.horizon"] == cached_env(task).eval_episode_length // 2
