"""Run logging: resolved config.json, metrics.jsonl, TensorBoard scalars, progress display, timers.

    logger = RunLogger(run_dir, config_dict, total_steps, resume_step=restored_step_or_None)
    with logger.timer("collect"):
        ...                                        # block_until_ready inside, or the time is dispatch only
    logger.log(step, {"wm/loss": 1.2, "eval/success": 0.4})
    logger.log_visitation(step, views)               # evaluate.visitation of the replay
    logger.close()

provenance.jsonl gets one line per start or resume (step, code commit, host, time; provenance.py).
metrics.jsonl holds one JSON object per `log` call: "step", the caller's flat metrics and the wall-clock
fields, all named "time/..." (compare runs on the other keys). Resume contract: the loop logs a step's
metrics BEFORE it saves that step's checkpoint; on resume from the checkpoint at step S, lines with
step > S are dropped (they are logged again by the resumed run), so the resumed file has the same
non-time lines as an uninterrupted run's. TensorBoard's event files are cut back to S the same way
(tb_events.py); `flush` (called before every checkpoint) makes sure all that S covers is on disk.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pathlib
import socket
import sys
import time
from typing import Any

import numpy as np

from morefree_jax.provenance import code_version
from morefree_jax.tb_events import ScalarWriter, truncate_events

PROGRESS_MODES = ("auto", "bar", "lines", "off")
PROVENANCE_FILE = "provenance.jsonl"  # one line per start or resume: step, code commit, host, time
DROPPED_SHARE = "train/dropped_share"  # updates dropped as non-finite / updates tried, since the run began
DROPPED_WARNING = 0.01  # a share above this is said once in the log: the learner is unstable


def _scalar(name: str, value: Any) -> float | int | bool:
    array = np.asarray(value)
    if array.size != 1:
        raise TypeError(f"metric {name!r} must be a scalar, got shape {array.shape}")
    item = array.reshape(()).item()
    if not isinstance(item, (bool, int, float)):
        raise TypeError(f"metric {name!r} must be numeric, got {type(item).__name__}")
    return item


def _write_text_atomically(path: pathlib.Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
    except OSError:
        tmp.unlink(missing_ok=True)  # a failed write (full disk) leaves no temporary file
        raise
    os.replace(tmp, path)


def read_metrics(path) -> list[dict]:
    """The records of a metrics.jsonl file (skipping a torn last line left by a killed process)."""
    records = []
    for line in pathlib.Path(path).read_text().splitlines():
        with contextlib.suppress(json.JSONDecodeError):
            records.append(json.loads(line))
    return records


class RunLogger:
    """Writes <run_dir>/config.json, metrics.jsonl, tb/ (TensorBoard) and plots/, and shows progress.

    resume_step: the step of the checkpoint the run resumed from (None for a fresh run: metrics.jsonl starts
    empty). progress: "auto" = a tqdm bar when stderr is a TTY, else a plain line every `line_every_s`
    seconds on stdout; "bar", "lines" or "off" force one.
    """

    def __init__(self, run_dir, config_dict: dict, total_steps: int, resume_step: int | None = None,
                 progress: str = "auto", line_every_s: float = 30.0, tensorboard: bool = True,
                 changes: dict | None = None):
        if progress not in PROGRESS_MODES:
            raise ValueError(f"progress must be one of {PROGRESS_MODES}, got {progress!r}")
        self.run_dir = pathlib.Path(run_dir)
        self.plots_dir = self.run_dir / "plots"
        self.plots_dir.mkdir(parents=True, exist_ok=True)
        config_text = json.dumps(config_dict, indent=2, sort_keys=True)
        _write_text_atomically(self.run_dir / "config.json", config_text)
        self.total_steps = total_steps
        self.metrics_path = self.run_dir / "metrics.jsonl"
        self._elapsed_offset = self._truncate_metrics(resume_step)
        self._record_start(resume_step, changes or {})
        self._metrics_file = open(self.metrics_path, "a")  # noqa: SIM115 - kept open for the run
        self._start = time.perf_counter()
        self._last_step = resume_step or 0
        self._last_time = self._start
        self._last_line_time = -math.inf
        self._line_every_s = line_every_s
        self.last_success: float | None = None
        self.last_dropped: float | None = None  # the share of updates dropped as non-finite (driver.py)
        self._warned_dropped = False
        self._timers: dict[str, list[float]] = {}
        self._writer = None
        if tensorboard:
            # What was logged after the checkpoint is logged again (a fresh start: everything).
            truncate_events(self.run_dir / "tb", -1 if resume_step is None else resume_step)
            self._writer = ScalarWriter(self.run_dir / "tb")
        if progress == "auto":
            progress = "bar" if sys.stderr.isatty() else "lines"
        self._progress_mode = progress
        self._bar = None
        if progress == "bar":
            from tqdm import tqdm

            self._bar = tqdm(total=total_steps, initial=resume_step or 0, unit="step", dynamic_ncols=True)

    def _record_start(self, resume_step: int | None, changes: dict) -> None:
        """Appends this start (step, code commit, host, time, settings changed since the last start:
        {key: [old, new]}) to provenance.jsonl (never truncated)."""
        line = {"start_step": int(resume_step or 0), "resumed": resume_step is not None, **code_version(),
                "host": socket.gethostname(), "time": time.time(), "changed": changes}
        with open(self.run_dir / PROVENANCE_FILE, "a") as file:
            file.write(json.dumps(line) + "\n")

    def _truncate_metrics(self, resume_step: int | None) -> float:
        """Keeps the lines with step <= resume_step (none for a fresh run); returns the last elapsed time."""
        if not self.metrics_path.exists():
            return 0.0
        records = [] if resume_step is None else read_metrics(self.metrics_path)
        kept = [r for r in records if r["step"] <= resume_step]
        _write_text_atomically(self.metrics_path, "".join(json.dumps(r) + "\n" for r in kept))
        return float(kept[-1].get("time/elapsed_s", 0.0)) if kept else 0.0

    # ---- metrics -------------------------------------------------------------------------------
    def log(self, step: int, metrics: dict) -> dict:
        """Appends one record (step, metrics, time/*) to metrics.jsonl and TensorBoard; returns the record."""
        now = time.perf_counter()
        record = {"step": int(step)}
        record.update({name: _scalar(name, value) for name, value in metrics.items()})
        if now > self._last_time and step > self._last_step:
            record["time/steps_per_s"] = (step - self._last_step) / (now - self._last_time)
            self._last_step, self._last_time = int(step), now
        record["time/elapsed_s"] = self._elapsed_offset + now - self._start
        record["time/wall"] = time.time()
        self._metrics_file.write(json.dumps(record) + "\n")
        self._metrics_file.flush()
        if self._writer is not None:
            for name, value in record.items():
                if name not in ("step", "time/wall"):
                    self._writer.add_scalar(name, float(value), int(step))
        if "eval/success" in record:
            self.last_success = float(record["eval/success"])
        if DROPPED_SHARE in record:
            self._note_dropped(float(record[DROPPED_SHARE]))
        self._show_progress(int(step), record.get("time/steps_per_s"))
        return record

    def _note_dropped(self, share: float) -> None:
        """Keeps the share for the progress line; says once when it passes DROPPED_WARNING."""
        self.last_dropped = share
        if share > DROPPED_WARNING and not self._warned_dropped:
            self._warned_dropped = True
            print(f"warning: {share:.1%} of this run's updates so far were non-finite and dropped (over "
                  f"{DROPPED_WARNING:.0%}; train/dropped_share in {self.metrics_path})", flush=True)

    def _show_progress(self, step: int, steps_per_s: float | None) -> None:
        success = "-" if self.last_success is None else f"{self.last_success:.2f}"
        if self.last_dropped is not None:
            success += f" dropped {self.last_dropped:.1%}"
        if self._bar is not None:
            self._bar.n = step
            self._bar.set_postfix_str(f"success {success}", refresh=True)
        elif self._progress_mode == "lines":
            now = time.perf_counter()
            if now - self._last_line_time >= self._line_every_s or step >= self.total_steps:
                self._last_line_time = now
                rate = "-" if steps_per_s is None else f"{steps_per_s:.0f}"
                percent = 100.0 * step / max(self.total_steps, 1)
                print(f"step {step}/{self.total_steps} ({percent:.1f}%) {rate} steps/s success {success}",
                      flush=True)

    def log_visitation(self, step: int, views: dict) -> dict:
        """Saves the visitation histograms of evaluate.visitation: "xy" as plots/visitation_<step>.npy and,
        for tasks with a side view, "xz" as plots/side_visitation_<step>.npy; logs the task-relevant share,
        the xy histogram's share of occupied cells and normalised entropy, and "in_air" where present."""
        histogram = np.asarray(views["xy"], dtype=np.float64)
        if histogram.ndim != 2:
            raise ValueError(f"the xy visitation histogram must be 2-D, got shape {histogram.shape}")
        np.save(self.plots_dir / f"visitation_{int(step):09d}.npy", histogram)
        record = {"visitation/task_relevant": float(views["task_relevant"]),
                  "visitation/occupied_cells": float(np.mean(histogram > 0)),
                  "visitation/entropy": normalised_entropy(histogram)}
        if "xz" in views:
            side = np.asarray(views["xz"], dtype=np.float64)
            np.save(self.plots_dir / f"side_visitation_{int(step):09d}.npy", side)
            record["visitation/in_air"] = float(views["in_air"])
        return self.log(step, record)

    def log_back_starts(self, step: int, xy, stream_step) -> None:
        """Saves the locations before each stored successful back chunk (back_starts.py) as
        plots/back_starts.npz (xy (n, 100, 2), stream_step (n,), step), replaced atomically at each call."""
        path = self.plots_dir / "back_starts.npz"
        temporary = path.with_name(path.name + ".tmp.npz")
        try:
            np.savez(temporary, xy=np.asarray(xy, np.float32), stream_step=np.asarray(stream_step, np.int64),
                     step=np.int64(step))
        except OSError:
            temporary.unlink(missing_ok=True)
            raise
        os.replace(temporary, path)

    # ---- timers --------------------------------------------------------------------------------
    @contextlib.contextmanager
    def timer(self, name: str):
        """Times the block; the first duration of each name is kept apart (it includes compilation)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self._timers.setdefault(name, []).append(time.perf_counter() - start)

    def timing_metrics(self) -> dict:
        """time/<name>_first_s (compile + run) and time/<name>_s (mean of the later calls)."""
        metrics = {}
        for name, durations in self._timers.items():
            metrics[f"time/{name}_first_s"] = durations[0]
            if len(durations) > 1:
                metrics[f"time/{name}_s"] = float(np.mean(durations[1:]))
        return metrics

    def flush(self) -> None:
        """Puts everything logged so far on disk (before a checkpoint: what it covers is in every log)."""
        self._metrics_file.flush()
        os.fsync(self._metrics_file.fileno())
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        self._metrics_file.flush()
        self._metrics_file.close()
        if self._writer is not None:
            self._writer.flush()
            self._writer.close()
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def normalised_entropy(histogram: np.ndarray) -> float:
    """Entropy of the histogram's distribution over its cells, divided by the most it can be (log cells)."""
    total = histogram.sum()
    if histogram.size <= 1 or total <= 0:
        return 0.0
    probabilities = histogram.ravel() / total
    nonzero = probabilities[probabilities > 0]
    return float((nonzero * np.log(1.0 / nonzero)).sum() / np.log(histogram.size))  # 0.0, never -0.0
