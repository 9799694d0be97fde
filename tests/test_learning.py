"""Learning checks (slow, `make test-slow`): whole runs of the `cpu` preset that must solve a task.

PointUMaze with MoReFree at the `cpu` preset, seed 0: the goal-conditioned policy, evaluated episodically
from the start state on the task's goal, must reach the goal (PEG's success: within 0.6 at any step) in
at least half of the 10 evaluation episodes at some evaluation within 20,000 env steps. The recorded
run (README "Results so far") first did so at 7,500 steps. About 12-15 minutes on the idle 2-core CPU.
"""

from __future__ import annotations

import pytest

import envs_mjx
from morefree_jax.config_run import resolve_config
from morefree_jax.logger import read_metrics
from morefree_jax.loop import prepare_run

STEPS = 20_000
REQUIRED_SUCCESS = 0.5


@pytest.mark.slow
def test_morefree_solves_point_umaze_at_cpu_preset(tmp_path):
    arguments = ["env=point_umaze", "agent=morefree", "preset=cpu", "seed=0", f"steps={STEPS}",
                 "eval_every=2500", f"run_dir={tmp_path}"]
    summary = prepare_run(resolve_config(arguments, envs_mjx.ALL_ENVS)).train(progress="off")
    assert summary.env_steps == STEPS
    curve = [(r["step"], r["eval/success"]) for r in read_metrics(tmp_path / "metrics.jsonl")
             if "eval/success" in r]
    assert len(curve) == STEPS // 2500
    assert max(success for _, success in curve) >= REQUIRED_SUCCESS, curve
