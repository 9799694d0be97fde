"""Run records (experiments/analysis/records.py, `make records`): a record holds what its run dir's
metrics.jsonl holds at every evaluation, and the figures and tables drawn from records equal those drawn
from the run dirs."""

from __future__ import annotations

import json
import math
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from experiments import plots, records
from experiments.analysis import run_record, zero_action
from experiments.analysis.records import FORMAT, config_digest, read_record, write_record
from morefree_jax.logger import DROPPED_SHARE, read_metrics
from tests.plot_helpers import STEPS, SUCCESS, write_run, write_runs
from tests.run_helpers import debug_config, debug_programs


def _metrics_at_evaluations(run_dir) -> dict[int, dict]:
    """Straight from metrics.jsonl: per evaluated step, its eval/* and visitation/* values and the dropped
    share and the back chunks' share and reach rate last logged at or before it."""
    lines = read_metrics(run_dir / "metrics.jsonl")
    evaluated = sorted({line["step"] for line in lines if "eval/success" in line})
    expected = {}
    for step in evaluated:
        values = {key: value for line in lines if line["step"] == step for key, value in line.items()
                  if key.startswith(("eval/", "visitation/"))}
        for key in (DROPPED_SHARE, "goal/share_initial", "go/reach_rate_initial"):
            logged = [line[key] for line in lines if key in line and line["step"] <= step]
            if logged:
                values[key] = logged[-1]
        expected[step] = values
    return expected


def test_a_runs_record_holds_what_its_metrics_jsonl_holds(tmp_path):
    from morefree_jax import driver

    run_dir = tmp_path / "run"
    config = debug_config("morefree", f"run_dir={run_dir}", "steps=420", "eval_every=200", "log_every=100")
    driver.train(config, programs=debug_programs("morefree"), progress="off")
    jsonl, npz = write_record(run_dir, tmp_path / "data")
    assert jsonl == tmp_path / "data" / "tabletop" / "morefree" / "seed0.jsonl" and npz.exists()
    lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
    head, evaluations = lines[0], lines[1:]
    run_config = json.loads((run_dir / "config.json").read_text())
    assert head["format"] == FORMAT and head["config"] == run_config
    identity = (head["task"], head["agent"], head["seed"], head["precision"])
    assert identity == ("tabletop", "morefree", 0, "f32")
    assert head["config_digest"] == config_digest(run_config) and len(head["starts"]) == 1
    expected = _metrics_at_evaluations(run_dir)
    assert [line["step"] for line in evaluations] == sorted(expected) and len(expected) >= 2
    for line in evaluations:
        assert {key: value for key, value in line.items() if key != "step"} == expected[line["step"]]
    assert {"goal/share_initial", "go/reach_rate_initial"} <= set(evaluations[-1])
    with np.load(npz) as arrays:
        last = max(expected)
        assert int(arrays["visitation_step"]) == last
        assert np.array_equal(arrays["visitation"], np.load(run_dir / "plots" / f"visitation_{last:09d}.npy"))


def test_plots_from_records_equal_plots_from_the_run_dirs(tmp_path):
    runs = write_runs(tmp_path / "runs")
    assert records.main([f"runs={runs}", f"out={tmp_path / 'data'}", "chance_episodes=0"]) == 0
    assert len(list((tmp_path / "data" / "point_umaze").rglob("seed*.jsonl"))) == 5
    for source, out in ((runs, "from_runs"), (tmp_path / "data", "from_records")):
        assert plots.main([f"runs={source}", f"out={tmp_path / out}", "window=2500:7500"]) == 0
    drawn = sorted(path.name for path in (tmp_path / "from_runs").iterdir())
    assert drawn == sorted(path.name for path in (tmp_path / "from_records").iterdir())
    assert {"point_umaze_visitation.png", "point_umaze_back_starts.png", "point_umaze_window.md",
            "ablation.csv"} <= set(drawn)
    for name in drawn:
        from_runs, from_records = (tmp_path / out / name for out in ("from_runs", "from_records"))
        assert from_runs.read_bytes() == from_records.read_bytes(), name


def test_a_record_reads_back_as_the_run_dir_reads(tmp_path):
    runs = write_runs(tmp_path / "runs")
    run_dir = runs / "point_umaze" / "morefree" / "seed1"
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(config | {"agent": {"replay": {"capacity": 9000}}}))
    jsonl, _ = write_record(run_dir, tmp_path / "data")
    from_dir, from_record = run_record.read_run(run_dir), read_record(jsonl)
    assert from_record.replay_capacity == 9000
    for field in ("task", "agent", "seed", "commits", "base_agent", "replay_capacity"):
        assert getattr(from_record, field) == getattr(from_dir, field)
    assert from_record.evaluations() == from_dir.evaluations()
    for step in from_dir.evaluations():
        assert from_record.latest(DROPPED_SHARE, step) == from_dir.latest(DROPPED_SHARE, step)
    assert from_record.saved_views() == {max(from_dir.saved_views())}
    xy, step = from_record.back_starts()
    assert np.array_equal(xy, from_dir.back_starts()[0], equal_nan=True) and step == 7500
    with pytest.raises(KeyError, match="keeps the visitation histogram of steps"):
        from_record.histogram("visitation", 2500)


def test_records_of_runs_still_going_are_written_again_and_without_evaluations_skipped(tmp_path, capsys):
    runs = write_runs(tmp_path / "runs")
    (runs / "fresh").mkdir()
    (runs / "fresh" / "config.json").write_text(json.dumps({"run": {"env": "point_umaze", "agent": "morefree",
                                                                    "seed": 9}}))
    out = tmp_path / "data"
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    assert "skipped" in capsys.readouterr().out
    record = out / "point_umaze" / "morefree" / "seed0.jsonl"
    before = len(record.read_text().splitlines())
    metrics = runs / "point_umaze" / "morefree" / "seed0" / "metrics.jsonl"
    with open(metrics, "a") as file:
        file.write(json.dumps({"step": 10000, "eval/success": 0.9, "eval/final_success": 0.5}) + "\n")
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    assert len(record.read_text().splitlines()) == before + 1
    assert math.isclose(read_record(record).evaluations()[10000], 0.9)


def _restart_from_scratch(runs, agent, seed, successes):
    """The run dir of a run started again from step 0 (its machine lost), now at its first evaluation."""
    run_dir = runs / "point_umaze" / agent / f"seed{seed}"
    shutil.rmtree(run_dir)
    write_run(run_dir, "point_umaze", agent, seed, successes)
    lines = read_metrics(run_dir / "metrics.jsonl")
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines
                                                   if line["step"] <= STEPS[0]))


def test_a_restarted_run_keeps_the_longer_committed_record_and_says_whether_they_agree(tmp_path, capsys):
    runs, out = write_runs(tmp_path / "runs"), tmp_path / "data"
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    committed = {path: path.read_bytes() for path in out.rglob("seed*.*")}
    _restart_from_scratch(runs, "morefree", 0, SUCCESS["morefree", 0])  # deterministic: the same values
    _restart_from_scratch(runs, "rf_peg", 1, [0.7, 0.3, 0.4])  # another machine's numbers
    capsys.readouterr()
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    printed = capsys.readouterr().out
    assert "morefree/seed0.jsonl holds evaluations to step 7500, the run dir only to 2500 (shared " \
           "evaluations identical: 1 of 1): not replaced; replace=1 replaces it" in printed
    assert "rf_peg/seed1.jsonl holds evaluations to step 7500, the run dir only to 2500 (shared " \
           "evaluations differ from step 2500 on)" in printed
    assert {path: path.read_bytes() for path in out.rglob("seed*.*")} == committed
    assert records.main([f"runs={runs / 'point_umaze' / 'rf_peg' / 'seed1'}", f"out={out}",
                         "chance_episodes=0"]) == 2
    assert capsys.readouterr().err.strip().startswith("error: no record written: the 1 run dirs")
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0", "replace=1"]) == 0
    assert read_record(out / "point_umaze" / "rf_peg" / "seed1.jsonl").evaluations() == {2500: 0.7}


def _append_evaluation(run_dir, step, success):
    with open(run_dir / "metrics.jsonl", "a") as file:
        line = {"step": step, "eval/success": success, "eval/final_success": success / 2}
        file.write(json.dumps(line) + "\n")


def test_a_run_that_passes_its_record_with_other_numbers_keeps_the_record(tmp_path, capsys):
    runs, out = write_runs(tmp_path / "runs"), tmp_path / "data"
    seed0 = runs / "point_umaze" / "morefree" / "seed0"
    metrics = (seed0 / "metrics.jsonl").read_text()
    (seed0 / "metrics.jsonl").write_text(metrics.rsplit("{", 1)[0])  # between 7500's eval and visitation
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    (seed0 / "metrics.jsonl").write_text(metrics)
    _append_evaluation(seed0, 10000, 0.9)  # the same run, further on: its record grows
    seed1 = runs / "point_umaze" / "rf_peg" / "seed1"
    committed = (out / "point_umaze" / "rf_peg" / "seed1.jsonl").read_bytes()
    shutil.rmtree(seed1)
    write_run(seed1, "point_umaze", "rf_peg", 1, [0.7, 0.3, 0.4])  # restarted elsewhere, other numbers
    _append_evaluation(seed1, 10000, 0.5)
    capsys.readouterr()
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0"]) == 0
    printed = capsys.readouterr().out
    assert "rf_peg/seed1.jsonl and the run dir differ from step 2500 on (the run dir reaches 10000, the " \
           "record 7500): not replaced; replace=1 replaces it" in printed
    assert (out / "point_umaze" / "rf_peg" / "seed1.jsonl").read_bytes() == committed
    grown = out / "point_umaze" / "morefree" / "seed0.jsonl"
    assert read_record(grown).evaluations()[10000] == 0.9 and printed.count("skipped") == 1
    at_7500 = [json.loads(line) for line in grown.read_text().splitlines()][-2]
    assert at_7500["step"] == 7500 and "visitation/task_relevant" in at_7500  # the line written late
    assert records.main([f"runs={runs}", f"out={out}", "chance_episodes=0", "replace=1"]) == 0
    assert read_record(out / "point_umaze" / "rf_peg" / "seed1.jsonl").evaluations()[2500] == 0.7


def test_the_chance_level_counts_goals_met_without_acting_and_window_tables_quote_it(tmp_path, monkeypatch):
    env = envs_mjx.make("tabletop")
    start = env.reset(jax.random.PRNGKey(0)).obs
    # every other evaluation goal is the start itself: met at once by a policy that never acts
    goals = lambda key, count: jnp.where((jnp.arange(count) % 2 == 0)[:, None], start,  # noqa: E731
                                         type(env).evaluation_goals(env, key, count))
    monkeypatch.setattr(env, "evaluation_goals", goals)
    reached, final = zero_action.zero_action_rollout(env, jax.random.PRNGKey(1), 8)
    assert reached.tolist() == final.tolist() == [True, False] * 4
    reference = zero_action.zero_action_reference("tabletop", episodes=16)
    assert (reference["success"], reference["episodes"]) == (0.0, 16)  # its goals are away from the start
    runs = write_runs(tmp_path / "runs")
    zero_action.write_reference({**reference, "task": "point_umaze", "success": 0.085}, runs)
    assert plots.main([f"runs={runs}", f"out={tmp_path / 'out'}", "window=2500:7500"]) == 0
    table = (tmp_path / "out" / "point_umaze_window.md").read_text()
    assert "Chance level: a policy that never acts succeeds in 0.085 of 16 episodes" in table


@pytest.mark.parametrize("argv, message", [(["runs=/nonexistent"], "runs=/nonexistent is not a directory"),
                                           (["out=x"], "runs=... required"), (["runs=."], None)])
def test_bad_records_input_is_one_line(tmp_path, monkeypatch, argv, message, capsys):
    monkeypatch.chdir(tmp_path)  # runs=. : a directory without run dirs
    assert records.main(argv) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and error.startswith("error:")
    assert message is None or message in error
