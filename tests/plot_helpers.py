"""Hand-made run dirs for the tests of experiments.plots and run records."""

from __future__ import annotations

import json

import numpy as np

SUCCESS = {("morefree", 0): [0.0, 0.5, 1.0], ("morefree", 1): [0.0, 0.3, 0.8],
           ("morefree", 2): [0.2, 0.4, 0.6], ("rf_peg", 0): [0.0, 0.1, 0.2], ("rf_peg", 1): [0.0, 0.3, 0.4]}
STEPS = (2500, 5000, 7500)


def write_run(run_dir, task, agent, seed, successes, commit="a" * 40, back_starts=False):
    (run_dir / "plots").mkdir(parents=True)
    run = {"env": task, "agent": agent, "seed": seed, "update_cadence": "interleaved"}
    (run_dir / "config.json").write_text(json.dumps({"run": run}))
    (run_dir / "provenance.jsonl").write_text(json.dumps({"start_step": 0, "commit": commit, "dirty": False})
                                              + "\n")
    lines = []
    for step, success in zip(STEPS, successes, strict=True):
        back = {"goal/share_initial": 0.15 if agent == "morefree" else 0.0,
                "go/reach_rate_initial": 0.1 * seed}
        lines.append({"step": step, "wm/loss": 1.0, "train/dropped_share": 0.002 * seed, **back})
        lines.append({"step": step, "eval/success": success, "eval/final_success": success / 2})
        lines.append({"step": step, "visitation/task_relevant": 0.1 * seed})
        histogram = np.zeros((50, 50))
        histogram[10 + seed, 20] = step
        np.save(run_dir / "plots" / f"visitation_{step:09d}.npy", histogram)
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    if back_starts:
        xy = np.random.default_rng(seed).uniform(-1, 9, (3, 100, 2)).astype(np.float32)
        xy[0, :10] = np.nan  # before the stream started
        np.savez(run_dir / "plots" / "back_starts.npz", xy=xy, stream_step=np.arange(3), step=np.int64(7500))


def write_runs(root):
    """Three morefree seeds (with back-chunk starts) and two rf_peg seeds on point_umaze below `root`."""
    for (agent, seed), successes in SUCCESS.items():
        write_run(root / "point_umaze" / agent / f"seed{seed}", "point_umaze", agent, seed, successes,
                  back_starts=agent == "morefree")
    return root
