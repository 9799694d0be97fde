"""Run records: what the repository keeps of a run, so that a fresh clone redraws every figure and table
(docs/experiments.md, "Run records").

    paths = write_record(run_dir, "results/data")   # results/data/<task>/<group>/seed<k>.jsonl and .npz
    record = read_record(path)                      # a run_record.RunRecord, as read_run gives for a run dir

A record is two files per run:
  seed<k>.jsonl  a header line (format, task, agent, group label, seed, preset, precision, update cadence,
                 config digest, every start's commit, the config), then one line per evaluation: the step,
                 every eval/* and visitation/* value logged at that step, and train/dropped_share and the
                 back chunks' share and reach rate as last logged at or before it
  seed<k>.npz    the visitation histograms at the run's last saved step (the top view; the side view where
                 the task has one) and the starts of successful back chunks (plots/back_starts.npz)
A few tens of KB per run. The record is a function of the run dir: writing it again after more evaluations
replaces it, but a record that reaches a later step than its run dir (a run restarted on a new machine) is
kept unless replace=True. Reading it back gives the same RunRecord as the run dir, so that the tables
agree and the figures agree but for visitation_step= (a record keeps the last heatmap only).
"""

from __future__ import annotations

import copy
import io
import json
import math
import os
import pathlib

import numpy as np

from experiments.analysis.run_record import (
    BACK_REACHED,
    BACK_SHARE,
    RunRecord,
    read_run,
    read_starts,
    replay_capacity,
    short_commits,
)
from morefree_jax.checkpoint import config_hash
from morefree_jax.config import RESUMABLE_KEYS
from morefree_jax.legacy import stored_value
from morefree_jax.logger import DROPPED_SHARE

FORMAT = "morefree-jax run record 1"
KEPT_PREFIXES = ("eval/", "visitation/")  # the values the figures and tables read, per evaluation
LATEST_KEYS = (DROPPED_SHARE, BACK_SHARE, BACK_REACHED)  # and those they read as last logged before it
VIEW_PREFIXES = ("visitation", "side_visitation")  # the heatmaps a run dir saves (figures.HeatmapView)
BACK_STARTS = "back_starts.npz"


def config_digest(config: dict) -> str:
    """A digest of what the run computes, the same for every seed of a group: the config without the seed
    and the keys a resume may change (config.RESUMABLE_KEYS)."""
    kept = copy.deepcopy(config)
    for dotted in (*RESUMABLE_KEYS, "run.seed"):
        group, key = dotted.split(".")
        kept.get(group, {}).pop(key, None)
    return config_hash(kept)


def group_dir_name(label: str) -> str:
    """The record's directory for an agent label ("morefree cadence=chunk" -> "morefree_cadence=chunk")."""
    return label.replace(" ", "_")


def _provenance(run_dir: pathlib.Path) -> list[dict]:
    fields = ("start_step", "commit", "dirty", "changed")
    return [{key: entry.get(key) for key in fields} for entry in read_starts(run_dir)]


def evaluation_lines(run) -> list[dict]:
    """One dict per evaluation of a run_record.RunRecord: step, eval/* and visitation/* at that step, and
    LATEST_KEYS as last logged at or before it (they are logged with the training metrics)."""
    lines = []
    for step in run.evaluations():
        line = {"step": step}
        logged = sorted(run.steps[step].items())
        line.update({key: value for key, value in logged if key.startswith(KEPT_PREFIXES)})
        for key in LATEST_KEYS:
            value = run.latest(key, step)
            if not math.isnan(value):  # model-free agents log none of them
                line[key] = value
        lines.append(line)
    return lines


def header(run, config: dict) -> dict:
    return {"format": FORMAT, "task": run.task, "agent": run.base_agent, "label": run.agent,
            "seed": run.seed, "preset": config["run"].get("preset"),
            "precision": stored_value(config, "agent.precision"),
            "update_cadence": stored_value(config, "run.update_cadence"),
            "config_digest": config_digest(config), "starts": _provenance(run.source), "config": config}


def _write_atomically(path: pathlib.Path, data: bytes) -> None:
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_bytes(data)
    os.replace(temporary, path)


def _arrays(run) -> dict[str, np.ndarray]:
    arrays = {}
    for prefix in VIEW_PREFIXES:
        steps = run.saved_views(prefix)
        if steps:
            arrays[f"{prefix}_step"] = np.int64(max(steps))
            arrays[prefix] = run.histogram(prefix, max(steps))
    back = run.back_starts()
    if back is not None:
        arrays["back_starts_xy"], arrays["back_starts_step"] = back[0], np.int64(back[1])
    return arrays


def _text(line: dict) -> str:
    return json.dumps(line, sort_keys=True)  # as written: NaN equals NaN, floats round-trip exactly


def _keeps(new: dict, old: dict) -> bool:
    """Whether evaluation line `new` holds every value of `old` (it may add some: a record written between
    a step's eval and visitation lines lacks the latter)."""
    return all(key in new and _text(new[key]) == _text(value) for key, value in old.items())


def _first_differing_step(old: list[dict], new: list[dict]) -> int | None:
    """The first step both lists hold an evaluation of where `new` does not keep `old`; None if none."""
    by_step = {line["step"]: line for line in old}
    differing = [line["step"] for line in new
                 if line["step"] in by_step and not _keeps(line, by_step[line["step"]])]
    return differing[0] if differing else None


def _shared_evaluations_agree(old: list[dict], new: list[dict]) -> str:
    """Whether the evaluations at the steps both lists hold are equal, in words."""
    differing = _first_differing_step(old, new)
    if differing is not None:
        return f"shared evaluations differ from step {differing} on"
    shared = len({line["step"] for line in old} & {line["step"] for line in new})
    return f"shared evaluations identical: {shared} of {shared}"


def check_keeps_committed(path: pathlib.Path, lines: list[dict]) -> None:
    """ValueError (one line) where writing `lines` (the evaluation lines of a run dir) would lose what the
    record at `path` holds: it reaches a later step (a run restarted from scratch on a new machine, say), or
    an evaluation both hold differs (a restart on other hardware or code that has since passed the record).
    A deterministic rerun that has passed the record replaces it: every evaluation it held is kept."""
    if not path.exists() or not lines:
        return
    old = [json.loads(line) for line in path.read_text().splitlines()[1:]]
    if not old:
        return
    if old[-1]["step"] > lines[-1]["step"]:
        raise ValueError(f"{path} holds evaluations to step {old[-1]['step']}, the run dir only to "
                         f"{lines[-1]['step']} ({_shared_evaluations_agree(old, lines)}): not replaced; "
                         "replace=1 replaces it")
    differing = _first_differing_step(old, lines)
    if differing is not None:
        raise ValueError(f"{path} and the run dir differ from step {differing} on (the run dir reaches "
                         f"{lines[-1]['step']}, the record {old[-1]['step']}): not replaced; "
                         "replace=1 replaces it")


def write_record(run_dir, data_root, replace: bool = False) -> list[pathlib.Path]:
    """Writes the record of the run in `run_dir` below `data_root`; ValueError (one line) if the run dir has
    no evaluation yet or is not a run dir, or, unless `replace`, if the record there already reaches a later
    step than the run dir or differs from it (check_keeps_committed)."""
    run_dir = pathlib.Path(run_dir)
    run = read_run(run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    where = pathlib.Path(data_root) / run.task / group_dir_name(run.agent)
    evaluations = evaluation_lines(run)
    paths = [where / f"seed{run.seed}.jsonl", where / f"seed{run.seed}.npz"]
    if not replace:
        check_keeps_committed(paths[0], evaluations)
    where.mkdir(parents=True, exist_ok=True)
    lines = [header(run, config), *evaluations]
    text = "".join(_text(line) + "\n" for line in lines)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **_arrays(run))
    _write_atomically(paths[0], text.encode())
    _write_atomically(paths[1], buffer.getvalue())
    return paths


class RecordArtifacts:
    """A run's heatmaps and back-chunk starts (as run_record.RunDirArtifacts gives them) from its record's
    .npz: the heatmaps of the last saved step only."""

    def __init__(self, path: pathlib.Path):
        self.arrays = {}
        if path.exists():
            with np.load(path) as data:
                self.arrays = {key: data[key] for key in data.files}

    def saved_views(self, prefix: str) -> set[int]:
        return {int(self.arrays[f"{prefix}_step"])} if prefix in self.arrays else set()

    def histogram(self, prefix: str, step: int) -> np.ndarray:
        if step not in self.saved_views(prefix):
            raise KeyError(f"the record keeps the {prefix} histogram of steps {self.saved_views(prefix)}, "
                           f"not of step {step}")
        return self.arrays[prefix]

    def back_starts(self) -> tuple[np.ndarray, int] | None:
        if "back_starts_xy" not in self.arrays:
            return None
        return self.arrays["back_starts_xy"], int(self.arrays["back_starts_step"])


def is_record(path: pathlib.Path) -> bool:
    """Whether `path` is a record's .jsonl (its first line names the format)."""
    try:
        with open(path) as file:
            first = json.loads(file.readline())
    except (OSError, ValueError):
        return False
    return isinstance(first, dict) and first.get("format") == FORMAT


def read_record(path) -> RunRecord:
    """The run_record.RunRecord of the record at `path` (.jsonl; its .npz beside it); ValueError (one line)
    when it cannot be used."""
    path = pathlib.Path(path)
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not lines or lines[0].get("format") != FORMAT:
        raise ValueError(f"not a run record (its first line does not say format {FORMAT!r})")
    head, evaluations = lines[0], lines[1:]
    if not evaluations:
        raise ValueError("no evaluation yet")
    steps = {int(line["step"]): line for line in evaluations}
    return RunRecord(path, head["task"], head["label"], int(head["seed"]), steps,
                     short_commits(head["starts"]), head["agent"], RecordArtifacts(path.with_suffix(".npz")),
                     replay_capacity(head.get("config", {})))
