"""Fetch Push, Pick&Place (IBC's "ergodic" versions) and their MoReFree "hard" variants, reset-free, in MJX.

Model (assets/fetch_scene.xml, fetch.xml, fetch_hard.xml). The original Fetch (15-DOF arm with mesh
geoms) does not load in MJX and costs ~22 ms per substep on CPU. Its gripper is moved by a mocap target,
so the arm only follows the gripper; we keep the gripper alone: a body on three world-axis slide joints
with critically damped position actuators (kp 3000, kv 110 for 1.2 kg: ~50 rad/s, like the original
weld's solref 0.02), gravity-compensated, carrying the two slide fingers with the original finger boxes
(half sizes 0.0385 x 0.007 x 0.0135), condim 4, friction (1, 0.05, 0.01), contact solimp/solref, range
[0, 0.05], armature 100, damping 1000 and position actuators kp 30000. The block is
the original 5 cm cube (mass 2, friction (1, 0.005, 0.0001), condim 3) and the table top is at z 0.4.

Control, as the original: each step the target is the gripper's current position plus 0.05 * a[0:3]
(the original snaps the mocap to the gripper, then adds the displacement), clipped to the workspace;
the finger actuators get current finger qpos + a[3], clipped to [0, 0.05]. In `push`
the fingers are held closed (IBC's block_gripper: ctrl 0 and finger qpos/qvel zeroed after each step);
in the other three tasks they work. 0.01 s x 4 substeps = 0.04 s per action (original 0.002 s x 20).

Observation (25-D, the original's order): grip position (3), block position (3), block - grip (3),
finger qpos (2), block rotation as static-xyz Euler angles (3), (block - grip) linear velocity * dt (3),
block angular velocity (world frame) * dt (3), grip linear velocity * dt (3), finger qvel * dt (2).

Deviations from the original, on purpose (also in docs/tasks.md,
"Fetch tasks: push, pick_place, push_hard, pick_place_hard"):
  - floating gripper instead of the arm; the grip site is 1.5 cm above the finger bottoms and the palm
    box is visual only (a block on the table cannot reach it: the grip target is clipped to z >= 0.417,
    so the finger bottoms stay 2 mm above the table and the palm 3 cm above the block);
  - the gripper follows its target through position actuators on three slides (gravity-compensated),
    not a mocap weld on a free body: same control rule, no weld constraint rows to solve;
  - finger targets are clipped to the joint range [0, 0.05], not to the original's ctrlrange [0, 0.2],
    which drives the fingers ~1.5 cm past their limit when opening (MuJoCo limits are soft);
  - only block-table, block-fingers (and block-walls) collide: the fingers never touch the table or walls;
  - timestep 0.01 x 4 substeps, Newton 6 iterations / 6 line-search steps, pyramidal cone;
  - the finger contact parameters get priority over the block's (no averaging): a held block creeps
    < 0.1 mm per step instead of ~0.15 mm;
  - the gripper workspace is a box, the slide joints' range (the original's arm reach has no box):
    x, y over the table top minus the finger half-width, z in [0.417, 0.9];
  - push / pick_place: the block hangs on IBC's slides + ball joint with +-0.2 m x/y limits around the
    initial gripper xy + 2.5 cm (IBC_BLOCK_OFFSET), with IBC v2's hardened limit solref/solimp (v1 used
    the softer defaults);
  - hard variants (MoReFree's, no public code): free block; frictionless walls whose inner faces are the
    table edges (0.6 x 0.7 m, 2.6x IBC's 0.4 x 0.4 box), colliding as planes; block start fixed at
    (1.43, 0.76) (IBC v2's near-fixed start) up to a U(-0.005, 0.005) xy jitter (the setting
    block_start_noise; 0 makes it exact) so that resets with different keys differ; push_hard goals
    uniform in the nominal block start +- 0.15 on the table; pick_place_hard goals uniform in
    x, y = nominal block start +- 0.025, z in [0.475, 0.575] (a 5 x 5 x 10 cm box);
  - initial gripper: push at table height 0.425 (its mocap target lies below the table top, so the
    gripper settles on it, which is also why IBC's push xy differs from pick-and-place's); pick_place at
    z 0.5347, where the original's target (0.2 higher) is reached unobstructed: the start FetchReach
    publishes for the same arm pose and extra height, whose xy (1.34183, 0.74910) is IBC's pick-and-place
    limit centre. pick_place_hard starts like push_hard (the paper: "the same ... initial state ... with
    Fetch Push described above");
  - evaluation goals are full observations: block at the goal, zero velocities, and the gripper 4.5 cm
    above the block with closed fingers, or (for goals in the air) holding it (grip at the block,
    fingers at the grasp width).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import ResetFreeEnv, distance_to_box, learner_defaults, physics_substeps, put_mjx_model

TABLE_LOW = np.array([1.05, 0.40])
TABLE_HIGH = np.array([1.65, 1.10])
BLOCK_REST_Z = 0.425  # block centre resting on the table top (z 0.4)
# "In the air" in the side visitation view: the block centre 2 cm above rest, higher than the 5 cm cube
# reaches tipped onto an edge (1.0 cm) or balanced on a corner (1.8 cm), so only a lifted block counts.
BLOCK_AIR_Z = BLOCK_REST_Z + 0.02
BLOCK_SIDE_VIEW = (3, 5)  # observation indices of the block's x and z
MAX_DISPLACEMENT = 0.05  # metres of gripper target displacement per unit action
FINGER_CTRL_MAX = 0.05  # the joint range; the original clips at 0.2 and so overdrives the limit
FINGER_GRASP_WIDTH = 0.0235  # finger qpos holding the 5 cm block (measured)
GRIP_ABOVE_BLOCK = 0.045  # goal pose: finger bottoms 5 mm above the block top
IBC_CONFINEMENT = 0.2  # block centre within +- this of the initial gripper xy (IBC's slide limits)
IBC_OBJ_RANGE = 0.15  # block start / goal xy range around the initial gripper xy
IBC_MIN_START_DISTANCE = 0.1  # block start at least this far from the gripper xy
IBC_AIR_HEIGHT = 0.45  # pick_place: half of the goals rise up to this above the table
# IBC's block body sits 2.5 cm off its slides' frame in x and y, and the sampled start (like the slide
# limits' centre, the initial gripper xy) is written into the slide qpos: block starts and the confinement
# box are centred 2.5 cm off the gripper xy, the goals are not
# (docs/tasks.md, "IBC's block-position constraint").
IBC_BLOCK_OFFSET = np.array([0.025, 0.025, 0.0])
HARD_BLOCK_START = np.array([1.43, 0.76, BLOCK_REST_Z])
# qpos layout of both models: grip slides x y z, fingers r l, block position (3) + quaternion (4).
BLOCK_POSITION = slice(5, 8)
BLOCK_QUATERNION = slice(8, 12)
PUSH_GRIPPER_START = (1.3479, 0.7489, 0.425)  # IBC's initial gripper xy (its limit centres) per task
PICK_PLACE_GRIPPER_START = (1.3419, 0.7491, 0.5347)


def ibc_box(gripper_start: tuple[float, float, float], height: float = 0.0,
            offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """IBC's block goal box (start box: offset IBC_BLOCK_OFFSET): xy +- 0.15 around the initial gripper xy,
    z from rest up by height."""
    center = np.array([gripper_start[0], gripper_start[1], BLOCK_REST_Z])
    center = center if offset is None else center + offset
    return center - [IBC_OBJ_RANGE, IBC_OBJ_RANGE, 0.0], center + [IBC_OBJ_RANGE, IBC_OBJ_RANGE, height]


def matrix_from_quaternion(quat: jax.Array) -> jax.Array:
    """Rotation matrix (3, 3) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quat / jnp.linalg.norm(quat)
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def euler_from_matrix(mat: jax.Array) -> jax.Array:
    """Static-xyz Euler angles (roll, pitch, yaw) of a rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = jnp.arctan2(mat[2, 1], mat[2, 2])
    pitch = jnp.arctan2(-mat[2, 0], jnp.sqrt(mat[2, 1] ** 2 + mat[2, 2] ** 2))
    yaw = jnp.arctan2(mat[1, 0], mat[0, 0])
    return jnp.stack([roll, pitch, yaw])


class _Fetch(ResetFreeEnv):
    """What the four tasks share: model indices, control rule, observation, goals as observations."""

    obs_size = 25
    act_size = 4
    goal_dims = (3, 4, 5)
    frames_per_step = 4

    fingers_locked: ClassVar[bool] = False
    gripper_start: ClassVar[tuple[float, float, float]]
    block_start_low: ClassVar[np.ndarray]  # box of block starts (for task_relevant)
    block_start_high: ClassVar[np.ndarray]
    goal_low: ClassVar[np.ndarray]  # box of block goals
    goal_high: ClassVar[np.ndarray]

    @classmethod
    def default_config(cls) -> dict:
        """PEG's closest task, 3-block stacking (docs/tasks.md, "Per-task defaults"): actor entropy 1e-5,
        negatives 0.1, discounts 0.99, subgoal threshold 1, prefill 25 episodes x 150 = 3750 steps. Budget 5e5
        steps: the paper's 5 hard resets at one per 1e5 steps for the hard tasks (IBC's versions: the same, no
        count published). Planner: PEG's 3-stack MPPI (gamma 10, std_scale 0.5, last 10 steps) with 500
        instead of 2000 candidates for this CPU (choice); horizon 25 = H_G. Observations min-max normalised by
        observation_bounds, as PEG's 3-stack agent sees them (its std_scale is in those units)."""
        return {
            "run.total_steps": 500_000, "run.prefill": 3_750, "run.train_every": 2,
            "run.subgoal_threshold": 1.0,
            **learner_defaults(entropy=1e-5, discount=0.99, p2e_discount=0.99, neg_factor=0.1),
            "planner.method": "mppi", "planner.num_candidates": 500, "planner.iterations": 5,
            "planner.mppi_temperature": 10.0, "planner.init_std": 0.5, "planner.horizon": 25,
            "planner.use_last_steps": 10, "planner.init_mean": "current",
            "agent.normalise_observations": True,
        }

    def __init__(self, eval_episode_length: int = 50, hard_reset_every: int = 100_000,
                 success_threshold: float = 0.05):
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        model = self.mj_model
        self._grip_qpos = int(model.joint("grip_x").qposadr[0])  # x, y, z slides are consecutive
        # The workspace of the grip site is the slide joints' range (assets/fetch_scene.xml).
        grip_range = np.array([model.joint(f"grip_{axis}").range for axis in "xyz"])
        self.workspace_low, self.workspace_high = grip_range[:, 0], grip_range[:, 1]
        self._finger_qpos = int(model.joint("r_gripper_finger_joint").qposadr[0])  # r, then l
        self._finger_dof = int(model.joint("r_gripper_finger_joint").dofadr[0])
        block_joint = model.body("object0").jntadr[0]
        self._block_dof = int(model.jnt_dofadr[block_joint])
        layout = (self._grip_qpos, self._finger_qpos, model.jnt_qposadr[block_joint], model.nq)
        assert layout == (0, 3, BLOCK_POSITION.start, BLOCK_QUATERNION.stop), f"qpos layout {layout}"
        self._block_origin = jnp.asarray(self._place_block_body(), jnp.float32)
        self.mjx_model = put_mjx_model(self.mj_model)
        self._empty_data = mjx.make_data(self.mjx_model)

    def _place_block_body(self) -> np.ndarray:
        """Moves the block body if the task needs it; returns the world position of block qpos 0."""
        return np.zeros(3)

    # ---- observation ---------------------------------------------------------------------------
    def _observe(self, data: mjx.Data) -> jax.Array:
        # From qpos, not site_xpos: after mjx.step the kinematics are one substep (0.01 s) stale.
        # Both sites sit at their body origins; the block's joints give its position and quaternion.
        grip = data.qpos[self._grip_qpos : self._grip_qpos + 3]
        block = self._block_origin + data.qpos[BLOCK_POSITION]
        block_mat = matrix_from_quaternion(data.qpos[BLOCK_QUATERNION])
        grip_vel = data.qvel[self._grip_qpos : self._grip_qpos + 3]  # the grip site rides the slides
        block_vel = data.qvel[self._block_dof : self._block_dof + 3]
        block_angvel = block_mat @ data.qvel[self._block_dof + 3 : self._block_dof + 6]  # local -> world
        fingers = data.qpos[self._finger_qpos : self._finger_qpos + 2]
        finger_vel = data.qvel[self._finger_dof : self._finger_dof + 2]
        dt = self.dt
        return jnp.concatenate([
            grip, block, block - grip, fingers, euler_from_matrix(block_mat),
            (block_vel - grip_vel) * dt, block_angvel * dt, grip_vel * dt, finger_vel * dt,
        ])

    def _goal_observation(self, block: jax.Array, held: jax.Array) -> jax.Array:
        """Block at `block` at rest; gripper holding it (held) or just above it with closed fingers."""
        grip = jnp.where(held, block, block + jnp.array([0.0, 0.0, GRIP_ABOVE_BLOCK]))
        fingers = jnp.where(held, FINGER_GRASP_WIDTH, 0.0) * jnp.ones(2)
        return jnp.concatenate([grip, block, block - grip, fingers, jnp.zeros(14)])

    # ---- brax Env contract -----------------------------------------------------------------------
    def _sample_block_start(self, rng: jax.Array) -> jax.Array:
        raise NotImplementedError

    def reset(self, rng: jax.Array) -> State:
        rng, key_block = jax.random.split(rng)
        block = self._sample_block_start(key_block)
        grip = jnp.asarray(self.gripper_start)
        block_qpos = jnp.concatenate([block - self._block_origin, jnp.array([1.0, 0.0, 0.0, 0.0])])
        qpos = jnp.concatenate([grip, jnp.zeros(2), block_qpos])
        data = self._empty_data.replace(
            qpos=qpos, qvel=jnp.zeros(self.mj_model.nv), ctrl=jnp.concatenate([grip, jnp.zeros(2)])
        )
        data = mjx.kinematics(self.mjx_model, data)
        return self._state(data, self._observe(data), rng)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state
        action = jnp.clip(action, -1.0, 1.0)
        grip = data.qpos[self._grip_qpos : self._grip_qpos + 3]
        target = jnp.clip(grip + MAX_DISPLACEMENT * action[:3], self.workspace_low, self.workspace_high)
        fingers = data.qpos[self._finger_qpos : self._finger_qpos + 2]
        finger_ctrl = jnp.clip(fingers + action[3], 0.0, FINGER_CTRL_MAX)
        if self.fingers_locked:
            finger_ctrl = jnp.zeros(2)
        data = data.replace(ctrl=jnp.concatenate([target, finger_ctrl]))
        data = physics_substeps(self.mjx_model, data, self.frames_per_step)
        if self.fingers_locked:
            finger = slice(self._finger_qpos, self._finger_qpos + 2)
            finger_dof = slice(self._finger_dof, self._finger_dof + 2)
            data = data.replace(qpos=data.qpos.at[finger].set(0.0), qvel=data.qvel.at[finger_dof].set(0.0))
        obs = self._observe(data)
        return state.replace(pipeline_state=data, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()))

    # ---- reset-free extension --------------------------------------------------------------------
    def _sample_goal_block(self, rng: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(block goal position (3,), held in the air?) from the task's goal distribution."""
        goal = jax.random.uniform(rng, (3,), minval=self.goal_low, maxval=self.goal_high)
        return goal, goal[2] > BLOCK_REST_Z + 1e-6

    def eval_goals(self, rng: jax.Array) -> jax.Array:
        block, held = self._sample_goal_block(rng)
        return self._goal_observation(block, held)

    def initial_states(self, rng: jax.Array) -> jax.Array:
        return self.reset(rng).obs

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        block = obs[3:6]
        to_start = distance_to_box(self.block_start_low, self.block_start_high, block)
        to_goal = distance_to_box(self.goal_low, self.goal_high, block)
        return jnp.minimum(to_start, to_goal) <= self.success_threshold

    def xy(self, obs: jax.Array) -> jax.Array:
        return obs[3:5]

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        grip_low, grip_high = self.workspace_low - 0.01, self.workspace_high + 0.01
        # The block stays over the table (walls or slide limits) and cannot rise far above the gripper.
        block_low = np.array([TABLE_LOW[0], TABLE_LOW[1], 0.39])
        block_high = np.array([TABLE_HIGH[0], TABLE_HIGH[1], self.workspace_high[2] + 0.2])
        low = np.concatenate([
            grip_low, block_low, block_low - grip_high, [-0.005, -0.005], [-np.pi] * 3,
            [-0.5] * 3, [-2.0] * 3, [-0.2] * 3, [-0.05] * 2,
        ])
        high = np.concatenate([
            grip_high, block_high, block_high - grip_low, [0.055, 0.055], [np.pi] * 3,
            [0.5] * 3, [2.0] * 3, [0.2] * 3, [0.05] * 2,
        ])
        return low.astype(np.float32), high.astype(np.float32)


class _FetchIBC(_Fetch):
    """IBC's versions: block on limited slides around the initial gripper xy, random block start."""

    xml_name = "fetch.xml"

    @property
    def block_center(self) -> np.ndarray:
        """Centre of the block's start box and confinement box (IBC_BLOCK_OFFSET from the gripper xy)."""
        return np.array([*self.gripper_start[:2], BLOCK_REST_Z]) + IBC_BLOCK_OFFSET

    def _place_block_body(self) -> np.ndarray:
        origin = self.block_center
        self.mj_model.body("object0").pos[:] = origin
        return origin

    def _sample_block_start(self, rng: jax.Array) -> jax.Array:
        """Offset uniform in +-0.15, at least 0.1 from 0 (first of 16 candidates), from block_center."""
        offsets = jax.random.uniform(rng, (16, 2), minval=-IBC_OBJ_RANGE, maxval=IBC_OBJ_RANGE)
        distance = jnp.linalg.norm(offsets, axis=-1)
        valid = distance >= IBC_MIN_START_DISTANCE
        first = jnp.argmax(valid)
        # All 16 too close has probability ~5e-8; then push the first one out to the minimum distance.
        fallback = offsets[0] * IBC_MIN_START_DISTANCE / jnp.maximum(distance[0], 1e-6)
        offset = jnp.where(valid[first], offsets[first], fallback)
        return jnp.asarray(self.block_center, jnp.float32) + jnp.concatenate([offset, jnp.zeros(1)])


class _FetchHard(_Fetch):
    """MoReFree's versions: free block walled in on the table, block start fixed up to a few mm."""

    xml_name = "fetch_hard.xml"

    def __init__(self, eval_episode_length: int = 50, hard_reset_every: int = 100_000,
                 success_threshold: float = 0.05, block_start_noise: float = 0.005):
        """block_start_noise: half-width (m) of the uniform xy jitter of the block start (0: fixed)."""
        if block_start_noise < 0:
            raise ValueError(f"{self.name}: block_start_noise must be >= 0, got {block_start_noise}")
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        self.block_start_noise = float(block_start_noise)
        jitter = np.array([block_start_noise, block_start_noise, 0.0])
        self.block_start_low, self.block_start_high = HARD_BLOCK_START - jitter, HARD_BLOCK_START + jitter

    def _sample_block_start(self, rng: jax.Array) -> jax.Array:
        return jax.random.uniform(rng, (3,), minval=self.block_start_low, maxval=self.block_start_high)


class FetchPush(_FetchIBC):
    name = "push"
    gripper_start = PUSH_GRIPPER_START
    fingers_locked = True
    block_start_low, block_start_high = ibc_box(PUSH_GRIPPER_START, offset=IBC_BLOCK_OFFSET)
    goal_low, goal_high = ibc_box(PUSH_GRIPPER_START)


class FetchPickPlace(_FetchIBC):
    name = "pick_place"
    side_view_dims, air_height = BLOCK_SIDE_VIEW, BLOCK_AIR_Z
    gripper_start = PICK_PLACE_GRIPPER_START
    block_start_low, block_start_high = ibc_box(PICK_PLACE_GRIPPER_START, offset=IBC_BLOCK_OFFSET)
    goal_low, goal_high = ibc_box(PICK_PLACE_GRIPPER_START, height=IBC_AIR_HEIGHT)

    def _sample_goal_block(self, rng: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Table-height goals, half of them lifted by U(0, 0.45) (the original's target_in_the_air)."""
        key_xy, key_air, key_height = jax.random.split(rng, 3)
        xy = jax.random.uniform(key_xy, (2,), minval=self.goal_low[:2], maxval=self.goal_high[:2])
        in_air = jax.random.bernoulli(key_air)
        lift = jnp.where(in_air, jax.random.uniform(key_height, (), maxval=IBC_AIR_HEIGHT), 0.0)
        return jnp.concatenate([xy, (BLOCK_REST_Z + lift)[None]]), in_air


class FetchPushHard(_FetchHard):
    name = "push_hard"
    gripper_start = PUSH_GRIPPER_START
    goal_low = HARD_BLOCK_START - np.array([0.15, 0.15, 0.0])
    goal_high = HARD_BLOCK_START + np.array([0.15, 0.15, 0.0])


class FetchPickPlaceHard(_FetchHard):
    name = "pick_place_hard"
    side_view_dims, air_height = BLOCK_SIDE_VIEW, BLOCK_AIR_Z
    gripper_start = PUSH_GRIPPER_START  # the paper: Push (hard)'s initial state
    goal_low = HARD_BLOCK_START + np.array([-0.025, -0.025, 0.05])
    goal_high = HARD_BLOCK_START + np.array([0.025, 0.025, 0.15])
