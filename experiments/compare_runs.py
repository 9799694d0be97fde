"""Evaluation curves of run directories side by side, as a markdown table
(docs/experiments.md, "Other tools").

    python -m experiments.compare_runs runs=runs/point_umaze/morefree/seed0,runs/point_umaze/rf_peg/seed0

One row per evaluation step that every run has reached; per run: success (any step) / success (last step) /
final distance / task-relevant share of the replay / wall-clock minutes since the run started. A directory
without metrics.jsonl is an error naming it.
"""

from __future__ import annotations

import pathlib
import sys

from experiments.cli import REQUIRED, KeyValueError, parse_keys
from morefree_jax.logger import read_metrics

COLUMNS = ("eval/success", "eval/final_success", "eval/final_distance", "visitation/task_relevant")


def evaluation_rows(run_dir: str) -> dict[int, dict]:
    """{step: merged record} of the steps at which the run evaluated."""
    path = pathlib.Path(run_dir) / "metrics.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} has no metrics.jsonl (not a run dir, or not started)")
    merged: dict[int, dict] = {}
    for record in read_metrics(path):
        merged.setdefault(record["step"], {}).update(record)
    return {step: record for step, record in merged.items() if "eval/success" in record}


def cell(record: dict) -> str:
    minutes = record.get("time/elapsed_s", float("nan")) / 60
    success, final, distance, relevant = (record.get(name, float("nan")) for name in COLUMNS)
    return f"{success:.1f} / {final:.1f} / {distance:.2f} / {relevant:.3f} / {minutes:.0f} min"


def markdown_table(run_dirs: list[str]) -> str:
    curves = [evaluation_rows(run_dir) for run_dir in run_dirs]
    steps = sorted(set.intersection(*(set(curve) for curve in curves)))
    header = "| env steps | " + " | ".join(run_dirs) + " |"
    lines = [header, "|---" * (len(run_dirs) + 1) + "|"]
    lines += [f"| {step:,} | " + " | ".join(cell(curve[step]) for curve in curves) + " |" for step in steps]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if any(arg in ("-h", "--help") for arg in argv):
        print(__doc__)
        return 0
    try:
        run_dirs = [d for d in parse_keys(argv, {"runs": REQUIRED})["runs"].split(",") if d]
        print(markdown_table(run_dirs))
    except (KeyValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
