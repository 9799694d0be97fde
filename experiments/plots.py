"""The paper's figures and a results table from run directories (`make plots RUNS=runs OUT=results`).

    python -m experiments.plots runs=runs [out=results] [task=point_umaze] [agents=oracle_sac,r3l]
                                [marks=25000,50000,100000] [window=75000:100000] [visitation_step=100000]

Reads every run dir (config.json + metrics.jsonl) and run record (results/data, experiments/records.py)
below the given directory (with agents= only those agents'), groups them by task and agent, and writes to
out=, per task (PNG and SVG):
  <task>_success           eval success (any step of the episode) against env steps, mean over seeds with a
                           standard-error band, seed count in the legend (the paper's protocol)
  <task>_final_success     the same for success at the episode's last step
  <task>_task_relevant     share of the replay near an initial state or an evaluation goal
  <task>_visitation        the replay's xy visitation per agent at the latest step all its seeds have
                           saved (visitation_step=N: at or below N, to compare agents at one step): each
                           cell's share of the visits summed over seeds, one log colour scale and its colour
                           bar; step and task-relevant share in the title; the task-relevant region
                           outlined, start (o) and goal (*) samples; the maze walls for PointUMaze
  <task>_side_visitation   tasks with a side view (pick_place, pick_place_hard): the same for the block's
                           x and height, the share of the replay with the block in the air in the title and
                           the air height as a red line (the paper's XZ heatmap of Pick&Place (hard))
  <task>_back_starts       where successful "back" chunks started: the 100 locations before each, shaded by
                           how long the agent / object rested there (agents with Back-and-Forth Go-Explore)
and <task>_results.csv / .md: success at step marks (default: 4 evenly spaced evaluated steps; each agent at
its latest evaluation at or before a mark) per task and agent, mean +- standard error over seeds, seed count,
and the commits of the code that wrote the runs.
and <task>_window.csv / .md, the results table of the paper's protocol: each seed's mean success over its
evaluations in a window of steps, mean +- standard error over seeds, and the task-relevant share at its end
(agents whose every seed has evaluated at its end); window=START:STOP, by default each task's last quarter
of the steps every agent reached; under it the task's chance level where runs= holds <task>/zero_action.json
(`make records` writes it, experiments/analysis/zero_action.py).
Across tasks, where morefree and at least one ablation variant (rf_peg, mf_task_only, mf_no_bfge,
mf_no_imag) ran: ablation.png / .svg / .csv / .md, the paper's ablation figure (final success normalised by
MoReFree's, mean over tasks; experiments/analysis/ablation_summary.py says how). The drawing code is
experiments/analysis/figures.py.
Every file is stamped with those commits and the commit that drew it. A run dir that cannot be used is
skipped with one line saying why; finding no run is a one-line error (exit 2).
"""

from __future__ import annotations

import pathlib
import sys

from experiments.analysis import run_groups, zero_action
from experiments.analysis.figures import write_ablation, write_table, write_task, write_window
from experiments.analysis.run_groups import NoRunsError
from experiments.cli import REQUIRED, KeyValueError, parse_keys
from morefree_jax.provenance import code_version


def _parse(argv):
    args = parse_keys(argv, {"runs": REQUIRED, "out": "results", "task": None, "agents": "", "marks": "",
                             "window": "", "visitation_step": 0})
    args["agents"] = [a.strip() for a in args["agents"].split(",") if a.strip()] or None
    try:
        args["marks"] = [int(m) for m in args["marks"].split(",") if m.strip()]
    except ValueError:
        raise KeyValueError(f"marks must be comma-separated integers, got {args['marks']!r}") from None
    if args["window"]:
        try:
            start, stop = (int(part) for part in args["window"].split(":"))
        except ValueError:
            raise KeyValueError(f"window must be START:STOP env steps, e.g. 75000:100000, "
                                f"got {args['window']!r}") from None
        if not 0 <= start <= stop:
            raise KeyValueError(f"window needs 0 <= START <= STOP, got {args['window']!r}")
        args["window"] = (start, stop)
    args["visitation_step"] = args["visitation_step"] or None  # 0: each agent's latest
    return args


def main(argv: list[str]) -> int:
    try:
        args = _parse(argv)
        runs, skipped = run_groups.find_runs(args["runs"], args["task"], args["agents"])
    except (KeyValueError, NoRunsError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    groups = run_groups.group_runs(runs, skipped)
    for line in skipped:
        print(line)
    tasks = sorted({task for task, _ in groups})
    drawn = code_version()["commit"]
    stamp_for = lambda commits: f"runs: {' '.join(commits)} · drawn: {(drawn or 'unknown')[:7]}"  # noqa: E731
    out = pathlib.Path(args["out"])
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for task in tasks:
        written += write_task(task, groups, out, stamp_for, args["visitation_step"])
        written += write_table(task, groups, out, args["marks"], stamp_for)
        window = args["window"] or run_groups.last_quarter(groups, task)
        if window:
            chance = zero_action.read_reference(args["runs"], task)
            written += write_window(task, groups, out, window, stamp_for, chance)
    written += write_ablation(groups, out, stamp_for)
    for (task, agent), group in sorted(groups.items()):
        print(f"{task} {agent}: seeds {','.join(str(r.seed) for r in group)}")
    print(f"wrote {len(written)} files to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
