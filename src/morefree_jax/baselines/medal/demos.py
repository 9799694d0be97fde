"""MEDAL's demonstrations: loading, checking and writing the stored files (numpy only; no JAX at import).

The originals (EARL's pickles; for PointUMaze and Fetch, 30 episodes of a trained MoReFree agent) are not
available, so ours are scripted (envs_mjx/scripted.py, rolled out by `make demos`). One file per task,
envs_mjx/demos/<task>.npz, holds EARL's flat transition fields per direction, float32:

    forward/observations       (N, 2*O)  observation ++ goal (EARL keeps the goal inside the observation)
    forward/actions            (N, A)
    forward/rewards            (N,)      sparse {0, 1}: success of the next observation
    forward/terminals          (N,)      1.0 on the last step of each episode (its first success)
    forward/next_observations  (N, 2*O)  next observation ++ goal

and the same under reverse/ where the task has reverse demonstrations (tabletop, sawyer_door).
envs_mjx/demos/checksums.json records a sha256 of each file's arrays (`array_checksum`).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import pathlib
import zipfile
from typing import NamedTuple

import numpy as np

# task -> {direction: episodes}; MEDAL's counts (docs/baselines.md, "Demonstrations").
DEMO_COUNTS: dict[str, dict[str, int]] = {
    "point_umaze": {"forward": 30},
    "tabletop": {"forward": 12, "reverse": 12},
    "sawyer_door": {"forward": 5, "reverse": 5},
    "push": {"forward": 30},
    "pick_place": {"forward": 30},
    "push_hard": {"forward": 30},
    "pick_place_hard": {"forward": 30},
}
CHECKSUMS = "checksums.json"


class DemoSet(NamedTuple):
    """Flat transitions of one direction, numpy float32; N transitions."""

    observations: np.ndarray  # (N, O)  the env observation alone
    goals: np.ndarray  # (N, O)  the goal slot (the second half of EARL's observation)
    actions: np.ndarray  # (N, A)
    rewards: np.ndarray  # (N,)
    terminals: np.ndarray  # (N,)
    next_observations: np.ndarray  # (N, O)


def tasks_with_demos() -> tuple[str, ...]:
    return tuple(DEMO_COUNTS)


def default_directory() -> pathlib.Path:
    """envs_mjx/demos, found without importing envs_mjx (whose import loads JAX and MuJoCo)."""
    spec = importlib.util.find_spec("envs_mjx")
    return pathlib.Path(next(iter(spec.submodule_search_locations))) / "demos"


def shown(path: pathlib.Path) -> str:
    """`path` as messages show it: relative to the repository (envs_mjx/demos/push.npz) where it is inside."""
    root = default_directory().parent.parent
    try:
        return str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path)


def array_checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the arrays in sorted key order: key, dtype, shape, then the C-order bytes of each, so it
    depends on the contents only (not on the npz's compression or zip timestamps)."""
    digest = hashlib.sha256()
    for key in sorted(arrays):
        array = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def to_arrays(direction: str, demo: DemoSet) -> dict[str, np.ndarray]:
    """EARL's flat fields of one direction, goal appended to both observations."""
    return {
        f"{direction}/observations": np.concatenate([demo.observations, demo.goals], axis=1),
        f"{direction}/actions": demo.actions,
        f"{direction}/rewards": demo.rewards,
        f"{direction}/terminals": demo.terminals,
        f"{direction}/next_observations": np.concatenate([demo.next_observations, demo.goals], axis=1),
    }


def from_arrays(direction: str, arrays: dict[str, np.ndarray]) -> DemoSet:
    observations = arrays[f"{direction}/observations"]
    size = observations.shape[1] // 2
    return DemoSet(
        observations=observations[:, :size],
        goals=observations[:, size:],
        actions=arrays[f"{direction}/actions"],
        rewards=arrays[f"{direction}/rewards"],
        terminals=arrays[f"{direction}/terminals"],
        next_observations=arrays[f"{direction}/next_observations"][:, :size],
    )


def write_npz(path: pathlib.Path, arrays: dict[str, np.ndarray]) -> None:
    """A compressed .npz that np.load reads, byte-identical for identical arrays: np.savez stamps each
    member with the current time, so regenerated files would differ in git without any change."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key in sorted(arrays):
            member = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            member.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(member, "w") as stream:
                np.lib.format.write_array(stream, np.ascontiguousarray(arrays[key]), allow_pickle=False)


def write_demos(task: str, demos: dict[str, DemoSet], directory: pathlib.Path | None = None) -> pathlib.Path:
    """Writes <directory>/<task>.npz (float32) and records its checksum in <directory>/checksums.json."""
    directory = pathlib.Path(directory or default_directory())
    directory.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for direction, demo in demos.items():
        arrays.update(to_arrays(direction, demo))
    arrays = {key: np.asarray(value, np.float32) for key, value in arrays.items()}
    path = directory / f"{task}.npz"
    write_npz(path, arrays)
    checksums = read_checksums(directory)
    checksums[path.name] = array_checksum(arrays)
    (directory / CHECKSUMS).write_text(json.dumps(dict(sorted(checksums.items())), indent=2) + "\n")
    return path


def read_checksums(directory: pathlib.Path) -> dict[str, str]:
    path = pathlib.Path(directory) / CHECKSUMS
    return json.loads(path.read_text()) if path.exists() else {}


def valid_tasks_line() -> str:
    return f"tasks with demonstrations: {', '.join(DEMO_COUNTS)}"


def demo_path(task: str, directory: pathlib.Path | None = None) -> pathlib.Path:
    """The task's file; ValueError (one line) for ant and unknown tasks."""
    if task == "ant":
        raise ValueError(f"there are no demonstrations for ant (no MEDAL on Ant); {valid_tasks_line()}")
    if task not in DEMO_COUNTS:
        raise ValueError(f"unknown task {task!r}: no demonstrations; {valid_tasks_line()}")
    return pathlib.Path(directory or default_directory()) / f"{task}.npz"


def expected_shapes(task: str, observation_size: int, action_size: int) -> dict[str, tuple[int | None, ...]]:
    """{key: shape} of a task's arrays, None standing for the number of transitions."""
    shapes = {}
    for direction in DEMO_COUNTS[task]:
        both = 2 * observation_size
        shapes |= {f"{direction}/observations": (None, both), f"{direction}/actions": (None, action_size),
                   f"{direction}/rewards": (None,), f"{direction}/terminals": (None,),
                   f"{direction}/next_observations": (None, both)}
    return shapes


def shape_problem(task: str, arrays: dict[str, np.ndarray], env) -> str | None:
    """What is wrong with the keys, dtypes or shapes of a task's arrays, or None."""
    expected = expected_shapes(task, env.observation_size, env.action_size)
    if set(arrays) != set(expected):
        return f"has keys {sorted(arrays)}, {task} needs {sorted(expected)}"
    size = env.observation_size
    rule = {"observations": f"2*{size}={2 * size}", "actions": str(env.action_size)}
    for key, shape in expected.items():
        array, field = arrays[key], key.split("/")[1]
        if array.dtype != np.float32:
            return f"{key} is {array.dtype}, needs float32"
        if array.ndim != len(shape):
            return f"{key} has {array.ndim} dimensions, needs {len(shape)}"
        if len(shape) == 2 and array.shape[1] != shape[1]:
            return f"{key} has {array.shape[1]} columns, {task} needs {rule[field.removeprefix('next_')]}"
        direction = key.split("/")[0]
        rows = len(arrays[f"{direction}/terminals"])
        if len(array) != rows:
            return f"{key} has {len(array)} rows, {direction}/terminals has {rows}"
    for direction, count in DEMO_COUNTS[task].items():
        episodes = int(arrays[f"{direction}/terminals"].sum())
        if episodes != count:
            return f"{direction} has {episodes} episodes, {task} needs {count}"
    return None


def load_demos(task: str, env, directory: pathlib.Path | str | None = None) -> dict[str, DemoSet]:
    """{"forward": DemoSet, ["reverse": DemoSet]} of `task`, checked against checksums.json (in the same
    directory) and against env.observation_size / env.action_size. Any problem raises ValueError with one
    line naming the file, what is wrong and what is valid. `directory` defaults to envs_mjx/demos."""
    path = demo_path(task, directory)
    if not path.exists():
        raise ValueError(f"{shown(path)}: missing; regenerate it with `make demos ENV={task}`")
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    recorded = read_checksums(path.parent).get(path.name)
    actual = array_checksum(arrays)
    if recorded != actual:
        raise ValueError(
            f"{shown(path)}: arrays' sha256 {actual[:12]}... differs from {CHECKSUMS}'s "
            f"{(recorded or 'none')[:12]}...; regenerate it with `make demos ENV={task}`"
        )
    problem = shape_problem(task, arrays, env)
    if problem:
        raise ValueError(f"{shown(path)}: {problem}")
    return {direction: from_arrays(direction, arrays) for direction in DEMO_COUNTS[task]}


def episode_problems(demo: DemoSet, goal_dims, threshold: float) -> list[str]:
    """Checks each episode in numpy: the terminal step's next observation is a success, no earlier one
    is, the goal is constant within the episode and rewards equal the success. Returns what is wrong."""
    dims = np.asarray(goal_dims)
    distance = np.linalg.norm(demo.next_observations[:, dims] - demo.goals[:, dims], axis=-1)
    success = distance < np.float32(threshold)
    problems = []
    ends = np.flatnonzero(demo.terminals == 1.0)
    if len(ends) == 0 or ends[-1] != len(demo.terminals) - 1:
        problems.append("the last transition is not terminal")
    differ = np.flatnonzero(success != (demo.terminals == 1.0))
    if len(differ):
        problems.append(f"success and terminals differ at steps {differ[:5].tolist()}")
    if not np.array_equal(demo.rewards, success.astype(np.float32)):
        problems.append("rewards differ from the success of the next observation")
    starts = np.concatenate([[0], ends[:-1] + 1])
    for start, end in zip(starts, ends, strict=True):
        if not np.all(demo.goals[start : end + 1] == demo.goals[start]):
            problems.append(f"the goal changes within the episode at steps {start}..{end}")
    return problems
