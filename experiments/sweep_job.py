"""The body of one sweep job, as a Ray task runs it: the job's train command as a child process, its output
appended to the job's train.log, pinned to a core of its own where one is free, and killed with the Ray
worker that started it (a driver killed or stopped takes its jobs with it; their checkpoints stay, and
the next sweep resumes them).

    code = run_job(command, "runs/x/morefree/train.log", repo, {"PYTHONPATH": ...})   # the exit code
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import os
import pathlib
import signal
import subprocess
import tempfile
import time

PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent dies
CORE_LOCKS = pathlib.Path(tempfile.gettempdir()) / "morefree_jax_sweep_cores"


@contextlib.contextmanager
def claimed_core():
    """A core of this machine no other sweep job holds (a flock per core, released when the job ends or its
    worker dies), or None when every core is taken (jobs asking for several CPUs, or more jobs than cores).
    Ray packs one-CPU jobs by count only; pinning keeps two jobs from sharing a core's time."""
    CORE_LOCKS.mkdir(parents=True, exist_ok=True)
    for core in sorted(os.sched_getaffinity(0)):
        handle = open(CORE_LOCKS / f"core{core}.lock", "w")  # noqa: SIM115 (held until the job ends)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            continue
        try:
            yield core
        finally:
            handle.close()
        return
    yield None


def _child_setup(core: int | None, niceness: int | None):
    def setup():
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)  # die with the worker
        if core is not None:
            os.sched_setaffinity(0, {core})
        if niceness is not None:  # Ray starts its workers niced (15): back to the driver's, where allowed
            with contextlib.suppress(PermissionError):
                os.setpriority(os.PRIO_PROCESS, 0, niceness)
    return setup


def run_job(command: list[str], log: str, cwd: str, env: dict[str, str], cpus: int = 1,
            niceness: int | None = None) -> int:
    """Runs `command` to its end; its exit code. One CPU asked: pinned to a free core. niceness: the
    process's (the driver's, on this machine), where the user may set it."""
    with claimed_core() if cpus == 1 else contextlib.nullcontext() as core, open(log, "a") as output:
        where = f"core {core}" if core is not None else "no pinned core"
        output.write(f"# sweep job on {os.uname().nodename}, {where}, "
                     f"{time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(command[1:])}\n")
        output.flush()
        process = subprocess.Popen(command, cwd=cwd, env={**os.environ, **env}, stdout=output,
                                   stderr=subprocess.STDOUT, preexec_fn=_child_setup(core, niceness))
        return process.wait()
