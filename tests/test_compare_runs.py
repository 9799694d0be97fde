"""experiments.compare_runs: the side-by-side evaluation tables from metrics.jsonl files
(docs/experiments.md, "Other tools")."""

from __future__ import annotations

import json

from experiments import compare_runs


def write_run(path, evaluations):
    path.mkdir()
    lines = []
    for step, success in evaluations:
        lines.append({"step": step, "wm/loss": 1.0, "time/elapsed_s": 60.0 * step / 1000})
        lines.append({"step": step, "eval/success": success, "eval/final_success": success / 2,
                      "eval/final_distance": 1.25, "visitation/task_relevant": 0.03})
    (path / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))


def test_table_lists_the_steps_every_run_reached(tmp_path, capsys):
    write_run(tmp_path / "a", [(1000, 0.0), (2000, 0.5), (3000, 1.0)])
    write_run(tmp_path / "b", [(1000, 0.2), (2000, 0.4)])
    assert compare_runs.main([f"runs={tmp_path / 'a'},{tmp_path / 'b'}"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4  # header, rule, steps 1,000 and 2,000
    assert lines[3] == "| 2,000 | 0.5 / 0.2 / 1.25 / 0.030 / 2 min | 0.4 / 0.2 / 1.25 / 0.030 / 2 min |"


def test_missing_run_is_one_line_error(tmp_path, capsys):
    assert compare_runs.main([f"runs={tmp_path / 'nothing'}"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
