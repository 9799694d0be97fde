"""IBC's per-task settings (docs/baselines.md, "IBC": its "Segments" and "Curriculum" sections), keyed by our
task names.

IBC keeps these in dicts keyed by task in its `train.py` and `env_utils.py`; we keep them together here,
in the ibc agent's own file, rather than in each task's `default_config()`, so that they sit beside the
one agent that reads them (and no env file changes for a baseline).

Observation layouts (envs_mjx/*.py) decide the proprioceptive part of a backward goal:
point_umaze (x, y, heading, velocities): xy [0:2]; tabletop (gripper xy, mug xy, attachment): gripper xy
[0:2]; sawyer_door (hand xyz, gripper opening, handle xyz): hand [0:3]; fetch (grip xyz, block xyz, ...):
grip [0:3]; ant (qpos, qvel): torso xy [0:2].

push_hard / pick_place_hard use IBC's Fetch settings (docs/baselines.md, "IBC's choices and deviations";
the paper, Appendix B.2, keeps IBC's hyperparameters unchanged).
ant is not in IBC's code; our choices: the proprioceptive goal is the torso xy (the ant's goal space, as
UMaze's point xy), backward threshold = the task's success threshold (1.0), noises scaled from UMaze's
(uniform +-0.1 on target initial states, Gaussian 0.3 on curriculum goals of both directions, on the
torso xy, pool move 0.1), segment length 200 (IBC's longest, Sawyer's; the ant's 500-step evaluation
episode would make the pool and its valuation 2.5x larger) and K = 50 reset targets as for the other
goal-distribution tasks.

In IBC's EARL tasks (sawyer_door, tabletop; `earl`) the goal is a whole state: the observation is
[state, goal state] (env_utils.py NonEpisodicWrapper, WraptoGoalEnv: achieved goal = the state), so the
forward agent sees every entry of its goal, not only those its success test reads (forward_goal_dims).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np


class IBCTask(NamedTuple):
    """segment_length: `max_episode_timesteps`; proprio_dims: the backward goal's observation indices;
    backward_threshold: its success distance; init_noise: uniform +- noise on the target pairs' initial
    states (IBC's `add_noise_to_goal`); corridor (point_umaze): the target pairs' desired goals are
    `corridor_points` evenly spaced points along this polyline (goal_dims) plus uniform +- corridor_noise,
    IBC's replacement of UMaze's goal set; curriculum_noise: Gaussian std on a curriculum goal of either
    direction (IBC's MatchSampler.sample); curriculum_noise_dims: which goal_dims (positions in
    env.goal_dims) of a forward goal get it; backward_noise_dims: which observation indices of a backward
    goal get it (MatchSampler.add_noise with proprioceptive_only: in the EARL tasks the same object entries
    as forward, which the backward success test ignores, elsewhere the whole proprioceptive goal);
    pool_move: least movement of a forward segment's achieved goal or agent part to enter the pool;
    num_targets: K target pairs; earl: IBC's EARL tasks (K = 2 {initial, goal}, K = 5 {initial, 4 goals}):
    the first target's desired goal is the initial state, the forward goal is the whole state
    (forward_goal_dims), and every matching draws each slot's initial state afresh with new noise (train.py
    resets its hgg env per slot there; elsewhere the K pairs and their noise are drawn once);
    forward_goal_box: (observation index, low, high) clips of a noised forward goal (IBC's
    MatchSampler.add_noise: Tabletop's positions to its table, Sawyer Door's handle height, the Fetch
    block to IBC's goal box and, for push, to the table; none on PointUMaze, nor on the tasks IBC never
    ran: the hard Fetch variants, Ant)."""

    segment_length: int
    proprio_dims: tuple[int, ...]
    backward_threshold: float
    init_noise: float
    curriculum_noise: float
    curriculum_noise_dims: tuple[int, ...]
    backward_noise_dims: tuple[int, ...]
    pool_move: float
    num_targets: int
    earl: bool
    corridor: tuple[tuple[float, float], ...] = ()
    corridor_points: int = 0
    corridor_noise: float = 0.0
    forward_goal_box: tuple[tuple[int, float, float], ...] = ()


_FETCH = IBCTask(segment_length=50, proprio_dims=(0, 1, 2), backward_threshold=0.05, init_noise=0.05,
                 curriculum_noise=0.03, curriculum_noise_dims=(0, 1, 2), backward_noise_dims=(0, 1, 2),
                 pool_move=0.01, num_targets=50, earl=False)

# IBC's Fetch clip box of a forward (block) goal, world coordinates: x, y +- 0.15 around its gripper start.
_FETCH_BLOCK_XY = ((3, 1.19786948, 1.49786948), (4, 0.59894948, 0.89894948))

IBC_TASKS: dict[str, IBCTask] = {
    "point_umaze": IBCTask(segment_length=100, proprio_dims=(0, 1), backward_threshold=0.6, init_noise=0.1,
                           curriculum_noise=0.3, curriculum_noise_dims=(0, 1), backward_noise_dims=(0, 1),
                           pool_move=0.1, num_targets=50, earl=False,
                           corridor=((0.0, 0.0), (8.0, 0.0), (8.0, 8.0), (0.0, 8.0)), corridor_points=30,
                           corridor_noise=0.1),
    # EARL: the backward noise lands on the mug (IBC's add_noise on goal[2:4]), not on the gripper.
    "tabletop": IBCTask(segment_length=100, proprio_dims=(0, 1), backward_threshold=0.2, init_noise=0.05,
                        curriculum_noise=0.1, curriculum_noise_dims=(2, 3), backward_noise_dims=(2, 3),
                        pool_move=0.01, num_targets=5, earl=True,
                        forward_goal_box=tuple((index, -2.8, 2.8) for index in range(4))),
    # EARL: the backward noise lands on the handle xy (IBC's add_noise on goal[4:6]), not on the hand.
    "sawyer_door": IBCTask(segment_length=200, proprio_dims=(0, 1, 2), backward_threshold=0.05,
                           init_noise=0.05, curriculum_noise=0.005, curriculum_noise_dims=(0, 1),
                           backward_noise_dims=(4, 5), pool_move=0.01, num_targets=2, earl=True,
                           forward_goal_box=((6, 0.1, 0.11),)),
    "push": _FETCH._replace(forward_goal_box=(*_FETCH_BLOCK_XY, (5, 0.42, 0.43))),  # on the table
    "pick_place": _FETCH._replace(forward_goal_box=(*_FETCH_BLOCK_XY, (5, 0.42, 1.0))),
    "push_hard": _FETCH,
    "pick_place_hard": _FETCH,
    "ant": IBCTask(segment_length=200, proprio_dims=(0, 1), backward_threshold=1.0, init_noise=0.1,
                   curriculum_noise=0.3, curriculum_noise_dims=(0, 1), backward_noise_dims=(0, 1),
                   pool_move=0.1, num_targets=50, earl=False),
}


def ibc_task(env, segment_length: int | None = None) -> IBCTask:
    """The settings of env's task (segment_length, if given, replaces the task's); a task without them is
    a one-line error."""
    if env.name not in IBC_TASKS:
        raise ValueError(f"ibc has no settings for task {env.name!r}; tasks with settings: "
                         f"{', '.join(IBC_TASKS)}")
    task = IBC_TASKS[env.name]
    return task if segment_length is None else task._replace(segment_length=segment_length)


def corridor_points(task: IBCTask) -> np.ndarray:
    """(corridor_points, 2) evenly spaced by arc length along task.corridor, both ends included."""
    corners = np.asarray(task.corridor, np.float64)
    lengths = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    at = np.linspace(0.0, arc[-1], task.corridor_points)
    return np.stack([np.interp(at, arc, corners[:, 0]), np.interp(at, arc, corners[:, 1])], -1)


def forward_goal_dims(task: IBCTask, env) -> tuple[int, ...]:
    """The observation indices of a forward goal that the forward agent sees and the curriculum stores:
    the whole state in the EARL tasks (module docstring), env.goal_dims elsewhere (IBC's desired goal)."""
    return tuple(range(env.observation_size)) if task.earl else tuple(int(d) for d in env.goal_dims)


def backward_goal_dims(task: IBCTask, env) -> tuple[int, ...]:
    """The observation indices of a backward goal that the backward agent sees: the whole state in the EARL
    tasks (IBC's backward goal there is a trajectory's whole first state, its desired goal the whole goal
    state; only the success test is proprioceptive), the proprioceptive dims elsewhere (IBC's backward
    env's desired goal is the gripper or point position)."""
    return tuple(range(env.observation_size)) if task.earl else tuple(task.proprio_dims)


def proprio_reached(task: IBCTask, obs, goal):
    """The backward success test: the proprioceptive parts closer than task.backward_threshold."""
    dims = jnp.asarray(task.proprio_dims)
    return jnp.linalg.norm(obs[dims] - goal[dims]) < task.backward_threshold
