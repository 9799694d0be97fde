"""Checkpoints of the WHOLE run state (agent, optimisers, replay, env state, planner, schedule, keys).

An orbax CheckpointManager under `<run_dir>/checkpoints/<step>/` holds two items per step: `state` (the run
state pytree: nested flax.struct dataclasses / dicts of arrays, raw uint32 PRNG keys included) and `meta`
(JSON: the caller's counters, the resolved config and its hash, a CRC32 per array). Orbax writes each step
into `<step>.orbax-checkpoint-tmp-<time>` and renames it when complete, so a process killed mid-write
leaves only a tmp dir, which the listing ignores and the next manager removes. After the rename we add
`files.json` (size and CRC32 of every file) so a later truncation or bit flip is reported with the file
name; the per-array CRCs catch anything the file check cannot (and cover checkpoints killed before
`files.json` was written).

    checkpointer = RunCheckpointer(run_dir, config_dict, every_steps=10_000, keep=3)
    restored = checkpointer.latest_valid(template_state)   # None on a fresh run dir
    ...
    checkpointer.save(step, state, {"env_steps": step})     # every `every_steps`; force=True at exit
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import pathlib
import shutil
import signal
import threading
import warnings
import zlib
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

from morefree_jax.legacy import LEGACY_VALUES

FILE_MANIFEST = "files.json"
QUARANTINE_DIR = "checkpoints_bad"


class CheckpointError(RuntimeError):
    """No checkpoint in the run dir loads and verifies."""


class ConfigMismatchError(ValueError):
    """The run dir was made with a different config."""


class CheckpointWarning(UserWarning):
    """A bad checkpoint was skipped in favour of an older good one."""


def _one_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0][:300] if text else type(error).__name__


class Restored(NamedTuple):
    step: int
    state: Any
    metadata: dict  # the caller's metadata dict as saved


def config_hash(config_dict: dict) -> str:
    return hashlib.sha256(json.dumps(config_dict, sort_keys=True).encode()).hexdigest()[:16]


def _flatten_dict(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten_dict(value, name + "."))
        else:
            flat[name] = value
    return flat


def _as_json(tree: dict) -> dict:
    return json.loads(json.dumps(tree))


def config_differences(stored: dict, current: dict, ignore: tuple[str, ...] = ()) -> list[str]:
    """Dotted keys whose values differ between two nested config dicts (missing on one side counts). Both
    are compared in their JSON form (tuples and lists are equal)."""
    current_flat = _flatten_dict(_as_json(current))
    stored_flat = _flatten_dict(_as_json(stored))
    keys = sorted(set(stored_flat) | set(current_flat))
    absent = "<absent>"
    return [k for k in keys if k not in ignore
            and stored_flat.get(k, LEGACY_VALUES.get(k, absent)) != current_flat.get(k, absent)]


def refuse_config_change(stored: dict, current: dict, where: str, ignore: tuple[str, ...] = ()) -> None:
    """Raises ConfigMismatchError naming the differing keys (with both values) if the configs differ."""
    differing = config_differences(stored, current, ignore)
    if differing:
        current_flat, stored_flat = _flatten_dict(_as_json(current)), _flatten_dict(_as_json(stored))
        absent = "<absent>"
        shown = ", ".join(f"{k}: {stored_flat.get(k, LEGACY_VALUES.get(k, absent))!r} -> "
                          f"{current_flat.get(k, absent)!r}" for k in differing[:8])
        more = f" (+{len(differing) - 8} more)" if len(differing) > 8 else ""
        raise ConfigMismatchError(
            f"{where} was made with a different config ({shown}{more}); use a new run dir or the same config"
        )


def array_checksums(tree: Any) -> dict[str, str]:
    """'crc32:dtype:shape' of every array leaf, keyed by its path in the tree."""
    sums = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        array = np.ascontiguousarray(np.asarray(leaf))
        sums[jax.tree_util.keystr(path)] = f"{zlib.crc32(array.tobytes()):08x}:{array.dtype}:{array.shape}"
    return sums


def _storable(tree: Any) -> dict:
    """The tree's non-empty array leaves as a flat dict {"leaf_<index>": array}. Orbax cannot save
    zero-size arrays (mjx.Data has some) and flat simple names keep odd tree paths out of file names."""
    leaves = jax.tree_util.tree_leaves(tree)
    return {f"leaf_{i:05d}": leaf for i, leaf in enumerate(leaves) if np.size(leaf) > 0}


def _rebuild(template: Any, stored: dict) -> Any:
    """Inverse of _storable: the template's structure, stored leaves, the template's zero-size leaves.

    Restored arrays are made uncommitted (like the outputs of a jitted init), so that a jitted function
    fed a restored state hits the same compiled entry as with a fresh state instead of tracing again."""
    leaves, treedef = jax.tree_util.tree_flatten(template)
    key = "leaf_{:05d}".format
    leaves = [jax.device_put(np.asarray(stored[key(i)])) if key(i) in stored else leaf
              for i, leaf in enumerate(leaves)]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _file_manifest(step_dir: pathlib.Path) -> dict[str, list]:
    manifest = {}
    for path in sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != FILE_MANIFEST):
        data = path.read_bytes()
        manifest[str(path.relative_to(step_dir))] = [len(data), f"{zlib.crc32(data):08x}"]
    return manifest


def _check_files(step_dir: pathlib.Path) -> None:
    """Compares the step's files with files.json; raises naming the first bad file. No manifest: no check."""
    manifest_path = step_dir / FILE_MANIFEST
    if not manifest_path.exists():
        return
    expected = json.loads(manifest_path.read_text())
    for name, (size, crc) in expected.items():
        path = step_dir / name
        if not path.exists():
            raise CheckpointError(f"file {path} is missing")
        data = path.read_bytes()
        if len(data) != size:
            raise CheckpointError(f"file {path} is truncated or resized ({len(data)} bytes, expected {size})")
        if f"{zlib.crc32(data):08x}" != crc:
            raise CheckpointError(f"file {path} is corrupted (checksum mismatch)")


@contextlib.contextmanager
def _interrupts_deferred():
    """A Ctrl-C during a save lets the save finish, then is handed to the SIGINT handler that was in place
    (Python's default raises KeyboardInterrupt; a training loop's own handler may stop after the chunk).
    Main thread only; elsewhere, and for SIGKILL, orbax's tmp-dir + rename keeps the dir consistent."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        if callable(previous) and previous is not signal.default_int_handler:
            previous(signal.SIGINT, None)
        else:
            raise KeyboardInterrupt


def _write_json_atomically(path: pathlib.Path, payload: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(payload))
        with open(tmp, "rb") as handle:
            os.fsync(handle.fileno())
    except OSError:
        tmp.unlink(missing_ok=True)  # a failed write (full disk) leaves no temporary file
        raise
    os.replace(tmp, path)


class RunCheckpointer:
    """Saves and restores the whole run state under `<run_dir>/checkpoints`, keeping the last `keep`.

    config_dict: the resolved run config (JSON-able); a run dir whose checkpoints carry a different config
    is refused (ConfigMismatchError) except for keys in `ignore_config_keys` (dotted).
    """

    def __init__(self, run_dir, config_dict: dict, every_steps: int, keep: int = 3,
                 ignore_config_keys: tuple[str, ...] = (), read_only: bool = False):
        if every_steps <= 0 or keep <= 0:
            raise ValueError(f"checkpoint every_steps and keep must be positive, got {every_steps}, {keep}")
        self.run_dir = pathlib.Path(run_dir)
        self.directory = (self.run_dir / "checkpoints").absolute()
        self.config_dict = config_dict
        self.every_steps = every_steps
        self.ignore_config_keys = ignore_config_keys
        # read_only (evaluation beside a live run): no tmp-dir cleanup, no quarantine moves.
        self.read_only = read_only
        options = ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=not read_only, cleanup_tmp_directories=not read_only,
            enable_async_checkpointing=False, read_only=read_only,
        )
        self.manager = ocp.CheckpointManager(self.directory, options=options)

    def all_steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def save(self, step: int, state: Any, metadata: dict | None = None, force: bool = False) -> bool:
        """Saves at multiples of every_steps (or always with force); returns whether it saved."""
        if not force and step % self.every_steps != 0:
            return False
        if step in self.manager.all_steps():
            return False  # the exit save right after a periodic one
        meta = {
            "user": metadata or {},
            "config": self.config_dict,
            "config_hash": config_hash(self.config_dict),
            "checksums": array_checksums(state),
        }
        self._check_space(step, state)
        with _interrupts_deferred():
            items = ocp.args.Composite(state=ocp.args.StandardSave(_storable(state)),
                                       meta=ocp.args.JsonSave(meta))
            try:
                self.manager.save(step, args=items, force=True)
                self.manager.wait_until_finished()
            except Exception as error:  # noqa: BLE001 - a failed save leaves no partial step behind
                for partial in self.directory.glob(f"{step}.orbax-checkpoint-tmp*"):
                    shutil.rmtree(partial, ignore_errors=True)
                if "No space left on device" in str(error):
                    raise OSError(errno.ENOSPC, "No space left on device", str(self.directory / str(step))) \
                        from None
                raise
            step_dir = self.directory / str(step)
            _write_json_atomically(step_dir / FILE_MANIFEST, _file_manifest(step_dir))
        return True

    def _check_space(self, step: int, state: Any) -> None:
        """OSError(ENOSPC) naming the step's dir when the free space cannot hold the checkpoint (its arrays
        plus 10% and 1 MiB): a clean refusal instead of a write that fails halfway (orbax's failure then
        prints hundreds of tracebacks from its writer threads)."""
        need = 1.1 * sum(np.size(x) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(state))
        need += 2**20
        free = shutil.disk_usage(self.directory).free
        if need > free:
            message = f"No space left on device: the checkpoint needs ~{need / 2**20:.1f} MiB"
            raise OSError(errno.ENOSPC, message, str(self.directory / str(step)))

    def _restore_verified(self, step: int, target: Any) -> Restored:
        step_dir = self.directory / str(step)
        _check_files(step_dir)
        restored = self.manager.restore(
            step, args=ocp.args.Composite(state=ocp.args.StandardRestore(_storable(target)),
                                          meta=ocp.args.JsonRestore())
        )
        meta, state = restored["meta"], _rebuild(target, restored["state"])
        refuse_config_change(meta["config"], self.config_dict, f"checkpoint {step_dir}",
                             self.ignore_config_keys)
        stored_sums, actual_sums = meta["checksums"], array_checksums(state)
        bad = [k for k in stored_sums if actual_sums.get(k) != stored_sums[k]]
        if bad or set(actual_sums) != set(stored_sums):
            raise CheckpointError(f"arrays of {step_dir}/state fail their checksums: {bad[:5]}")
        return Restored(step, state, meta["user"])

    def restore_step(self, step: int, target: Any) -> Restored:
        """The checkpoint of `step`, verified (CheckpointError / ConfigMismatchError when it is not good)."""
        self.manager.reload()
        if step not in self.manager.all_steps():
            raise CheckpointError(f"no checkpoint {self.directory / str(step)}")
        try:
            return self._restore_verified(step, target)
        except (ConfigMismatchError, CheckpointError):
            raise
        except Exception as error:  # noqa: BLE001 - any failure to load means "not a good checkpoint"
            message = f"checkpoint {self.directory / str(step)} is bad ({_one_line(error)})"
            raise CheckpointError(message) from None

    def latest_valid(self, target: Any) -> Restored | None:
        """Restores the newest checkpoint that loads and verifies, into the structure of `target`.

        Newer bad checkpoints are moved to `<run_dir>/checkpoints_bad/` with a warning naming them (nothing
        is deleted). Returns None when the run dir has no checkpoint; raises CheckpointError (one line) if
        none is good, ConfigMismatchError if the checkpoints were made with a different config.
        """
        self.manager.reload()
        steps = self.all_steps()
        failures = []
        for step in reversed(steps):
            try:
                restored = self._restore_verified(step, target)
            except ConfigMismatchError:
                raise
            except Exception as error:  # noqa: BLE001 - any failure to load means "not a good checkpoint"
                failures.append((step, _one_line(error)))
                continue
            for bad_step, reason in failures:
                bad_dir = self.directory / str(bad_step)
                moved = "" if self.read_only else f"; moved it to {self._quarantine(bad_step)}"
                message = f"checkpoint {bad_dir} is bad ({reason}); using checkpoint {step} instead{moved}"
                warnings.warn(message, CheckpointWarning, stacklevel=2)
            return restored
        if not steps:
            return None
        detail = "; ".join(f"{self.directory / str(s)}: {r}" for s, r in failures)
        raise CheckpointError(f"no valid checkpoint in {self.directory} ({detail})")

    def _quarantine(self, step: int) -> pathlib.Path:
        destination = self.run_dir / QUARANTINE_DIR / str(step)
        suffix = 0
        while destination.exists():
            suffix += 1
            destination = self.run_dir / QUARANTINE_DIR / f"{step}.{suffix}"
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(self.directory / str(step)), str(destination))
        self.manager.reload()
        return destination

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def latest_valid(
    run_dir, target: Any, config_dict: dict, ignore_config_keys: tuple[str, ...] = ()
) -> Restored | None:
    """Read-only RunCheckpointer.latest_valid (for evaluation scripts; safe beside a live run)."""
    checkpointer = RunCheckpointer(
        run_dir, config_dict, every_steps=1, ignore_config_keys=ignore_config_keys, read_only=True
    )
    try:
        return checkpointer.latest_valid(target)
    finally:
        checkpointer.close()


def check_run_dir_config(run_dir, config_dict: dict, ignore: tuple[str, ...] = ()) -> dict[str, list]:
    """Refuses a run dir whose config.json differs from `config_dict` outside the `ignore` keys; returns the
    ignored keys that did change, {key: [stored, new]} (empty for a new run dir)."""
    path = pathlib.Path(run_dir) / "config.json"
    if not path.exists():
        return {}
    stored = json.loads(path.read_text())
    refuse_config_change(stored, config_dict, f"run dir {run_dir}", ignore)
    stored_flat, current_flat = _flatten_dict(_as_json(stored)), _flatten_dict(_as_json(config_dict))
    changed = config_differences(stored, config_dict)
    return {key: [stored_flat.get(key), current_flat.get(key)] for key in changed}
