"""experiments/analysis/goal_probe.py: the line of probe positions, the probe observations, the report, and
a probe of a tiny run's checkpoint."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from envs_mjx.normalise import NormalisedObservations
from experiments.analysis import goal_probe
from morefree_jax import driver
from tests.run_helpers import CHUNK, debug_config, debug_programs

PREFILL = 20  # run_helpers.DEBUG_ARGS


def test_the_line_runs_from_the_goal_to_the_end_evenly():
    positions = goal_probe.line_positions(np.array([0.0, 8.0]), np.array([1.0, 9.5]), 4)
    np.testing.assert_allclose(positions, [[0.0, 8.0], [1 / 3, 8.5], [2 / 3, 9.0], [1.0, 9.5]])


def test_a_probe_is_the_goal_observation_moved_in_its_goal_dims_only():
    goal = np.array([0.0, 8.0, 0.3, 0.1, 0.2, 0.5])
    probes = goal_probe.probe_observations(goal, (0, 1), np.array([[1.0, 2.0], [3.0, 4.0]]))
    np.testing.assert_array_equal(probes[:, :2], [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_allclose(probes[:, 2:], np.repeat(goal[None, 2:], 2, axis=0), rtol=1e-6)


def test_only_the_episodes_of_the_first_goal_are_kept():
    goals = np.array([[0.0, 8.0], [1.0, 1.0], [0.0, 8.0]])
    assert goal_probe.goal_episodes(goals, goals[0]).tolist() == [True, False, True]


def test_the_report_marks_the_goal_the_end_and_where_the_minimum_lies():
    line = [{"position": [0.0, 8.0 + 0.5 * i], "learned_distance": d} for i, d in enumerate([2.3, 1.0, 1.8])]
    found = {"goal": [0.0, 8.0], "episodes": 10, "success": 0, "final_success": 0, "mean_end": [0.0, 9.0],
             "final_distance": 1.5, "line": line}
    lines = goal_probe.report(found)
    assert lines[0].startswith("goal (0.00, 8.00): 0/10 episodes reach it")
    assert lines[2].endswith("<- goal") and lines[4].endswith("<- mean end")
    assert lines[-1] == "minimum 1.00 at 0.50 of the way from the goal to the mean end (at the goal: 2.30)"


@pytest.mark.parametrize(("arguments", "message"), [
    (["episodes=0"], "episodes must be > 0, got 0"),
    (["points=1"], "points must be >= 2 (the goal and the mean end), got 1"),
    (["points=x"], "points expects int, got 'x'"),
])
def test_bad_input_is_one_line_naming_what_is_valid(arguments, message, tmp_path, capsys):
    assert goal_probe.main([f"run_dir={tmp_path}", *arguments]) == 2
    assert capsys.readouterr().err.strip() == f"error: {message}"


def test_a_dir_that_is_no_run_dir_is_refused(tmp_path, capsys):
    assert goal_probe.main([f"run_dir={tmp_path}"]) == 2
    assert "is not a run dir" in capsys.readouterr().err


def test_a_checkpoint_is_probed_from_the_goal_to_where_its_episodes_end(tmp_path):
    config = debug_config("morefree", f"run_dir={tmp_path}", f"steps={PREFILL + CHUNK}")
    driver.train(config, programs=debug_programs("morefree"), progress="off")
    found = goal_probe.probe_run(tmp_path, episodes=3, points=3)
    assert found["agent"] == "morefree" and found["checkpoint_step"] == PREFILL + CHUNK
    assert 1 <= found["episodes"] <= 3 and len(found["ends"]) == found["episodes"]
    np.testing.assert_allclose(found["mean_end"], np.mean(found["ends"], axis=0), rtol=1e-6)
    positions = np.array([row["position"] for row in found["line"]])
    np.testing.assert_allclose(positions[0], found["goal"], rtol=1e-6)
    np.testing.assert_allclose(positions[-1], found["mean_end"], rtol=1e-5)
    distances = [row["learned_distance"] for row in found["line"]]
    assert np.all(np.isfinite(distances))
    # The goal's own row: the agent's distance from the goal observation to itself, computed directly.
    run, state, _ = driver.restore_run(tmp_path)
    goal = jnp.asarray(found["goal_observation"], jnp.float32)[None]
    if isinstance(run.env, NormalisedObservations):
        goal = run.env.normalise(goal)
    direct = run.agent.goal_distance(state.agent, run.agent.initial_latent((1,)), goal, obs=goal)
    assert float(direct[0]) == pytest.approx(distances[0], rel=1e-4, abs=1e-5)
    json.dumps(found)  # what out= writes
