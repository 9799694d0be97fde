"""PointUMaze (IBC's goal-conditioned point in a U-maze), reset-free.

The original (mujoco-maze's point, used by IBC) moves the point kinematically: each action turns the
heading by a1 in [-0.25, 0.25] rad and then displaces the point by a0 in [-1, 1] along the new heading,
written straight into qpos. A manual collision rule keeps it out of the walls: the segment from the old
to the new position is tested against the wall faces inflated by a radius of 0.4; on a crossing the point
goes to the hit point plus 0.8 times the mirrored remainder, and if that path also crosses a wall it stays
where it was. We reproduce this exactly in JAX (one vectorised segment test against every exposed face).

The MuJoCo physics step of the original only integrates the joint velocities, which nothing ever sets
after the initial N(0, 0.1) noise; floor friction then damps them. Rather than running a physics step per
action (milliseconds on CPU), we integrate qpos += qvel * dt and decay qvel by per-step factors fitted to
C MuJoCo on this MJCF (x, y: 0.96; heading: 0.9996). This affects positions by about 0.01 over an episode.

Deviations from the original, on purpose:
  - the observation is 6-D (x, y, heading, their velocities): the original's 7th entry, 0.001 x steps since
    reset, has no meaning in a reset-free stream and would make goals unreachable in that entry;
  - contact forces between the point and the walls (the sphere of radius 0.5 may overlap an inflated
    face by 0.1) are not simulated; the manual collision rule alone keeps the point in the maze.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import ResetFreeEnv, clip_action, learner_defaults

LAYOUT = ("11111", "10001", "11101", "10001", "11111")  # 1 = wall block; (row i, col j)
CELL = 4.0
COLLISION_RADIUS = 0.4
RESTITUTION = 0.8
MAX_TURN = 0.25
VELOCITY_LIMIT = 10.0
VELOCITY_DECAY = np.array([0.96, 0.96, 0.9996])  # fitted to C MuJoCo floor friction on this MJCF
START_XY = np.array([0.0, 0.0])
GOAL_XY = np.array([0.0, 8.0])


def cell_center(i: int, j: int) -> tuple[float, float]:
    return CELL * j - CELL, CELL * i - CELL


def wall_faces(layout=LAYOUT, radius=COLLISION_RADIUS) -> np.ndarray:
    """Segments (L, 2, 2) on the wall-block faces that border a free cell, pushed out by `radius`."""
    rows, cols = len(layout), len(layout[0])

    def is_free(i, j):
        return 0 <= i < rows and 0 <= j < cols and layout[i][j] == "0"

    faces = []
    for i in range(rows):
        for j in range(cols):
            if layout[i][j] != "1":
                continue
            x, y = cell_center(i, j)
            r = CELL / 2 + radius
            lo_x, hi_x, lo_y, hi_y = x - r, x + r, y - r, y + r
            if is_free(i, j - 1):
                faces.append(((lo_x, lo_y), (lo_x, hi_y)))
            if is_free(i, j + 1):
                faces.append(((hi_x, lo_y), (hi_x, hi_y)))
            if is_free(i - 1, j):
                faces.append(((lo_x, lo_y), (hi_x, lo_y)))
            if is_free(i + 1, j):
                faces.append(((lo_x, hi_y), (hi_x, hi_y)))
    return np.asarray(faces, dtype=np.float32)


def _cross(a: jax.Array, b: jax.Array) -> jax.Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def first_crossing(faces: jax.Array, start: jax.Array, end: jax.Array):
    """The face the segment start->end crosses first: (crossed?, hit point (2,), mirror of end (2,))."""
    a, b = faces[:, 0], faces[:, 1]
    move, face = end - start, b - a
    denom = _cross(move, face)
    safe = jnp.where(jnp.abs(denom) < 1e-12, 1.0, denom)
    t = _cross(a - start, face) / safe  # position along the move
    u = _cross(a - start, move) / safe  # position along the face
    hits = (jnp.abs(denom) >= 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    hits &= jnp.linalg.norm(move) > 1e-8
    first = jnp.argmin(jnp.where(hits, t, jnp.inf))
    hit_point = start + t[first] * move
    direction = face[first] / jnp.linalg.norm(face[first])
    foot = a[first] + jnp.dot(end - a[first], direction) * direction
    return jnp.any(hits), hit_point, 2.0 * foot - end


def collide_with_walls(faces: jax.Array, old_xy: jax.Array, new_xy: jax.Array) -> jax.Array:
    """The original's manual collision: reflect off the first face crossed, or stay put."""
    crossed, hit_point, mirrored = first_crossing(faces, old_xy, new_xy)
    bounced = hit_point + RESTITUTION * (mirrored - hit_point)
    bounce_crosses, _, _ = first_crossing(faces, old_xy, bounced)
    bounced = jnp.where(bounce_crosses, old_xy, bounced)
    return jnp.where(crossed, bounced, new_xy)


def wrap_angle(angle: jax.Array) -> jax.Array:
    return (angle + jnp.pi) % (2 * jnp.pi) - jnp.pi


class PointUMaze(ResetFreeEnv):
    name = "point_umaze"
    xml_name = "point_umaze.xml"
    obs_size = 6
    act_size = 2
    goal_dims = (0, 1)

    def __init__(self, eval_episode_length: int = 100, hard_reset_every: int = 200_000,
                 success_threshold: float = 0.6):
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        self.faces = jnp.asarray(wall_faces())
        self._empty_data = mjx.make_data(self.mjx_model)

    def _obs(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([data.qpos, data.qvel])

    def reset(self, rng: jax.Array) -> State:
        rng, key_pos, key_vel = jax.random.split(rng, 3)
        qpos = jax.random.uniform(key_pos, (3,), minval=-0.1, maxval=0.1)
        qvel = 0.1 * jax.random.normal(key_vel, (3,))
        data = self._empty_data.replace(qpos=qpos, qvel=qvel)
        return self._state(data, self._obs(data), rng)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state
        action = clip_action(action)
        heading = wrap_angle(data.qpos[2] + MAX_TURN * action[1])
        forward = action[0] * jnp.array([jnp.cos(heading), jnp.sin(heading)])
        qvel = jnp.clip(data.qvel, -VELOCITY_LIMIT, VELOCITY_LIMIT)
        drift = qvel * self.dt  # what the original's physics step integrates
        new_xy = collide_with_walls(self.faces, data.qpos[:2], data.qpos[:2] + forward + drift[:2])
        qpos = jnp.concatenate([new_xy, (heading + drift[2])[None]])
        data = data.replace(qpos=qpos, qvel=qvel * VELOCITY_DECAY)
        obs = self._obs(data)
        return state.replace(pipeline_state=data, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()))

    @classmethod
    def default_config(cls) -> dict:
        """PEG's point-maze values (agent.md 8.1, 4.1, 5.2): entropy 1e-4, discounts 0.99, no distance
        negatives, prefill 50 x 50 = 2500 steps; train ratio 2 (paper); budget 2e5 steps (the paper: one
        hard reset, at the start, at one per 2e5 steps). Planner: PEG's shooting CEM (500 candidates, 5
        iterations, elite 0.2, std_scale 4, initial-state candidate, all steps scored), horizon 50 = H_G.
        Deviation: subgoal threshold 1 step instead of PEG's 5: the point moves at most 1 unit per step
        and succeeds within 0.6, and with PEG's 5 the go phase ended after one step in most chunks of our
        first runs (far goals sit near 0.3 x 15 = 4.7 steps of learned distance without negatives)."""
        return {
            "run.total_steps": 200_000, "run.prefill": 2_500, "run.train_every": 2,
            "run.subgoal_threshold": 1.0,
            **learner_defaults(entropy=1e-4, discount=0.99, p2e_discount=0.99, neg_factor=0.0),
            "planner.method": "cem", "planner.num_candidates": 500, "planner.iterations": 5,
            "planner.cem_elite_fraction": 0.2, "planner.init_std": 4.0, "planner.horizon": 50,
            "planner.use_last_steps": None, "planner.init_mean": "initial_state",
        }

    def eval_goals(self, rng: jax.Array) -> jax.Array:
        del rng  # a single fixed goal, as in the original
        return jnp.concatenate([jnp.asarray(GOAL_XY, jnp.float32), jnp.zeros(4)])

    def initial_states(self, rng: jax.Array) -> jax.Array:
        pose = jax.random.uniform(rng, (3,), minval=-0.1, maxval=0.1)
        return jnp.concatenate([pose, jnp.zeros(3)])

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        anchors = jnp.asarray(np.stack([START_XY, GOAL_XY]), jnp.float32)
        return jnp.min(jnp.linalg.norm(anchors - obs[:2], axis=-1)) < self.success_threshold

    def xy(self, obs: jax.Array) -> jax.Array:
        return obs[:2]

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        high = np.array([10.0, 10.0, np.pi, 1.0, 1.0, 1.0], np.float32)
        low = np.array([-2.0, -2.0, -np.pi, -1.0, -1.0, -1.0], np.float32)
        return low, high
