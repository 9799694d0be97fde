"""Go-Explore goal schedules: which kind of goal each chunk of the reset-free stream pursues.

Kinds (ScheduleConfig.kind):
  "planner"          reset-free PEG: a freshly optimised planner goal every chunk (paper appendix: reset-free
                     PEG optimises "the goal distribution every H_G+H_E steps").
  "back_and_forth"   MoReFree's Back-and-Forth Go-Explore (paper Alg. alg:bfge): each decision draws r; if
                     r < alpha, a "forth" chunk to an evaluation goal g* and then a "back" chunk to an
                     initial-state goal g0 sampled with it, continuing from where the forth chunk ended;
                     otherwise one planner chunk. alpha = 0 is reset-free PEG, alpha = 1 only goes back and
                     forth. At alpha = 0.2 the share of task chunks is 2 alpha / (1 + alpha) = 1/3.
  "episodic_planner" episodic PEG: one planner goal per hard-reset segment; the segment is one chunk whose
                     go phase lasts at most half the segment (H_G, `phase_lengths`; the early switch on
                     learned distance may end it sooner) and the explore phase the rest.
  "eval_only"        goal-conditioned Dreamer: evaluation goals for the whole stream.

The schedule is two pure, jittable steps so the caller can skip the goal search when the chunk does not
pursue a planner goal (`lax.cond(choice.search, plan_goal, no_search)`):

    choice = choose_goal_type(config, state, key)                     # GoalChoice(goal_type, search)
    goal, state = commit_goal(config, state, choice, eval_goal, initial_goal, planner_goal)

`next_chunk_goal` puts both steps together with the planner: a full search on every planner chunk.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from morefree_jax.batching import lazy_cond
from morefree_jax.planner import PlannerState

SCHEDULE_KINDS = ("planner", "back_and_forth", "episodic_planner", "eval_only")


class GoalType(enum.IntEnum):
    PLANNER = 0  # exploratory goal from the PEG planner
    EVAL = 1  # an evaluation goal of the task ("forth")
    INITIAL = 2  # an initial state of the task ("back": emulates a reset)


GOAL_TYPE_NAMES = tuple(t.name.lower() for t in GoalType)  # ("planner", "eval", "initial")


@dataclasses.dataclass(frozen=True)
class ScheduleConfig:
    """kind: one of SCHEDULE_KINDS. alpha: probability that a back_and_forth decision starts a forth/back
    pair (paper Alg. alg:bfge, "if r < alpha"); unused by the other kinds."""

    kind: str = "back_and_forth"
    alpha: float = 0.2

    def __post_init__(self):
        if self.kind not in SCHEDULE_KINDS:
            raise ValueError(f"schedule kind must be one of {SCHEDULE_KINDS}, got {self.kind!r}")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha}")

    def task_chunk_share(self) -> float:
        """Expected share of chunks that pursue task goals: a decision yields 2 task chunks with
        probability alpha, else 1 planner chunk, so 2 alpha / (1 + alpha) (1/3 at alpha 0.2)."""
        if self.kind == "eval_only":
            return 1.0
        if self.kind != "back_and_forth":
            return 0.0
        return 2 * self.alpha / (1 + self.alpha)

    @property
    def resets_every_chunk(self) -> bool:
        """Episodic PEG hard-resets the stream at every chunk (one chunk = one episode)."""
        return self.kind == "episodic_planner"

    def phase_lengths(self, eval_episode_length: int, hard_reset_every: int) -> tuple[int, int]:
        """(H_G, H_E): half the evaluation episode each (paper section 5 setup); episodic PEG splits its
        hard-reset segment in half instead."""
        total = hard_reset_every if self.resets_every_chunk else eval_episode_length
        return total // 2, total - total // 2


@struct.dataclass
class ScheduleState:
    """back_pending: the previous chunk went forth, so this one goes back to `back_goal` (D,).
    type_counts (3,): chunks so far per GoalType; chunk: chunks so far."""

    back_pending: jax.Array
    back_goal: jax.Array
    type_counts: jax.Array
    chunk: jax.Array


def init_schedule(goal_size: int) -> ScheduleState:
    """The schedule state before the first chunk (the same for every kind)."""
    return ScheduleState(
        back_pending=jnp.zeros((), bool),
        back_goal=jnp.zeros((goal_size,), jnp.float32),
        type_counts=jnp.zeros((len(GoalType),), jnp.int32),
        chunk=jnp.zeros((), jnp.int32),
    )


class GoalChoice(NamedTuple):
    goal_type: jax.Array  # int32 GoalType
    search: jax.Array  # bool: a planner chunk, so the goal search runs (every planner chunk)


def choose_goal_type(config: ScheduleConfig, state: ScheduleState, key: jax.Array) -> GoalChoice:
    """The goal type of the next chunk, and whether the goal search runs for it (planner chunks)."""
    if config.kind == "eval_only":
        return GoalChoice(jnp.asarray(GoalType.EVAL, jnp.int32), jnp.zeros((), bool))
    if config.kind == "back_and_forth":
        # Alg. alg:bfge, read literally: one draw per decision; a pending back chunk is the second half
        # of the previous decision, so it draws nothing.
        starts_pair = jax.random.uniform(key) < config.alpha
        goal_type = jnp.where(
            state.back_pending, GoalType.INITIAL, jnp.where(starts_pair, GoalType.EVAL, GoalType.PLANNER)
        ).astype(jnp.int32)
    else:  # "planner" and "episodic_planner"
        goal_type = jnp.asarray(GoalType.PLANNER, jnp.int32)
    return GoalChoice(goal_type, goal_type == GoalType.PLANNER)


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
        type_counts=state.type_counts + jax.nn.one_hot(goal_type, len(GoalType), dtype=jnp.int32),
        chunk=state.chunk + 1,
    )
    return goal, new_state


def schedule_metrics(choice: GoalChoice, state: ScheduleState) -> dict:
    """Per-chunk log: goal type used (0 planner, 1 eval, 2 initial), searched, running type shares."""
    shares = state.type_counts / jnp.maximum(state.chunk, 1)
    metrics = {"goal/type": choice.goal_type, "goal/searched": choice.search.astype(jnp.float32)}
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
):
    """The next chunk's goal (D,) with the planner wired in; jittable (jit at the caller).

    search_fn(planner_state, key) -> (goal, planner_state, metrics): a full goal search (e.g. plan_goal from
    start_search(config, current obs) with the agent's score). It runs on every planner chunk (a fresh
    optimisation each time, paper appendix on reset-free PEG) and is skipped under lax.cond on task chunks,
    whose planner metrics are zeros of the same structure (batching.lazy_cond: lazy under vmap too).
    planner_state.searches counts the searches.
    Returns (goal, GoalChoice, schedule_state, planner_state, metrics).
    """
    key_type, key_search = jax.random.split(key)
    choice = choose_goal_type(config, schedule_state, key_type)
    goal_shape, _, metric_shapes = jax.eval_shape(search_fn, planner_state, key_search)

    def search(state):
        goal, new_state, metrics = search_fn(state, key_search)
        return goal, new_state.replace(searches=state.searches + 1), metrics

    def no_search(state):
        zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), metric_shapes)
        return jnp.zeros(goal_shape.shape, goal_shape.dtype), state, zeros

    # lazy_cond: vmapped over seeds, the search still runs only on chunks where some seed needs it.
    planner_goal, planner_state, planner_metrics = lazy_cond(choice.search, search, no_search, planner_state)
    goal, schedule_state = commit_goal(config, schedule_state, choice, eval_goal, initial_goal, planner_goal)
    metrics = {**schedule_metrics(choice, schedule_state), **planner_metrics}
    return goal, choice, schedule_state, planner_state, metrics
