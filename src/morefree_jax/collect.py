"""The fused collection of the reset-free stream: one chunk of H_G + H_E env steps in one `lax.scan`.

    stream, schedule, planner, transitions, metrics = collect_chunk(
        env, agent, cfg, planner_cfg, schedule_cfg, agent_state, stream, schedule, planner, key)

At the start of a chunk a hard reset that is due on the chunk's first step is applied first (so the goal
is chosen from the state the chunk really starts in), then the goal schedule (goal_schedule.py) picks the
chunk's goal: an evaluation goal, an initial state, or a planner goal (PEG's search from the current
latent, run afresh on every planner chunk). Then every step, inside the same scan and with no host round
trip: the agent filters the observation into its latent and acts (goal-conditioned policy in the go phase,
exploration policy after), the env steps, and in the go phase the learned temporal distance from the new
observation to the goal is checked; below `subgoal_threshold` (or after H_G go steps) the chunk switches
to exploring. The latent and the last action carry over between the phases and across chunks. A hard
reset of the stream happens on the step whose stream position is a multiple of `hard_reset_every` (that
step stores the reset observation with a zero action and reset=True, and zeroes the latent: an is_first
step).

The goal search's box: the task's observation bounds intersected with the range of observations the
replay has visited (`goal_bounds`, from replay.visited_range), so candidates stay inside states the stream
has been in (a velocity box of +-10 where the data sits near 0 would be out of distribution).

Early switch threshold: `subgoal_threshold`, per task (the task's `default_config`, run.subgoal_threshold).
A task's own success radius decides the logged `go/reached` (env.success during the go phase).

Episodic PEG (`episodic=True`): the goal is chosen once per hard-reset segment, at the first chunk that
starts in it; the go phase lasts until the early switch or at the latest the segment's midpoint (H_G, half
the segment), and the explore phase the rest, carried across chunks (docs/fidelity.md).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.agent import MODE_EXPLORE, MODE_GOAL
from morefree_jax.batching import lazy_cond
from morefree_jax.goal_schedule import GoalChoice, GoalType, ScheduleConfig, commit_goal, next_chunk_goal
from morefree_jax.goal_schedule import schedule_metrics as _schedule_metrics
from morefree_jax.planner import PlannerConfig, peg_score, plan_goal, start_search


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    """Static settings of the collection. go_steps/explore_steps: H_G/H_E of a chunk; explore False: the
    goal-conditioned policy runs the whole chunk (no switch); episodic: phases span hard-reset segments."""

    go_steps: int
    explore_steps: int
    subgoal_threshold: float
    hard_reset_every: int
    explore: bool = True
    episodic: bool = False

    @property
    def chunk_len(self) -> int:
        return self.go_steps + self.explore_steps


def collect_config_for(env, schedule: ScheduleConfig, explore: bool, subgoal_threshold: float,
                       hard_reset_every: int | None = None) -> CollectConfig:
    """H_G = H_E = half the evaluation episode (paper section 5); without exploration H_G = the chunk.
    subgoal_threshold: learned distance (env steps) of the early switch (the task's default_config)."""
    length = env.eval_episode_length
    go_steps = length // 2 if explore else length
    episodic = schedule.kind == "episodic_planner"
    reset_every = hard_reset_every or env.hard_reset_every
    return CollectConfig(go_steps, length - go_steps, float(subgoal_threshold), int(reset_every), explore,
                         episodic)


@struct.dataclass
class StreamState:
    """The single reset-free stream. latent/prev_action: the agent's filter state BEFORE filtering
    env_state.obs; goal (O,): the current go goal; go_steps_left: go steps before the timeout switch;
    steps: transitions emitted so far (the stream position, drives hard resets); reset_applied: the hard
    reset due at `steps` was already applied at the chunk start (before the goal choice), so the step that
    emits it must not reset again."""

    env_state: object
    latent: object
    prev_action: jax.Array
    goal: jax.Array
    go_active: jax.Array
    go_steps_left: jax.Array
    steps: jax.Array
    reset_applied: jax.Array


class Transition(NamedTuple):
    """What the replay stores per step (N, ...): obs, the action that led to it, reset flag."""

    obs: jax.Array
    action: jax.Array
    reset: jax.Array


class StepRecord(NamedTuple):
    go: jax.Array  # this step ran the goal-conditioned policy
    success: jax.Array  # env.success(new obs, goal)
    learned_distance: jax.Array  # agent distance (env steps) to the goal; inf when not checked
    task_distance: jax.Array  # env.goal_distance(new obs, goal)
    reset: jax.Array


def init_stream(env, agent, key: jax.Array) -> StreamState:
    """A stream at position 0: its first step is a hard reset (the env state here is a placeholder)."""
    size = env.observation_size
    return StreamState(
        env_state=env.reset(key), latent=agent.initial_latent(), prev_action=jnp.zeros(env.action_size),
        goal=jnp.zeros(size, jnp.float32), go_active=jnp.ones((), bool),
        go_steps_left=jnp.zeros((), jnp.int32), steps=jnp.zeros((), jnp.int32),
        reset_applied=jnp.zeros((), bool))


def _advance(env, agent, cfg: CollectConfig, stream: StreamState, act_fn, distance_fn, key: jax.Array):
    """One stream step: a hard reset when due, else act_fn -> env.step -> distance_fn on the new obs."""
    key_reset, key_act = jax.random.split(key)
    no_distance = jnp.asarray(jnp.inf, jnp.float32)

    def hard_reset():
        env_state = jax.lax.cond(stream.reset_applied, lambda: stream.env_state, lambda: env.reset(key_reset))
        return env_state, agent.initial_latent(), jnp.zeros_like(stream.prev_action), no_distance

    def step():
        action, latent = act_fn(stream, key_act)
        env_state = env.step(stream.env_state, action)
        return env_state, latent, action, distance_fn(stream, latent, env_state.obs)

    due = stream.steps % cfg.hard_reset_every == 0
    env_state, latent, action, learned_distance = lazy_cond(due, hard_reset, step)  # lazy over seeds too
    go = stream.go_active
    go_steps_left = stream.go_steps_left - go.astype(jnp.int32)
    # Without exploration the go phase never ends; otherwise it ends on the learned distance or timeout.
    still_going = (learned_distance >= cfg.subgoal_threshold) & (go_steps_left > 0)
    go_active = go & still_going if cfg.explore else go
    record = StepRecord(go, env.success(env_state.obs, stream.goal), learned_distance,
                        env.goal_distance(env_state.obs, stream.goal), due)
    stream = stream.replace(env_state=env_state, latent=latent, prev_action=action, go_active=go_active,
                            go_steps_left=go_steps_left, steps=stream.steps + 1,
                            reset_applied=jnp.zeros((), bool))
    return stream, Transition(env_state.obs, action, due), record


def _policy_fns(agent, cfg: CollectConfig, agent_state):
    """(act_fn, distance_fn) of the learned policies: the goal-conditioned policy in the go phase, the
    exploration policy after it (one lax.cond inside agent.act); the learned distance in the go phase."""

    def act_fn(stream: StreamState, key):
        mode = jnp.where(stream.go_active, MODE_GOAL, MODE_EXPLORE) if cfg.explore else MODE_GOAL
        return agent.act(agent_state, stream.latent, stream.prev_action, stream.env_state.obs, stream.goal,
                         key, mode)

    def distance_fn(stream: StreamState, latent, next_obs):
        if not cfg.explore:  # no switch to check for
            return jnp.asarray(jnp.inf, jnp.float32)
        # PEG checks the distance of the observation the step led to, go phase only (docs/learner.md,
        # "Go-Explore and Back-and-Forth Go-Explore").
        return lazy_cond(stream.go_active,
                            lambda: agent.goal_distance(agent_state, latent, stream.goal, next_obs),
                            lambda: jnp.asarray(jnp.inf, jnp.float32))

    return act_fn, distance_fn


def prefill_stream(env, agent, cfg: CollectConfig, stream: StreamState, key: jax.Array, num_steps: int):
    """num_steps uniform random actions (hard resets included) -> (stream, Transition (num_steps, ...)).
    The latent is left at zeros: the first learned step filters its observation as an is_first step."""

    def random_act(stream, key):
        return jax.random.uniform(key, stream.prev_action.shape, minval=-1.0, maxval=1.0), stream.latent

    def no_distance(stream, latent, next_obs):
        return jnp.asarray(jnp.inf, jnp.float32)

    def body(stream, key):
        stream, transition, _ = _advance(env, agent, cfg, stream.replace(go_active=jnp.zeros((), bool)),
                                         random_act, no_distance, key)
        return stream, transition

    stream, transitions = jax.lax.scan(body, stream, jax.random.split(key, num_steps))
    return stream.replace(latent=agent.initial_latent(), prev_action=jnp.zeros_like(stream.prev_action)), \
        transitions


def peg_goal_scores(agent, agent_state, start_latent, candidates: jax.Array, planner_cfg: PlannerConfig,
                    key: jax.Array) -> jax.Array:
    """PEG's fitness of candidate goals (G, O) -> (G,): imagine the goal-conditioned policy from the start
    latent for `horizon` steps, then sum the exploration value (docs/learner.md, "Goal search (planner)",
    step 4).

    When only the last k returns count (`use_last_steps`), only the last k + 1 imagined states enter them
    (a lambda-return looks forward only), so the disagreement ensemble and the critic run on those states
    alone: for the ant config (horizon 250, k 10) that is 11 of 251 states, the same numbers at a fraction
    of the cost."""
    trajectory = agent.imagine_to_goals(agent_state, start_latent, candidates, planner_cfg.horizon, key)
    last = planner_cfg.use_last_steps
    if last is not None and last < planner_cfg.horizon:
        tail = lambda x: x[-(last + 1):]  # noqa: E731
        trajectory = trajectory._replace(latent=jax.tree.map(tail, trajectory.latent),
                                         feat=tail(trajectory.feat), action=tail(trajectory.action))
    reward, returns = agent.exploration_value(agent_state, trajectory)
    return peg_score(reward, returns, last)


def choose_goal(env, agent, planner_cfg: PlannerConfig, schedule_cfg: ScheduleConfig, agent_state,
                stream: StreamState, schedule, planner, key, goal_bounds):
    """The schedule's next goal (O,), with PEG's goal search from the current latent on planner chunks.
    goal_bounds: (low, high) (O,) box of the search. -> (goal, GoalChoice, schedule, planner, metrics)."""
    key_eval, key_initial, key_goal, key_filter, key_start = jax.random.split(key, 5)
    eval_goal, initial_goal = env.eval_goals(key_eval), env.initial_states(key_initial)
    if schedule_cfg.kind == "eval_only":  # no planner at all (compiles faster)
        choice = GoalChoice(jnp.asarray(GoalType.EVAL, jnp.int32), jnp.zeros((), bool))
        goal, schedule = commit_goal(schedule_cfg, schedule, choice, eval_goal, initial_goal, eval_goal)
        return goal, choice, schedule, planner, _schedule_metrics(choice, schedule)
    low, high = goal_bounds
    # PEG starts its search from the posterior of the current observation (docs/learner.md,
    # "Goal search (planner)", step 1).
    _, start_latent = agent.act(agent_state, stream.latent, stream.prev_action, stream.env_state.obs,
                                stream.goal, key_filter, MODE_EXPLORE)
    current = planner_cfg.init_mean == "current"
    init_mean = stream.env_state.obs if current else env.initial_states(key_start)

    def search_fn(planner_state, key_search):
        def score_fn(candidates, key_score):  # (G, O) -> (G,)
            return peg_goal_scores(agent, agent_state, start_latent, candidates, planner_cfg, key_score)

        # Every search starts from the initial Gaussian (PEG); only the search count carries over.
        fresh = start_search(planner_cfg, init_mean).replace(searches=planner_state.searches)
        return plan_goal(score_fn, fresh, low, high, key_search, planner_cfg)

    return next_chunk_goal(schedule_cfg, schedule, planner, key_goal, eval_goal, initial_goal, search_fn)


def apply_due_reset(env, agent, cfg: CollectConfig, stream: StreamState, key: jax.Array) -> StreamState:
    """The stream after the hard reset due at its current position, if one is (else unchanged): the goal of
    a chunk is chosen after that reset, from the state the chunk really starts in. The first step of the
    chunk then emits the reset observation without resetting again (`reset_applied`)."""
    due = (stream.steps % cfg.hard_reset_every == 0) & ~stream.reset_applied

    def reset():
        return stream.replace(env_state=env.reset(key), latent=agent.initial_latent(),
                              prev_action=jnp.zeros_like(stream.prev_action),
                              reset_applied=jnp.ones((), bool))

    return jax.lax.cond(due, reset, lambda: stream)


def _chunk_start(env, agent, cfg, planner_cfg, schedule_cfg, agent_state, stream, schedule, planner, key,
                 goal_bounds):
    """Goal and phase at the start of a chunk (episodic PEG: only when a segment starts)."""
    key_reset, key_goal = jax.random.split(key)
    stream = apply_due_reset(env, agent, cfg, stream, key_reset)

    def choose(stream, schedule, planner):
        return choose_goal(env, agent, planner_cfg, schedule_cfg, agent_state, stream, schedule, planner,
                           key_goal, goal_bounds)

    if not cfg.episodic:
        goal, _, schedule, planner, metrics = choose(stream, schedule, planner)
        return stream.replace(goal=goal, go_active=jnp.ones((), bool),
                              go_steps_left=jnp.asarray(cfg.go_steps, jnp.int32)), schedule, planner, metrics
    into_segment = stream.steps % cfg.hard_reset_every
    # The first chunk that starts in a new segment chooses its goal: on the segment's first step when chunks
    # line up with the resets, else up to chunk_len - 1 steps after a reset that fell inside the previous
    # chunk (sawyer_door: 2e5 is no multiple of 300), whose remaining steps explored on from the reset state.
    new_goal = (into_segment < cfg.chunk_len) | (schedule.chunk == 0)

    def choose_for_segment(operand):
        stream, schedule, planner = operand
        goal, _, schedule, planner, metrics = choose(stream, schedule, planner)
        go_steps_left = jnp.maximum(cfg.hard_reset_every // 2 - into_segment, 0).astype(jnp.int32)
        stream = stream.replace(goal=goal, go_active=go_steps_left > 0, go_steps_left=go_steps_left)
        return stream, schedule, planner, metrics

    shapes = jax.eval_shape(choose_for_segment, (stream, schedule, planner))[3]

    def keep(operand):
        stream, schedule, planner = operand
        return stream, schedule, planner, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    return lazy_cond(new_goal, choose_for_segment, keep, (stream, schedule, planner))


def collect_chunk(env, agent, cfg: CollectConfig, planner_cfg: PlannerConfig, schedule_cfg: ScheduleConfig,
                  agent_state, stream: StreamState, schedule, planner, key: jax.Array, goal_bounds=None):
    """One chunk of cfg.chunk_len steps -> (stream, schedule, planner, Transition (N, ...), metrics).
    goal_bounds: (low, high) (O,) box of the goal search; None = the task's observation bounds."""
    key_goal, key_steps = jax.random.split(key)
    stream, schedule, planner, metrics = start_chunk(env, agent, cfg, planner_cfg, schedule_cfg, agent_state,
                                                     stream, schedule, planner, key_goal, goal_bounds)
    stream, transitions, records = advance_steps(env, agent, cfg, agent_state, stream,
                                                 jax.random.split(key_steps, cfg.chunk_len))
    return stream, schedule, planner, transitions, {**metrics, **chunk_metrics(records)}


def start_chunk(env, agent, cfg: CollectConfig, planner_cfg: PlannerConfig, schedule_cfg: ScheduleConfig,
                agent_state, stream: StreamState, schedule, planner, key: jax.Array, goal_bounds=None):
    """The chunk's goal and phase: (stream, schedule, planner, the goal choice's metrics). goal_bounds as
    collect_chunk's."""
    if goal_bounds is None:
        goal_bounds = tuple(jnp.asarray(b, jnp.float32) for b in env.observation_bounds)
    return _chunk_start(env, agent, cfg, planner_cfg, schedule_cfg, agent_state, stream, schedule, planner,
                        key, goal_bounds)


def advance_steps(env, agent, cfg: CollectConfig, agent_state, stream: StreamState, keys: jax.Array):
    """len(keys) steps of the stream with the learned policies of `agent_state`, in one lax.scan
    -> (stream, Transition (N, ...), StepRecord (N, ...))."""
    act_fn, distance_fn = _policy_fns(agent, cfg, agent_state)

    def body(stream, key_step):
        stream, transition, record = _advance(env, agent, cfg, stream, act_fn, distance_fn, key_step)
        return stream, (transition, record)

    stream, (transitions, records) = jax.lax.scan(body, stream, keys)
    return stream, transitions, records


def chunk_metrics(records: StepRecord) -> dict:
    """Go-phase summary of a chunk: go steps, reached (task success during the go phase), the smallest task
    and learned distances to the goal in the go phase (-1: none), whether the chunk ended still going."""
    go = records.go
    checked = jnp.isfinite(records.learned_distance) & go

    def smallest(values, mask):  # -1 when no step qualifies, so every metric stays finite
        return jnp.where(jnp.any(mask), jnp.min(jnp.where(mask, values, jnp.inf)), -1.0)

    return {
        "go/steps": jnp.sum(go).astype(jnp.float32),
        "go/reached": jnp.any(records.success & go).astype(jnp.float32),
        "go/min_task_distance": smallest(records.task_distance, go),
        "go/min_learned_distance": smallest(records.learned_distance, checked),
        "go/active_at_end": go[-1].astype(jnp.float32),
        "collect/hard_resets": jnp.sum(records.reset).astype(jnp.float32),
    }
