"""PointUMaze (IBC's goal-conditioned point in a U-maze), reset-free, with the original's physics.

Each step does what the original (mujoco-maze's point, used by IBC) does, in the same order:
  1. turn the heading by a1 in [-0.25, 0.25] rad (wrapped once into [-pi, pi]) and move the point by a0 in
     [-1, 1] along the new heading, written straight into qpos (the action never reaches `ctrl`; the
     MJCF's motors only carry the action box);
  2. clip the joint velocities to +-10;
  3. one MuJoCo physics step (RK4, 0.02 s) in MJX: the sphere (r 0.5) and the arrow box touch the wall
     blocks before the manual rule below fires, so contacts turn the kinematic moves into velocities of
     several units per second that carry the point on for many steps;
  4. the original's manual collision rule on the segment from the position before step 1 to the one after
     step 3: on crossing a wall face inflated by 0.4 the point goes to the hit point plus 0.8 times the
     mirrored remainder, and if that path also crosses a wall it stays where it was. Only x, y change;
     the velocities stay as the physics step left them.

The original's floor "friction" is a floating-point accident that we inherit rather than model: the body
has no z joint and the sphere rests exactly on the floor, so the floor contact exists only when rounding
puts the sphere's centre a hair below z = 0.5, which depends on the last bits of cos^2 + sin^2 of the
heading in each RK4 stage. It then acts as a stiff velocity damper, otherwise not at all. MJX (float32)
and C MuJoCo (float64) toss this coin differently for the same state but with the same odds, so
trajectories agree only in distribution once the point moves (docs/tasks.md, "PointUMaze", and
tests/test_point_umaze_physics.py, for the measured agreement).

Deviations from the original, on purpose:
  - the observation is 6-D (x, y, heading, their velocities): the original's 7th entry, 0.001 x steps since
    reset, has no meaning in a reset-free stream and would make goals unreachable in that entry;
  - the original calls mj_forward after writing the corrected position; we skip it because the observation
    reads only qpos and qvel, so the derived fields of `pipeline_state` (xpos, contacts) are those of the
    physics step, before the manual rule (`mj_data_from` recomputes them for rendering).
A difference we did not choose: MJX's box-box routine reports contact points on a face rather than midway
between the surfaces (and in some deep poses other points than C's), which changes the friction torque
when the arrow sits deep in a wall block (docs/tasks.md, "PointUMaze").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import ResetFreeEnv, clip_action, learner_defaults, physics_substeps

LAYOUT = ("11111", "10001", "11101", "10001", "11111")  # 1 = wall block; (row i, col j)
CELL = 4.0
COLLISION_RADIUS = 0.4
RESTITUTION = 0.8
MAX_TURN = 0.25
VELOCITY_LIMIT = 10.0
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
    """One shift by 2 pi into [-pi, pi], as the original does: the heading it is applied to is within
    0.25 rad plus one physics step's turn of [-pi, pi], so once is enough."""
    shift = jnp.where(angle > jnp.pi, -2 * jnp.pi, jnp.where(angle < -jnp.pi, 2 * jnp.pi, 0.0))
    return angle + shift


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
        old_xy = data.qpos[:2]
        heading = wrap_angle(data.qpos[2] + MAX_TURN * action[1])
        moved_xy = old_xy + action[0] * jnp.stack([jnp.cos(heading), jnp.sin(heading)])
        qvel = jnp.clip(data.qvel, -VELOCITY_LIMIT, VELOCITY_LIMIT)
        data = data.replace(qpos=jnp.concatenate([moved_xy, heading[None]]), qvel=qvel)
        data = physics_substeps(self.mjx_model, data, self.frames_per_step)
        # The rule tests the whole move, kinematic and physical, from where the step started.
        xy = collide_with_walls(self.faces, old_xy, data.qpos[:2])
        data = data.replace(qpos=data.qpos.at[:2].set(xy))
        obs = self._obs(data)
        return state.replace(pipeline_state=data, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()))

    @classmethod
    def default_config(cls) -> dict:
        """PEG's point-maze values (docs/tasks.md, "Per-task defaults"): entropy 1e-4, discounts 0.99, no
        distance negatives, prefill 50 x 50 = 2500 steps; train ratio 2 (paper); budget 2e5 steps (the paper:
        one hard reset, at the start, at one per 2e5 steps). Planner: PEG's shooting CEM (500 candidates, 5
        iterations, elite 0.2, std_scale 4, initial-state candidate, all steps scored), horizon 50 = H_G.
        Deviation: subgoal threshold 1 step instead of PEG's 5: the point's action moves it at most 1 unit
        per step (physics adds up to ~0.3) and success is within 0.6, and with PEG's 5 the go phase ended
        after one step in most chunks of our first runs (far goals sit near 0.3 x 15 = 4.7 steps of learned
        distance without negatives)."""
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
        # xy: the free cells +- half a cell (the original's box). Heading: the wrap comes before the physics
        # step, which can turn it by up to |qvel_heading| x 0.02 more. Velocities: 50k-step MJX rollouts
        # (2026-11-29), uniform random actions / wall-seeking (full forward at the nearest wall, 20% random):
        # heading in [-3.32, 3.34] / [-2.07, 0.64]; qvel x [-11.8, 15.7] / [-13.6, 10.6], y [-13.9, 16.6] /
        # [-8.9, 17.8], heading [-25.4, 28.0] / [-19.0, 19.3] (99.9% quantiles of |qvel| 8-14 in x, y and
        # 16-18 in heading); C MuJoCo, 20k random steps: max |qvel| 13.9, 14.1, 28.7.
        high = np.array([10.0, 10.0, 3.5, 18.0, 18.0, 30.0], np.float32)
        low = np.array([-2.0, -2.0, -3.5, -18.0, -18.0, -30.0], np.float32)
        return low, high
