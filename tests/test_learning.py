"""Learning checks (slow, `make test-slow`): runs that must solve a task.

PointUMaze with MoReFree at the `cpu` preset, seed 0: the goal-conditioned policy, evaluated episodically
from the start state on the task's goal, must reach the goal (PEG's success: within 0.6 at any step) in
at least half of the 10 evaluation episodes at some evaluation within 20,000 env steps.

Why this level (docs/testing.md, "The slow suite"; issue 15's runs: 3 seeds each of morefree and rf_peg,
commit 0ee41fe, each group on one core): every one of the six seeds met it by 20,000 steps. morefree's seeds
first reached 0.7, 1.0 and 0.7 at 12,500, 12,500 and 20,000 steps; rf_peg's 0.7, 0.7 and 0.6 at 12,500,
15,000 and 12,500. Success at single evaluations swings between 0 and 1 in these runs (seed 0: 0.7 at
12,500, then 0.0 at 15,000), so the check takes the best evaluation, not the last. The margin: seed 0
first meets it 7,500 steps (three evaluations) before the budget; a budget of 15,000 would have failed
one seed in six. The test runs seed 0 alone and unpinned, which is not bit-identical to seed 0 inside the
3-seed group on one core (XLA sizes its thread pool from the CPU affinity), so it is the level, not the
curve, that carries over. About 12 minutes idle.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

import envs_mjx
from morefree_jax import driver
from morefree_jax.compile import jit_run_fns
from morefree_jax.config import resolve_config
from morefree_jax.logger import read_metrics
from morefree_jax.registry import make_run_fns

STEPS = 20_000
REQUIRED_SUCCESS = 0.5


@pytest.mark.slow
def test_morefree_solves_point_umaze_at_cpu_preset(tmp_path):
    arguments = ["env=point_umaze", "agent=morefree", "preset=cpu", "seed=0", f"steps={STEPS}",
                 "eval_every=2500", f"run_dir={tmp_path}"]
    summary = driver.train(resolve_config(arguments, envs_mjx.ALL_ENVS), progress="off")[0]
    assert summary.env_steps == STEPS
    curve = [(r["step"], r["eval/success"]) for r in read_metrics(tmp_path / "metrics.jsonl")
             if "eval/success" in r]
    assert curve[-1][0] == STEPS  # evaluations every 2,500 steps from the first one after the prefill
    assert max(success for _, success in curve) >= REQUIRED_SUCCESS, curve


class _NearGoalPointUMaze(envs_mjx.env_class("point_umaze")):
    """PointUMaze with its goal 2 units down the first corridor: a reach on which episodic SAC learns
    within minutes here (the U-maze's own goal takes the Oracle far longer on a sparse reward)."""

    def eval_goals(self, rng):
        del rng
        return jnp.asarray([2.0, 0.0, 0.0, 0.0, 0.0, 0.0], jnp.float32)


ORACLE_PREFILL, ORACLE_CHUNK, ORACLE_STEPS = 5_000, 2_500, 45_000


@pytest.mark.slow
def test_oracle_sac_learns_to_reach_a_near_goal():
    """oracle_sac (MEDAL's episodic SAC, sparse reward, episodes end on success) on _NearGoalPointUMaze,
    seed 0, a 5,000-step seed phase: at least 8 of 10 evaluation episodes succeed at some evaluation within
    45,000 env steps. Measured (2026-11-30): success 0 at every evaluation to 30,000 steps (early on the
    entropy bonus outweighs the 10 x 1 of ending an episode, so the policy avoids the goal until the
    temperature falls to ~0.03), then 1.0 at 32,500 and 35,000; the budget leaves 10,000 steps of margin.
    About 3 minutes on the idle machine."""
    config = resolve_config(["env=point_umaze", "agent=oracle_sac", f"prefill={ORACLE_PREFILL}",
                             f"baseline.chunk_len={ORACLE_CHUNK}", "baseline.replay_capacity=100000",
                             "eval_episodes=10"], envs_mjx.ALL_ENVS)
    fns = jit_run_fns(make_run_fns(config, _NearGoalPointUMaze()))
    state, steps, curve = fns.prefill(fns.init(jax.random.PRNGKey(0))), ORACLE_PREFILL, []
    while steps < ORACLE_STEPS:
        state, _ = fns.collect(state)
        steps += ORACLE_CHUNK
        metrics, _ = fns.evaluate(state.agent, jax.random.PRNGKey(steps))
        curve.append((steps, float(metrics["eval/success"])))
    assert max(success for _, success in curve) >= 0.8, curve
