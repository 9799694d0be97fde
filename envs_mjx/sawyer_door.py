"""Sawyer Door (EARL `sawyer_door`, as MoReFree simplified it): close a door that starts open.

Control as the original (docs/tasks.md, "Sawyer Door"): action a in [-1, 1]^4; the mocap target moves by
a[0:3] / 100 (at most 1 cm per axis and step) and is clipped to the workspace box
[-0.5, 0.4, 0.05]..[0.5, 0.825, 0.5]; the hand follows the target through a soft equality (solref 0.02, 1);
the fingers get ctrl = [a3, -a3] on position actuators (kp 400). One step = 5 substeps of 0.0025 s.
Observation (7,): hand position, gripper opening clip(|right pad - left pad| / 0.1, 0, 1), handle
position. The goal part of the original's 14-D observation is not included (goals are passed
separately). The door starts open at -pi/3 + U(0, pi/10): the paper's "60 degree with noise sampled
from (0, 18) degree" for MoReFree's simplified door (EARL's code draws U(0, pi/20); the paper wins). The
only evaluation goal is the closed door with the hand at the handle and the gripper open (EARL's goal
vector); success when the handle is within 0.02 of its closed position (goal_dims 4, 5, 6).

Deviations from the original (all forced by MJX on CPU or by MoReFree's simplification):
- No Sawyer arm (7 mesh links, not MJX-friendly and ~1.4 s per substep): the hand is a body on three
  world-aligned slide joints, pulled to the mocap by a `connect` equality. Its orientation is fixed, as
  the original's weld (quat (1, 0, 1, 0)) holds it; the arm's own dynamics (joint damping 10) are gone.
- The reset places hand and mocap at the reference hand position (0.00592, 0.39968, 0.19493); the
  original holds the mocap at (0, 0.4, 0.2) and lets the arm sag onto that hand position. Gravity is
  zero: the door hinge is vertical, so gravity only made the hand sag below its target.
- Gripper: each finger is one box (claw and pad merged, half (0.01, 0.015, 0.045), centred at the hand
  position, closing along world x); open pads are 0.11 apart (opening 1.0), closed 0.04 apart (0.4).
  The gripper base is visual only.
- Door: leaf panel box and placement as the original; handle cylinders become capsules (stem; one bar
  covering both grip cylinders); the handle's base disc is left out. The hinge range is [-pi/3, 0]
  (MoReFree's stopper: the door opens at most 60 degrees) instead of [-1.4, 0]. The observed handle
  point is a marker geom at the original handle mesh's centre, so initial and goal handle positions
  match EARL's (0.01007, 0.47105, 0.10004) and (0.29072, 0.74286, 0.10004).
- Workspace box: Meta-World's hand box [-0.5, 0.4, 0.05]..[0.5, 1.0, 0.5] with y capped at 0.825, the
  "workspace box in front of the door" of MoReFree (whose numbers are not public): the pads reach the
  closed leaf's front face but never the frame, which therefore need not collide.
- Collisions: only finger pads against the leaf panel and the handle (frame, table, gripper base are
  visual), pyramidal friction cone, Newton with at most 4 iterations and 6 line-search iterations
  (original: elliptic, 50). Leaf density 54.4 gives the original leaf mass 0.111 kg; the hinge limit is
  stiffened (solreflimit 0.005, solimplimit 0.99 0.999) so pushing does not carry the door past it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from envs_mjx.base import ResetFreeEnv, learner_defaults, physics_substeps

MOCAP_STEP = 0.01  # metres of mocap displacement per unit action and axis
WORKSPACE_LOW = np.array([-0.5, 0.40, 0.05], np.float32)
# Meta-World's hand box with y capped in front of the door (MoReFree's numbers are unknown): the pads
# (half depth 0.015) reach the closed leaf's front face (y 0.84) but never the frame (y >= 0.844).
WORKSPACE_HIGH = np.array([0.5, 0.825, 0.5], np.float32)
OPENING_SCALE = 0.1  # finger distance that counts as fully open

HINGE = np.array([-0.085, 0.85], np.float32)  # hinge axis (world xy); door (0.1, 0.95) + leaf (-0.185, -0.1)
HANDLE_IN_LEAF = np.array([0.37572, -0.10714], np.float32)  # handle point in the leaf frame (xy)
HANDLE_Z = 0.10004
OPEN_ANGLE = -np.pi / 3  # the stopper: the door opens at most 60 degrees
INITIAL_NOISE = np.pi / 10  # initial angle = OPEN_ANGLE + U(0, INITIAL_NOISE): the paper's 0..18 degrees
INITIAL_HAND = np.array([0.00592, 0.39968, 0.19493], np.float32)


def handle_position(angle: jax.Array) -> jax.Array:
    """World position (3,) of the handle point for door angle `angle` (0 closed, negative open)."""
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    x, y = HANDLE_IN_LEAF
    return jnp.stack([HINGE[0] + cos * x - sin * y, HINGE[1] + sin * x + cos * y, jnp.asarray(HANDLE_Z)])


def door_angle_of_handle(handle: jax.Array) -> jax.Array:
    """Inverse of handle_position in the plane: the door angle (...) whose handle is nearest `handle`."""
    relative = handle[..., 0:2] - HINGE
    rest = np.arctan2(HANDLE_IN_LEAF[1], HANDLE_IN_LEAF[0])
    return jnp.arctan2(relative[..., 1], relative[..., 0]) - rest


def state_vector(hand: jax.Array, opening: jax.Array, handle: jax.Array) -> jax.Array:
    return jnp.concatenate([hand, jnp.reshape(opening, (1,)), handle])


# handle_position(0.0) (cos 1, sin 0) in numpy, bit for bit: a jnp call here would start JAX's backend on
# import, too early for morefree_jax.runtime.configure()
GOAL_HANDLE = np.array([HINGE[0] + HANDLE_IN_LEAF[0], HINGE[1] + HANDLE_IN_LEAF[1], HANDLE_Z], np.float32)
GOAL_STATE = np.concatenate([GOAL_HANDLE, [1.0], GOAL_HANDLE]).astype(np.float32)


class SawyerDoor(ResetFreeEnv):
    name = "sawyer_door"
    xml_name = "sawyer_door.xml"
    obs_size = 7
    act_size = 4
    goal_dims = (4, 5, 6)
    frames_per_step = 5

    @classmethod
    def default_config(cls) -> dict:
        """No PEG config exists. Learner: PEG's 3-block-stacking values (entropy 1e-5, negatives 0.1), its
        closest task (a gripper manipulating an object). Train ratio 5 (paper), budget 4e5 steps (the paper:
        2 hard resets at one per 2e5 steps), prefill 2500 steps (PEG's point maze and ant maze; its config
        default is 10000: choice) and subgoal threshold 2 (PEG's walker and ant maze; choice). Planner:
        PEG's default MPPI (gamma 10, last 10 steps), std_scale 0.5 for a workspace of ~0.5 m (choice),
        horizon 150 = H_G."""
        return {
            "run.total_steps": 400_000, "run.prefill": 2_500, "run.train_every": 5,
            "run.subgoal_threshold": 2.0,
            **learner_defaults(entropy=1e-5, discount=0.99, p2e_discount=0.99, neg_factor=0.1),
            "planner.method": "mppi", "planner.num_candidates": 500, "planner.iterations": 5,
            "planner.mppi_temperature": 10.0, "planner.init_std": 0.5, "planner.horizon": 150,
            "planner.use_last_steps": 10, "planner.init_mean": "current",
        }

    def __init__(self, eval_episode_length=300, hard_reset_every=200_000, success_threshold=0.02):
        super().__init__(eval_episode_length, hard_reset_every, success_threshold)
        m = self.mj_model
        joint = {name: m.jnt_qposadr[m.joint(name).id] for name in ("hand_x", "doorjoint")}
        self._hand_qpos = slice(int(joint["hand_x"]), int(joint["hand_x"]) + 3)
        self._door_qpos = int(joint["doorjoint"])
        self._hand_body = m.body("hand").id
        self._handle_geom = m.geom("handle").id
        self._pad_sites = (m.site("rightEndEffector").id, m.site("leftEndEffector").id)
        self._template = mjx.make_data(self.mjx_model)

    # ---- brax Env contract -------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        key_angle, key_info = jax.random.split(rng)
        angle = OPEN_ANGLE + jax.random.uniform(key_angle, (), minval=0.0, maxval=INITIAL_NOISE)
        qpos = self._template.qpos.at[self._hand_qpos].set(INITIAL_HAND).at[self._door_qpos].set(angle)
        data = self._template.replace(
            qpos=qpos,
            mocap_pos=jnp.asarray(INITIAL_HAND)[None],
            ctrl=jnp.array([-1.0, 1.0]),  # fingers open, as the original's hand reset
        )
        # Kinematics suffice: every mjx.step recomputes the rest from qpos, qvel, mocap and ctrl.
        data = mjx.kinematics(self.mjx_model, data)
        return self._state(data, self.observe(data), key_info)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.pipeline_state
        action = jnp.clip(action, -1.0, 1.0).astype(data.ctrl.dtype)  # strips a weak type (else: retrace)
        mocap = jnp.clip(data.mocap_pos + MOCAP_STEP * action[0:3], WORKSPACE_LOW, WORKSPACE_HIGH)
        data = data.replace(mocap_pos=mocap, ctrl=jnp.stack([action[3], -action[3]]))
        data = physics_substeps(self.mjx_model, data, self.frames_per_step)
        return state.replace(pipeline_state=data, obs=self.observe(data))

    def observe(self, data: mjx.Data) -> jax.Array:
        """(7,) hand xyz, gripper opening, handle xyz, read from the data's kinematics (as the original)."""
        right, left = self._pad_sites
        distance = jnp.linalg.norm(data.site_xpos[right] - data.site_xpos[left])
        opening = jnp.clip(distance / OPENING_SCALE, 0.0, 1.0)
        return state_vector(data.xpos[self._hand_body], opening, data.geom_xpos[self._handle_geom])

    def door_angle(self, data: mjx.Data) -> jax.Array:
        return data.qpos[..., self._door_qpos]

    # ---- reset-free extension ----------------------------------------------------------------
    def eval_goals(self, rng: jax.Array) -> jax.Array:
        del rng  # a single goal, as in EARL
        return jnp.asarray(GOAL_STATE)

    def initial_states(self, rng: jax.Array) -> jax.Array:
        angle = OPEN_ANGLE + jax.random.uniform(rng, (), minval=0.0, maxval=INITIAL_NOISE)
        return state_vector(jnp.asarray(INITIAL_HAND), jnp.ones(()), handle_position(angle))

    def task_relevant(self, obs: jax.Array) -> jax.Array:
        handle = obs[4:7]
        nearest_angle = jnp.clip(door_angle_of_handle(handle), OPEN_ANGLE, OPEN_ANGLE + INITIAL_NOISE)
        candidates = jnp.stack(
            [
                handle_position(nearest_angle),
                handle_position(OPEN_ANGLE),
                handle_position(OPEN_ANGLE + INITIAL_NOISE),
                jnp.asarray(GOAL_HANDLE),
            ]
        )
        distance = jnp.min(jnp.linalg.norm(candidates - handle, axis=-1))
        return distance < self.success_threshold

    def xy(self, obs: jax.Array) -> jax.Array:
        return obs[4:6]  # the handle

    @property
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        margin = 0.02  # the hand lags its clipped target by up to about a centimetre
        # Evaluated eagerly: the bounds are read while collect_chunk is traced, where jnp ops would stage.
        with jax.ensure_compile_time_eval():
            arc = np.asarray(jax.vmap(handle_position)(jnp.linspace(OPEN_ANGLE, 0.0, 61)))
        low = np.concatenate([WORKSPACE_LOW - margin, [0.0], arc.min(0) - margin])
        high = np.concatenate([WORKSPACE_HIGH + margin, [1.0], arc.max(0) + margin])
        return low.astype(np.float32), high.astype(np.float32)


