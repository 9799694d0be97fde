"""make sweep (experiments/sweep.py) on a local Ray instance: a debug grid of two jobs runs and draws its
plots; a driver killed mid-way and started again resumes both jobs from their checkpoints to the metrics of
an uninterrupted sweep; a failing job is run once more, then reported, while the other finishes; a bad grid
is one line, exit 2."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from experiments import sweep
from experiments.sweep_grid import GridError, load_grid
from tests.run_helpers import REPO, cli_env, records_without_time, wait_until_unlocked

CHUNK, PREFILL = 200, 20
DEBUG_KEYS = ["prefill=20", "train_every=20", "pretrain=5", "eval_episodes=4",
              "checkpoint_every=100", "log_every=100", "visitation_bins=8", "codegen=fast",
              "agent.precision=f32", "planner.num_candidates=16", "planner.iterations=2", "planner.horizon=5"]


def write_grid(path, runs, steps: int, eval_every: int = CHUNK) -> None:
    keys = [*DEBUG_KEYS, f"eval_every={eval_every}"]
    path.write_text(f"tasks = [\"tabletop\"]\nagents = [\"morefree\", \"rf_peg\"]\nseeds = [0]\n"
                    f"steps = {steps}\npreset = \"debug\"\nargs = {json.dumps(keys)}\nruns = \"{runs}\"\n")


def start_sweep(grid) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "experiments.sweep", f"grid={grid}", "progress_every=5"],
                            cwd=REPO, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(process: subprocess.Popen, timeout_s: float = 900) -> tuple[int, str, str]:
    out, err = process.communicate(timeout=timeout_s)
    return process.returncode, out.decode(), err.decode()


def has_a_checkpoint(run_dir) -> bool:
    """A complete checkpoint: a step's dir (named by its step, after orbax's rename) with its files.json,
    which is written last."""
    return any(path.parent.name.isdigit() for path in (run_dir / "checkpoints").glob("*/files.json"))


def kill_once_checkpointed(driver: subprocess.Popen, run_dirs, timeout_s: float = 900) -> None:
    """SIGKILLs the sweep's driver (only it) as soon as every one of `run_dirs` holds a checkpoint. Any
    checkpoint, not one step's: runs keep only their newest three, so a job a few chunks ahead of the other
    may have deleted a given step's checkpoint before the other writes its own."""
    deadline = time.monotonic() + timeout_s
    while not all(has_a_checkpoint(run_dir) for run_dir in run_dirs):
        assert driver.poll() is None, driver.stderr.read().decode()[-3000:]
        assert time.monotonic() < deadline, "no checkpoint in time"
        time.sleep(0.05)
    driver.kill()
    driver.wait()


def test_a_killed_sweep_resumes_both_jobs_to_the_metrics_of_an_uninterrupted_one(tmp_path):
    # Long enough that neither job can finish before the other's first checkpoint (the driver is killed
    # then): their programs may take a few seconds apart to compile or load.
    steps = PREFILL + 25 * CHUNK
    write_grid(tmp_path / "whole.toml", tmp_path / "whole", steps, eval_every=1000)
    code, out, err = finish(start_sweep(tmp_path / "whole.toml"))
    assert code == 0, err[-3000:]
    assert "tabletop/morefree" in out and "env steps/s per seed" in out  # the progress table
    whole = [tmp_path / "whole" / "tabletop" / agent / "seed0" for agent in ("morefree", "rf_peg")]
    assert all((run_dir.parent / sweep.DONE_FILE).exists() for run_dir in whole)
    assert (tmp_path / "whole" / "results" / "tabletop_success.png").exists()
    again = subprocess.run([sys.executable, "-m", "experiments.sweep", f"grid={tmp_path / 'whole.toml'}"],
                           cwd=REPO, env=cli_env(), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and again.stdout.count("finished before, skipped") == 2

    write_grid(tmp_path / "killed.toml", tmp_path / "killed", steps, eval_every=1000)
    killed = [tmp_path / "killed" / "tabletop" / agent / "seed0" for agent in ("morefree", "rf_peg")]
    driver = start_sweep(tmp_path / "killed.toml")
    kill_once_checkpointed(driver, killed)
    for run_dir in killed:  # the jobs die with the driver's Ray workers
        wait_until_unlocked(run_dir, timeout_s=120)
    for run_dir in killed:
        checkpoints = [int(p.name) for p in (run_dir / "checkpoints").iterdir() if p.name.isdigit()]
        assert checkpoints and max(checkpoints) < steps, run_dir  # stopped part-way, with a checkpoint
    code, _, err = finish(start_sweep(tmp_path / "killed.toml"))
    assert code == 0, err[-3000:]
    for resumed, reference in zip(killed, whole, strict=True):
        starts = [json.loads(line) for line in (resumed / "provenance.jsonl").read_text().splitlines()]
        assert [start["resumed"] for start in starts] == [False, True]  # from its checkpoint, not anew
        assert records_without_time(resumed) == records_without_time(reference)


def test_sigterm_stops_the_sweep_and_its_jobs_with_exit_130(tmp_path):
    write_grid(tmp_path / "grid.toml", tmp_path / "runs", PREFILL + 25 * CHUNK, eval_every=1000)
    run_dirs = [tmp_path / "runs" / "tabletop" / agent / "seed0" for agent in ("morefree", "rf_peg")]
    driver = start_sweep(tmp_path / "grid.toml")
    deadline = time.monotonic() + 900
    while not all((run_dir / "metrics.jsonl").exists() for run_dir in run_dirs):
        assert driver.poll() is None and time.monotonic() < deadline, driver.stderr.read().decode()[-3000:]
        time.sleep(0.05)
    driver.send_signal(signal.SIGTERM)
    code, _, err = finish(driver, timeout_s=120)
    assert code == sweep.STOPPED_EXIT and "stopped; every job keeps its last checkpoint" in err
    for run_dir in run_dirs:  # the train processes ended with the sweep
        wait_until_unlocked(run_dir, timeout_s=30)
        assert not (run_dir.parent / sweep.DONE_FILE).exists()


def test_a_failing_job_is_run_once_more_then_reported_while_the_other_finishes(tmp_path):
    write_grid(tmp_path / "grid.toml", tmp_path / "runs", PREFILL + CHUNK)
    blocked = tmp_path / "runs" / "tabletop" / "rf_peg"
    blocked.mkdir(parents=True)
    (blocked / "seed0").write_text("a file where the run dir should be")
    code, out, err = finish(start_sweep(tmp_path / "grid.toml"))
    assert code == 1
    assert "tabletop/rf_peg failed (exit 2); running it once more" in out
    assert "tabletop/rf_peg failed twice (exit 2); the last lines of" in err and "error:" in err
    assert (blocked / "train.log").read_text().count("# sweep job on") == 2
    assert (tmp_path / "runs" / "tabletop" / "morefree" / sweep.DONE_FILE).exists()
    assert not (blocked / sweep.DONE_FILE).exists()


BASE = "tasks = [\"tabletop\"]\nagents = [\"morefree\"]\nseeds = [0]\n"
BAD_GRIDS = {
    "tasks = [\"tabletop\"\n": "not valid TOML",
    BASE + "speed = 2\n": "unknown key speed; valid keys:",
    "tasks = [\"tabletop\"]\nagents = [\"morefree\"]\n": "missing seeds",
    BASE.replace("tabletop", "moon"): "tasks: moon; valid: point_umaze",
    BASE.replace("[0]", "[\"a\"]"): "seeds must be",
    BASE + "steps = -5\n": "steps must be a positive",
    BASE + "exclude = [\"ant/medal\"]\n": "exclude must",
    BASE + "args = [\"wm.nope=1\"]\n": "tabletop/morefree:",
}


@pytest.mark.parametrize("text", list(BAD_GRIDS))
def test_a_bad_grid_is_one_line_exit_2(text, tmp_path, capsys):
    path = tmp_path / "grid.toml"
    path.write_text(text)
    assert sweep.main([f"grid={path}"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and error.startswith(f"error: grid {path}: ") and BAD_GRIDS[text] in error


def test_missing_grid_file_and_missing_ray_are_one_line(tmp_path, monkeypatch, capsys):
    assert sweep.main([f"grid={tmp_path / 'nope.toml'}"]) == 2
    assert "no such file" in capsys.readouterr().err
    write_grid(tmp_path / "grid.toml", tmp_path / "runs", PREFILL + CHUNK)
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    assert sweep.main([f"grid={tmp_path / 'grid.toml'}"]) == 2
    assert capsys.readouterr().err == f"error: {sweep.INSTALL_HINT}\n"


def test_the_shipped_grids_load():
    paper = load_grid(REPO / "experiments" / "grids" / "paper.toml")
    assert len(paper.jobs) == 8 * 8 - 1 and all(job.seeds == (0, 1, 2, 3, 4) for job in paper.jobs)
    assert "ant/medal" not in {job.name for job in paper.jobs}
    debug = load_grid(REPO / "experiments" / "grids" / "debug.toml")
    assert [job.name for job in debug.jobs] == ["tabletop/morefree", "tabletop/rf_peg"]
    assert "seed=0" in debug.jobs[0].train_arguments()
    with pytest.raises(GridError, match="no such file"):
        load_grid(REPO / "experiments" / "grids" / "none.toml")
