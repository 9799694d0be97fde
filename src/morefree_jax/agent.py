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
from typing import NamedTuple

import flax
import jax
import jax.numpy as jnp

from morefree_jax.actor_critic import (
    actor_critic_update,
    imagine_with,
    init_actor_critic,
    make_actor_critic,
    policy,
    project,
    returns_of,
    start_without_gradient,
)
from morefree_jax.config import AgentConfig
from morefree_jax.distance import distance, distance_update, goal_projection, init_distance, make_distance
from morefree_jax.explore import disagreement, ensemble_update, init_ensemble, make_ensemble
from morefree_jax.imagination import (
    SOURCE_EVAL,
    SOURCE_INITIAL,
    GoalPools,
    Trajectory,
    sample_imagination_goals,
)
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
from morefree_jax.world_model import Batch, encode, init_world_model, make_world_model, world_model_update

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
    Python-side acting loop should pass this (42 leaves at `cpu`) rather than the whole state with its
    optimiser moments (326 leaves).
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
    modules: dict


def make_agent(config: AgentConfig, spec: EnvSpec) -> Agent:
    wm = make_world_model(config.wm, spec.obs_size)
    wm_opt = make_optimizer(config.wm.opt)
    gc = make_actor_critic(config.gc, spec.action_size, use_context=True)
    explore_ac = make_actor_critic(config.explore.ac, spec.action_size, use_context=False)
    dist = make_distance(config.distance)
    ens = make_ensemble(config.explore, config.wm.stoch)
    feat_size = config.wm.deter + config.wm.stoch

    def init(key: jax.Array) -> AgentState:
        key_wm, key_gc, key_dist, key_ens, key_expl = jax.random.split(key, 5)
        gc_actor, gc_critic = init_actor_critic(gc, key_gc, feat_size, wm.embed_size)
        explore_actor, explore_critic = init_actor_critic(explore_ac, key_expl, feat_size, 0)
        return AgentState(
            wm=init_net_state(init_world_model(wm, key_wm, spec.obs_size, spec.action_size), wm_opt),
            gc_actor=gc_actor, gc_critic=gc_critic, distance=init_distance(dist, key_dist, wm.embed_size),
            ensemble=init_ensemble(ens, key_ens, feat_size + spec.action_size),
            explore_actor=explore_actor, explore_critic=explore_critic, updates=jnp.zeros((), jnp.int32),
        )

    def initial_latent(batch_shape: tuple[int, ...] = ()) -> Latent:
        """The zero latent; filtering an observation from it equals an is_first step."""
        return zero_latent(config.wm.deter, config.wm.stoch, batch_shape)

    def goal_context(state: AgentState, goal) -> GoalContext:
        """Prepares goal observations (..., O) for `act` (see GoalContext)."""
        return GoalContext(project(gc.actor, state.gc_actor.params, encode(wm, state.wm.params, goal)))

    def act(state: AgentState, latent: Latent, prev_action, obs, goal, key, mode):
        """Filters `obs` into the latent one step, then acts -> (action (A,), latent).

        latent (...), prev_action (..., A), obs (..., O); goal: a goal observation (..., O) or its
        `goal_context` (same actions, less work per call); mode: MODE_GOAL or MODE_EXPLORE, optionally
        | MODE_DETERMINISTIC; a Python int selects statically, an int array selects under lax.cond.

        A jitted single call on CPU costs more in XLA's runtime than in arithmetic: independent branches
        (goal encoding, the random draws) are handed to other threads. Hence one random draw per call and
        the optional goal context.
        """
        params = state.wm.params
        noise, action_unit = _acting_noise(key, latent.stoch.shape[:-1], config.wm.stoch, spec.action_size)
        latent, _, _ = wm.rssm.apply(params["rssm"], latent, prev_action, encode(wm, params, obs), noise)
        feat = feature(latent)

        def goal_policy():
            context = goal if isinstance(goal, GoalContext) else goal_context(state, goal)
            return tuple(policy(gc, state.gc_actor.params, feat, context.projection))

        def explore_policy():
            return tuple(policy(explore_ac, state.explore_actor.params, feat, None))

        if isinstance(mode, int):
            loc, scale = explore_policy() if mode & MODE_EXPLORE else goal_policy()
            deterministic = bool(mode & MODE_DETERMINISTIC)
        else:
            loc, scale = jax.lax.cond(mode & MODE_EXPLORE != 0, explore_policy, goal_policy)
            deterministic = mode & MODE_DETERMINISTIC != 0
        actor = TruncNormal(loc, scale)
        action = jnp.where(deterministic, actor.mode(), actor.sample_from_uniform(action_unit))
        return action, latent

    def goal_distance(state: AgentState, latent: Latent, goal_obs, obs=None) -> jax.Array:
        """Learned temporal distance to `goal_obs` in env steps (D * horizon, PEG's go-phase check).

        PEG embeds the current observation with the encoder; pass `obs` for that. Without it the current
        state is embedded by the embed head from `latent` (what the goal reward uses).
        """
        params = state.wm.params
        if obs is None:
            state_embed = wm.embed_head.apply(params["embed_head"], feature(latent))
        else:
            state_embed = encode(wm, params, obs)
        goal_embed = encode(wm, params, goal_obs)
        return distance(dist, state.distance.params, state_embed, goal_embed) * config.gc.horizon

    def imagine_to_goals(state: AgentState, start: Latent, goals, horizon: int, key) -> Trajectory:
        """Goal-conditioned policy rolled out in the model from one start latent (unbatched) to each of G
        goals (G, O) -> Trajectory with N = G (time-major, H+1 states)."""
        num = goals.shape[0]
        starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (num, *x.shape)), start)
        goal_embed = encode(wm, state.wm.params, goals)
        horizon_gc = gc._replace(config=dataclasses.replace(gc.config, horizon=horizon))
        return imagine_with(horizon_gc, state.gc_actor.params, wm.rssm, state.wm.params["rssm"], starts,
                            goal_embed, key)

    def exploration_value(state: AgentState, trajectory: Trajectory):
        """-> (disagreement reward (H+1, G), explore target-critic TD(lambda) returns (H, G))."""
        reward = disagreement(ens, state.ensemble.params, trajectory.feat, trajectory.action)
        target, _ = returns_of(explore_ac, state.explore_critic.target, trajectory, reward[:-1], None)
        return reward, target

    def world_model_part(state: AgentState, batch: Batch, key: jax.Array):
        """World-model update -> (wm state, posterior of the batch, metrics)."""
        return world_model_update(wm, wm_opt, state.wm, batch, key)

    def goal_conditioned_part(state: AgentState, wm_params, posterior, batch: Batch, goals: GoalPools,
                              key_starts, key):
        """Goal-conditioned actor-critic and temporal distance -> (gc actor, gc critic, distance, metrics).

        `key_starts` picks the imagination starts (shared with the exploration part, as in PEG)."""
        key_goals, key_gc, key_dist = jax.random.split(key, 3)
        starts, sequence_id, replay_obs = _imagination_starts(posterior.latent, batch.obs, key_starts)
        goal_obs, source = sample_imagination_goals(key_goals, replay_obs, goals, config.alpha,
                                                    sequence_id.shape[0])
        goal_embed = encode(wm, wm_params, goal_obs)
        distance_projection = goal_projection(dist, state.distance.params, goal_embed)

        def embed(feat):
            return wm.embed_head.apply(wm_params["embed_head"], feat)

        def goal_reward(trajectory: Trajectory):
            # Reward on states 0..H-1; the distance trains on the embeddings of all H+1 states, and the
            # last one needs no gradient (it enters no reward).
            def reward_and_embed(feat):
                embeds = embed(feat)
                d = dist.net.apply(state.distance.params, embeds, distance_projection[None],
                                   method=dist.net.from_projection)[..., 0]
                return -d, embeds

            reward, embeds = start_without_gradient(reward_and_embed, trajectory.feat[:-1])
            last = embed(jax.lax.stop_gradient(trajectory.feat[-1:]))
            return reward, jnp.concatenate([embeds, last], 0)

        gc_actor, gc_critic, imagined, gc_metrics = actor_critic_update(
            gc, state.gc_actor, state.gc_critic, state.updates, wm.rssm, wm_params["rssm"], goal_reward,
            starts, goal_embed, key_gc, "gc")
        distance_state, distance_metrics = distance_update(dist, state.distance, imagined.reward_extras,
                                                           sequence_id, key_dist)
        metrics = {**gc_metrics, **distance_metrics, "gc/goal_eval_frac": jnp.mean(source == SOURCE_EVAL),
                   "gc/goal_initial_frac": jnp.mean(source == SOURCE_INITIAL)}
        return gc_actor, gc_critic, distance_state, metrics

    def explore_part(state: AgentState, wm_params, posterior, batch: Batch, key_starts, key_expl):
        """Plan2Explore ensemble and exploration actor-critic -> (ensemble, actor, critic, metrics)."""
        starts, _, _ = _imagination_starts(posterior.latent, batch.obs, key_starts)
        ensemble_state, ensemble_metrics = ensemble_update(ens, state.ensemble, posterior.latent,
                                                           jnp.swapaxes(batch.action, 0, 1))

        def explore_reward(trajectory: Trajectory):
            reward = start_without_gradient(partial(disagreement, ens, ensemble_state.params),
                                            trajectory.feat[:-1], trajectory.action[:-1])
            return reward, None

        explore_actor, explore_critic, _, explore_metrics = actor_critic_update(
            explore_ac, state.explore_actor, state.explore_critic, state.updates, wm.rssm, wm_params["rssm"],
            explore_reward, starts, None, key_expl, "explore")
        return ensemble_state, explore_actor, explore_critic, {**ensemble_metrics, **explore_metrics}

    def train_step(state: AgentState, batch: Batch, goals: GoalPools, key: jax.Array):
        """All five updates on one replay batch (B, T, ...) -> (state, metrics)."""
        key_wm, key_starts, key_gc, key_expl = jax.random.split(key, 4)
        wm_state, posterior, wm_metrics = world_model_part(state, batch, key_wm)
        gc_actor, gc_critic, distance_state, gc_metrics = goal_conditioned_part(
            state, wm_state.params, posterior, batch, goals, key_starts, key_gc)
        # The two imagination parts are independent and XLA may interleave them; the barrier makes the
        # exploration part wait for the goal-conditioned one (measured: paper step 6.85 -> 6.56 s median).
        (gc_actor, gc_critic, distance_state), posterior = jax.lax.optimization_barrier(
            ((gc_actor, gc_critic, distance_state), posterior))
        ensemble_state, explore_actor, explore_critic, explore_metrics = explore_part(
            state, wm_state.params, posterior, batch, key_starts, key_expl)
        new_state = AgentState(wm_state, gc_actor, gc_critic, distance_state, ensemble_state, explore_actor,
                               explore_critic, state.updates + 1)
        return new_state, {**wm_metrics, **gc_metrics, **explore_metrics}

    def _imagination_starts(latent: Latent, obs, key):
        """Flattened posterior starts (N, ...), their replay row (N,), and the batch observations (T*B, O)."""
        length, batch_size = latent.deter.shape[:2]
        flat = jax.tree.map(lambda x: x.reshape(length * batch_size, *x.shape[2:]), latent)
        sequence_id = jnp.tile(jnp.arange(batch_size), length)
        replay_obs = jnp.swapaxes(obs, 0, 1).reshape(length * batch_size, -1)
        num = config.imag_starts
        if 0 < num < length * batch_size:
            index = jax.random.permutation(key, length * batch_size)[:num]
            flat, sequence_id = jax.tree.map(lambda x: x[index], flat), sequence_id[index]
        return flat, sequence_id, replay_obs

    # Building blocks, for benchmarks and notebooks: the modules and the three parts of train_step.
    modules = {"world_model": wm, "gc": gc, "explore_ac": explore_ac, "distance": dist, "ensemble": ens,
               "world_model_part": world_model_part, "goal_conditioned_part": goal_conditioned_part,
               "explore_part": explore_part}
    return Agent(init, initial_latent, goal_context, act, train_step, goal_distance, imagine_to_goals,
                 exploration_value, config, spec, modules)
