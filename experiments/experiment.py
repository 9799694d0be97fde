"""Several agents on one task, each agent's seeds in one program, then the figures
(`make experiment TASK=point_umaze AGENTS=morefree,rf_peg SEEDS=0,1,2 STEPS=100000`).

    python -m experiments.experiment task=point_umaze agents=morefree,rf_peg seeds=0,1,2 steps=100000 \
        [preset=cpu] [parallel=2] [out=runs/<task>/results] [key=value ...]

Each agent trains in its own process (`experiments.train ... seeds=...`) with run dirs
runs/<task>/<agent>/seed<k> and its output in runs/<task>/<agent>/train.log; `parallel` agents run at once
(default: one per CPU core, each pinned to its own core). Other key=value arguments go to every agent's
train command. While they run, one progress line per agent is printed every 60 s. Re-running the same
command resumes every agent from its checkpoints (a finished agent returns at once). When all have
finished, `experiments.plots runs=runs/<task> out=<out>` draws the task's figures and table; `out` defaults to
runs/<task>/results, beside the runs and outside git, so that a later run from the same checkout is not
stamped `+dirty` by redrawn tracked figures (`make plots OUT=results` updates the repository's).
Ctrl-C (or `kill -INT` / `kill` of this process, also when it runs in the background) stops every agent
after its current chunk (each saves a checkpoint) and starts no further agent; a second one quits the
agents at once (their last checkpoints stay). A stopped experiment draws no figures and exits 130. Bad
input: one line, exit 2.
"""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time
from typing import NamedTuple

from experiments import plots
from experiments.analysis.run_record import read_run
from morefree_jax.config import ConfigError
from morefree_jax.seeds import parse_seeds

OWN_KEYS = ("task", "agents", "seeds", "steps", "parallel", "out")
PROGRESS_EVERY_S = 60.0
STOPPED_EXIT = 130  # the shell's code for a run ended by Ctrl-C


def parse_args(argv: list[str]) -> tuple[dict, list[str]]:
    """({task, agents, seeds, steps, parallel, out}, the arguments passed on to every train command)."""
    import envs_mjx
    from morefree_jax.registry import AGENTS

    own, passed = {}, []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if not sep:
            raise ConfigError(f"arguments are key=value, got {arg!r}")
        if key not in OWN_KEYS:
            passed.append(arg)
        elif key in own:
            raise ConfigError(f"{key} is given twice")
        else:
            own[key] = value
    if own.get("task") not in envs_mjx.ALL_ENVS:
        raise ConfigError(f"task={own.get('task')!r} is not a task; valid: {', '.join(envs_mjx.ALL_ENVS)}")
    agents = [a for a in own.get("agents", "morefree,rf_peg").split(",") if a]
    if not agents or any(a not in AGENTS for a in agents) or len(set(agents)) != len(agents):
        raise ConfigError(f"agents must be distinct names among {', '.join(AGENTS)}; "
                          f"got {','.join(agents) or '(none)'}")
    settings = {"task": own["task"], "agents": agents, "seeds": parse_seeds(own.get("seeds", "0,1,2")),
                "steps": own.get("steps"), "out": own.get("out", f"runs/{own['task']}/results")}
    settings["parallel"] = _positive_int("parallel", own.get("parallel", str(os.cpu_count() or 1)))
    if settings["steps"] is not None:
        _positive_int("steps", settings["steps"])
    _check_train_arguments(settings, passed)
    return settings, passed


def _check_train_arguments(settings: dict, passed: list[str]) -> None:
    """Resolves every agent's train arguments here, so that bad input is one line before any agent starts
    (not an exit 2 per agent, its message in that agent's train.log)."""
    import envs_mjx
    from experiments.train import split_seeds
    from morefree_jax.config import resolve_config

    for agent in settings["agents"]:
        _, arguments = split_seeds(train_arguments(settings, agent, passed))
        try:
            resolve_config(arguments, envs_mjx.ALL_ENVS)
        except ValueError as error:  # ConfigError is one; the config constructors' checks are others
            raise ConfigError(f"{agent}: {str(error).splitlines()[0]}") from None


def _positive_int(name: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value <= 0:
        raise ConfigError(f"{name} must be a positive integer, got {text!r}")
    return value


def train_arguments(settings: dict, agent: str, passed: list[str]) -> list[str]:
    seeds = ",".join(map(str, settings["seeds"]))
    steps = [f"steps={settings['steps']}"] if settings["steps"] else []
    return [f"env={settings['task']}", f"agent={agent}", f"seeds={seeds}", *steps, *passed]


def train_command(settings: dict, agent: str, passed: list[str]) -> list[str]:
    return [sys.executable, "-m", "experiments.train", *train_arguments(settings, agent, passed)]


def agent_dir(settings: dict, agent: str) -> pathlib.Path:
    return pathlib.Path("runs") / settings["task"] / agent


def progress_line(settings: dict, agent: str, process) -> str:
    """'agent: step s/total, success m over seeds' from the seeds' metrics (or the process state)."""
    state = "running" if process is not None and process.poll() is None else "waiting"
    if process is not None and process.poll() is not None:
        state = "done" if process.returncode == 0 else f"exit {process.returncode}"
    successes, step = [], None
    for seed in settings["seeds"]:
        try:
            run = read_run(agent_dir(settings, agent) / f"seed{seed}")
        except (ValueError, FileNotFoundError):
            continue
        evaluations = run.evaluations()
        step = max(run.steps) if step is None else min(step, max(run.steps))
        successes.append(evaluations[max(evaluations)])
    total = settings["steps"] or "task budget"
    where = "no evaluation yet" if step is None else \
        f"step {step:,}/{total}, success {sum(successes) / len(successes):.2f} ({len(successes)} seeds)"
    return f"{agent}: {where} [{state}]"


def _start(settings, agent, passed, core):
    directory = agent_dir(settings, agent)
    directory.mkdir(parents=True, exist_ok=True)
    pin = (lambda: os.sched_setaffinity(0, {core})) if core is not None else None
    with open(directory / "train.log", "a") as log:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(train_command(settings, agent, passed), stdout=log, stderr=subprocess.STDOUT,
                                preexec_fn=pin, start_new_session=True)


def _raise_stop(signum, frame):
    raise KeyboardInterrupt  # SIGTERM too: one way out of the loop below


def _signal_all(processes) -> None:
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)


def stop_on_signals() -> dict:
    """Installs _raise_stop for SIGINT and SIGTERM -> the previous handlers. Explicitly, because a shell
    starts a background command (`nohup make experiment ... &`) with SIGINT ignored, and Python keeps an
    ignored SIGINT ignored: `kill -INT` would then do nothing, and `kill` would leave the agents running."""
    return {signum: signal.signal(signum, _raise_stop) for signum in (signal.SIGINT, signal.SIGTERM)}


class Outcome(NamedTuple):
    codes: dict[str, int]  # {agent: exit code} of the agents that ran
    stopped: bool  # Ctrl-C or SIGTERM stopped the experiment
    unstarted: list[str]  # the agents the stop kept from starting


def run_agents(settings: dict, passed: list[str]) -> Outcome:
    """Runs every agent (`parallel` at a time); a stop signal stops the running ones after their chunk and
    starts no more."""
    cores = sorted(os.sched_getaffinity(0))
    pending, running, started, codes = list(settings["agents"]), {}, {}, {}
    last_print = -float("inf")
    previous = stop_on_signals()
    try:
        while pending or running:
            free = [c for c in cores if c not in {core for _, core in running.values()}]
            while pending and len(running) < settings["parallel"]:
                core = free.pop(0) if settings["parallel"] > 1 and free else None
                agent = pending[0]
                running[agent] = (_start(settings, agent, passed, core), core)
                started[agent] = running[agent][0]
                pending.pop(0)  # only now: a stop signal during the start leaves the agent in one list
            for agent, (process, _) in list(running.items()):
                if process.poll() is not None:
                    codes[agent] = process.returncode
                    del running[agent]
            if time.monotonic() - last_print >= PROGRESS_EVERY_S or not (pending or running):
                last_print = time.monotonic()
                for agent in settings["agents"]:
                    print(progress_line(settings, agent, started.get(agent)), flush=True)
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("stopping every agent after its current chunk (each saves a checkpoint; Ctrl-C again to quit "
              "now)", flush=True)
        processes = [process for process, _ in running.values()]
        _signal_all(processes)
        for signum in previous:  # a second signal: the agents' own "quit now"; the waits below go on
            signal.signal(signum, lambda *_: _signal_all(processes))
        for agent, (process, _) in running.items():
            codes[agent] = process.wait()
        return Outcome(codes, True, pending)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return Outcome(codes, False, [])


def main(argv: list[str]) -> int:
    if not argv or any(arg in ("-h", "--help") for arg in argv):
        print(__doc__)
        return 0 if argv else 2
    try:
        settings, passed = parse_args(argv)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    outcome = run_agents(settings, passed)
    failed = {agent: code for agent, code in outcome.codes.items() if code != 0}
    for agent, code in failed.items():
        print(f"{agent} exited with {code}; see {agent_dir(settings, agent) / 'train.log'}", file=sys.stderr)
    if outcome.stopped:
        unstarted = f" (not started: {', '.join(outcome.unstarted)})" if outcome.unstarted else ""
        print(f"stopped{unstarted}; re-run the same command to resume; no figures drawn", file=sys.stderr)
        return STOPPED_EXIT
    plotted = plots.main([f"runs={pathlib.Path('runs') / settings['task']}", f"out={settings['out']}",
                          f"task={settings['task']}"])
    return 1 if failed else plotted


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
