"""MEDAL's stored demonstrations (envs_mjx/demos): counts, success of every episode, checksums, errors.

Reads the committed files only (no rollouts, no JAX compiles): `make demos` regenerates them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import cached_env

from morefree_jax.baselines.medal import demos

COUNTS = {"tabletop": (12, 12), "sawyer_door": (5, 5), "point_umaze": (30, 0), "push": (30, 0),
          "pick_place": (30, 0), "push_hard": (30, 0), "pick_place_hard": (30, 0)}


@pytest.fixture(params=list(COUNTS))
def task(request):
    return request.param


def test_tasks_with_demos_are_the_counted_tasks():
    assert set(demos.tasks_with_demos()) == set(COUNTS)


def test_every_stored_episode_ends_in_its_first_success(task):
    env = cached_env(task)
    loaded = demos.load_demos(task, env)
    forward, reverse = COUNTS[task]
    assert set(loaded) == ({"forward", "reverse"} if reverse else {"forward"})
    for direction, count in zip(("forward", "reverse"), (forward, reverse), strict=True):
        if not count:
            continue
        demo = loaded[direction]
        assert int(demo.terminals.sum()) == count and demo.terminals[-1] == 1.0
        # Success recomputed here in numpy on the goal dims: only the terminal steps are successes.
        dims = np.asarray(env.goal_dims)
        distance = np.linalg.norm(demo.next_observations[:, dims] - demo.goals[:, dims], axis=-1)
        np.testing.assert_array_equal(distance < env.success_threshold, demo.terminals == 1.0)
        np.testing.assert_array_equal(demo.rewards, demo.terminals)
        assert demos.episode_problems(demo, env.goal_dims, env.success_threshold) == []
        lengths = np.diff(np.concatenate([[-1], np.flatnonzero(demo.terminals)]))
        assert lengths.max() <= env.eval_episode_length
        # Consecutive steps chain: each step starts where the previous one ended (within an episode).
        inside = demo.terminals[:-1] == 0.0
        np.testing.assert_array_equal(demo.observations[1:][inside], demo.next_observations[:-1][inside])
        assert all(a.dtype == np.float32 for a in demo)
        assert np.all(np.abs(demo.actions) <= 1.0)


def test_reverse_episodes_start_where_forward_ones_succeeded():
    for task in ("tabletop", "sawyer_door"):
        env = cached_env(task)
        loaded = demos.load_demos(task, env)
        first_steps = np.concatenate([[0], np.flatnonzero(loaded["reverse"].terminals)[:-1] + 1])
        starts = loaded["reverse"].observations[first_steps]
        dims = np.asarray(env.goal_dims)
        forward_goals = np.unique(loaded["forward"].goals[:, dims], axis=0)
        distance = np.linalg.norm(starts[:, None, dims] - forward_goals[None], axis=-1).min(axis=1)
        assert np.all(distance < env.success_threshold), (task, distance)


def copy_demos(tmp_path, task):
    for name in (f"{task}.npz", demos.CHECKSUMS):
        shutil.copy(demos.default_directory() / name, tmp_path / name)


def test_checksum_detects_a_changed_byte(tmp_path):
    copy_demos(tmp_path, "push")
    with np.load(tmp_path / "push.npz") as data:
        arrays = {key: data[key].copy() for key in data.files}
    raw = arrays["forward/actions"].view(np.uint8)
    raw[7] ^= 1  # one bit of one byte
    np.savez_compressed(tmp_path / "push.npz", **arrays)
    expected = r"push\.npz: arrays' sha256 .* differs from checksums\.json"
    with pytest.raises(ValueError, match=expected) as error:
        demos.load_demos("push", cached_env("push"), directory=tmp_path)
    assert "\n" not in str(error.value)


def test_wrong_shape_is_rejected_in_one_line(tmp_path):
    copy_demos(tmp_path, "push")
    loaded = demos.load_demos("push", cached_env("push"))
    short = {"forward": loaded["forward"]._replace(
        observations=loaded["forward"].observations[:, :10], goals=loaded["forward"].goals[:, :10],
        next_observations=loaded["forward"].next_observations[:, :10])}
    demos.write_demos("push", short, tmp_path)  # consistent checksum: the shape check must catch it
    with pytest.raises(ValueError) as error:
        demos.load_demos("push", cached_env("push"), directory=tmp_path)
    message = str(error.value)
    assert "\n" not in message
    assert message.endswith("push.npz: forward/observations has 20 columns, push needs 2*25=50"), message


def test_missing_file_is_rejected_in_one_line(tmp_path):
    with pytest.raises(ValueError, match=r"push\.npz: missing; regenerate it with `make demos ENV=push`$"):
        demos.load_demos("push", cached_env("push"), directory=tmp_path)


@pytest.mark.parametrize("task, expected", [("ant", "no demonstrations for ant"), ("reach", "unknown task")])
def test_ant_and_unknown_tasks_get_one_line(task, expected):
    with pytest.raises(ValueError) as error:
        demos.load_demos(task, env=None)
    message = str(error.value)
    assert expected in message and "\n" not in message
    assert "tasks with demonstrations: point_umaze, tabletop, sawyer_door, push" in message


def test_checksums_file_covers_exactly_the_stored_files():
    directory = demos.default_directory()
    recorded = json.loads((directory / demos.CHECKSUMS).read_text())
    assert set(recorded) == {f"{task}.npz" for task in COUNTS}
    for name in recorded:
        assert (directory / name).stat().st_size < 1_000_000


def test_importing_the_module_does_not_load_jax():
    code = "import sys; import morefree_jax.baselines.medal.demos; print('jax' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            env={"PYTHONPATH": "src:."})
    assert result.stdout.strip() == "False"
