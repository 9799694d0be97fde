"""PointUMaze's MJX step against C MuJoCo running the original's step on the same MJCF (env.mj_model).

The reference (`reference_step`) is the original's step in float64 C MuJoCo: turn (wrap once) and move in
qpos, clip qvel, mj_forward, one mj_step (RK4), the manual wall rule from the old xy (numpy, written here
independently of the env's), write xy, mj_forward. The env runs the same in MJX (float32).

Measured (2026-11-29, seeds 0-9, 200 steps, MuJoCo 4.0 / MJX 3.17), and why the bounds are what they are:
  - free run from rest (qvel 0): no velocity until a wall is touched, so MJX and C agree to float32
    rounding (<= 1e-6) until C's first wall contact, and within 0.007 on that step. From then on they part:
    0.02-0.2 within 10 steps, O(1) within 50. Two sources, neither a bug of the port:
      * the floor contact is a coin toss (see envs_mjx/point_umaze.py): it exists only when rounding puts
        the sphere a hair into the floor, then damps the xy speed by x0.45-0.87 in one step. C (float64)
        and MJX (float32) toss differently for the same state but with the same odds: the contact exists
        in 18.6% (C) / 19.7% (MJX) of forward passes, xy speed kept over a step in free space: mean 0.879
        (C) / 0.867 (MJX), unchanged in 51% / 49% of steps (4,000 random states);
      * MJX's box-box routine (the arrow buried up to 0.7 in a block) reports the contact point on a face
        instead of midway, and in some poses other points and depths than C, so the friction torque differs.
  - one step from identical states (MJX set to C's qpos, qvel, qacc_warmstart): xy error median <= 4e-4,
    max 0.073 (random) / 0.020 (wall-seeking); heading error max 0.124. Velocities: of the velocity change
    C's physics makes on steps with a wall contact, MJX misses 10-25% (random) / 45-73% (wall-seeking:
    the arrow sits buried in the block with a vertical contact normal, where the two solvers settle the
    unbounded friction differently, ~0.04 apart every step); the previous decay-only port missed 100% /
    180-300%.
  - long runs (3,000 random steps, same actions, seeds 0-3): mean |v_xy| C 1.36-1.62 vs MJX 1.14-1.52
    (within 16%), mean |v_heading| 1.51-1.99 vs 1.40-1.69 (within 16%), share of steps with |v_xy| > 0.5
    0.57-0.63 vs 0.46-0.62; the decay-only port: mean |v_xy| <= 0.004.
So the tests assert exact agreement before the first contact, agreement on the first contact step, the
one-step agreement everywhere (with the impulse share that tells physics from the decay model), and the
long-run velocity statistics; they do not assert step-by-step agreement of long free runs, which the coin
toss alone rules out for any float32 port.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import cached_env

from envs_mjx.point_umaze import (
    COLLISION_RADIUS,
    MAX_TURN,
    RESTITUTION,
    VELOCITY_LIMIT,
    collide_with_walls,
    wall_faces,
)

ENV = "point_umaze"
STEPS = 200


# ---- the C MuJoCo reference: the original's step, in float64 --------------------------------------
def _first_crossing(faces: np.ndarray, start: np.ndarray, end: np.ndarray):
    """The first inflated wall face the segment start->end crosses: None, or (hit point, mirrored end)."""
    a, b = faces[:, 0], faces[:, 1]
    move, face = end - start, b - a
    cross = lambda p, q: p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]  # noqa: E731
    denom = cross(move, face)
    parallel = np.abs(denom) < 1e-12
    denom = np.where(parallel, 1.0, denom)
    t, u = cross(a - start, face) / denom, cross(a - start, move) / denom
    hits = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1) & (np.linalg.norm(move) > 1e-8)
    if not hits.any():
        return None
    k = np.argmin(np.where(hits, t, np.inf))
    along = face[k] / np.linalg.norm(face[k])
    foot = a[k] + np.dot(end - a[k], along) * along
    return start + t[k] * move, 2 * foot - end


def manual_rule(faces: np.ndarray, old_xy: np.ndarray, new_xy: np.ndarray) -> np.ndarray:
    """The original's collision rule: bounce off the first face crossed with restitution, else stay."""
    crossing = _first_crossing(faces, old_xy, new_xy)
    if crossing is None:
        return new_xy
    hit, mirrored = crossing
    bounced = hit + RESTITUTION * (mirrored - hit)
    return old_xy.copy() if _first_crossing(faces, old_xy, bounced) is not None else bounced


def reference_step(model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> bool:
    """One step of the original (docs/tasks.md, "PointUMaze"), in place: turn (wrap once) and move in qpos,
    clip qvel, set_state (mj_forward), one mj_step, the manual rule from the old xy, set_xy (mj_forward).
    Returns whether a wall block touched the point when the physics step began."""
    action = np.clip(action, -1.0, 1.0)
    old_xy = data.qpos[:2].copy()
    heading = data.qpos[2] + MAX_TURN * action[1]
    heading += -2 * np.pi if heading > np.pi else (2 * np.pi if heading < -np.pi else 0.0)
    data.qpos[:] = [*(old_xy + action[0] * np.array([np.cos(heading), np.sin(heading)])), heading]
    data.qvel[:] = np.clip(data.qvel, -VELOCITY_LIMIT, VELOCITY_LIMIT)
    mujoco.mj_forward(model, data)
    floor = model.geom("floor").id
    touched = any(c.dist < 0 and floor not in (c.geom1, c.geom2) for c in data.contact[: data.ncon])
    mujoco.mj_step(model, data)
    data.qpos[:2] = manual_rule(_faces(), old_xy, data.qpos[:2].copy())
    mujoco.mj_forward(model, data)
    return touched


def decay_only_step(qpos: np.ndarray, qvel: np.ndarray, action: np.ndarray, dt: float) -> np.ndarray:
    """The port's previous model, no contacts: kinematic move + qvel dt, the rule, qvel x (0.96, 0.96,
    0.9996). Only here to show that the bounds below tell it apart from the physics."""
    action = np.clip(action, -1.0, 1.0)
    heading = qpos[2] + MAX_TURN * action[1]
    heading += -2 * np.pi if heading > np.pi else (2 * np.pi if heading < -np.pi else 0.0)
    qvel = np.clip(qvel, -VELOCITY_LIMIT, VELOCITY_LIMIT)
    moved = qpos[:2] + action[0] * np.array([np.cos(heading), np.sin(heading)]) + qvel[:2] * dt
    xy = manual_rule(_faces(), qpos[:2], moved)
    return np.concatenate([xy, [heading + qvel[2] * dt], qvel * np.array([0.96, 0.96, 0.9996])])


@functools.cache
def _faces(radius: float = COLLISION_RADIUS) -> np.ndarray:
    return wall_faces(radius=radius).astype(np.float64)


def wall_seeking_action(qpos: np.ndarray) -> np.ndarray:
    """Full forward while turning toward the nearest point of a wall block, so the point hits walls."""
    a, b = _faces(0.0)[:, 0], _faces(0.0)[:, 1]
    along = np.clip(np.sum((qpos[:2] - a) * (b - a), -1) / np.sum((b - a) ** 2, -1), 0.0, 1.0)
    nearest = a + along[:, None] * (b - a)
    delta = nearest[np.argmin(np.linalg.norm(nearest - qpos[:2], axis=-1))] - qpos[:2]
    error = (np.arctan2(delta[1], delta[0]) - qpos[2] + np.pi) % (2 * np.pi) - np.pi
    return np.array([1.0, np.clip(error / MAX_TURN, -1.0, 1.0)])


def reference_rollout(model, policy: str, seed: int, num_steps: int, qvel0=None):
    """C MuJoCo rollout from the reset distribution -> (states (T+1, 3 + 3 + 3) of qpos, qvel,
    qacc_warmstart before each step, actions (T, 2), wall_contact (T,) bool: a wall touched the point in
    the mj_step's first stage)."""
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(model)
    data.qpos[:] = rng.uniform(-0.1, 0.1, 3)
    data.qvel[:] = 0.1 * rng.normal(size=3) if qvel0 is None else qvel0
    mujoco.mj_forward(model, data)
    states, actions, wall_contact = [], [], []
    for _ in range(num_steps):
        states.append(np.concatenate([data.qpos, data.qvel, data.qacc_warmstart]))
        action = rng.uniform(-1.0, 1.0, 2) if policy == "random" else wall_seeking_action(data.qpos)
        actions.append(action)
        wall_contact.append(reference_step(model, data, action))
    states.append(np.concatenate([data.qpos, data.qvel, data.qacc_warmstart]))
    return np.array(states), np.array(actions), np.array(wall_contact)


# ---- the MJX side -------------------------------------------------------------------------------
@functools.cache
def jitted_step():
    env = cached_env(ENV)
    return jax.jit(env.step), jax.jit(env.reset)(jax.random.PRNGKey(0))


def mjx_from(template, state: np.ndarray):
    """A brax State whose pipeline state holds the C state (qpos, qvel, qacc_warmstart)."""
    data = template.pipeline_state.replace(
        qpos=jnp.asarray(state[:3], jnp.float32), qvel=jnp.asarray(state[3:6], jnp.float32),
        qacc_warmstart=jnp.asarray(state[6:9], jnp.float32))
    return template.replace(pipeline_state=data, obs=jnp.concatenate([data.qpos, data.qvel]))


def one_step_predictions(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """MJX's next (qpos, qvel) (T, 6) from each C state and action."""
    step, template = jitted_step()
    return np.array([np.asarray(step(mjx_from(template, s), jnp.asarray(a, jnp.float32)).obs)
                     for s, a in zip(states[:-1], actions, strict=True)])


def free_run(state0: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """MJX's own trajectory (T, 6) from the C start state under the same actions."""
    step, template = jitted_step()
    state, observations = mjx_from(template, state0), []
    for action in actions:
        state = step(state, jnp.asarray(action, jnp.float32))
        observations.append(np.asarray(state.obs))
    return np.array(observations)


def decay_only_rollout(state0: np.ndarray, actions: np.ndarray, dt: float) -> np.ndarray:
    """The decay-only model's trajectory (T, 6) from state0 under the actions."""
    state, observations = state0[:6], []
    for action in actions:
        state = decay_only_step(state[:3], state[3:6], action, dt)
        observations.append(state)
    return np.array(observations)


# ---- tests ----------------------------------------------------------------------------------------
def test_reference_rule_matches_env_rule():
    """The test's numpy rule and the env's JAX rule agree, so the reference checks physics, not the rule."""
    rng = np.random.default_rng(0)
    old = rng.uniform(-1.6, 9.6, (2000, 2))
    new = old + rng.uniform(-1.5, 1.5, (2000, 2))
    faces = jnp.asarray(wall_faces())
    ours = np.asarray(jax.jit(jax.vmap(collide_with_walls, (None, 0, 0)))(faces, old, new))
    reference = np.array([manual_rule(_faces(), o, n) for o, n in zip(old, new, strict=True)])
    assert np.abs(ours - reference).max() < 1e-4
    moved_by_rule = np.linalg.norm(reference - new, axis=-1) > 1e-6
    assert moved_by_rule.mean() > 0.1, "too few segments hit a wall to test the rule"


def test_free_run_from_rest_matches_c_until_first_wall_contact():
    env = cached_env(ENV)
    for seed in (1, 6):  # C's first wall contact at step 42 / 73 of these random-action runs
        states, actions, wall = reference_rollout(env.mj_model, "random", seed, 120, qvel0=np.zeros(3))
        first = int(np.argmax(wall))
        assert wall.any() and first > 30
        ours = free_run(states[0], actions[: first + 1])
        error = np.abs(ours[:, :3] - states[1 : first + 2, :3]).max(axis=-1)
        assert error[:first].max() < 1e-4, f"seed {seed}: diverged before any wall contact"
        assert error[first] < 0.02, f"seed {seed}: first wall contact off by {error[first]:.3f}"


@pytest.mark.parametrize(("policy", "max_missed", "decay_missed"),
                         [("random", 0.4, 0.9), ("wall", 0.85, 1.5)])
def test_one_step_from_c_states_matches_c(policy, max_missed, decay_missed):
    env = cached_env(ENV)
    states, actions, wall = reference_rollout(env.mj_model, policy, 0, STEPS)
    target, ours = states[1:, :6], one_step_predictions(states, actions)
    xy_error = np.linalg.norm(ours[:, :2] - target[:, :2], axis=-1)
    assert np.median(xy_error) < 2e-3 and xy_error.max() < 0.1
    assert np.abs(ours[:, 2] - target[:, 2]).max() < 0.15
    # Velocities: the share of C's velocity change on wall-contact steps that a model gets wrong.
    assert wall.sum() > 30
    change = np.abs(target[:, 3:] - np.clip(states[:-1, 3:6], -VELOCITY_LIMIT, VELOCITY_LIMIT)).sum(-1)
    decay = np.array([decay_only_step(state[:3], state[3:6], action, env.dt)
                      for state, action in zip(states[:-1], actions, strict=True)])

    def missed(prediction):
        return np.abs(prediction[wall, 3:] - target[wall, 3:]).sum() / change[wall].sum()

    assert missed(ours) < max_missed, f"MJX misses {missed(ours):.2f} of C's wall impulses"
    assert missed(decay) > decay_missed, "the bound would not tell the decay-only model from physics"


def velocity_statistics(observations: np.ndarray) -> np.ndarray:
    """mean |v_xy|, mean |v_heading|, share of steps with |v_xy| > 0.5."""
    speed = np.linalg.norm(observations[:, 3:5], axis=-1)
    return np.array([speed.mean(), np.abs(observations[:, 5]).mean(), np.mean(speed > 0.5)])


def test_long_run_velocity_statistics_match_c():
    env = cached_env(ENV)
    states, actions, _ = reference_rollout(env.mj_model, "random", 0, 3000)
    reference = velocity_statistics(states[1:, :6])
    ours = velocity_statistics(free_run(states[0], actions))
    assert reference[0] > 1.0, "C's runs should move on their own after wall hits"
    np.testing.assert_allclose(ours[:2], reference[:2], rtol=0.3)
    assert abs(ours[2] - reference[2]) < 0.12
    decay = velocity_statistics(decay_only_rollout(states[0], actions, env.dt))
    assert decay[0] < 0.3 * reference[0], "the bound would not tell the decay-only model from physics"


def test_max_geom_pairs_keeps_every_touching_wall(monkeypatch):
    """The MJCF lets MJX collide each agent geom with its `max_geom_pairs` nearest blocks only (nearest by
    bounding-sphere gap, as MJX ranks them): every block C MuJoCo finds touching must be among them."""
    env = cached_env(ENV)
    model = env.mj_model
    limit = int(model.numeric("max_geom_pairs").data[0])
    walls = np.array([i for i in range(model.ngeom) if model.geom(i).name.startswith("wall")])
    agent = {model.geom("pointbody").id, model.geom("pointarrow").id}
    worst, original_step = 0, mujoco.mj_step

    def ranked_step(m, d):  # runs on the state mj_step starts from, after the kinematic move
        nonlocal worst
        for c in d.contact[: d.ncon]:
            geom, other = (c.geom1, c.geom2) if c.geom1 in agent else (c.geom2, c.geom1)
            if c.dist < 0 and geom in agent and other in walls:
                gap = np.linalg.norm(d.geom_xpos[walls] - d.geom_xpos[geom], axis=-1) - m.geom_rbound[walls]
                worst = max(worst, 1 + int(np.sum(gap < gap[list(walls).index(other)])))
        original_step(m, d)

    monkeypatch.setattr(mujoco, "mj_step", ranked_step)
    for policy in ("random", "wall"):
        reference_rollout(model, policy, 3, 1500)
    assert 2 <= worst <= limit
