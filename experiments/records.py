"""Run records for the repository: every run dir below `runs=` as results/data/<task>/<group>/seed<k>.jsonl
and .npz (`make records RUNS=$HOME/runs/x`; experiments/analysis/records.py says what they hold).

    python -m experiments.records runs=$HOME/runs/push_hard [out=results/data] [chance_episodes=1000]
                                  [replace=0]

Re-run it after each evaluation and commit results/data: a lost machine then loses nothing committed, and
`make plots` on a fresh clone draws from the records. A run dir with no evaluation yet is skipped with one
line saying why, as is one whose record already reaches a later step (a run restarted from scratch after
its machine was lost: the line says whether the evaluations both hold agree; replace=1 overwrites it);
finding none is a one-line error (exit 2). For each task without one yet it also writes
the task's chance level, <task>/zero_action.json (experiments/analysis/zero_action.py; about a minute per
task; chance_episodes=0 skips it), which the window tables quote.
"""

from __future__ import annotations

import pathlib
import sys

from experiments.analysis import zero_action
from experiments.analysis.records import write_record
from experiments.cli import REQUIRED, KeyValueError, parse_keys

DATA_DIR = "results/data"


def main(argv: list[str]) -> int:
    try:
        args = parse_keys(argv, {"runs": REQUIRED, "out": DATA_DIR, "chance_episodes": zero_action.EPISODES,
                                  "replace": False})
    except KeyValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    root = pathlib.Path(args["runs"]).expanduser()
    if not root.is_dir():
        print(f"error: runs={root} is not a directory", file=sys.stderr)
        return 2
    tasks, written, skipped = set(), 0, 0
    for config in sorted(root.rglob("config.json")):
        try:
            paths = write_record(config.parent, args["out"], replace=args["replace"])
        except ValueError as error:
            print(f"skipped {config.parent}: {error}")
            skipped += 1
            continue
        tasks.add(paths[0].parent.parent.name)
        written += 1
        print(f"{config.parent} -> {paths[0]}")
    if not tasks:
        message = (f"no record written: the {skipped} run dirs below {root} were skipped (above)" if skipped
                   else f"no run dir with evaluations below {root}")
        print(f"error: {message}", file=sys.stderr)
        return 2
    print(f"wrote {written} run records to {args['out']}")
    if args["chance_episodes"] > 0:
        write_missing_references(sorted(tasks), args["out"], args["chance_episodes"])
    return 0


def write_missing_references(tasks: list[str], data_root, episodes: int) -> None:
    """<task>/zero_action.json for the tasks that have none (zero_action.py)."""
    for task in tasks:
        if zero_action.read_reference(data_root, task) is None:
            reference = zero_action.zero_action_reference(task, episodes)
            path = zero_action.write_reference(reference, data_root)
            print(f"chance level of {task} -> {path}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
