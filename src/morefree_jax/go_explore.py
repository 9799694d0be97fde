"""Go-Explore goal schedules: which kind of goal each chunk of the reset-free stream pursues.

Kinds (ScheduleConfig.kind):
  "planner"          reset-free PEG: a planner (exploratory) goal every chunk.
  "back_and_forth"   MoReFree's Back-and-Forth Go-Explore (paper Alg. 2): a "forth" chunk to an evaluation
                     goal is always followed by a "back" chunk to an initial-state goal sampled with it;
                     other chunks take planner goals. alpha = 0 is reset-free PEG, alpha = 1 only goes back
                     and forth.
  "episodic_planner" episodic PEG: one planner goal per hard-reset segment; the segment is one chunk whose
                     go and explore phases are each half the segment (`phase_lengths`).
  "eval_only"        goal-conditioned Dreamer: evaluation goals for the whole stream.

The schedule is two pure, jittable steps so the caller can skip an expensive goal search when the chunk
does not need one (e.g. `lax.cond(choice.replan, plan_goal, sample_stored_goal)`):

    choice = choose_goal_type(config, state, key)                     # GoalChoice(goal_type, replan)
    goal, state = commit_goal(config, state, choice, eval_goal, initial_goal, planner_goal)

`next_chunk_goal` puts both steps together with the planner: a search (under lax.cond, only when due) or
a sample of the stored Gaussian. The fused collection scan (go phase, early switch, explore phase) is added
at integration.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.planner import PlannerState, sample_stored_goal

SCHEDULE_KINDS = ("planner", "back_and_forth", "episodic_planner", "eval_only")


class GoalType(enum.IntEnum):
    PLANNER = 0  # exploratory goal from the PEG planner
    EVAL = 1  # an evaluation goal of the task ("forth")
    INITIAL = 2  # an initial state of the task ("back": emulates a reset)


GOAL_TYPE_NAMES = tuple(t.name.lower() for t in GoalType)  # ("planner", "eval", "initial")


@dataclasses.dataclass(frozen=True)
class ScheduleConfig:
    """kind: one of SCHEDULE_KINDS. alpha: share of chunks spent on task goals (back_and_forth only).
    goal_update_every: chunks between planner re-optimisations (PEG: 50 episodes, agent.md 4.3)."""

    kind: str = "back_and_forth"
    alpha: float = 0.2
    goal_update_every: int = 50

    def __post_init__(self):
        if self.kind not in SCHEDULE_KINDS:
            raise ValueError(f"schedule kind must be one of {SCHEDULE_KINDS}, got {self.kind!r}")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha}")
        if self.goal_update_every < 1:
            raise ValueError(f"goal_update_every must be >= 1, got {self.goal_update_every}")

    @property
    def resets_every_chunk(self) -> bool:
        """Episodic PEG hard-resets the stream at every chunk (one chunk = one episode)."""
        return self.kind == "episodic_planner"

    def phase_lengths(self, eval_episode_length: int, hard_reset_every: int) -> tuple[int, int]:
        """(H_G, H_E): half the evaluation episode each (paper section 5 setup); episodic PEG splits its
        hard-reset segment in half instead."""
        total = hard_reset_every if self.resets_every_chunk else eval_episode_length
        return total // 2, total - total // 2


def pair_start_probability(alpha: float) -> float:
    """Probability that a free chunk (one not forced to go back) starts a forth/back pair.

    How alpha is read: the paper draws r < alpha once per Back-and-Forth call, and a pair call lasts two
    chunks, so taken literally the share of forth chunks would be alpha / (1 + alpha) = 1/6 for alpha 0.2.
    We read alpha as the share of collected chunks spent on task-relevant goals, split evenly between
    evaluation and initial-state goals (alpha/2 each, 1 - alpha planner), matching the paper's imagination
    mix (alpha/2, alpha/2, 1 - alpha) and issue 4's "fraction of forth chunks is 0.1" at alpha 0.2.
    With p the pair probability per free chunk, the forth share is p / (1 + p); setting it to alpha / 2
    gives p = alpha / (2 - alpha) (= 1/9 at alpha 0.2, 1 at alpha 1: always back and forth).
    """
    return alpha / (2.0 - alpha)


@struct.dataclass
class ScheduleState:
    """back_pending: the previous chunk went forth, so this one goes back to `back_goal` (D,).
    chunks_since_plan: chunks since the last planner re-optimisation (large at start: plan at once).
    type_counts (3,): chunks so far per GoalType; chunk: chunks so far."""

    back_pending: jax.Array
    back_goal: jax.Array
    chunks_since_plan: jax.Array
    type_counts: jax.Array
    chunk: jax.Array


def init_schedule(goal_size: int, config: ScheduleConfig) -> ScheduleState:
    return ScheduleState(
        back_pending=jnp.zeros((), bool),
        back_goal=jnp.zeros((goal_size,), jnp.float32),
        chunks_since_plan=jnp.asarray(config.goal_update_every, jnp.int32),
        type_counts=jnp.zeros((len(GoalType),), jnp.int32),
        chunk=jnp.zeros((), jnp.int32),
    )


class GoalChoice(NamedTuple):
    goal_type: jax.Array  # int32 GoalType
    replan: jax.Array  # bool: a planner goal whose Gaussian is due for re-optimisation


def choose_goal_type(config: ScheduleConfig, state: ScheduleState, key: jax.Array) -> GoalChoice:
    """The goal type of the next chunk, and whether the planner must re-optimise for it."""
    if config.kind == "eval_only":
        return GoalChoice(jnp.asarray(GoalType.EVAL, jnp.int32), jnp.zeros((), bool))
    if config.kind == "back_and_forth":
        starts_pair = jax.random.uniform(key) < pair_start_probability(config.alpha)
        goal_type = jnp.where(
            state.back_pending, GoalType.INITIAL, jnp.where(starts_pair, GoalType.EVAL, GoalType.PLANNER)
        ).astype(jnp.int32)
    else:  # "planner" and "episodic_planner"
        goal_type = jnp.asarray(GoalType.PLANNER, jnp.int32)
    replan = (goal_type == GoalType.PLANNER) & (state.chunks_since_plan >= config.goal_update_every)
    return GoalChoice(goal_type, replan)


def commit_goal(
    config: ScheduleConfig,
    state: ScheduleState,
    choice: GoalChoice,
    eval_goal: jax.Array,
    initial_goal: jax.Array,
    planner_goal: jax.Array,
) -> tuple[jax.Array, ScheduleState]:
    """The chunk's goal (D,) and the advanced schedule state.

    eval_goal / initial_goal: fresh samples of the task's distributions (D,). A forth chunk stores
    initial_goal as the back goal of the next chunk (the paper samples the pair (g*, g0) together); a back
    chunk uses the stored one. planner_goal (D,) is used for planner chunks only.
    """
    goal_type = choice.goal_type
    goal = jnp.select(
        [goal_type == GoalType.EVAL, goal_type == GoalType.INITIAL],
        [eval_goal, state.back_goal],
        planner_goal,
    )
    goes_forth = (goal_type == GoalType.EVAL) & (config.kind == "back_and_forth")
    new_state = ScheduleState(
        back_pending=goes_forth,
        back_goal=jnp.where(goes_forth, initial_goal, state.back_goal),
        chunks_since_plan=jnp.where(choice.replan, 1, state.chunks_since_plan + 1),
        type_counts=state.type_counts + jax.nn.one_hot(goal_type, len(GoalType), dtype=jnp.int32),
        chunk=state.chunk + 1,
    )
    return goal, new_state


def schedule_metrics(choice: GoalChoice, state: ScheduleState) -> dict:
    """Per-chunk log: goal type used (0 planner, 1 eval, 2 initial), re-planned, running type shares."""
    shares = state.type_counts / jnp.maximum(state.chunk, 1)
    metrics = {"goal/type": choice.goal_type, "goal/replanned": choice.replan.astype(jnp.float32)}
    metrics.update({f"goal/share_{name}": shares[t] for t, name in enumerate(GOAL_TYPE_NAMES)})
    return metrics


def next_chunk_goal(
    config: ScheduleConfig,
    schedule_state: ScheduleState,
    planner_state: PlannerState,
    key: jax.Array,
    eval_goal: jax.Array,
    initial_goal: jax.Array,
    search_fn,
    low: jax.Array,
    high: jax.Array,
):
    """The next chunk's goal (D,) with the planner wired in; jittable (jit at the caller).

    search_fn(planner_state, key) -> (goal, planner_state, metrics): a full goal search (e.g. plan_goal from
    start_search(config, current obs) with the agent's score), run only when the schedule says a
    re-optimisation is due; otherwise the planner goal is a sample of the stored Gaussian and the metrics
    are zeros of the same structure. Returns (goal, GoalChoice, schedule_state, planner_state, metrics).
    """
    key_type, key_search, key_sample = jax.random.split(key, 3)
    choice = choose_goal_type(config, schedule_state, key_type)
    metric_shapes = jax.eval_shape(search_fn, planner_state, key_search)[2]

    def search(state):
        return search_fn(state, key_search)

    def reuse(state):
        zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), metric_shapes)
        return sample_stored_goal(state, low, high, key_sample), state, zeros

    planner_goal, planner_state, planner_metrics = jax.lax.cond(choice.replan, search, reuse, planner_state)
    goal, schedule_state = commit_goal(config, schedule_state, choice, eval_goal, initial_goal, planner_goal)
    metrics = {**schedule_metrics(choice, schedule_state), **planner_metrics}
    return goal, choice, schedule_state, planner_state, metrics
