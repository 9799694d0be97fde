"""One writer per run directory: an exclusive lock held for the whole run.

    with RunDirLock(run_dir):          # RunDirLockedError (one line, naming the owner) if another process
        ...                            # holds it; released on exit, also when the process dies

The lock is `<run_dir>/.lock`, held with `fcntl.flock`, which the kernel releases when the owning process
dies (SIGKILL included), so a lock left by a dead run is never mistaken for a live one. The file also names
its owner (pid, host, start time) for the error message; when a new run finds a previous owner's name in a
lock nobody holds, it says it is taking over from that (dead) process. Readers (`evaluate`, `plots`) do not
lock. flock does not reach across machines on every network file system: one host per run dir.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import pathlib
import shutil
import socket
import sys
import time

LOCK_FILE = ".lock"


class RunDirError(RuntimeError):
    """The run directory cannot be used: another live process writes it, or it cannot be written."""


class RunDirLockedError(RunDirError):
    """Another live process is writing this run directory (one-line message naming it)."""


def _owner_text(text: str) -> str:
    try:
        owner = json.loads(text)
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(owner["time"]))
        return f"pid {owner['pid']} on {owner['host']} (since {started})"
    except (ValueError, KeyError, TypeError):
        return "another process"


class RunDirLock:
    """Exclusive lock on a run dir (module docstring). `created`: this lock made the directory."""

    def __init__(self, run_dir):
        self.run_dir = pathlib.Path(run_dir)
        self.created = False
        self._file = None

    def acquire(self) -> RunDirLock:
        self.created = not self.run_dir.exists()
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            file = open(self.run_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held open for the whole run
        except OSError as error:
            raise RunDirError(f"cannot write to run dir {self.run_dir} ({error.strerror})") from None
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            file.seek(0)
            owner = _owner_text(file.read())
            file.close()
            raise RunDirLockedError(f"run dir {self.run_dir} is in use by {owner}; stop that run first, or "
                                    "give another run_dir") from None
        file.seek(0)
        previous = file.read().strip()
        if previous:
            print(f"taking over the lock of {self.run_dir} from {_owner_text(previous)}, which is no longer "
                  "running", file=sys.stderr, flush=True)
        self._file = file
        try:
            file.seek(0)
            file.truncate()
            file.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()}))
            file.flush()
        except OSError as error:  # e.g. a full disk
            self.release()
            raise RunDirError(f"cannot write to run dir {self.run_dir} ({error.strerror}; "
                              f"{shutil.disk_usage(self.run_dir).free / 2**20:.1f} MiB free)") from None
        return self

    def release(self) -> None:
        """Empties and unlocks the lock file (an empty lock file means: released cleanly)."""
        file, self._file = self._file, None
        if file is None:
            return
        with contextlib.suppress(OSError, ValueError):  # a full disk may refuse even the truncation
            file.seek(0)
            file.truncate()
            file.flush()
        with contextlib.suppress(OSError, ValueError):
            fcntl.flock(file, fcntl.LOCK_UN)
        with contextlib.suppress(OSError, ValueError):
            file.close()

    def remove_if_unused(self) -> None:
        """After a refused start: deletes the run dir this lock created if nothing but the lock is in it."""
        self.release()
        if self.created:
            with contextlib.suppress(OSError):
                (self.run_dir / LOCK_FILE).unlink()
                self.run_dir.rmdir()  # fails (kept) when anything else was written

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
