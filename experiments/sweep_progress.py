"""The sweep's progress table, read from the jobs' run dirs: state, steps reached, env steps/s, last
evaluation.

    progress = Progress(grid.jobs)
    progress.submitted(job, attempt=1); progress.ended(job, "done")
    print(progress.table())
"""

from __future__ import annotations

import contextlib
import time

from morefree_jax.logger import read_metrics


def reached(job) -> tuple[int | None, tuple[int, float] | None]:
    """(the step every seed has logged, (step, mean success over seeds) of the latest evaluation every
    seed has made); None where no seed has yet."""
    steps, evaluations = [], []
    for seed in job.seeds:
        path = job.run_dir(seed) / "metrics.jsonl"
        records = read_metrics(path) if path.exists() else []
        if not records:
            return None, None
        steps.append(max(record["step"] for record in records))
        evaluations.append({r["step"]: r["eval/success"] for r in records if "eval/success" in r})
    common = set.intersection(*(set(e) for e in evaluations))
    if not common:
        return min(steps), None
    last = max(common)
    return min(steps), (last, sum(e[last] for e in evaluations) / len(evaluations))


class Progress:
    def __init__(self, jobs):
        self.jobs = list(jobs)
        self.states = {job.name: "finished before" for job in self.jobs}
        self.previous: dict[str, tuple[float, int]] = {}  # job -> (time, step) at the last table
        self.submitted_at: dict[str, float] = {}

    def submitted(self, job, attempt: int) -> None:
        self.states[job.name] = "queued" if attempt == 1 else f"queued (attempt {attempt})"
        self.submitted_at[job.name] = time.time()

    def _state(self, job) -> str:
        """The state, with "queued" read as "running" once the job has written to its log (sweep_job.py
        does as it starts)."""
        state = self.states[job.name]
        if state.startswith("queued"):
            with contextlib.suppress(OSError):
                if job.log.stat().st_mtime >= self.submitted_at[job.name]:
                    return state.replace("queued", "running")
        return state

    def ended(self, job, state: str) -> None:
        self.states[job.name] = state

    def _speed(self, job, step: int | None) -> str:
        now, before = time.monotonic(), self.previous.get(job.name)
        if step is not None:
            self.previous[job.name] = (now, step)
        if step is None or before is None or now <= before[0] or step <= before[1]:
            return "-"
        return f"{(step - before[1]) / (now - before[0]):.1f}"

    def table(self) -> str:
        rows = [("job", "state", "steps reached", "env steps/s per seed", "last evaluation")]
        for job in self.jobs:
            step, evaluation = reached(job)
            target = f"{job.steps:,}" if job.steps else "budget"
            shown = "-" if step is None else f"{step:,} / {target}"
            last = "-" if evaluation is None else f"success {evaluation[1]:.2f} at {evaluation[0]:,}"
            rows.append((job.name, self._state(job), shown, self._speed(job, step), last))
        widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
        lines = ("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True))
                 for row in rows)
        return "\n".join(line.rstrip() for line in lines)
