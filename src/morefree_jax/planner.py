"""PEG's goal search: a Gaussian over goal space refined by MPPI or CEM against a score function.

The planner is generic: it never sees a network. The caller supplies
`score_fn(candidates (G, D), key) -> (G,)`; for PEG that is "encode each candidate goal, roll out the
goal-conditioned policy in the world model from the current latent, sum the exploration value"
(docs/learner.md, "Goal search (planner)"), and `peg_score` turns the imagined exploration rewards /
lambda-returns into that sum.

    state = start_search(config, init_mean)                        # N(init_mean, init_std)
    goal, state, metrics = plan_goal(score_fn, state, low, high, key, config)

Everything is pure and jittable. Build `score_fn` INSIDE the jitted function from traced arguments, so the
agent's parameters are inputs rather than baked-in constants and one compilation serves every call:

    @functools.partial(jax.jit, static_argnames="config")
    def search(agent_state, start_latent, planner_state, key, config):
        def score_fn(candidates, key):                       # (G, D) -> (G,)
            reward, returns = imagine_explore_value(agent_state, start_latent, candidates, key)  # (H, G) each
            return peg_score(reward, returns, config.use_last_steps)
        return plan_goal(score_fn, planner_state, low, high, key, config)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import struct

METHODS = ("mppi", "cem")
INIT_MEANS = ("current", "initial_state")

ScoreFn = Callable[[jax.Array, jax.Array], jax.Array]


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """Goal-search settings. Defaults are PEG's shared values [PEG:dreamerv2/configs.yaml planner].

    init_mean: where each re-optimisation centres its first Gaussian: "current" = the current observation,
      "initial_state" = a sample of the task's initial states (PEG's fixed init candidate, docs/learner.md,
      "Goal search (planner)", step 2).
    use_last_steps: sum only the last N imagined steps of the score (PEG `final_step_cost` -> 10), None = all.
    min_std: floor on the refitted std; PEG has none for MPPI and sqrt(var + 1e-6) for CEM (0 keeps that).
    clip_final_goal: PEG returns an unclipped final sample; we clip it to the bounds by default, since a goal
      outside the observation box is unreachable (deviation, documented).
    """

    method: str = "mppi"
    num_candidates: int = 500
    iterations: int = 5
    mppi_temperature: float = 10.0
    cem_elite_fraction: float = 0.2
    init_std: float = 1.0
    min_std: float = 0.0
    horizon: int = 50
    use_last_steps: int | None = 10
    init_mean: str = "current"
    clip_final_goal: bool = True

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"planner.method must be one of {METHODS}, got {self.method!r}")
        if self.init_mean not in INIT_MEANS:
            raise ValueError(f"planner.init_mean must be one of {INIT_MEANS}, got {self.init_mean!r}")
        if self.num_candidates < 2 or self.iterations < 1 or self.horizon < 1:
            raise ValueError("planner: num_candidates >= 2, iterations >= 1 and horizon >= 1")
        if not 0.0 < self.cem_elite_fraction <= 1.0:
            raise ValueError(f"planner.cem_elite_fraction must be in (0, 1], got {self.cem_elite_fraction}")
        if self.init_std <= 0 or self.min_std < 0 or self.mppi_temperature <= 0:
            raise ValueError("planner: init_std and mppi_temperature must be > 0, min_std >= 0")
        if self.use_last_steps is not None and self.use_last_steps < 1:
            raise ValueError(f"planner.use_last_steps must be None or >= 1, got {self.use_last_steps}")

    @property
    def num_elites(self) -> int:
        return max(1, int(round(self.num_candidates * self.cem_elite_fraction)))


@struct.dataclass
class PlannerState:
    """The search's diagonal Gaussian in goal space after the last search.

    mean, std: (D,). score: mean score of the last iteration of the last search (for logging).
    searches: goal searches run so far (next_chunk_goal counts them).
    """

    mean: jax.Array
    std: jax.Array
    score: jax.Array
    searches: jax.Array = struct.field(default_factory=lambda: jnp.zeros((), jnp.int32))


def start_search(config: PlannerConfig, init_mean: jax.Array) -> PlannerState:
    """The Gaussian a re-optimisation starts from: N(init_mean, init_std) in every dim
    (docs/learner.md, "Goal search (planner)", step 2)."""
    init_mean = jnp.asarray(init_mean, jnp.float32)
    return PlannerState(mean=init_mean, std=jnp.full_like(init_mean, config.init_std),
                        score=jnp.zeros((), jnp.float32), searches=jnp.zeros((), jnp.int32))


def sample_candidates(state: PlannerState, low, high, key: jax.Array, num: int) -> jax.Array:
    """num goals (num, D) from N(mean, std), clipped to the box [low, high]."""
    noise = jax.random.normal(key, (num,) + state.mean.shape, state.mean.dtype)
    return jnp.clip(state.mean + state.std * noise, low, high)


def sample_stored_goal(state: PlannerState, low, high, key: jax.Array, clip: bool = True) -> jax.Array:
    """One goal (D,) from the search's Gaussian, clipped to [low, high] when `clip`."""
    goal = state.mean + state.std * jax.random.normal(key, state.mean.shape, state.mean.dtype)
    return jnp.clip(goal, low, high) if clip else goal


def _mppi_refit(candidates: jax.Array, scores: jax.Array, config: PlannerConfig):
    """Weights softmax(temperature * score); weighted mean and std (PEG: no floor)."""
    finite = jnp.isfinite(scores)
    logits = jnp.where(finite, config.mppi_temperature * scores, -jnp.inf)
    logits = jnp.where(jnp.any(finite), logits, 0.0)  # all scores bad: uniform weights, not NaN
    weights = jax.nn.softmax(logits)
    mean = weights @ candidates
    std = jnp.sqrt(weights @ jnp.square(candidates - mean))
    return mean, std


def _cem_refit(candidates: jax.Array, scores: jax.Array, config: PlannerConfig):
    """Mean and std of the top `num_elites` candidates; std = sqrt(var + 1e-6) (PEG)."""
    ranked = jnp.where(jnp.isfinite(scores), scores, -jnp.inf)
    _, elite_index = jax.lax.top_k(ranked, config.num_elites)
    elites = candidates[elite_index]
    return elites.mean(axis=0), jnp.sqrt(elites.var(axis=0) + 1e-6)


def plan_goal(
    score_fn: ScoreFn, state: PlannerState, low, high, key: jax.Array, config: PlannerConfig
) -> tuple[jax.Array, PlannerState, dict]:
    """Refines `state` for config.iterations rounds (lax.scan) and returns a goal sampled from the result.

    Each round: G candidates from the Gaussian, clipped to [low, high] (D,); scores = score_fn(candidates,
    key) (G,); MPPI or CEM refit. Returns (goal (D,), refined state, metrics).
    """
    key_rounds, key_goal = jax.random.split(key)
    refit = _mppi_refit if config.method == "mppi" else _cem_refit

    def one_round(state: PlannerState, key_round):
        key_sample, key_score = jax.random.split(key_round)
        candidates = sample_candidates(state, low, high, key_sample, config.num_candidates)
        scores = score_fn(candidates, key_score)
        mean, std = refit(candidates, scores, config)
        finite = jnp.isfinite(scores)
        score_mean = jnp.sum(jnp.where(finite, scores, 0.0)) / jnp.maximum(jnp.sum(finite), 1)
        new_state = state.replace(mean=mean, std=jnp.maximum(std, config.min_std), score=score_mean)
        record = dict(score_mean=score_mean, score_max=jnp.max(jnp.where(finite, scores, -jnp.inf)),
                      nonfinite=jnp.mean(~finite))
        return new_state, record

    state, records = jax.lax.scan(one_round, state, jax.random.split(key_rounds, config.iterations))
    goal = sample_stored_goal(state, low, high, key_goal, clip=config.clip_final_goal)
    metrics = {
        "planner/score_first": records["score_mean"][0],
        "planner/score": records["score_mean"][-1],
        "planner/score_max": records["score_max"][-1],
        "planner/std": jnp.mean(state.std),
        "planner/nonfinite_scores": jnp.mean(records["nonfinite"]),
    }
    return goal, state, metrics


def peg_score(
    explore_reward: jax.Array, explore_returns: jax.Array, use_last_steps: int | None, use_value: bool = True
) -> jax.Array:
    """PEG's fitness of each candidate goal from its imagined rollout, time-major (docs/learner.md,
    "Goal search (planner)", step 4).

    explore_reward (H, G): Plan2Explore disagreement at each imagined state.
    explore_returns (H', G): TD(lambda) returns of those rewards bootstrapped with the explore target critic.
    Sums the returns (PEG `cost_use_p2e_value: True`) or, with use_value=False, the rewards, over the last
    `use_last_steps` steps (PEG `final_step_cost`), or over all steps when None. Returns (G,).
    The paper's appendix describes the score as the exploration value of the rollout's last state; this is
    PEG's code, which MoReFree extends (docs/fidelity.md, "Learner and schedule").
    """
    values = explore_returns if use_value else explore_reward
    if use_last_steps is not None:
        values = values[-use_last_steps:]
    return jnp.sum(values, axis=0)
