"""IBC's bidirectional goal curriculum (reference/baselines.md 4.4; HGG's trajectory pool and matching).

    curriculum = Curriculum(env, task, config.baseline.ibc, discount)
    state = curriculum.init(key)
    state = curriculum.record(state, obs, next_obs, segment_step)    # each forward step
    state = curriculum.end_forward(state, length, value_fn, key)     # pool push; matching at 5, 20, 40, ...
    goal, slot = curriculum.forward_goal(state, obs, key)            # slot goal + noise, or a task goal
    goal = curriculum.backward_goal(state, key)                      # the same slot's first state + noise

The pool keeps the achieved goals (env.goal_dims) of recent forward segments with each one's first state.
The matching pairs each of `slots` curriculum slots (slot j serves target pair j % K: an initial state and
a desired goal) with one pool trajectory i at least cost
    min_t [ |ag_it - g_j| - V_it max_dis (1 - discount) / L ] + c |proprio(s_i0) - proprio(init_j)|,
V_it the forward critic's value of reaching ag_it from s_i0 (value_fn), clipped to [-1/(1-discount), 0].
Slot j's forward goal becomes ag at the minimising t, its backward goal the trajectory's first state: a
forward goal and the backward goal that returns to where it is reachable from come as a pair.

The valuation and costs are compiled (a lax.map over the pool, in the scan); the assignment itself is
scipy's linear_sum_assignment through jax.pure_callback (IBC's min-cost flow solves the same problem). It
runs only under a lazy_cond at the matching segments (every `match_every` forward segments, i.e. every
thousand or more env steps), on a (slots, pool_size) matrix that scipy solves in 0.1-0.2 ms (50 x 1000,
measured 2026 on this project's 2-core CPU), so the host round trip costs nothing per env step and keeps
one fused chunk. The whole matching at IBC's sizes (push: pool 1000 x 50 steps, 10 actions, 3 x 512 nets)
took 11 s there, nearly all of it the compiled valuation (by a FLOP estimate, not measured, about 10% of the
1,000+ UTD-1 updates at batch 512 between two matchings).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.optimize import linear_sum_assignment

from morefree_jax.baselines.config import IBCConfig
from morefree_jax.baselines.ibc_tasks import IBCTask, corridor_points
from morefree_jax.batching import lazy_cond

NO_MATCH = 1e9  # cost of an empty pool row: never preferred over a real trajectory
RESET_SAMPLES = 1000  # IBC: 1000 env resets before training (max_dis, target pairs)


@struct.dataclass
class CurriculumState:
    pool_goals: jax.Array  # (P, L, G) achieved goals of forward segments
    pool_lengths: jax.Array  # (P,) steps of each
    pool_first: jax.Array  # (P, O) each one's first state
    pool_count: jax.Array  # trajectories ever pushed (FIFO of P)
    trace: jax.Array  # (L, G) the open forward segment's achieved goals
    trace_first: jax.Array  # (O,) its first state
    trace_last: jax.Array  # (O,) its latest state
    forward_slots: jax.Array  # (S, O) curriculum goals (goal_dims hold them)
    backward_slots: jax.Array  # (S, O) their paired backward goals (proprioceptive dims hold them)
    slot: jax.Array  # the slot the current forward goal came from
    forward_segments: jax.Array  # forward segments ended
    matches: jax.Array  # matchings run
    target_init: jax.Array  # (K, O) the target pairs' initial states
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
    """(cost (K, P), t* (K, P)) of pairing target k with pool trajectory i (module docstring).
    goals (P, L, G), lengths (P,), first_proprio (P, D), valid (P,), values (P, L), target_goal (K, G),
    target_proprio (K, D)."""
    distance = jnp.linalg.norm(goals[None] - target_goal[:, None, None], axis=-1)  # (K, P, L)
    per_step = distance - values[None] * max_dis * (1.0 - discount) / cost_l
    in_segment = jnp.arange(goals.shape[1])[None, None] < lengths[None, :, None]
    per_step = jnp.where(in_segment, per_step, jnp.inf)
    best_t = jnp.argmin(per_step, axis=-1)
    start = jnp.linalg.norm(first_proprio[None] - target_proprio[:, None], axis=-1)
    cost = jnp.min(per_step, axis=-1) + cost_c * start
    return jnp.where(valid[None], cost, NO_MATCH), best_t


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
    def proprio_dims(self) -> jax.Array:
        return jnp.asarray(self.task.proprio_dims)

    def init(self, key) -> CurriculumState:
        key_targets, key_far, key_slots, key_noise = jax.random.split(key, 4)
        target_init, target_goal = self.target_pairs(key_targets)
        far_init, far_goal = self.reset_pairs(key_far, RESET_SAMPLES)
        max_dis = jnp.max(jnp.linalg.norm(far_init[:, self.goal_dims] - far_goal[:, self.goal_dims], axis=-1))
        # Before the first matching: the initial achieved goal + N(0, success threshold) (IBC).
        slots, obs_size, cfg = self.config.slots, self.env.observation_size, self.config
        starts, _ = self.reset_pairs(key_slots, slots)
        noise = self.env.success_threshold * jax.random.normal(key_noise, (slots, len(self.env.goal_dims)))
        forward = starts.at[:, self.goal_dims].add(noise)
        length, width = self.task.segment_length, len(self.env.goal_dims)
        return CurriculumState(
            pool_goals=jnp.zeros((cfg.pool_size, length, width)),
            pool_lengths=jnp.zeros(cfg.pool_size, jnp.int32),
            pool_first=jnp.zeros((cfg.pool_size, obs_size)), pool_count=jnp.zeros((), jnp.int32),
            trace=jnp.zeros((length, width)), trace_first=jnp.zeros(obs_size), trace_last=jnp.zeros(obs_size),
            forward_slots=forward, backward_slots=starts, slot=jnp.zeros((), jnp.int32),
            forward_segments=jnp.zeros((), jnp.int32), matches=jnp.zeros((), jnp.int32),
            target_init=target_init, target_goal=target_goal, max_dis=max_dis)

    def reset_pairs(self, key, count: int) -> tuple[jax.Array, jax.Array]:
        """`count` (initial state, task goal) draws, (count, O) each."""
        key_init, key_goal = jax.random.split(key)
        return (jax.vmap(self.env.initial_states)(jax.random.split(key_init, count)),
                jax.vmap(self.env.eval_goals)(jax.random.split(key_goal, count)))

    def target_pairs(self, key) -> tuple[jax.Array, jax.Array]:
        """K target pairs (baselines.md 4.4): env draws; in the EARL tasks the first desired goal is the
        initial state itself (IBC's {initial, goal states}); on PointUMaze the desired goals are draws of
        IBC's 30 corridor points with uniform noise (ibc_tasks.corridor_points)."""
        key_pairs, key_point, key_noise = jax.random.split(key, 3)
        init, goal = self.reset_pairs(key_pairs, self.task.num_targets)
        if self.task.initial_target:
            goal = goal.at[0].set(init[0])
        if self.task.corridor:
            points = jnp.asarray(corridor_points(self.task), jnp.float32)
            chosen = points[jax.random.randint(key_point, (self.task.num_targets,), 0, len(points))]
            noise = self.task.corridor_noise
            chosen = chosen + jax.random.uniform(key_noise, chosen.shape, minval=-noise, maxval=noise)
            goal = goal.at[:, self.goal_dims].set(chosen)
        return init, goal

    def record(self, state: CurriculumState, obs, next_obs, segment_step) -> CurriculumState:
        """One forward step: the achieved goal after it joins the open segment's trace."""
        first = jnp.where(segment_step == 0, obs, state.trace_first)
        trace = state.trace.at[segment_step].set(next_obs[self.goal_dims])
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
        (their cost is NO_MATCH anyway): a pool of 1,000 fills only after 1,000 forward segments."""
        template = jnp.zeros(self.env.observation_size)

        def one(args):
            goals, first, key_one, filled = args
            goal_obs = jax.vmap(lambda g: template.at[self.goal_dims].set(g))(goals)
            firsts = jnp.broadcast_to(first, goal_obs.shape)
            return lazy_cond(filled, lambda: value_fn(firsts, goal_obs, key_one),
                             lambda: jnp.zeros(goals.shape[0]))

        keys = jax.random.split(key, self.config.pool_size)
        filled = jnp.arange(self.config.pool_size) < state.pool_count
        values = jax.lax.map(one, (state.pool_goals, state.pool_first, keys, filled))
        return jnp.clip(values, -1.0 / (1.0 - self.discount), 0.0)

    def match(self, state: CurriculumState, value_fn, key) -> CurriculumState:
        """New slots from the least-cost assignment of slots to pool trajectories (module docstring);
        with an empty pool the slots take the target pairs themselves (IBC)."""
        values = self.pool_values(state, value_fn, key)
        valid = jnp.arange(self.config.pool_size) < state.pool_count
        cost, best_t = matching_costs(
            state.pool_goals, state.pool_lengths, state.pool_first[:, self.proprio_dims], valid, values,
            state.target_goal[:, self.goal_dims], state.target_init[:, self.proprio_dims], state.max_dis,
            self.discount, self.config.cost_c, self.config.cost_l)
        target = jnp.arange(self.config.slots) % self.task.num_targets
        column = assign_on_host(cost[target])
        matched = cost[target, column] < NO_MATCH / 2
        ag = state.pool_goals[column, best_t[target, column]]
        forward = jnp.where(matched[:, None], state.forward_slots.at[:, self.goal_dims].set(ag),
                            state.target_goal[target])
        backward = jnp.where(matched[:, None], state.pool_first[column], state.target_init[target])
        return state.replace(forward_slots=forward, backward_slots=backward, matches=state.matches + 1)

    def forward_goal(self, state: CurriculumState, obs, key) -> tuple[jax.Array, jax.Array]:
        """(goal, slot): a uniform slot's goal + Gaussian noise on the task's noise dims, drawn up to
        goal_draws times until obs does not already satisfy it; else a task goal."""
        keys = jax.random.split(key, 2 * self.config.goal_draws + 1)
        noise_dims = self.goal_dims[jnp.asarray(self.task.curriculum_noise_dims)]
        goal, slot = self.env.eval_goals(keys[-1]), state.slot
        for draw in reversed(range(self.config.goal_draws)):  # the first unsatisfied draw wins
            candidate_slot = jax.random.randint(keys[2 * draw], (), 0, self.config.slots)
            noise = self.task.curriculum_noise * jax.random.normal(keys[2 * draw + 1], noise_dims.shape)
            candidate = state.forward_slots[candidate_slot].at[noise_dims].add(noise)
            fresh = ~self.env.success(obs, candidate)
            goal = jnp.where(fresh, candidate, goal)
            slot = jnp.where(fresh, candidate_slot, slot)
        return goal, slot

    def backward_goal(self, state: CurriculumState, key) -> jax.Array:
        """The current slot's backward goal + uniform noise on the proprioceptive dims, clipped to the
        observation bounds."""
        dims, size = self.proprio_dims, self.task.backward_noise
        noise = jax.random.uniform(key, dims.shape, minval=-size, maxval=size)
        dims_np = np.asarray(self.task.proprio_dims)
        low, high = (np.asarray(bound)[dims_np] for bound in self.env.observation_bounds)
        goal = state.backward_slots[state.slot]
        return goal.at[dims].set(jnp.clip(goal[dims] + noise, low, high))
