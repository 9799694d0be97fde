"""Ant (PEG's mrl ant body) in a square walled room, reset-free.

Body, joints, actuators and contact parameters follow the mrl ant used by PEG (docs/tasks.md, "Ant"):
8 motors with ctrl range +-30 (actions in [-1, 1] are scaled by 30), timestep 0.02, frame skip 5.
MoReFree put the ant in a square room with the start (0, 0) at its centre and the goal square [2, 3]^2 in
its top-right corner (paper, appendix and task list); the room's size is not published, so ours is
[-4, 4]^2, the goal square 1 unit (more than a leg's reach along x or y) from the north and east walls. The
walls are inward-facing planes that collide with the torso and the lower legs.

Deviations, on purpose:
  - integrator: MuJoCo's default semi-implicit Euler instead of the original RK4. MJX's RK4 runs four full
    forward passes (collision and constraint solve included) per substep and makes the single stream about
    7x slower on CPU; `make("ant", integrator="rk4")` restores the original.
  - friction cones stay pyramidal (MuJoCo's default, as the original), but note: where a contact
    activates, MJX's pyramidal solve differs from C MuJoCo's by up to about 2e-2 in one control step
    (elsewhere they agree to 1e-6). `make("ant", cone="elliptic")` agrees with C MuJoCo to 1e-5 over 20
    steps but runs about 4x slower in MJX.
  - observation 29-D (qpos without the time entry mrl appends), as the MoReFree paper states.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import (
    ResetFreeEnv,
    clip_action,
    distance_to_box,
    learner_defaults,
    physics_substeps,
    put_mjx_model,
)

GEAR = 30.0
INIT_QPOS = np.array([0.0, 0.0, 0.55, 1.0, 0.0, 0.0, 0.0] + [0.0] * 8, np.float32)
GOAL_LOW, GOAL_HIGH = np.array([2.0, 2.0], np.float32), np.array([3.0, 3.0], np.float32)
ROOM_LOW, ROOM_HIGH = -4.0, 4.0
INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
               "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


class Ant(ResetFreeEnv):
    name = "ant"
    xml_name = "ant.xml"
    obs_size = 29
    act_size = 8
    goal_dims = (0, 1)
    frames_per_step = 5

    def __init__(self, eval_episode_length: int = 500, hard_reset_every: int = 200_000,
                 success_threshold: float = 1.0, integrator: str = "euler", cone: str = "pyramidal"):
        if integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {integrator!r}; valid: {', '.join(INTEGRATORS)}")
        if cone not in CONES:
            raise ValueError(f"unknown cone {cone!r}; valid: {', '.join(CONES)}")
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        self.mj_model.opt.integrator = INTEGRATORS[integrator]
        self.mj_model.opt.cone = CONES[cone]
        self.mjx_model = put_mjx_model(self.mj_model)
        self._empty_data = mjx.make_data(self.mjx_model)
        self.resting_pose = jnp.asarray(resting_pose(self.mj_model))

    def _obs(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([data.qpos, data.qvel])

    def reset(self, rng: jax.Array) -> State:
        rng, key_pos, key_vel = jax.random.split(rng, 3)
        # As the original: uniform noise on every qpos entry (the quaternion too, renormalised by the
        # integrator) and Gaussian noise on every velocity.
        qpos = jnp.asarray(INIT_QPOS) + jax.random.uniform(key_pos, (15,), minval=-0.1, maxval=0.1)
        qvel = 0.1 * jax.random.normal(key_vel, (14,))
        data = self._empty_data.replace(qpos=qpos, qvel=qvel)
        return self._state(data, self._obs(data), rng)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state.replace(ctrl=GEAR * clip_action(action))
        data = physics_substeps(self.mjx_model, data, self.frames_per_step)
        return state.replace(pipeline_state=data, obs=self._obs(data), reward=jnp.zeros(()),
                             done=jnp.zeros(()))

    def _resting_at(self, xy: jax.Array) -> jax.Array:
        """Observation of the ant at rest (settled pose, zero velocity) with its torso at xy."""
        return jnp.concatenate([xy, self.resting_pose, jnp.zeros(14)])

    def eval_goals(self, rng: jax.Array) -> jax.Array:
        return self._resting_at(jax.random.uniform(rng, (2,), minval=GOAL_LOW, maxval=GOAL_HIGH))

    def initial_states(self, rng: jax.Array) -> jax.Array:
        return self._resting_at(jax.random.uniform(rng, (2,), minval=-0.1, maxval=0.1))

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        xy = obs[:2]
        near_start = jnp.linalg.norm(xy) < self.success_threshold
        goal_gap = distance_to_box(jnp.asarray(GOAL_LOW), jnp.asarray(GOAL_HIGH), xy)
        return near_start | (goal_gap < self.success_threshold)

    def xy(self, obs: jax.Array) -> jax.Array:
        return obs[:2]

    @classmethod
    def default_config(cls) -> dict:
        """PEG's ant-maze values (docs/tasks.md, "Per-task defaults") but the planner horizon; budget 8e5
        steps (the paper: 4 hard resets at one per 2e5 steps)."""
        return {
            "run.total_steps": 800_000, "run.prefill": 2_500, "run.train_every": 2,
            "run.subgoal_threshold": 2.0,
            **learner_defaults(entropy=1e-5, discount=0.996, p2e_discount=0.996, neg_factor=0.1),
            # MPPI gamma 2, 500 candidates, 5 iterations, std_scale 10, initial-state candidate, last 10
            # steps. Horizon 250 = H_G: PEG scores a goal over the go phase the policy will get (its ant maze:
            # 150 = 0.3 x 500), as every other task here does; MoReFree's go phase is half the episode (250).
            "planner.method": "mppi", "planner.num_candidates": 500, "planner.iterations": 5,
            "planner.mppi_temperature": 2.0, "planner.init_std": 10.0, "planner.horizon": 250,
            "planner.use_last_steps": 10, "planner.init_mean": "initial_state",
        }

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        joint_low, joint_high = self.mj_model.jnt_range[1:].T + np.array([[-0.1], [0.1]])  # soft limits
        velocity = np.concatenate([5 * np.ones(6), 10 * np.ones(8)])  # torso (6), joints (8)
        low = np.concatenate([[ROOM_LOW, ROOM_LOW, 0.0], -np.ones(4), joint_low, -velocity])
        high = np.concatenate([[ROOM_HIGH, ROOM_HIGH, 1.5], np.ones(4), joint_high, velocity])
        return low.astype(np.float32), high.astype(np.float32)


def resting_pose(model: mujoco.MjModel, settle_steps: int = 200) -> np.ndarray:
    """qpos[2:] (height, quaternion, joints) of the ant settled from its initial pose under zero action."""
    data = mujoco.MjData(model)
    data.qpos[:] = INIT_QPOS
    for _ in range(settle_steps * Ant.frames_per_step):
        mujoco.mj_step(model, data)
    return data.qpos[2:].astype(np.float32)
