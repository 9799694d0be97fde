"""The paper's ablation figure: each variant's final performance normalised by MoReFree's, over tasks.

    rows = task_rows(groups)          # per task and agent: final performance, and / MoReFree's on that task
    summary = summary_rows(rows)      # per agent: mean and standard error of the normalised value over tasks

The paper ("Ablations on 5 variants of MoReFree over 3 hard environments ... with normalized final
performance") does not say how it normalises or what "final" spans. Our choice: a task counts once
morefree and at least one ablation variant ran on it; its final step is the last evaluation every seed of
every one of them reached (so all are compared at one budget); an agent's final performance is the mean
over seeds of each seed's mean success (any step) over its evaluations in the last quarter before that
step, since single evaluations swing between 0 and 1; normalised = that / morefree's on the same task
(NaN where morefree's is 0).
"""

from __future__ import annotations

import math

import numpy as np

from experiments.analysis import run_groups

REFERENCE = "morefree"
ABLATIONS = ("rf_peg", "mf_task_only", "mf_no_bfge", "mf_no_imag")  # the paper's other four variants
TASK_COLUMNS = ("task", "agent", "seeds", "start", "stop", "evaluations", "success_mean", "success_stderr",
                "normalised", "commits")
SUMMARY_COLUMNS = ("agent", "tasks", "normalised_mean", "normalised_stderr")


def _compared(groups, task: str) -> list[str]:
    present = [agent for agent in (REFERENCE, *ABLATIONS) if (task, agent) in groups]
    return present if REFERENCE in present and len(present) > 1 else []


def _final_steps(series: dict[str, list[dict]]) -> list[int]:
    """The evaluations in the last quarter before the last step every seed of every agent reached."""
    common = set.intersection(*(set(s) for seeds in series.values() for s in seeds))
    return sorted(step for step in common if step >= max(common) * 3 // 4) if common else []


def task_rows(groups) -> list[dict]:
    """Per task with morefree and an ablation: each compared agent's final performance and its normalised
    one."""
    rows = []
    for task in sorted({task for task, _ in groups}):
        agents = _compared(groups, task)
        series = {agent: [run.evaluations("eval/success") for run in groups[(task, agent)]]
                  for agent in agents}
        steps = _final_steps(series) if agents else []
        if not steps:
            continue
        finals = {agent: run_groups.mean_stderr([np.mean([s[step] for step in steps]) for s in seeds])
                  for agent, seeds in series.items()}
        reference = finals[REFERENCE][0]
        for agent in agents:
            commits = " ".join(sorted({c for run in groups[(task, agent)] for c in run.commits}))
            normalised = finals[agent][0] / reference if reference > 0 else math.nan
            values = (task, agent, len(series[agent]), steps[0], steps[-1], len(steps), *finals[agent],
                      normalised, commits)
            rows.append(dict(zip(TASK_COLUMNS, values, strict=True)))
    return rows


def summary_rows(rows: list[dict]) -> list[dict]:
    """Per agent: mean and standard error over tasks of the normalised final performance (finite ones)."""
    summary = []
    for agent in (REFERENCE, *ABLATIONS):
        values = [row["normalised"] for row in rows
                  if row["agent"] == agent and math.isfinite(row["normalised"])]
        if values:
            summary.append(dict(zip(SUMMARY_COLUMNS, (agent, len(values), *run_groups.mean_stderr(values)),
                                    strict=True)))
    return summary


def markdown(rows: list[dict], summary: list[dict]) -> str:
    lines = ["| agent | tasks | normalised final performance (mean ± s.e. over tasks) |", "|---|---|---|"]
    lines += [f"| {s['agent']} | {s['tasks']} | "
              f"{run_groups.with_error(s['normalised_mean'], s['normalised_stderr'])} |" for s in summary]
    lines += ["", "| task | agent | seeds | env steps | evaluations | "
              f"mean {run_groups.SUCCESS_ANY} | normalised | commits |",
              "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['task']} | {r['agent']} | {r['seeds']} | {r['start']:,}-{r['stop']:,} | "
              f"{r['evaluations']} | {run_groups.with_error(r['success_mean'], r['success_stderr'])} | "
              f"{r['normalised']:.2f} | {r['commits']} |" for r in rows]
    return "\n".join(lines) + "\n"


def figure(rows: list[dict], summary: list[dict], new_figure):
    """Bars: mean normalised final performance per agent over tasks (standard error); dots: each task."""
    fig = new_figure(1.2 * len(summary) + 2.0, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    positions = np.arange(len(summary))
    errors = [0.0 if math.isnan(s["normalised_stderr"]) else s["normalised_stderr"] for s in summary]
    ax.bar(positions, [s["normalised_mean"] for s in summary], yerr=errors, color="0.75", ecolor="0.45",
           capsize=3)
    for position, entry in zip(positions, summary, strict=True):
        values = [r["normalised"] for r in rows if r["agent"] == entry["agent"]]
        ax.scatter(np.full(len(values), position), values, s=10, color="black", zorder=3)
    tasks = sorted({r["task"] for r in rows})
    ax.set(xticks=positions, ylabel=f"{run_groups.SUCCESS_ANY} / morefree's",
           title=f"ablations, normalised final performance ({', '.join(tasks)})")
    # Bars may rest on different tasks (a variant counts where it ran): each label says on how many.
    ax.set_xticklabels([f"{s['agent']} ({s['tasks']})" for s in summary], rotation=20, fontsize=8)
    ax.title.set_fontsize(9)
    return fig
