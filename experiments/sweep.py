"""A grid of experiments as Ray tasks (`make sweep GRID=experiments/grids/paper.toml`).

    python -m experiments.sweep grid=experiments/grids/debug.toml [progress_every=60] [plots=1]

The grid (experiments/sweep_grid.py says its keys) expands to one job per (task, agent), each running its
seeds in one program (`experiments.train ... seeds=...`) with run dirs <runs>/<task>/<agent>/seed<k>.
Jobs run as Ray tasks: on a Ray instance started on this machine (jobs packed by the CPUs they ask for,
one each by default, each pinned to a core of its own), or on the cluster RAY_ADDRESS names, with a GPU
per job where the cluster has GPUs. Re-running the same command resumes: finished jobs are skipped, the
others resume from their checkpoints. A job that fails is run once more; if it fails again, it is reported
with its log's last lines and the others go on. A progress table (job, state, steps reached, env steps/s,
last evaluation) is printed every `progress_every` seconds; at the end the figures and tables of every
run below <runs> go to <runs>/results. Ctrl-C or SIGTERM stops every job (each keeps its last checkpoint).
Exit codes: 0 all done, 1 a job failed twice, 2 bad input (one line), 130 stopped.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time

from experiments import plots
from experiments.cli import REQUIRED, KeyValueError, parse_keys
from experiments.experiment import STOPPED_EXIT, stop_on_signals
from experiments.sweep_grid import REPO, GridError, Job, load_grid
from experiments.sweep_progress import Progress

INSTALL_HINT = "make sweep needs Ray: make install SWEEP=1 (or pip install -e '.[sweep]')"
DONE_FILE = "sweep_done.json"  # in a job's directory: the train arguments it finished with
ATTEMPTS = 2  # a failed job runs once more
LOG_TAIL_LINES = 15


def finished(job: Job) -> bool:
    """Whether a sweep already ran `job` to its end with these train arguments."""
    path = job.directory / DONE_FILE
    try:
        return json.loads(path.read_text())["arguments"] == job.train_arguments()
    except (OSError, ValueError, KeyError):
        return False


def _mark_finished(job: Job) -> None:
    (job.directory / DONE_FILE).write_text(json.dumps({"arguments": job.train_arguments()}) + "\n")


def log_tail(job: Job, lines: int = LOG_TAIL_LINES) -> str:
    try:
        return "\n".join(job.log.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def _job_env() -> dict[str, str]:
    """The train processes' environment: this checkout importable, jemalloc preloaded where installed."""
    from morefree_jax import runtime

    return {"PYTHONPATH": f"{REPO / 'src'}:{REPO}", **runtime.allocator_env()}


def _gpus_per_job(grid, ray) -> int:
    if grid.gpus_per_job != "auto":
        return grid.gpus_per_job
    return 1 if ray.cluster_resources().get("GPU", 0) > 0 else 0


class Sweep:
    """Submits the jobs, retries a failed one once, and collects the outcomes."""

    def __init__(self, grid, ray, progress: Progress):
        from experiments.sweep_job import run_job

        self.ray, self.progress = ray, progress
        gpus = _gpus_per_job(grid, ray)
        self.remote = ray.remote(run_job).options(num_cpus=grid.cpus_per_job, num_gpus=gpus, max_retries=0)
        self.cpus, self.env = grid.cpus_per_job, _job_env()
        self.niceness = os.getpriority(os.PRIO_PROCESS, 0)
        self.pending: dict = {}  # Ray reference -> (job, attempt)
        self.failed: list[Job] = []

    def submit(self, job: Job, attempt: int = 1) -> None:
        job.directory.mkdir(parents=True, exist_ok=True)
        reference = self.remote.remote(job.command(), str(job.log), str(REPO), self.env, self.cpus,
                                       self.niceness)
        self.pending[reference] = (job, attempt)
        self.progress.submitted(job, attempt)

    def _outcome(self, reference) -> int | str:
        try:
            return self.ray.get(reference)
        except self.ray.exceptions.RayError as error:  # the worker or node died
            return f"Ray error: {str(error).splitlines()[0]}"

    def collect(self, timeout_s: float) -> None:
        """Waits up to `timeout_s` for jobs to end; marks, retries or reports each that did."""
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=timeout_s)
        for reference in ready:
            job, attempt = self.pending.pop(reference)
            code = self._outcome(reference)
            if code == 0:
                _mark_finished(job)
                self.progress.ended(job, "done")
            elif attempt < ATTEMPTS:
                print(f"{job.name} failed ({_said(code)}); running it once more", flush=True)
                self.submit(job, attempt + 1)
            else:
                self.failed.append(job)
                self.progress.ended(job, f"failed ({_said(code)})")
                print(f"{job.name} failed twice ({_said(code)}); the last lines of {job.log}:\n"
                      f"{log_tail(job)}", file=sys.stderr, flush=True)

    def run(self, jobs, progress_every: float) -> None:
        for job in jobs:
            self.submit(job)
        last_print = time.monotonic()
        while self.pending:
            self.collect(timeout_s=min(1.0, progress_every))
            if time.monotonic() - last_print >= progress_every:
                last_print = time.monotonic()
                print(self.progress.table(), flush=True)


def run_jobs(grid, jobs, ray, progress_every: float) -> list[Job]:
    """Runs `jobs` on Ray to their ends; the jobs that failed twice. Ctrl-C or SIGTERM: KeyboardInterrupt,
    after Ray is shut down (its workers end, and their train processes with them; checkpoints stay)."""
    if os.environ.get("RAY_ADDRESS"):  # the cluster's own settings
        ray.init(log_to_driver=False)
    else:  # a Ray instance of this program's own, without the dashboard's processes
        ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False)
    progress = Progress(grid.jobs)
    sweep = Sweep(grid, ray, progress)
    previous = stop_on_signals()  # `kill` of a sweep in the background stops it as Ctrl-C does
    try:
        sweep.run(jobs, progress_every)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        ray.shutdown()
    print(progress.table(), flush=True)
    return sweep.failed


def _said(code) -> str:
    return f"exit {code}" if isinstance(code, int) else code


def _parse(argv):
    args = parse_keys(argv, {"grid": REQUIRED, "progress_every": 60.0, "plots": True})
    if args["progress_every"] <= 0:
        raise KeyValueError(f"progress_every must be > 0 seconds, got {args['progress_every']}")
    return args


def main(argv: list[str]) -> int:
    if any(arg in ("-h", "--help") for arg in argv):
        print(__doc__)
        return 0
    try:
        args = _parse(argv)
        grid = load_grid(args["grid"])
    except (KeyValueError, GridError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        import ray
    except ImportError:
        print(f"error: {INSTALL_HINT}", file=sys.stderr)
        return 2
    todo = [job for job in grid.jobs if not finished(job)]
    for job in grid.jobs:
        if job not in todo:
            print(f"{job.name}: finished before, skipped", flush=True)
    failed = []
    if todo:
        try:
            failed = run_jobs(grid, todo, ray, args["progress_every"])
        except KeyboardInterrupt:
            print("stopped; every job keeps its last checkpoint; re-run the same command to resume",
                  file=sys.stderr)
            return STOPPED_EXIT
    if failed:
        print(f"{len(failed)} job(s) failed: {', '.join(job.name for job in failed)}", file=sys.stderr)
    if args["plots"]:
        agents = sorted({job.agent for job in grid.jobs})
        plots.main([f"runs={grid.runs}", f"out={grid.runs / 'results'}", f"agents={','.join(agents)}"])
    return 1 if failed else 0

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
