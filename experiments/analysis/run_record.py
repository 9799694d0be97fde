"""One run as the figures and tables read it, from its run dir (read_run) or its record (records.py).

    run = read_run(pathlib.Path("runs/point_umaze/morefree/seed0"))
    run.evaluations("eval/success")        # {step: success}
    run.histogram("visitation", run_step)  # a saved heatmap; run.back_starts(): the back-chunk starts
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
from typing import Any

import numpy as np

from morefree_jax import variants
from morefree_jax.legacy import stored_value
from morefree_jax.logger import PROVENANCE_FILE, read_metrics

# Logged with the training metrics, running since the run's start: the share of chunks that went back to
# an initial state (Back-and-Forth Go-Explore), and the share of those whose go phase met the success test.
BACK_SHARE, BACK_REACHED = "goal/share_initial", "go/reach_rate_initial"


class RunDirArtifacts:
    """The heatmaps and back-chunk starts a run dir saves in plots/ (logger.RunLogger)."""

    def __init__(self, run_dir: pathlib.Path):
        self.plots = run_dir / "plots"

    def saved_views(self, prefix: str) -> set[int]:
        return {int(p.stem.rsplit("_", 1)[1]) for p in self.plots.glob(f"{prefix}_*.npy")}

    def histogram(self, prefix: str, step: int) -> np.ndarray:
        return np.load(self.plots / f"{prefix}_{step:09d}.npy")

    def back_starts(self) -> tuple[np.ndarray, int] | None:
        """(xy (n, 100, 2), the step the file was saved at), None before a back chunk succeeded."""
        path = self.plots / "back_starts.npz"
        if not path.exists():
            return None
        with np.load(path) as data:
            return data["xy"], int(data["step"])


@dataclasses.dataclass
class RunRecord:
    """One run, from its run dir or its record (records.py): task, agent and seed, per-step merged metrics,
    the commits that wrote it, and its saved heatmaps and back-chunk starts."""

    source: pathlib.Path  # the run dir, or the record's .jsonl
    task: str
    agent: str  # the group's label: the agent's name, with its alpha when a sweep changed it
    seed: int
    steps: dict[int, dict]
    commits: tuple[str, ...]
    base_agent: str = ""  # the registry's name (agents= filters on it)
    artifacts: Any = None  # RunDirArtifacts, records.RecordArtifacts: saved_views, histogram, back_starts
    replay_capacity: int | None = None  # rows its replay keeps (None: the config does not say)

    def evaluations(self, key: str = "eval/success") -> dict[int, float]:
        return {step: record[key] for step, record in sorted(self.steps.items()) if key in record}

    def latest(self, key: str, step: int) -> float:
        """`key` as last logged at or before `step` (NaN if never): the dropped share is logged every
        log_every steps, not with the evaluations."""
        logged = [value for at, value in self.evaluations(key).items() if at <= step]
        return logged[-1] if logged else math.nan

    def back_reach_rate(self, step: int) -> float:
        """The share of the back chunks so far that reached their initial state, as last logged at or before
        `step`; NaN for a run that sends none back (or logged none)."""
        if not self.latest(BACK_SHARE, step) > 0:  # NaN or 0
            return math.nan
        return self.latest(BACK_REACHED, step)

    def saved_views(self, prefix: str = "visitation") -> set[int]:
        """Steps with a saved heatmap of this view (prefix "visitation" or "side_visitation")."""
        return self.artifacts.saved_views(prefix)

    def histogram(self, prefix: str, step: int) -> np.ndarray:
        return self.artifacts.histogram(prefix, step)

    def back_starts(self) -> tuple[np.ndarray, int] | None:
        return self.artifacts.back_starts()


def short_commits(starts: list[dict]) -> tuple[str, ...]:
    """Short commits of every start of a run (provenance.jsonl's entries), '+dirty' where the tree had
    changes."""
    seen = []
    for entry in starts:
        commit = (entry.get("commit") or "unknown")[:7] + ("+dirty" if entry.get("dirty") else "")
        if commit not in seen:
            seen.append(commit)
    return tuple(seen) or ("unknown",)


def read_starts(run_dir: pathlib.Path) -> list[dict]:
    """The entries of the run dir's provenance.jsonl, one per start or resume ([] where there is none)."""
    path = run_dir / PROVENANCE_FILE
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def agent_label(config: dict) -> str:
    """The agent's name, plus what the run set away from its defaults that splits a comparison: its alpha
    (an alpha sweep: "morefree alpha=0.5", or both keys when they differ), the chunk update cadence, a bf16
    learner ("morefree cadence=chunk precision=bf16"). A key a config.json lacks (an older run dir) reads
    as the value that run computed with (legacy.py)."""
    agent, extras = config["run"]["agent"], []
    if agent in variants.VARIANTS:
        chosen = variants.VARIANTS[agent]
        collect = config.get("schedule", {}).get("alpha", chosen.collect_alpha)
        imagine = config.get("agent", {}).get("alpha", chosen.imagination_alpha)
        if (collect, imagine) != (chosen.collect_alpha, chosen.imagination_alpha):
            extras += ([f"alpha={collect:g}"] if collect == imagine
                       else [f"schedule.alpha={collect:g}", f"agent.alpha={imagine:g}"])
        if stored_value(config, "run.update_cadence") != "interleaved":
            extras.append(f"cadence={stored_value(config, 'run.update_cadence')}")
    if stored_value(config, "agent.precision") != "f32":
        extras.append(f"precision={stored_value(config, 'agent.precision')}")
    return " ".join([agent, *extras])


def replay_capacity(config: dict) -> int | None:
    """The rows the run's replay keeps: a world-model agent's agent.replay.capacity, a model-free agent's
    baseline.replay_capacity; None where the config does not say."""
    if config.get("run", {}).get("agent") in variants.VARIANTS:
        capacity = config.get("agent", {}).get("replay", {}).get("capacity")
    else:
        capacity = config.get("baseline", {}).get("replay_capacity")
    return None if capacity is None else int(capacity)


def read_run(run_dir: pathlib.Path) -> RunRecord:
    """The run in `run_dir`; ValueError (one line: why) when it cannot be used."""
    metrics = run_dir / "metrics.jsonl"
    if not metrics.exists():
        raise ValueError("no metrics.jsonl (not started yet?)")
    try:
        config = json.loads((run_dir / "config.json").read_text())
        run = config["run"]
        task, agent, seed, label = run["env"], run["agent"], int(run["seed"]), agent_label(config)
    except (KeyError, ValueError, TypeError) as error:
        raise ValueError(f"config.json is not a run config ({error})") from None
    steps: dict[int, dict] = {}
    for record in read_metrics(metrics):
        steps.setdefault(int(record["step"]), {}).update(record)
    record = RunRecord(run_dir, task, label, seed, steps, short_commits(read_starts(run_dir)), agent,
                       RunDirArtifacts(run_dir), replay_capacity(config))
    if not record.evaluations():
        raise ValueError("no evaluation yet")
    return record
