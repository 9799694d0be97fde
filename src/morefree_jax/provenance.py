"""Which code produced a run: the git commit of this checkout, recorded in every run dir at each start.

    code_version()  # {"commit": "316523b...", "dirty": False} (commit None outside a git checkout)

`RunLogger` appends one line per start or resume to `<run_dir>/provenance.jsonl` (step, commit, dirty,
host, time), so a results table can name the commit of the code behind every number (experiments/plots.py).
"""

from __future__ import annotations

import functools
import pathlib
import subprocess

_REPO = pathlib.Path(__file__).resolve().parents[2]  # src/morefree_jax/ -> the checkout's root
RESULTS_DIR = "results"  # the repository's figures and tables (make plots OUT=results)


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(_REPO), *args], capture_output=True, text=True, timeout=10,
                              check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def code_version() -> dict:
    """{"commit": full sha or None, "dirty": tracked files differ from the commit (None if unknown)}.

    The figures and tables under results/ are outputs, not code: redrawing them while runs go on must not
    mark those runs' code as changed, so they are left out of the check."""
    commit = _git("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", f":(exclude){RESULTS_DIR}")
    return {"commit": commit, "dirty": None if status is None else bool(status)}
