"""The task API: brax's `Env` contract plus the reset-free extension.

Every task is an unbatched brax `Env` (`reset(rng) -> State`, `step(state, action) -> State`) whose
`pipeline_state` is an `mjx.Data` of the task's MJCF model, so brax wrappers and trainers run on it and
the state can be rendered or compared with C MuJoCo. Batch with `jax.vmap`. Step-time randomness lives in
`state.info["rng"]` and is split afresh on every use.

The reset-free extension (docs/tasks.md, "The task API"):
  eval_goals(rng) / initial_states(rng)  one sample of the evaluation-goal / initial-state distribution,
                                         as an observation vector (goal space = observation space)
  evaluation_goals(rng, num_episodes)    the goals of one evaluation (default: independent eval_goals)
  goal_dims                              observation indices that success depends on
  success(obs, goal)                     ||obs[goal_dims] - goal[goal_dims]|| < success_threshold
  reward(obs, goal)                      dense -distance on goal_dims (for reward-using baselines)
  task_relevant(obs)                     near an initial state or an evaluation goal
  xy(obs)                                the planar position shown in visitation heatmaps
  side_view(obs), air_height             (optional) horizontal position and height of the object, for a
                                         side visitation heatmap where lifting matters (side_view_dims set)
  observation_bounds                     (low, high) box of plausible observations, for goal search
  eval_episode_length, hard_reset_every  episodic evaluation length, hard-reset period of the stream
  default_config()                       the task's own defaults for a training run (PEG's per-task
                                         values, train ratio, budget, prefill, planner), as dotted keys
"""

from __future__ import annotations

import abc
import pathlib
from typing import ClassVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

ASSETS = pathlib.Path(__file__).parent / "assets"


def load_mj_model(xml_name: str) -> mujoco.MjModel:
    """Loads an MJCF file from envs_mjx/assets."""
    return mujoco.MjModel.from_xml_path(str(ASSETS / xml_name))


def put_mjx_model(mj_model: mujoco.MjModel) -> mjx.Model:
    """The MJX model on CPU with the pure-JAX implementation (the only one that runs on CPU)."""
    return mjx.put_model(mj_model, impl="jax")


def physics_substeps(model: mjx.Model, data: mjx.Data, num_substeps: int) -> mjx.Data:
    """Advances MJX physics `num_substeps` times with the controls already in `data`."""

    def substep(d, _):
        return mjx.step(model, d), None

    data, _ = jax.lax.scan(substep, data, None, length=num_substeps)
    return data


def clip_action(action: jax.Array) -> jax.Array:
    """Actions clipped to [-1, 1] as strong float32, so a weakly typed input (e.g. `jnp.full(n, 0.5)`)
    cannot change the state's dtypes and force a retrace of a jitted step."""
    return jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)


def distance_within(points: jax.Array, x: jax.Array) -> jax.Array:
    """Euclidean distance from x (D,) to the nearest of points (N, D)."""
    return jnp.min(jnp.linalg.norm(points - x, axis=-1))


def distance_to_box(low: jax.Array, high: jax.Array, x: jax.Array) -> jax.Array:
    """Euclidean distance from x to the axis-aligned box [low, high] (0 inside)."""
    return jnp.linalg.norm(x - jnp.clip(x, low, high))


def learner_defaults(entropy: float, discount: float, p2e_discount: float, neg_factor: float) -> dict:
    """PEG's per-task learner keys (actor_ent, discount, p2e_discount, dd_neg_sampling_factor;
    docs/tasks.md, "Per-task defaults") as dotted config keys. The Plan2Explore actor-critic shares the
    goal-conditioned one's entropy scale: PEG gives both learners the same actor, critic, optimiser,
    horizon, lambda and entropy settings (docs/learner.md, "Plan2Explore")."""
    return {"agent.gc.entropy": entropy, "agent.explore.ac.entropy": entropy, "agent.gc.discount": discount,
            "agent.explore.ac.discount": p2e_discount, "agent.distance.neg_factor": neg_factor}


class ResetFreeEnv(Env, abc.ABC):
    """Base of every task. Subclasses set the class attributes and implement the abstract methods.

    Constructor keyword arguments are the task's overridable settings (`envs_mjx.make(name, **overrides)`).
    """

    name: ClassVar[str]
    xml_name: ClassVar[str]
    obs_size: ClassVar[int]
    act_size: ClassVar[int]
    goal_dims: ClassVar[tuple[int, ...]]
    # Observation indices (horizontal, height) of the side visitation view, and the height above which the
    # object is in the air; only tasks where lifting an object matters set them (the paper's XZ heatmap).
    side_view_dims: ClassVar[tuple[int, int] | None] = None
    air_height: ClassVar[float | None] = None

    def __init__(self, eval_episode_length: int, hard_reset_every: int, success_threshold: float):
        if eval_episode_length <= 0 or hard_reset_every <= 0 or success_threshold <= 0:
            raise ValueError(
                f"{self.name}: eval_episode_length, hard_reset_every and success_threshold must be positive"
            )
        self.eval_episode_length = int(eval_episode_length)
        self.hard_reset_every = int(hard_reset_every)
        self.success_threshold = float(success_threshold)
        self.mj_model = load_mj_model(self.xml_name)
        self.mjx_model = put_mjx_model(self.mj_model)

    # ---- brax Env contract -------------------------------------------------------------------
    @abc.abstractmethod
    def reset(self, rng: jax.Array) -> State:
        """A fresh state drawn from the task's initial-state distribution (a hard reset)."""

    @abc.abstractmethod
    def step(self, state: State, action: jax.Array) -> State:
        """One control step; `action` in [-1, 1]^action_size. `done` is always 0 (never terminates)."""

    @property
    def observation_size(self) -> int:
        return self.obs_size

    @property
    def action_size(self) -> int:
        return self.act_size

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Seconds of simulated time per control step."""
        return float(self.mj_model.opt.timestep) * self.frames_per_step

    frames_per_step: ClassVar[int] = 1

    @classmethod
    @abc.abstractmethod
    def default_config(cls) -> dict:
        """The task's defaults for a training run, {dotted config key: value} (mujoco_playground's
        `default_config()` in spirit): run.total_steps (budget), run.prefill, run.train_every (the paper's
        train ratio), run.subgoal_threshold, PEG's per-task learner values (`learner_defaults`) and the
        planner.* settings. config.resolve_config layers them over the preset and under the variant
        and the user's keys, and config.json records the resolved values."""

    # ---- reset-free extension ----------------------------------------------------------------
    @abc.abstractmethod
    def eval_goals(self, rng: jax.Array) -> jax.Array:
        """One evaluation goal as a full observation vector (obs_size,)."""

    @abc.abstractmethod
    def initial_states(self, rng: jax.Array) -> jax.Array:
        """One initial state as a full observation vector (obs_size,)."""

    def evaluation_goals(self, rng: jax.Array, num_episodes: int) -> jax.Array:
        """The goals (num_episodes, obs_size) of one episodic evaluation: independent draws of eval_goals
        unless the task's evaluation fixes their order."""
        return jax.vmap(self.eval_goals)(jax.random.split(rng, num_episodes))

    @abc.abstractmethod
    def task_relevant(self, obs: jax.Array) -> jax.Array:
        """True where obs is within the success radius of an initial state or an evaluation goal."""

    @abc.abstractmethod
    def xy(self, obs: jax.Array) -> jax.Array:
        """The planar position (2,) used for visitation heatmaps."""

    def side_view(self, obs: jax.Array) -> jax.Array:
        """(horizontal, height) (2,) of the side visitation heatmap; tasks with side_view_dims only."""
        if self.side_view_dims is None:
            raise ValueError(f"{self.name} has no side view (only tasks that set side_view_dims do)")
        return obs[..., jnp.asarray(self.side_view_dims)]

    @property
    @abc.abstractmethod
    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) bounds of plausible observations; goal search clips candidates to them."""

    def goal_distance(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        """Euclidean distance between obs and goal on goal_dims."""
        dims = jnp.asarray(self.goal_dims)
        return jnp.linalg.norm(obs[..., dims] - goal[..., dims], axis=-1)

    def success(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        return self.goal_distance(obs, goal) < self.success_threshold

    def reward(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        """Dense reward -distance on goal_dims (only the model-free baselines use rewards)."""
        return -self.goal_distance(obs, goal)

    # ---- helpers shared by the tasks ---------------------------------------------------------
    def _state(self, data: mjx.Data, obs: jax.Array, rng: jax.Array) -> State:
        zero = jnp.zeros(())
        return State(pipeline_state=data, obs=obs, reward=zero, done=zero, metrics={}, info={"rng": rng})

    def mj_data_from(self, data: mjx.Data) -> mujoco.MjData:
        """A C MuJoCo MjData holding the same qpos/qvel/mocap as `data` (for rendering and checks)."""
        mj_data = mujoco.MjData(self.mj_model)
        mj_data.qpos[:] = np.asarray(data.qpos)
        mj_data.qvel[:] = np.asarray(data.qvel)
        if self.mj_model.nmocap:
            mj_data.mocap_pos[:] = np.asarray(data.mocap_pos)
            mj_data.mocap_quat[:] = np.asarray(data.mocap_quat)
        mujoco.mj_forward(self.mj_model, mj_data)
        return mj_data

    def render(self, data: mjx.Data, width: int = 320, height: int = 240, camera: int | str = -1):
        """An RGB frame (H, W, 3) of an unbatched pipeline state, rendered by C MuJoCo (no GPU needed)."""
        return self.render_frames([data], width, height, camera)[0]

    def render_frames(self, datas, width: int = 320, height: int = 240, camera: int | str = -1) -> np.ndarray:
        """RGB frames (T, H, W, 3) of an iterable of unbatched pipeline states, through one renderer: making
        a renderer costs more than rendering a frame (docs/performance.md, "Rendering")."""
        with mujoco.Renderer(self.mj_model, height=height, width=width) as renderer:
            frames = []
            for data in datas:
                renderer.update_scene(self.mj_data_from(data), camera=camera)
                frames.append(renderer.render())
        return np.stack(frames)
