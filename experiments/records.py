"""Run records for the repository: every run dir below `runs=` as results/data/<task>/<group>/seed<k>.jsonl
and .npz (`make records RUNS=$HOME/runs/x`; experiments/analysis/records.py says what they hold).

    python -m experiments.records runs=$HOME/runs/push_hard [out=results/data]

Re-run it after each evaluation and commit results/data: a lost machine then loses nothing committed, and
`make plots` on a fresh clone draws from the records. A run dir with no evaluation yet is skipped with one
line saying why; finding none is a one-line error (exit 2).
"""

from __future__ import annotations

import pathlib
import sys

from experiments.analysis.records import write_record
from experiments.cli import REQUIRED, KeyValueError, parse_keys

DATA_DIR = "results/data"


def main(argv: list[str]) -> int:
    try:
        args = parse_keys(argv, {"runs": REQUIRED, "out": DATA_DIR})
    except KeyValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    root = pathlib.Path(args["runs"]).expanduser()
    if not root.is_dir():
        print(f"error: runs={root} is not a directory", file=sys.stderr)
        return 2
    written = 0
    for config in sorted(root.rglob("config.json")):
        try:
            paths = write_record(config.parent, args["out"])
        except ValueError as error:
            print(f"skipped {config.parent}: {error}")
            continue
        written += 1
        print(f"{config.parent} -> {paths[0]}")
    if not written:
        print(f"error: no run dir with evaluations below {root}", file=sys.stderr)
        return 2
    print(f"wrote {written} run records to {args['out']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
