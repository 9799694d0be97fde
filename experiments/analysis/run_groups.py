"""Runs grouped by task and agent, with the statistics of the paper's protocol (mean and standard error over
seeds) and the results tables. No JAX, no matplotlib: experiments/plots.py draws from these.

    runs, skipped = find_runs("runs")                  # every run dir and run record below
    groups = group_runs(runs)                          # {(task, agent): [RunRecord, ...]} sorted by seed
    steps, mean, stderr = curve(groups[key], "eval/success")
    rows = results_rows(groups, marks={"point_umaze": [25000, 50000, 100000]})
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from experiments.analysis import records
from experiments.analysis.run_record import RunRecord, read_run
from morefree_jax.logger import DROPPED_SHARE


class NoRunsError(Exception):
    """No usable run directory was found (the message says where and why)."""


def _candidates(root: pathlib.Path):
    """(path, reader) for every run dir (config.json) and run record (seed<k>.jsonl, records.py) below."""
    for config in sorted(root.rglob("config.json")):
        yield config.parent, read_run
    for path in sorted(root.rglob("seed*.jsonl")):
        if records.is_record(path):
            yield path, records.read_record


def find_runs(root, task: str | None = None, agents=None) -> tuple[list[RunRecord], list[str]]:
    """(runs below `root`: run dirs and run records, one line per skipped one saying why); `agents`: only
    these agents' runs. NoRunsError when none is usable."""
    root = pathlib.Path(root)
    if not root.is_dir():
        raise NoRunsError(f"{root} is not a directory")
    runs, skipped = [], []
    for path, read in _candidates(root):
        try:
            record = read(path)
        except ValueError as error:
            skipped.append(f"skipped {path}: {error}")
            continue
        if task is not None and record.task != task:
            skipped.append(f"skipped {path}: holds task {record.task}, not {task}")
            continue
        runs.append(record)
    chosen = [run for run in runs if agents is None or run.base_agent in agents]
    if not chosen:
        where = f"{root}" + (f" for task {task}" if task else "")
        if runs:  # there are runs, of other agents
            found = ", ".join(sorted({run.agent for run in runs}))
            raise NoRunsError(f"no run of {', '.join(agents)} found below {where} (agents there: {found})")
        raise NoRunsError(f"no run with evaluations found below {where} (a run dir holds config.json and "
                          f"metrics.jsonl, a run record is a seed<k>.jsonl; {len(skipped)} skipped)")
    return chosen, skipped


Groups = dict[tuple[str, str], list["RunRecord"]]


def group_runs(runs: list[RunRecord], skipped: list[str] | None = None) -> Groups:
    """{(task, agent): runs sorted by seed}. A seed present twice (a copy, an archived run) keeps the first
    by path; a line saying which one is kept is appended to `skipped` when given."""
    groups: Groups = {}
    for run in sorted(runs, key=lambda r: (r.task, r.agent, r.seed, str(r.source))):
        group = groups.setdefault((run.task, run.agent), [])
        kept = next((other for other in group if other.seed == run.seed), None)
        if kept is None:
            group.append(run)
        elif skipped is not None:
            skipped.append(f"skipped {run.source}: seed {run.seed} of {run.agent} on {run.task} is taken "
                           f"from {kept.source} (give RUNS a narrower directory to choose)")
    return groups


def mean_stderr(values) -> tuple[float, float]:
    """Mean and standard error (sample std / sqrt(n); NaN for one value) of a sequence."""
    values = np.asarray(values, np.float64)
    if values.size < 2:
        return float(values.mean()), math.nan
    return float(values.mean()), float(values.std(ddof=1) / math.sqrt(values.size))


def curve(group: list[RunRecord], key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(steps, mean, standard error) of `key` over the seeds, at the steps every seed has logged it."""
    series = [run.evaluations(key) for run in group]
    steps = sorted(set.intersection(*(set(s) for s in series)))
    stats = [mean_stderr([s[step] for s in series]) for step in steps]
    return (np.asarray(steps), np.asarray([m for m, _ in stats]), np.asarray([e for _, e in stats]))


def default_marks(groups, task: str, count: int = 4) -> list[int]:
    """`count` evenly spaced step marks up to the furthest step every agent of `task` has evaluated (all
    seeds), each moved down to the nearest step some agent evaluated. Agents may evaluate at different steps
    (ibc, from its own seed phase): results_rows takes each one's latest evaluation at or before a mark."""
    evaluated = [curve(g, "eval/success")[0].tolist() for (t, _), g in groups.items() if t == task]
    if not evaluated or not all(evaluated):
        return []
    end, steps = min(s[-1] for s in evaluated), sorted(set().union(*evaluated))
    targets = [end * (i + 1) / count for i in range(count)]
    return sorted({max(s for s in steps if s <= target) for target in targets if steps[0] <= target})


def step_at_mark(group: list[RunRecord], mark: int) -> int | None:
    """The group's latest evaluation (every seed's) at or before `mark`; None if it did not reach the mark."""
    steps = curve(group, "eval/success")[0].tolist()
    if not steps or steps[-1] < mark or steps[0] > mark:
        return None
    return max(s for s in steps if s <= mark)


# The two success measures, named alike in every table and figure (docs/experiments.md, "Evaluation
# protocol").
SUCCESS_ANY, SUCCESS_LAST = "success (any step)", "success (last step)"
RESULT_COLUMNS = ("task", "agent", "seeds", "step", "success_mean", "success_stderr", "final_success_mean",
                  "final_success_stderr", "task_relevant_mean", "back_reached_mean", "dropped_share_mean",
                  "commits")


def results_rows(groups, marks: dict[str, list[int]]) -> list[dict]:
    """One row per (task, agent, step mark) the group reached, at its latest evaluation at or before the
    mark (`step`): success (any step) and at the last step of the evaluation episodes, task-relevant share
    of the replay, the share of the back chunks so far that reached their initial state; mean and standard
    error over seeds."""
    rows = []
    for (task, agent), group in sorted(groups.items()):
        for mark in marks.get(task, []):
            step = step_at_mark(group, mark)
            if step is None:
                continue
            at = [run.steps[step] for run in group]
            success = mean_stderr([r["eval/success"] for r in at])
            final = mean_stderr([r.get("eval/final_success", math.nan) for r in at])
            relevant = mean_stderr([r.get("visitation/task_relevant", math.nan) for r in at])
            back = mean_stderr([run.back_reach_rate(step) for run in group])
            dropped = mean_stderr([run.latest(DROPPED_SHARE, step) for run in group])
            commits = sorted({c for run in group for c in run.commits})
            values = (task, agent, len(group), step, *success, *final, relevant[0], back[0], dropped[0],
                      " ".join(commits))
            rows.append(dict(zip(RESULT_COLUMNS, values, strict=True)))
    return rows


WINDOW_COLUMNS = ("task", "agent", "seeds", "start", "stop", "evaluations", "success_mean", "success_stderr",
                  "final_success_mean", "final_success_stderr", "task_relevant_mean", "task_relevant_stderr",
                  "window_relevant_mean", "window_relevant_stderr", "commits")


def last_quarter(groups, task: str) -> tuple[int, int] | None:
    """The default window of `task`'s table: the last quarter of the steps every agent has evaluated (all
    seeds), (0.75 S, S); None before any evaluation."""
    ends = [curve(g, "eval/success")[0] for (t, _), g in groups.items() if t == task]
    if not ends or not all(len(steps) for steps in ends):
        return None
    stop = int(min(steps[-1] for steps in ends))
    return stop - stop // 4, stop


def window_rows(groups, start: int, stop: int) -> list[dict]:
    """One row per (task, agent) whose every seed has evaluated at `stop`: each seed's mean success over its
    evaluations in [start, stop], then mean and standard error of those over seeds; the task-relevant share
    of the replay at `stop`, and of the env steps between the window's first evaluation and `stop` alone
    (share_between), where the share of the whole replay hides a change. Success at a single evaluation
    swings between 0 and 1 in reset-free runs; a window says what the agent holds."""
    rows = []
    for (task, agent), group in sorted(groups.items()):
        series = [run.evaluations("eval/success") for run in group]
        if any(stop not in s for s in series):
            continue
        steps = sorted(set.intersection(*(set(s) for s in series)) & set(range(start, stop + 1)))
        finals = [run.evaluations("eval/final_success") for run in group]
        success = mean_stderr([np.mean([s[step] for step in steps]) for s in series])
        final = mean_stderr([np.mean([f.get(step, math.nan) for step in steps]) for f in finals])
        relevant = mean_stderr([run.steps[stop].get("visitation/task_relevant", math.nan) for run in group])
        in_window = mean_stderr([share_between(run, steps[0], stop) for run in group])
        commits = sorted({c for run in group for c in run.commits})
        values = (task, agent, len(group), start, stop, len(steps), *success, *final, *relevant, *in_window,
                  " ".join(commits))
        rows.append(dict(zip(WINDOW_COLUMNS, values, strict=True)))
    return rows


def share_between(run: RunRecord, first: int, last: int) -> float:
    """The task-relevant share of the env steps in (first, last] alone. The logged share is over every row
    the replay holds, one per env step since the start while the run is within the replay's capacity, so
    it is the difference of the in-region rows at the two steps over the steps between. NaN where that does
    not hold (first == last, a share missing, the capacity unknown or passed)."""
    shares = [run.steps[step].get("visitation/task_relevant", math.nan) for step in (first, last)]
    if first >= last or run.replay_capacity is None or last > run.replay_capacity:
        return math.nan
    share = (shares[1] * last - shares[0] * first) / (last - first)
    return float(np.clip(share, 0.0, 1.0))  # float32 shares: a window with no row in may read -1e-9


def percent(share: float) -> str:
    """A share as a percentage; "-" where none was logged (model-free agents drop no update)."""
    return "-" if math.isnan(share) else f"{100 * share:.1f}%"


def with_error(mean: float, stderr: float) -> str:
    return f"{mean:.2f}" if math.isnan(stderr) else f"{mean:.2f} ± {stderr:.2f}"


def percent_with_error(mean: float, stderr: float) -> str:
    if math.isnan(mean):
        return "-"
    return f"{100 * mean:.1f}%" if math.isnan(stderr) else f"{100 * mean:.1f}% ± {100 * stderr:.1f}"


def markdown_table(rows: list[dict]) -> str:
    lines = [f"| task | agent | seeds | env steps | {SUCCESS_ANY} | {SUCCESS_LAST} | task-relevant | "
             "back chunks reaching the start | dropped updates | commits |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['task']} | {row['agent']} | {row['seeds']} | {row['step']:,} | "
                     f"{with_error(row['success_mean'], row['success_stderr'])} | "
                     f"{with_error(row['final_success_mean'], row['final_success_stderr'])} | "
                     f"{row['task_relevant_mean']:.3f} | {percent(row['back_reached_mean'])} | "
                     f"{percent(row['dropped_share_mean'])} | "
                     f"{row['commits']} |")
    return "\n".join(lines) + "\n"


def window_markdown(rows: list[dict]) -> str:
    lines = [f"| task | agent | seeds | env steps | evaluations | mean {SUCCESS_ANY} | mean {SUCCESS_LAST} "
             "| task-relevant at the end | task-relevant in the window | commits |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        relevant = percent_with_error(row["task_relevant_mean"], row["task_relevant_stderr"])
        in_window = percent_with_error(row["window_relevant_mean"], row["window_relevant_stderr"])
        lines.append(f"| {row['task']} | {row['agent']} | {row['seeds']} | "
                     f"{row['start']:,}-{row['stop']:,} | {row['evaluations']} | "
                     f"{with_error(row['success_mean'], row['success_stderr'])} | "
                     f"{with_error(row['final_success_mean'], row['final_success_stderr'])} | "
                     f"{relevant} | {in_window} | {row['commits']} |")
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict], columns: tuple[str, ...] = RESULT_COLUMNS) -> str:
    def cell(value):
        return f"{value:.4f}" if isinstance(value, float) else str(value)

    return "\n".join([",".join(columns)] + [",".join(cell(row[c]) for c in columns) for row in rows]) + "\n"
