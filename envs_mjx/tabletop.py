"""Tabletop manipulation (EARL `tabletop_manipulation`): carry a mug to one of four pads.

Dynamics are the original's kinematic rule, written in JAX (docs/tasks.md, "Tabletop"); the original
writes joint positions and never steps physics, so neither does this port:
  action a in [-1, 1]^3, scaled by 0.2;
  grasp: if a[2] > 0 and nothing is held, the mug is attached when the gripper (before moving) is closer
         than 0.4 to it; if a[2] <= 0 the mug is released;
  gripper xy += a[0:2], clipped to [-2.8, 2.8]; a held mug moves by the gripper's realised displacement,
  then is clipped to [-2.8, 2.8].
Observation (6,): gripper xy, mug xy, attachment entries (-1, -1) free / (0, 0) held (the original's
`attached_object` tuple). The goal part of the original's 12-D observation is not included: goals are
passed separately (goal space = observation space). Initial state fixed [0, 0, 2.5, 0, -1, -1];
four evaluation goals (mug on a pad, gripper back at the origin); success when obs[0:4] is within 0.2 of
the goal's (goal_dims 0..3).

Deviations from the original:
- Meshes (magnet gripper, coffee mug) are replaced by primitives and the pinned `random_joint` is left
  out; neither affects the dynamics (nothing collides, nothing is simulated).
- `pipeline_state` (an mjx.Data) carries qpos = [gripper xy, mug xy]; step writes qpos and runs
  `mjx.kinematics` (positions of bodies, geoms, sites) where the original runs `sim.forward()`; the
  rest of forward (dynamics quantities) is never used and is skipped.
- The attachment flag lives in the observation (entries 4, 5), as in the original; step reads it there.
- Success uses `< 0.2` (task API) where the original uses `<= 0.2`; the two differ on a set of measure 0.
- The initial state is fixed, as in EARL: `reset(rng)` returns the same observation for every key (the
  key is only carried in `info["rng"]`). No noise is added.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import ResetFreeEnv, distance_within, learner_defaults

MOVE_SCALE = 0.2  # metres of gripper displacement per unit action
TABLE_LIMIT = 2.8  # gripper and mug xy are clipped to [-2.8, 2.8]
GRASP_RADIUS = 0.4  # the mug is attached when the gripper is closer than this
FREE, HELD = -1.0, 0.0  # attachment entries of the observation

INITIAL_STATE = np.array([0.0, 0.0, 2.5, 0.0, FREE, FREE], np.float32)
MUG_GOALS = np.array([[-2.5, -1.0], [-2.5, 1.0], [0.0, 2.0], [0.0, -2.0]], np.float32)
GOAL_STATES = np.concatenate(
    [np.zeros((4, 2), np.float32), MUG_GOALS, np.full((4, 2), FREE, np.float32)], axis=1
)


def kinematic_move(positions: jax.Array, held: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The original's `move`: positions (4,) = gripper xy, mug xy; held () bool; action (3,) in [-1, 1].

    Returns the new positions (4,) and held flag ()."""
    scaled = MOVE_SCALE * jnp.clip(action, -1.0, 1.0)
    gripper, mug = positions[0:2], positions[2:4]
    in_reach = jnp.linalg.norm(gripper - mug) < GRASP_RADIUS
    held = jnp.where(scaled[2] > 0, held | in_reach, False)
    new_gripper = jnp.clip(gripper + scaled[0:2], -TABLE_LIMIT, TABLE_LIMIT)
    carried_mug = jnp.clip(mug + (new_gripper - gripper), -TABLE_LIMIT, TABLE_LIMIT)
    new_mug = jnp.where(held, carried_mug, mug)
    return jnp.concatenate([new_gripper, new_mug]), held


def observation(positions: jax.Array, held: jax.Array) -> jax.Array:
    """(6,) = gripper xy, mug xy, attachment entries."""
    attachment = jnp.where(held, HELD, FREE) * jnp.ones(2)
    return jnp.concatenate([positions, attachment])


class Tabletop(ResetFreeEnv):
    name = "tabletop"
    xml_name = "tabletop.xml"
    obs_size = 6
    act_size = 3
    goal_dims = (0, 1, 2, 3)
    frames_per_step = 1

    @classmethod
    def default_config(cls) -> dict:
        """No PEG config exists. Learner: PEG's point-maze values (entropy 1e-4, no distance negatives),
        since like the point maze it is a planar task whose state is a few positions. Train ratio 1 (paper),
        budget 2e5 steps (the paper: one hard reset, at the start, at one per 2e5 steps), prefill 2500 steps
        (PEG's point maze and ant maze; its config default is 10000: choice) and subgoal threshold 2 (PEG's
        walker and ant maze; choice). Planner: PEG's default MPPI (gamma 10, last 10 steps),
        std_scale 1 matched to the +-2.5 coordinate range (choice), horizon 100 = H_G."""
        return {
            "run.total_steps": 200_000, "run.prefill": 2_500, "run.train_every": 1,
            "run.subgoal_threshold": 2.0,
            **learner_defaults(entropy=1e-4, discount=0.99, p2e_discount=0.99, neg_factor=0.0),
            "planner.method": "mppi", "planner.num_candidates": 500, "planner.iterations": 5,
            "planner.mppi_temperature": 10.0, "planner.init_std": 1.0, "planner.horizon": 100,
            "planner.use_last_steps": 10, "planner.init_mean": "current",
        }

    def __init__(self, eval_episode_length=200, hard_reset_every=200_000, success_threshold=0.2):
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        self._template = mjx.make_data(self.mjx_model)

    def reset(self, rng: jax.Array) -> State:
        data = self._template.replace(qpos=jnp.asarray(INITIAL_STATE[:4]))
        data = mjx.kinematics(self.mjx_model, data)
        return self._state(data, jnp.asarray(INITIAL_STATE), rng)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state
        held = state.obs[4] > 0.5 * (FREE + HELD)
        positions, held = kinematic_move(data.qpos, held, action)
        data = mjx.kinematics(self.mjx_model, data.replace(qpos=positions))
        return state.replace(pipeline_state=data, obs=observation(positions, held))

    # ---- reset-free extension ----------------------------------------------------------------
    def eval_goals(self, rng: jax.Array) -> jax.Array:
        index = jax.random.randint(rng, (), 0, len(GOAL_STATES))
        return jnp.asarray(GOAL_STATES)[index]

    def evaluation_goals(self, rng: jax.Array, num_episodes: int) -> jax.Array:
        """The four goals in turn (the paper: "four goal locations are sampled in turn"; EARL's
        get_next_goal cycles its list, carrying on from one evaluation to the next), from a goal drawn with
        `rng`: 10 episodes see them 3, 3, 2, 2 times, and which two get 3 changes between evaluations, so
        over a run the goals weigh the same on average (from the first each time, the first two had 60%)."""
        first = jax.random.randint(rng, (), 0, len(GOAL_STATES))
        return jnp.asarray(GOAL_STATES)[(first + jnp.arange(num_episodes)) % len(GOAL_STATES)]

    def initial_states(self, rng: jax.Array) -> jax.Array:
        del rng  # a single fixed initial state, as in EARL
        return jnp.asarray(INITIAL_STATE)

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        dims = jnp.asarray(self.goal_dims)
        references = jnp.concatenate([INITIAL_STATE[None], GOAL_STATES])[:, dims]
        return distance_within(jnp.asarray(references), obs[dims]) < self.success_threshold

    def xy(self, obs: jax.Array) -> jax.Array:
        return obs[2:4]  # the mug

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low = np.array([-TABLE_LIMIT] * 4 + [FREE, FREE], np.float32)
        high = np.array([TABLE_LIMIT] * 4 + [HELD, HELD], np.float32)
        return low, high
