"""experiments.experiment: argument checks, and the orchestration (agents in parallel, a log each, progress
lines, exit codes, plots at the end) with a stand-in for the train command that writes a small run dir."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from experiments import experiment
from morefree_jax.config import ConfigError
from tests.run_helpers import wait_until_unlocked

REPO = pathlib.Path(__file__).resolve().parents[1]

# Writes a run dir per seed like experiments.train would (config.json, metrics.jsonl with an evaluation).
FAKE_TRAIN = textwrap.dedent("""
    import json, pathlib, sys
    args = dict(arg.split("=", 1) for arg in sys.argv[1:])
    if args["agent"] == "dreamer_gc":
        print("error: a failing agent"); sys.exit(2)
    for seed in args["seeds"].split(","):
        run_dir = pathlib.Path("runs") / args["env"] / args["agent"] / f"seed{seed}"
        (run_dir / "plots").mkdir(parents=True, exist_ok=True)
        (run_dir / "config.json").write_text(json.dumps(
            {"run": {"env": args["env"], "agent": args["agent"], "seed": int(seed)}}))
        (run_dir / "metrics.jsonl").write_text(json.dumps({"step": 1000, "eval/success": 0.5}) + "\\n")
    print("done")
""")


def test_bad_arguments_are_one_line_errors():
    with pytest.raises(ConfigError, match="valid: point_umaze"):
        experiment.parse_args(["task=maze"])
    with pytest.raises(ConfigError, match="agents must be distinct names among morefree"):
        experiment.parse_args(["task=point_umaze", "agents=morefree,nope"])
    with pytest.raises(ConfigError, match="seeds must be"):
        experiment.parse_args(["task=point_umaze", "seeds=0,0"])
    with pytest.raises(ConfigError, match="steps must be a positive integer"):
        experiment.parse_args(["task=point_umaze", "steps=-5"])
    with pytest.raises(ConfigError, match="task is given twice"):
        experiment.parse_args(["task=point_umaze", "task=tabletop"])
    # the train commands' own arguments are checked before any agent starts
    with pytest.raises(ConfigError, match=r"run.preset is given twice \(preset=cpu and preset=paper\)"):
        experiment.parse_args(["task=point_umaze", "agents=morefree", "preset=cpu", "preset=paper"])
    with pytest.raises(ConfigError, match="oracle_sac: .*deter must be > 0"):
        experiment.parse_args(["task=point_umaze", "agents=oracle_sac", "wm.deter=0"])


def test_other_arguments_go_to_every_train_command():
    settings, passed = experiment.parse_args(["task=tabletop", "agents=morefree", "seeds=1,2", "steps=5000",
                                              "preset=debug", "wm.deter=32"])
    assert passed == ["preset=debug", "wm.deter=32"]
    command = experiment.train_command(settings, "morefree", passed)
    assert command[1:] == ["-m", "experiments.train", "env=tabletop", "agent=morefree", "seeds=1,2",
                           "steps=5000", "preset=debug", "wm.deter=32"]


def test_agents_run_in_parallel_and_report(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "fake_train.py").write_text(FAKE_TRAIN)
    monkeypatch.setattr(experiment, "train_command",
                        lambda settings, agent, passed: [sys.executable, str(tmp_path / "fake_train.py"),
                                                         f"env={settings['task']}", f"agent={agent}",
                                                         f"seeds={','.join(map(str, settings['seeds']))}"])
    plotted = []
    monkeypatch.setattr(experiment.plots, "main", lambda argv: plotted.append(argv) or 0)
    code = experiment.main(["task=tabletop", "agents=morefree,rf_peg,dreamer_gc", "seeds=0,1", "parallel=2"])
    out, err = capsys.readouterr()
    assert code == 1  # one agent failed
    assert "morefree: step 1,000/task budget, success 0.50 (2 seeds) [done]" in out
    assert "dreamer_gc: no evaluation yet [exit 2]" in out
    assert "dreamer_gc exited with 2; see runs/tabletop/dreamer_gc/train.log" in err
    assert "a failing agent" in (tmp_path / "runs/tabletop/dreamer_gc/train.log").read_text()
    assert (tmp_path / "runs/tabletop/rf_peg/seed1/metrics.jsonl").exists()
    assert plotted == [["runs=runs/tabletop", "out=runs/tabletop/results", "task=tabletop"]]


def _sigkill_lock_owner(run_dir: pathlib.Path, timeout_s: float = 60) -> None:
    """SIGKILLs the train process that holds run_dir's lock and waits until the lock is free. experiment
    starts each train in its own session (a terminal's Ctrl-C reaches experiment alone), so killing
    experiment's process group leaves its train running on."""
    os.kill(json.loads((run_dir / ".lock").read_text())["pid"], signal.SIGKILL)
    wait_until_unlocked(run_dir, timeout_s)


def test_a_debug_experiment_resumes_after_sigkill_and_plots(tmp_path):
    """The real command: r3l (the fused model-free chunk compiles in seconds) with 2 seeds at the debug
    preset, SIGKILLed with its train process once the first chunk's checkpoint is complete, then re-run."""
    from tests.run_helpers import cli_env, debug_args, sigkill_once_written
    from tests.test_stream import CHUNK, MF_ARGS, PREFILL

    # The train arguments of test_stream's r3l group run, so the compilation cache can serve them.
    passed = [arg for arg in debug_args("agent=r3l", *MF_ARGS)
              if arg.split("=")[0] not in ("env", "seed", "agent")]
    command = [sys.executable, "-m", "experiments.experiment", "task=tabletop", "agents=r3l", "seeds=0,1",
               f"steps={PREFILL + 3 * CHUNK}", "parallel=1", *passed]
    env = cli_env()
    # Its own process group, so that killing it spares pytest (its train runs in a session of its own).
    first = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, start_new_session=True)
    checkpoint = tmp_path / "runs/tabletop/r3l/seed1/checkpoints" / str(PREFILL + CHUNK) / "files.json"
    sigkill_once_written(first, checkpoint, group=True)
    _sigkill_lock_owner(tmp_path / "runs/tabletop/r3l/seed0")
    figures = tmp_path / "runs/tabletop/results"  # beside the runs: the repository's results/ stays as it is
    assert not figures.exists()  # killed before the end: no figures yet
    second = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    log = (tmp_path / "runs/tabletop/r3l/train.log").read_text()
    assert second.returncode == 0, log[-3000:]
    assert "r3l: step 250/250, success" in second.stdout and "[done]" in second.stdout
    log = (tmp_path / "runs/tabletop/r3l/train.log").read_text()
    assert "resuming from step" in log
    for seed in (0, 1):
        done = {p.name for p in (tmp_path / f"runs/tabletop/r3l/seed{seed}/checkpoints").iterdir()}
        assert str(PREFILL + 3 * CHUNK) in done
    drawn = {p.name for p in figures.iterdir()}
    assert not (tmp_path / "results").exists()
    assert {"tabletop_success.png", "tabletop_results.md"} <= drawn


# Waits for SIGINT as experiments.train does (then "saves" and exits 0); writes where it is.
WAITING_TRAIN = textwrap.dedent("""
    import pathlib, signal, sys, time
    agent = dict(arg.split("=", 1) for arg in sys.argv[1:])["agent"]
    marker = pathlib.Path("runs") / f"{agent}.state"
    def stop(signum, frame):
        marker.write_text("stopped"); sys.exit(0)
    signal.signal(signal.SIGINT, stop)
    marker.write_text("running")
    time.sleep(60)
    marker.write_text("finished unstopped")
""")

# experiments.experiment with the waiting stand-in for the train command.
EXPERIMENT_DRIVER = textwrap.dedent("""
    import sys
    from experiments import experiment
    experiment.train_command = lambda settings, agent, passed: [sys.executable, "waiting_train.py",
                                                                f"agent={agent}"]
    sys.exit(experiment.main(["task=tabletop", "agents=morefree,rf_peg", "seeds=0", "parallel=1"]))
""")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_background_experiment_stops_on_a_signal_and_starts_no_further_agent(tmp_path, signum):
    """Started as `nohup make experiment ... &` starts it: with SIGINT ignored, which Python keeps."""
    (tmp_path / "waiting_train.py").write_text(WAITING_TRAIN)
    (tmp_path / "driver.py").write_text(EXPERIMENT_DRIVER)
    (tmp_path / "runs").mkdir()
    env = {**os.environ, "PYTHONPATH": f"{REPO / 'src'}:{REPO}"}
    process = subprocess.Popen([sys.executable, "driver.py"], cwd=tmp_path, env=env, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    marker = tmp_path / "runs/morefree.state"
    deadline = time.monotonic() + 60
    while not (marker.exists() and marker.read_text() == "running"):
        assert time.monotonic() < deadline and process.poll() is None, process.stderr.read()
        time.sleep(0.1)
    process.send_signal(signum)
    out, err = process.communicate(timeout=60)
    assert process.returncode == experiment.STOPPED_EXIT, err
    assert marker.read_text() == "stopped"  # the agent got its Ctrl-C
    assert not (tmp_path / "runs/rf_peg.state").exists() and not (tmp_path / "runs/tabletop/rf_peg").exists()
    assert "stopping every agent after its current chunk" in out
    assert "stopped (not started: rf_peg); re-run the same command to resume; no figures drawn" in err
