"""IBC's bidirectional goal curriculum (docs/baselines.md, "Curriculum"; HGG's trajectory pool and matching).

    curriculum = Curriculum(env, task, config.baseline.ibc, discount)
    state = curriculum.init(key)
    state = curriculum.record(state, obs, next_obs, segment_step)    # each forward step
    state = curriculum.end_forward(state, length, value_fn, key)     # pool push; matching at 5, 20, 40, ...
    goal = curriculum.forward_goal(state, obs, key)                  # a slot's goal + noise, or a task goal
    goal = curriculum.backward_goal(state, obs, key)                 # a slot's first state + noise

The pool keeps the achieved goals (ibc_tasks.forward_goal_dims: the whole state in the EARL tasks, else
env.goal_dims) of recent forward segments with each one's first state. The matching pairs each of `slots`
curriculum slots (slot j serves desired goal j % K and its own initial state) with one pool trajectory i
at least cost
    min_t [ |ag_it - g_j| - V_it max_dis (1 - discount) / L ] + c |proprio(s_i0) - proprio(init_j)|,
distances on env.goal_dims, V_it the forward critic's value of reaching ag_it from s_i0 (value_fn),
clipped to [-1/(1-discount), 0]. Slot j's forward goal becomes ag at the minimising t, its backward goal
the trajectory's first state. A pool holding fewer trajectories than it can is padded by repeating them
(IBC's TrajectoryPool.pad), so one trajectory can serve several slots. Goals are then drawn from the slots
independently: a forward goal and the backward goal after it come from separate uniform draws (IBC's
train.py), so the pairing acts through the matching's costs, not through the draws.

The valuation and costs are compiled (a lax.map over the pool, in the scan); the assignment itself is
scipy's linear_sum_assignment through jax.pure_callback (IBC's min-cost flow solves the same problem). It
runs only under a lazy_cond at the matching segments (every `match_every` forward segments, i.e. every
thousand or more env steps), on a (slots, pool_size) matrix, so the host round trip is rare and the chunk
stays one fused call; the compiled valuation is nearly all of a matching's cost
(docs/baselines.md, "Where the matching runs").
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.optimize import linear_sum_assignment

from morefree_jax.baselines.baseline_config import IBCConfig
from morefree_jax.baselines.ibc.tasks import IBCTask, corridor_points, forward_goal_dims, proprio_reached
from morefree_jax.batching import lazy_cond

NO_MATCH = 1e9  # cost of an empty pool row: never preferred over a real trajectory
RESET_SAMPLES = 1000  # IBC: 1000 env resets before training (max_dis, target pairs)


@struct.dataclass
class CurriculumState:
    pool_goals: jax.Array  # (P, L, F) achieved goals (forward_goal_dims) of forward segments
    pool_lengths: jax.Array  # (P,) steps of each
    pool_first: jax.Array  # (P, O) each one's first state
    pool_count: jax.Array  # trajectories ever pushed (FIFO of P)
    trace: jax.Array  # (L, F) the open forward segment's achieved goals
    trace_first: jax.Array  # (O,) its first state
    trace_last: jax.Array  # (O,) its latest state
    forward_slots: jax.Array  # (S, O) curriculum goals (forward_goal_dims hold them)
    backward_slots: jax.Array  # (S, O) backward goals: first states of the matched trajectories
    forward_segments: jax.Array  # forward segments ended
    matches: jax.Array  # matchings run
    target_init: jax.Array  # (K, O) the target pairs' initial states (noised once, except in EARL tasks)
    target_goal: jax.Array  # (K, O) and desired goals
    max_dis: jax.Array  # largest |ag - g| over RESET_SAMPLES resets and task goals


def assignment(cost: np.ndarray) -> np.ndarray:
    """For each row of a (rows, cols) cost matrix, rows <= cols, its column in the least-cost one-to-one
    assignment (scipy's linear_sum_assignment; rows come back in order)."""
    rows, cols = linear_sum_assignment(np.asarray(cost, np.float64))
    out = np.zeros(cost.shape[0], np.int32)
    out[rows] = cols
    return out


def assign_on_host(cost: jax.Array) -> jax.Array:
    """assignment() from compiled code (a host callback; one call per seed under vmap)."""
    shape = jax.ShapeDtypeStruct(cost.shape[:1], jnp.int32)
    return jax.pure_callback(assignment, shape, cost, vmap_method="sequential")


def matching_costs(goals, lengths, first_proprio, valid, values, target_goal, target_proprio, max_dis,
                   discount: float, cost_c: float, cost_l: float):
    """(cost (S, P), t* (S, P)) of pairing slot j with pool trajectory i (module docstring).
    goals (P, L, G), lengths (P,), first_proprio (P, D), valid (P,), values (P, L), target_goal (S, G),
    target_proprio (S, D)."""
    distance = jnp.linalg.norm(goals[None] - target_goal[:, None, None], axis=-1)  # (S, P, L)
    per_step = distance - values[None] * max_dis * (1.0 - discount) / cost_l
    in_segment = jnp.arange(goals.shape[1])[None, None] < lengths[None, :, None]
    per_step = jnp.where(in_segment, per_step, jnp.inf)
    best_t = jnp.argmin(per_step, axis=-1)
    start = jnp.linalg.norm(first_proprio[None] - target_proprio[:, None], axis=-1)
    cost = jnp.min(per_step, axis=-1) + cost_c * start
    return jnp.where(valid[None], cost, NO_MATCH), best_t


def padded_rows(pool_count, pool_size: int) -> jax.Array:
    """(pool_size,) the stored row each matching column reads: the filled rows repeated in insertion order
    until the pool's length (IBC's TrajectoryPool.pad, num_episodes = pool_length 1000), so a pool of n < P
    trajectories offers each one about P / n times. A full pool maps to itself; an empty one to row 0,
    whose cost stays NO_MATCH."""
    filled = jnp.clip(pool_count, 1, pool_size)
    return jnp.arange(pool_size) % filled


@dataclasses.dataclass(frozen=True)
class Curriculum:
    env: Any
    task: IBCTask
    config: IBCConfig
    discount: float

    @property
    def goal_dims(self) -> jax.Array:
        return jnp.asarray(self.env.goal_dims)

    @property
    def forward_dims(self) -> jax.Array:
        """Observation indices of a stored achieved goal and of a forward goal the agent sees."""
        return jnp.asarray(forward_goal_dims(self.task, self.env))

    @property
    def goal_positions(self) -> jax.Array:
        """Where env.goal_dims sit among forward_dims: the costs measure distance on those only."""
        forward = list(forward_goal_dims(self.task, self.env))
        return jnp.asarray([forward.index(int(d)) for d in self.env.goal_dims])

    @property
    def proprio_dims(self) -> jax.Array:
        return jnp.asarray(self.task.proprio_dims)

    def init(self, key) -> CurriculumState:
        key_targets, key_far, key_slots, key_noise, key_back, key_init = jax.random.split(key, 6)
        target_init, target_goal = self.target_pairs(key_targets)
        if not self.task.earl:  # IBC noises its K predetermined initial states once (train.py)
            target_init = self.noisy_initial_states(target_init, key_init)
        far_init, far_goal = self.reset_pairs(key_far, RESET_SAMPLES)
        max_dis = jnp.max(jnp.linalg.norm(far_init[:, self.goal_dims] - far_goal[:, self.goal_dims], axis=-1))
        # Before the first matching both slot sets are an initial state + N(0, success threshold) on the
        # entries they hold (IBC's MatchSampler.__init__: pool and pool_inits_for_backward_proprioceptive).
        slots, obs_size, cfg = self.config.slots, self.env.observation_size, self.config
        starts, _ = self.reset_pairs(key_slots, slots)
        forward = self.with_normal_noise(starts, self.forward_dims, self.env.success_threshold, key_noise)
        backward_dims = self.forward_dims if self.task.earl else self.proprio_dims  # EARL: whole states
        backward = self.with_normal_noise(starts, backward_dims, self.env.success_threshold, key_back)
        length, width = self.task.segment_length, len(forward_goal_dims(self.task, self.env))
        return CurriculumState(
            pool_goals=jnp.zeros((cfg.pool_size, length, width)),
            pool_lengths=jnp.zeros(cfg.pool_size, jnp.int32),
            pool_first=jnp.zeros((cfg.pool_size, obs_size)), pool_count=jnp.zeros((), jnp.int32),
            trace=jnp.zeros((length, width)), trace_first=jnp.zeros(obs_size), trace_last=jnp.zeros(obs_size),
            forward_slots=forward, backward_slots=backward,
            forward_segments=jnp.zeros((), jnp.int32), matches=jnp.zeros((), jnp.int32),
            target_init=target_init, target_goal=target_goal, max_dis=max_dis)

    @staticmethod
    def with_normal_noise(states, dims, std: float, key) -> jax.Array:
        """states (N, O) with N(0, std) added on `dims`."""
        noise = std * jax.random.normal(key, (states.shape[0], dims.shape[0]))
        return states.at[:, dims].add(noise)

    def clip_to_bounds(self, goal, dims) -> jax.Array:
        """goal with `dims` clipped to the observation bounds (IBC clips Tabletop's positions to its +-2.8
        table and Fetch's gripper z to [0.42, 1]; the task's observation box holds both)."""
        low, high = (jnp.asarray(bound)[dims] for bound in self.env.observation_bounds)
        return goal.at[..., dims].set(jnp.clip(goal[..., dims], low, high))

    def noisy_initial_states(self, states, key) -> jax.Array:
        """states (N, O) + uniform +- task.init_noise on every entry, clipped to the observation bounds
        (IBC's add_noise_to_goal on the target pairs' initial goals; backward goals get MatchSampler.add_noise
        instead: backward_goal; docs/baselines.md, "IBC's choices and deviations")."""
        size = self.task.init_noise
        noisy = states + jax.random.uniform(key, states.shape, minval=-size, maxval=size)
        return self.clip_to_bounds(noisy, jnp.arange(states.shape[-1]))

    def reset_pairs(self, key, count: int) -> tuple[jax.Array, jax.Array]:
        """`count` (initial state, task goal) draws, (count, O) each."""
        key_init, key_goal = jax.random.split(key)
        return (jax.vmap(self.env.initial_states)(jax.random.split(key_init, count)),
                jax.vmap(self.env.eval_goals)(jax.random.split(key_goal, count)))

    def target_pairs(self, key) -> tuple[jax.Array, jax.Array]:
        """K target pairs (docs/baselines.md, "Curriculum"): env draws; in the EARL tasks the first desired
        goal is the initial state itself (IBC's {initial, goal states}); on PointUMaze the desired goals are
        draws of IBC's 30 corridor points with uniform noise (ibc_tasks.corridor_points)."""
        key_pairs, key_point, key_noise = jax.random.split(key, 3)
        init, goal = self.reset_pairs(key_pairs, self.task.num_targets)
        if self.task.earl:
            goal = goal.at[0].set(init[0])
        if self.task.corridor:
            points = jnp.asarray(corridor_points(self.task), jnp.float32)
            chosen = points[jax.random.randint(key_point, (self.task.num_targets,), 0, len(points))]
            noise = self.task.corridor_noise
            chosen = chosen + jax.random.uniform(key_noise, chosen.shape, minval=-noise, maxval=noise)
            goal = goal.at[:, self.goal_dims].set(chosen)
        return init, goal

    def slot_initial_states(self, state: CurriculumState, key) -> jax.Array:
        """(S, O) each slot's initial state for this matching: in the EARL tasks a fresh reset per slot with
        fresh uniform noise (IBC's train.py resets its hgg env for each of the 50 before every update);
        elsewhere the K noised initial states, cycled."""
        if self.task.earl:
            starts = jax.vmap(self.env.initial_states)(jax.random.split(key, self.config.slots))
            return self.noisy_initial_states(starts, jax.random.fold_in(key, 1))
        return state.target_init[jnp.arange(self.config.slots) % self.task.num_targets]

    def record(self, state: CurriculumState, obs, next_obs, segment_step) -> CurriculumState:
        """One forward step: the achieved goal after it joins the open segment's trace."""
        first = jnp.where(segment_step == 0, obs, state.trace_first)
        trace = state.trace.at[segment_step].set(next_obs[self.forward_dims])
        return state.replace(trace=trace, trace_first=first, trace_last=next_obs)

    def end_forward(self, state: CurriculumState, length, value_fn, key) -> CurriculumState:
        """A forward segment of `length` steps ended: it joins the pool if the goal part or the agent part
        moved more than task.pool_move; at forward segment match_first and every match_every the slots
        are matched afresh."""
        moved = jnp.maximum(
            jnp.linalg.norm(state.trace_last[self.goal_dims] - state.trace_first[self.goal_dims]),
            jnp.linalg.norm(state.trace_last[self.proprio_dims] - state.trace_first[self.proprio_dims]))
        row = state.pool_count % self.config.pool_size
        push = moved > self.task.pool_move

        def put(array, value):
            return array.at[row].set(jnp.where(push, value, array[row]))

        segments = state.forward_segments + 1
        state = state.replace(pool_goals=put(state.pool_goals, state.trace),
                              pool_lengths=put(state.pool_lengths, length),
                              pool_first=put(state.pool_first, state.trace_first),
                              pool_count=state.pool_count + push.astype(jnp.int32), forward_segments=segments)
        due = (segments == self.config.match_first) | (segments % self.config.match_every == 0)
        return lazy_cond(due, lambda: self.match(state, value_fn, key), lambda: state)

    def pool_values(self, state: CurriculumState, value_fn, key) -> jax.Array:
        """V (P, L): value_fn(first state, goal = ag_t) per pool step, one trajectory at a time (bounded
        memory), clipped to [-1/(1-discount), 0]. Rows not yet filled are 0 without running the critic
        (their cost is NO_MATCH, and padding reads filled rows only): a pool of 1,000 fills only after
        1,000 forward segments."""
        template = jnp.zeros(self.env.observation_size)

        def one(args):
            goals, first, key_one, filled = args
            goal_obs = jax.vmap(lambda g: template.at[self.forward_dims].set(g))(goals)
            firsts = jnp.broadcast_to(first, goal_obs.shape)
            return lazy_cond(filled, lambda: value_fn(firsts, goal_obs, key_one),
                             lambda: jnp.zeros(goals.shape[0]))

        keys = jax.random.split(key, self.config.pool_size)
        filled = jnp.arange(self.config.pool_size) < state.pool_count
        values = jax.lax.map(one, (state.pool_goals, state.pool_first, keys, filled))
        return jnp.clip(values, -1.0 / (1.0 - self.discount), 0.0)

    def match(self, state: CurriculumState, value_fn, key) -> CurriculumState:
        """New slots from the least-cost assignment of slots to the padded pool (module docstring); with
        an empty pool the slots take the target pairs themselves (IBC's MatchSampler.update)."""
        key_values, key_inits = jax.random.split(key)
        values = self.pool_values(state, value_fn, key_values)
        valid = jnp.arange(self.config.pool_size) < state.pool_count
        target = jnp.arange(self.config.slots) % self.task.num_targets
        slot_init = self.slot_initial_states(state, key_inits)
        cost, best_t = matching_costs(
            state.pool_goals[..., self.goal_positions], state.pool_lengths,
            state.pool_first[:, self.proprio_dims], valid, values,
            state.target_goal[target][:, self.goal_dims], slot_init[:, self.proprio_dims], state.max_dis,
            self.discount, self.config.cost_c, self.config.cost_l)
        # IBC's TrajectoryPool.pad pads the pool before matching (docs/baselines.md, "Curriculum"), so
        # without padding a young pool would leave most slots on the task goals.
        rows = padded_rows(state.pool_count, self.config.pool_size)
        column = assign_on_host(cost[:, rows])
        row = rows[column]
        slots = jnp.arange(self.config.slots)
        matched = cost[slots, row] < NO_MATCH / 2
        ag = state.pool_goals[row, best_t[slots, row]]
        forward = jnp.where(matched[:, None], state.forward_slots.at[:, self.forward_dims].set(ag),
                            state.target_goal[target])
        backward = jnp.where(matched[:, None], state.pool_first[row], slot_init)
        return state.replace(forward_slots=forward, backward_slots=backward, matches=state.matches + 1)

    def forward_goal(self, state: CurriculumState, obs, key) -> jax.Array:
        """A uniform slot's goal + Gaussian noise on the task's noise dims, clipped to the task's
        forward_goal_box, drawn up to goal_draws times until obs does not already satisfy it; else a task
        goal (IBC's train.py)."""
        keys = jax.random.split(key, 2 * self.config.goal_draws + 1)
        noise_dims = self.goal_dims[jnp.asarray(self.task.curriculum_noise_dims)]
        goal = self.env.eval_goals(keys[-1])
        for draw in reversed(range(self.config.goal_draws)):  # the first unsatisfied draw wins
            candidate_slot = jax.random.randint(keys[2 * draw], (), 0, self.config.slots)
            noise = self.task.curriculum_noise * jax.random.normal(keys[2 * draw + 1], noise_dims.shape)
            candidate = self.clip_forward(state.forward_slots[candidate_slot].at[noise_dims].add(noise))
            goal = jnp.where(self.env.success(obs, candidate), goal, candidate)
        return goal

    def clip_forward(self, goal) -> jax.Array:
        """goal with the task's forward_goal_box applied (IBC clips its noised forward goals per task)."""
        for index, low, high in self.task.forward_goal_box:
            goal = goal.at[index].set(jnp.clip(goal[index], low, high))
        return goal

    def backward_goal(self, state: CurriculumState, obs, key) -> jax.Array:
        """A uniform slot's backward goal + N(0, curriculum_noise) on task.backward_noise_dims, clipped to
        the observation bounds, drawn up to goal_draws times until obs does not already reach it; the last
        draw stands even if reached (IBC's train.py, forward -> backward: no task-goal fallback).

        In IBC's train.py each backward goal draws its own uniform slot, and its noise is
        MatchSampler.add_noise(proprioceptive_only=True) (Gaussian, the forward std), not the uniform
        add_noise_to_goal (docs/baselines.md, "IBC's choices and deviations")."""
        keys = jax.random.split(key, 2 * self.config.goal_draws)
        dims = jnp.asarray(self.task.backward_noise_dims)
        goal = None
        for draw in reversed(range(self.config.goal_draws)):  # the first unreached draw wins
            slot = jax.random.randint(keys[2 * draw], (), 0, self.config.slots)
            noise = self.task.curriculum_noise * jax.random.normal(keys[2 * draw + 1], dims.shape)
            candidate = self.clip_to_bounds(state.backward_slots[slot].at[dims].add(noise), dims)
            goal = candidate if goal is None else jnp.where(proprio_reached(self.task, obs, candidate), goal,
                                                            candidate)
        return goal
