"""The MoReFree/PEG agent as pure functions: `make_agent(config, env_spec) -> Agent`.

    agent = make_agent(preset("cpu"), EnvSpec.from_env(env))
    state = agent.init(key)
    latent = agent.initial_latent(())                       # zeros = is_first
    action, latent = agent.act(state, latent, prev_action, obs, goal, key, MODE_GOAL)
    context = agent.goal_context(state, goal)               # once per goal: the same act, less work per step
    action, latent = agent.act(state, latent, prev_action, obs, context, key, MODE_GOAL)
    state, metrics = jax.jit(agent.train_step)(state, batch, GoalPools(eval_goals, initial_states), key)

Nothing is jitted here; callers jit (donate the state in train_step). Everything works unbatched and under
`jax.vmap` (over envs in `act`, over seeds in `init`/`train_step`).

One `train_step` = world model -> goal-conditioned actor-critic (imagination from the batch posteriors to
alpha-mixed goals, reward -D) -> temporal distance (on that imagination) -> Plan2Explore ensemble ->
exploration actor-critic (reward = disagreement). The planner's building blocks are `imagine_to_goals`
and `exploration_value`; the go phase ends early on `goal_distance`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import flax
import jax
import jax.numpy as jnp

from morefree_jax import agent_update
from morefree_jax.actor_critic import (
    imagine_with,
    init_actor_critic,
    make_actor_critic,
    policy,
    project,
    returns_of,
)
from morefree_jax.distance import distance, init_distance, make_distance
from morefree_jax.imagination import (
    Trajectory,
)
from morefree_jax.learner_config import AgentConfig
from morefree_jax.networks import (
    ERF_INV_LIMIT,
    SQRT2,
    Latent,
    NetState,
    TruncNormal,
    feature,
    init_net_state,
    make_optimizer,
    zero_latent,
)
from morefree_jax.plan2explore import disagreement, init_ensemble, make_ensemble
from morefree_jax.precision import resolve_precision
from morefree_jax.world_model import encode, init_world_model, make_world_model

MODE_GOAL, MODE_EXPLORE = 0, 1  # policy choice (bit 0)
MODE_DETERMINISTIC = 2  # bit 1: actor mode instead of a sample; e.g. MODE_GOAL | MODE_DETERMINISTIC for eval


class EnvSpec(NamedTuple):
    obs_size: int
    action_size: int
    goal_dims: tuple[int, ...]

    @classmethod
    def from_env(cls, env) -> EnvSpec:
        """From an envs_mjx task (goal space = observation space; goal_dims for success checks)."""
        return cls(int(env.observation_size), int(env.action_size), tuple(int(d) for d in env.goal_dims))


class GoalContext(NamedTuple):
    """A goal prepared for acting (`agent.goal_context`): the goal-conditioned actor's first-layer
    projection of the goal's encoding. It is constant while the goal is, so an acting loop that computes
    it once per goal saves `act` the goal's encoder pass and one hidden-size matrix-vector product."""

    projection: jax.Array  # (..., actor hidden)


@flax.struct.dataclass
class AgentState:
    wm: NetState
    gc_actor: NetState
    gc_critic: NetState  # target critic in .target
    distance: NetState
    ensemble: NetState  # parameters stacked over the K members
    explore_actor: NetState
    explore_critic: NetState
    updates: jax.Array  # train steps done so far (int32); drives the target-critic copies


def acting_state(state: AgentState) -> AgentState:
    """The part of `state` that `act` reads: the encoder, RSSM and actor parameters; every other field is
    None, as are the decoder and embed head (`goal_distance` needs the full state).

    `act` gives the same result on it. A jitted call flattens its arguments on every dispatch, so a
    Python-side acting loop should pass this rather than the whole state with its optimiser moments (about
    an eighth of the leaves; docs/learner.md, "Using the agent directly", gives the counts).
    """
    def params_only(net: NetState) -> NetState:
        return NetState(net.params, None)

    acting_wm = NetState({part: state.wm.params[part] for part in ("encoder", "rssm")}, None)
    return AgentState(acting_wm, params_only(state.gc_actor), None, None, None,
                      params_only(state.explore_actor), None, state.updates)


def _acting_noise(key: jax.Array, batch_shape: tuple[int, ...], stoch: int, action_size: int):
    """One uniform draw for a whole `act` step -> (standard-normal latent noise, U[0, 1) for the action).

    The normal noise is the inverse CDF of the uniform, as in jax.random.normal. XLA:CPU runs each
    threefry call as its own rolled loop; one draw instead of split + two draws keeps the per-call graph
    short (see `act`).
    """
    unit = jax.random.uniform(key, (*batch_shape, stoch + action_size))
    symmetric = jnp.clip(2.0 * unit[..., :stoch] - 1.0, -ERF_INV_LIMIT, ERF_INV_LIMIT)
    return SQRT2 * jax.scipy.special.erfinv(symmetric), unit[..., stoch:]


class AgentModules(NamedTuple):
    """The agent's networks and optimiser (built once by make_agent; static under jit)."""

    wm: Any
    wm_opt: Any
    gc: Any
    explore_ac: Any
    dist: Any
    ens: Any
    config: AgentConfig
    spec: EnvSpec


class AgentParts(NamedTuple):
    """The three parts of train_step, bound to the agent's modules (benchmarks, notebooks)."""

    world_model_part: Callable  # (state, batch, key) -> (wm state, posterior, metrics)
    goal_conditioned_part: Callable  # (state, wm_params, posterior, batch, goals, key_starts, key)
    explore_part: Callable  # (state, wm_params, posterior, batch, key_starts, key)


class Agent(NamedTuple):
    """Pure functions of the agent (see the module docstring) and the pieces they are built from."""

    init: Callable
    initial_latent: Callable
    goal_context: Callable
    act: Callable
    train_step: Callable
    goal_distance: Callable
    imagine_to_goals: Callable
    exploration_value: Callable
    config: AgentConfig
    spec: EnvSpec
    modules: AgentModules
    parts: AgentParts


def make_agent(config: AgentConfig, spec: EnvSpec) -> Agent:
    """The agent of `config`; config.precision "auto" becomes this machine's default (precision.py)."""
    config = dataclasses.replace(config, precision=resolve_precision(config.precision))
    precision = config.precision
    m = AgentModules(wm=make_world_model(config.wm, spec.obs_size, precision),
                     wm_opt=make_optimizer(config.wm.opt),
                     gc=make_actor_critic(config.gc, spec.action_size, True, precision),
                     explore_ac=make_actor_critic(config.explore.ac, spec.action_size, False, precision),
                     dist=make_distance(config.distance, precision),
                     ens=make_ensemble(config.explore, config.wm.stoch, precision), config=config, spec=spec)
    parts = AgentParts(partial(agent_update.world_model_part, m),
                       partial(agent_update.goal_conditioned_part, m), partial(agent_update.explore_part, m))
    return Agent(partial(init, m), partial(initial_latent, m), partial(goal_context, m), partial(act, m),
                 partial(agent_update.train_step, m), partial(goal_distance, m), partial(imagine_to_goals, m),
                 partial(exploration_value, m), config, spec, m, parts)


def init(m: AgentModules, key: jax.Array) -> AgentState:
    key_wm, key_gc, key_dist, key_ens, key_expl = jax.random.split(key, 5)
    feat_size = m.config.wm.deter + m.config.wm.stoch
    gc_actor, gc_critic = init_actor_critic(m.gc, key_gc, feat_size, m.wm.embed_size)
    explore_actor, explore_critic = init_actor_critic(m.explore_ac, key_expl, feat_size, 0)
    return AgentState(
        wm=init_net_state(init_world_model(m.wm, key_wm, m.spec.obs_size, m.spec.action_size), m.wm_opt),
        gc_actor=gc_actor, gc_critic=gc_critic, distance=init_distance(m.dist, key_dist, m.wm.embed_size),
        ensemble=init_ensemble(m.ens, key_ens, feat_size + m.spec.action_size),
        explore_actor=explore_actor, explore_critic=explore_critic, updates=jnp.zeros((), jnp.int32),
    )


def initial_latent(m: AgentModules, batch_shape: tuple[int, ...] = ()) -> Latent:
    """The zero latent; filtering an observation from it equals an is_first step."""
    return zero_latent(m.config.wm.deter, m.config.wm.stoch, batch_shape)


def goal_context(m: AgentModules, state: AgentState, goal) -> GoalContext:
    """Prepares goal observations (..., O) for `act` (see GoalContext)."""
    return GoalContext(project(m.gc.actor, state.gc_actor.params, encode(m.wm, state.wm.params, goal)))


def act(m: AgentModules, state: AgentState, latent: Latent, prev_action, obs, goal, key, mode):
    """Filters `obs` into the latent one step, then acts -> (action (A,), latent).

    latent (...), prev_action (..., A), obs (..., O); goal: a goal observation (..., O) or its
    `goal_context` (same actions, less work per call); mode: MODE_GOAL or MODE_EXPLORE, optionally
    | MODE_DETERMINISTIC; a Python int selects statically, an int array selects under lax.cond.

    A jitted single call on CPU costs more in XLA's runtime than in arithmetic: independent branches
    (goal encoding, the random draws) are handed to other threads. Hence one random draw per call and
    the optional goal context.
    """
    params = state.wm.params
    noise, action_unit = _acting_noise(key, latent.stoch.shape[:-1], m.config.wm.stoch, m.spec.action_size)
    latent, _, _ = m.wm.rssm.apply(params["rssm"], latent, prev_action, encode(m.wm, params, obs), noise)
    feat = feature(latent)

    def goal_policy():
        context = goal if isinstance(goal, GoalContext) else goal_context(m, state, goal)
        return tuple(policy(m.gc, state.gc_actor.params, feat, context.projection))

    def explore_policy():
        return tuple(policy(m.explore_ac, state.explore_actor.params, feat, None))

    if isinstance(mode, int):
        loc, scale = explore_policy() if mode & MODE_EXPLORE else goal_policy()
        deterministic = bool(mode & MODE_DETERMINISTIC)
    else:
        loc, scale = jax.lax.cond(mode & MODE_EXPLORE != 0, explore_policy, goal_policy)
        deterministic = mode & MODE_DETERMINISTIC != 0
    actor = TruncNormal(loc, scale)
    action = jnp.where(deterministic, actor.mode(), actor.sample_from_uniform(action_unit))
    return action, latent


def goal_distance(m: AgentModules, state: AgentState, latent: Latent, goal_obs, obs=None) -> jax.Array:
    """Learned temporal distance to `goal_obs` in env steps (D * horizon, PEG's go-phase check).

    PEG embeds the current observation with the encoder; pass `obs` for that. Without it the current
    state is embedded by the embed head from `latent` (what the goal reward uses).
    """
    params = state.wm.params
    if obs is None:
        state_embed = m.wm.embed_head.apply(params["embed_head"], feature(latent))
    else:
        state_embed = encode(m.wm, params, obs)
    goal_embed = encode(m.wm, params, goal_obs)
    return distance(m.dist, state.distance.params, state_embed, goal_embed) * m.config.gc.horizon


def imagine_to_goals(m: AgentModules, state: AgentState, start: Latent, goals, horizon: int,
                     key) -> Trajectory:
    """Goal-conditioned policy rolled out in the model from one start latent (unbatched) to each of G
    goals (G, O) -> Trajectory with N = G (time-major, H+1 states)."""
    num = goals.shape[0]
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (num, *x.shape)), start)
    goal_embed = encode(m.wm, state.wm.params, goals)
    horizon_gc = m.gc._replace(config=dataclasses.replace(m.gc.config, horizon=horizon))
    return imagine_with(horizon_gc, state.gc_actor.params, m.wm.rssm, state.wm.params["rssm"], starts,
                        goal_embed, key)


def exploration_value(m: AgentModules, state: AgentState, trajectory: Trajectory):
    """-> (disagreement reward (H+1, G), explore target-critic TD(lambda) returns (H, G))."""
    reward = disagreement(m.ens, state.ensemble.params, trajectory.feat, trajectory.action)
    target, _ = returns_of(m.explore_ac, state.explore_critic.target, trajectory, reward[:-1], None)
    return reward, target
