"""A sweep's grid file and the jobs it expands to (`make sweep GRID=experiments/grids/paper.toml`).

    grid = load_grid("experiments/grids/debug.toml")
    for job in grid.jobs:              # one per (task, agent): its seeds in one program
        job.command()                  # python -m experiments.train env=... agent=... seeds=... run_dir=...

A grid is a TOML file (tomllib, in the standard library since Python 3.11):

    tasks = ["point_umaze", "push_hard"]     # required
    agents = ["morefree", "rf_peg"]          # required
    seeds = [0, 1, 2, 3, 4]                  # required: integers, or a string as seeds= takes ("0-4")
    steps = 100000                           # optional: every job's env steps (default: each task's budget)
    preset = "cpu"                           # optional (default "cpu")
    args = ["eval_every=5000"]               # optional: key=value words for every train command
    runs = "runs/paper"                      # optional: the run dirs' root, relative to the repository
    cpus_per_job = 1                         # optional: Ray CPUs a job asks for (default 1)
    gpus_per_job = "auto"                    # optional: 0, 1, ... or "auto" (1 where the cluster has GPUs)
    exclude = ["ant/medal"]                  # optional: task/agent pairs left out
    [steps_per_task]                         # optional: steps of some tasks (over `steps`)
    push_hard = 200000

A job's run dirs are <runs>/<task>/<agent>/seed<k> and its output <runs>/<task>/<agent>/train.log. A bad
grid is a GridError with one line naming the file and what is valid.
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
import tomllib

REPO = pathlib.Path(__file__).resolve().parents[1]
REQUIRED_KEYS = ("tasks", "agents", "seeds")
OPTIONAL_KEYS = ("steps", "preset", "args", "runs", "cpus_per_job", "gpus_per_job", "steps_per_task",
                 "exclude")


class GridError(ValueError):
    """A grid file that cannot be used (one line)."""


@dataclasses.dataclass(frozen=True)
class Job:
    """One (task, agent) of the grid: its seeds in one program, a run dir each."""

    task: str
    agent: str
    seeds: tuple[int, ...]
    steps: int | None
    preset: str
    args: tuple[str, ...]
    runs: pathlib.Path  # absolute

    @property
    def name(self) -> str:
        return f"{self.task}/{self.agent}"

    @property
    def directory(self) -> pathlib.Path:
        return self.runs / self.task / self.agent

    @property
    def log(self) -> pathlib.Path:
        return self.directory / "train.log"

    def run_dir(self, seed: int) -> pathlib.Path:
        return self.directory / f"seed{seed}"

    def train_arguments(self) -> list[str]:
        steps = [f"steps={self.steps}"] if self.steps else []
        if len(self.seeds) == 1:  # train keeps a single seed's run_dir as given: name its seed<k> here
            seeds = [f"seed={self.seeds[0]}", f"run_dir={self.run_dir(self.seeds[0])}"]
        else:
            seeds = [f"seeds={','.join(map(str, self.seeds))}", f"run_dir={self.directory}"]
        return [f"env={self.task}", f"agent={self.agent}", f"preset={self.preset}", *seeds, *steps,
                *self.args]

    def command(self) -> list[str]:
        return [sys.executable, "-m", "experiments.train", *self.train_arguments()]


@dataclasses.dataclass(frozen=True)
class Grid:
    path: pathlib.Path
    jobs: tuple[Job, ...]
    runs: pathlib.Path
    cpus_per_job: int
    gpus_per_job: int | str  # a count, or "auto"


def _fail(path, message: str):
    raise GridError(f"grid {path}: {message}")


def _names(path, table: dict, key: str, valid) -> list[str]:
    names = table[key]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        _fail(path, f"{key} must be a non-empty list of names, e.g. {key} = [\"{next(iter(valid))}\"]")
    unknown = [name for name in names if name not in valid]
    if unknown or len(set(names)) != len(names):
        _fail(path, f"{key}: {', '.join(unknown) or 'a name given twice'}; valid: {', '.join(valid)}")
    return names


def _seeds(path, value) -> tuple[int, ...]:
    from morefree_jax.seeds import parse_seeds

    text = ",".join(map(str, value)) if isinstance(value, list) else value
    if not isinstance(text, str) or (isinstance(value, list) and not all(type(s) is int for s in value)):
        _fail(path, f"seeds must be a list of integers or a string like \"0-4\", got {value!r}")
    try:
        return parse_seeds(text)
    except ValueError as error:
        _fail(path, f"seeds: {str(error).splitlines()[0]}")


def _positive(path, key: str, value, allow_none=False) -> int | None:
    if value is None and allow_none:
        return None
    if type(value) is not int or value <= 0:
        _fail(path, f"{key} must be a positive integer, got {value!r}")
    return value


def _read(path: pathlib.Path) -> dict:
    try:
        with open(path, "rb") as file:
            table = tomllib.load(file)
    except FileNotFoundError:
        raise GridError(f"grid {path}: no such file (grids ship in experiments/grids/)") from None
    except tomllib.TOMLDecodeError as error:
        _fail(path, f"not valid TOML ({error})")
    unknown = sorted(set(table) - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
    missing = [key for key in REQUIRED_KEYS if key not in table]
    if unknown or missing:
        what = f"unknown key {', '.join(unknown)}" if unknown else f"missing {', '.join(missing)}"
        _fail(path, f"{what}; valid keys: {', '.join(REQUIRED_KEYS + OPTIONAL_KEYS)}")
    return table


def load_grid(path) -> Grid:
    """The grid at `path`, each job's train arguments checked (GridError, one line, before anything runs)."""
    import envs_mjx
    from morefree_jax.registry import AGENTS

    path = pathlib.Path(path)
    table = _read(path)
    tasks, agents = _names(path, table, "tasks", envs_mjx.ALL_ENVS), _names(path, table, "agents", AGENTS)
    steps_per_task = table.get("steps_per_task", {})
    if not isinstance(steps_per_task, dict) or set(steps_per_task) - set(tasks):
        _fail(path, f"steps_per_task must be a table of the grid's tasks ({', '.join(tasks)}) to steps")
    args = table.get("args", [])
    if not isinstance(args, list) or not all(isinstance(a, str) and "=" in a for a in args):
        _fail(path, "args must be a list of \"key=value\" strings")
    runs = (REPO / table.get("runs", "runs")).resolve()
    seeds = _seeds(path, table["seeds"])
    default_steps = _positive(path, "steps", table.get("steps"), allow_none=True)
    excluded = _excluded(path, table.get("exclude", []), tasks, agents)
    jobs = tuple(Job(task, agent, seeds, _positive(path, f"steps_per_task.{task}",
                                                   steps_per_task.get(task, default_steps), allow_none=True),
                     str(table.get("preset", "cpu")), tuple(args), runs)
                 for task in tasks for agent in agents if f"{task}/{agent}" not in excluded)
    for job in jobs:
        _check_job(path, job)
    gpus = table.get("gpus_per_job", "auto")
    if gpus != "auto" and (type(gpus) is not int or gpus < 0):
        _fail(path, f"gpus_per_job must be \"auto\" or an integer >= 0, got {gpus!r}")
    return Grid(path, jobs, runs, _positive(path, "cpus_per_job", table.get("cpus_per_job", 1)), gpus)


def _excluded(path, exclude, tasks, agents) -> set[str]:
    pairs = {f"{task}/{agent}" for task in tasks for agent in agents}
    if not isinstance(exclude, list) or any(pair not in pairs for pair in exclude):
        _fail(path, f"exclude must list task/agent pairs of the grid, e.g. [\"{next(iter(sorted(pairs)))}\"]")
    return set(exclude)


def _check_job(path, job: Job) -> None:
    import envs_mjx
    from experiments.train import split_seeds
    from morefree_jax.config import resolve_config

    _, arguments = split_seeds(job.train_arguments())
    try:
        resolve_config(arguments, envs_mjx.ALL_ENVS)
    except ValueError as error:  # ConfigError is one; the config constructors' checks are others
        _fail(path, f"{job.name}: {str(error).splitlines()[0]}")
