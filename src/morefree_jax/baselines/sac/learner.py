"""MEDAL's SAC learner (docs/baselines.md, "The SAC learner") as pure functions, for the model-free baselines.

    config = SACConfig()
    state = init(config, obs_size, action_size, key)
    action = act(config, state.actor.params, obs, key, deterministic=False)
    state, metrics = update(config, state, batch, key)      # jit at the caller; batch: SACBatch (B, ...)

Networks (networks of MEDAL's `SACAgent`): the actor is trunk (Linear -> LayerNorm -> tanh, 50 wide) then
2 x 256 ReLU then mean and log-std (log-std hard-clipped to [-20, 2]), a tanh-squashed Gaussian whose
deterministic action is tanh(mean); the critic is its own trunk then twin heads on (features, action),
each 2 x 256 ReLU -> 1. Xavier-uniform weights, zero biases. One update, in MEDAL's order: critic (target
y = reward_scale * r + discount * not_done * (min target Q(s', a') - alpha log pi(a'|s')), a' sampled;
loss 0.5 (MSE1 + MSE2)), actor (mean(alpha log pi - min Q)), temperature (a fresh sample of the updated
actor: mean(alpha (-log pi - target entropy)), on log alpha), then Polyak averaging of the target critic.
Adam with its defaults at lr 3e-4 for all three, initial alpha 1, target entropy -|A|/2.
"""

from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from morefree_jax.baselines.baseline_config import SACConfig
from morefree_jax.networks import NetState, gradient_update, init_net_state
from morefree_jax.precision import dot_general_for


class SACBatch(NamedTuple):
    obs: jax.Array  # (B, O) observation (goal-conditioned agents: observation ++ goal)
    action: jax.Array  # (B, A) in [-1, 1]
    reward: jax.Array  # (B,)
    next_obs: jax.Array  # (B, O)
    not_done: jax.Array  # (B,) 0 where the episode ended on that step (no bootstrap), else 1


def _dense(features: int, weight_init: str, precision: str) -> nn.Dense:
    # built here, not at import: making an initializer starts JAX's backend (importing changes nothing)
    kernel_init = (nn.initializers.orthogonal() if weight_init == "orthogonal"
                   else nn.initializers.xavier_uniform())
    return nn.Dense(features, kernel_init=kernel_init, bias_init=nn.initializers.zeros,
                    dot_general=dot_general_for(precision))


class _Trunk(nn.Module):
    feature_dim: int
    weight_init: str
    precision: str

    @nn.compact
    def __call__(self, obs):  # LayerNorm in float32 at either precision
        return jnp.tanh(nn.LayerNorm()(_dense(self.feature_dim, self.weight_init, self.precision)(obs)))


class _Head(nn.Module):
    hidden_dim: int
    out: int
    depth: int
    weight_init: str
    precision: str

    @nn.compact
    def __call__(self, x):
        for _ in range(self.depth):
            x = nn.relu(_dense(self.hidden_dim, self.weight_init, self.precision)(x))
        return _dense(self.out, self.weight_init, self.precision)(x)


class Actor(nn.Module):
    """obs -> (mean, log_std) (..., A), log_std clipped (or tanh-squashed) into [log_std_min, log_std_max]."""

    action_size: int
    config: SACConfig

    @nn.compact
    def __call__(self, obs):
        cfg = self.config
        trunk = _Trunk(cfg.feature_dim, cfg.weight_init, cfg.precision)(obs)
        out = _Head(cfg.hidden_dim, 2 * self.action_size, cfg.hidden_depth, cfg.weight_init,
                    cfg.precision)(trunk)
        mean, log_std = jnp.split(out, 2, axis=-1)
        if cfg.log_std_squash:  # IBC: a smooth squash instead of MEDAL's hard clip
            unit = 0.5 * (jnp.tanh(log_std) + 1.0)
            return mean, cfg.log_std_min + (cfg.log_std_max - cfg.log_std_min) * unit
        return mean, jnp.clip(log_std, cfg.log_std_min, cfg.log_std_max)


class Critic(nn.Module):
    """(obs, action) -> (q1, q2) (...,): a shared trunk on obs, twin heads on (features, action)."""

    config: SACConfig

    @nn.compact
    def __call__(self, obs, action):
        cfg = self.config
        trunk = _Trunk(cfg.feature_dim, cfg.weight_init, cfg.precision)(obs)
        features = jnp.concatenate([trunk, action], axis=-1)
        q1 = _Head(cfg.hidden_dim, 1, cfg.hidden_depth, cfg.weight_init, cfg.precision)(features)[..., 0]
        q2 = _Head(cfg.hidden_dim, 1, cfg.hidden_depth, cfg.weight_init, cfg.precision)(features)[..., 0]
        return q1, q2


@struct.dataclass
class SACState:
    actor: NetState
    critic: NetState  # critic.target: the Polyak-averaged target critic
    log_alpha: NetState  # params: a scalar
    updates: jax.Array


def _modules(config: SACConfig, action_size: int) -> tuple[Actor, Critic]:
    return Actor(action_size, config), Critic(config)


def _optimizer(config: SACConfig) -> optax.GradientTransformation:
    return optax.adam(config.lr)  # MEDAL: Adam with its defaults


def target_entropy(config: SACConfig, action_size: int) -> float:
    if config.target_entropy is None:
        return config.target_entropy_per_dim * action_size
    return config.target_entropy


def init(config: SACConfig, obs_size: int, action_size: int, key: jax.Array) -> SACState:
    actor, critic = _modules(config, action_size)
    key_actor, key_critic = jax.random.split(key)
    obs, action = jnp.zeros((1, obs_size)), jnp.zeros((1, action_size))
    optimizer = _optimizer(config)
    return SACState(
        actor=init_net_state(actor.init(key_actor, obs), optimizer),
        critic=init_net_state(critic.init(key_critic, obs, action), optimizer, with_target=True),
        log_alpha=init_net_state(jnp.log(jnp.asarray(config.init_temperature, jnp.float32)), optimizer),
        updates=jnp.zeros((), jnp.int32),
    )


def squashed_sample(mean: jax.Array, log_std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(tanh(u), log pi(tanh(u))) for u ~ N(mean, exp(log_std)), summed over the action dims."""
    noise = jax.random.normal(key, mean.shape)
    u = mean + jnp.exp(log_std) * noise
    gaussian = -0.5 * noise**2 - log_std - 0.5 * jnp.log(2 * jnp.pi)
    # log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable for large |u|
    correction = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return jnp.tanh(u), jnp.sum(gaussian - correction, axis=-1)


def _action_size(actor_params) -> int:
    head = actor_params["params"]["_Head_0"]
    return head[f"Dense_{len(head) - 1}"]["bias"].shape[-1] // 2  # the last layer: mean and log-std


def policy(config: SACConfig, actor_params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(mean, log_std) (..., A) of the actor's Gaussian before the tanh."""
    return _modules(config, _action_size(actor_params))[0].apply(actor_params, obs)


def act(config: SACConfig, actor_params, obs: jax.Array, key: jax.Array, deterministic: bool = False):
    """An action in [-1, 1] for obs (..., O): a squashed sample, or tanh(mean) when deterministic."""
    mean, log_std = policy(config, actor_params, obs)
    return jnp.tanh(mean) if deterministic else squashed_sample(mean, log_std, key)[0]


def q_values(config: SACConfig, critic_params, obs, action) -> tuple[jax.Array, jax.Array]:
    return Critic(config).apply(critic_params, obs, action)


def critic_target(config: SACConfig, state: SACState, batch: SACBatch, key: jax.Array) -> jax.Array:
    """y = reward_scale r + discount not_done (min target Q(s', a') - alpha log pi(a'|s')), a' sampled."""
    mean, log_std = policy(config, state.actor.params, batch.next_obs)
    next_action, next_log_pi = squashed_sample(mean, log_std, key)
    q1, q2 = q_values(config, state.critic.target, batch.next_obs, next_action)
    soft_value = jnp.minimum(q1, q2) - jnp.exp(state.log_alpha.params) * next_log_pi
    return config.reward_scale * batch.reward + config.discount * batch.not_done * soft_value


def critic_loss(config: SACConfig, critic_params, batch: SACBatch, target: jax.Array):
    q1, q2 = q_values(config, critic_params, batch.obs, batch.action)
    loss = config.critic_loss_weight * (jnp.mean((q1 - target) ** 2) + jnp.mean((q2 - target) ** 2))
    return loss, {"loss": loss, "q": jnp.mean(q1), "target": jnp.mean(target)}


def actor_loss(config: SACConfig, actor_params, critic_params, alpha, obs, key):
    """mean(alpha log pi(a|s) - min Q(s, a)), a sampled (reparameterised) from the actor."""
    mean, log_std = policy(config, actor_params, obs)
    action, log_pi = squashed_sample(mean, log_std, key)
    q1, q2 = q_values(config, critic_params, obs, action)
    loss = jnp.mean(alpha * log_pi - jnp.minimum(q1, q2))
    return loss, {"loss": loss, "entropy": -jnp.mean(log_pi), "log_pi": log_pi}


def alpha_loss(log_alpha, log_pi: jax.Array, entropy_target: float):
    """mean(alpha (-log pi - target entropy)) with log pi held fixed: alpha rises when entropy is low."""
    return jnp.mean(jnp.exp(log_alpha) * jax.lax.stop_gradient(-log_pi - entropy_target)), {}


def update(config: SACConfig, state: SACState, batch: SACBatch, key: jax.Array) -> tuple[SACState, dict]:
    """One SAC update in MEDAL's order: critic, actor, temperature, Polyak target (module docstring). With
    actor_update_every / target_update_every > 1 (IBC) the later steps run only on every k-th update."""
    key_target, key_actor, key_alpha = jax.random.split(key, 3)
    optimizer = _optimizer(config)
    target = jax.lax.stop_gradient(critic_target(config, state, batch, key_target))
    critic, critic_aux, _ = gradient_update(
        state.critic, lambda p: critic_loss(config, p, batch, target), optimizer)
    actor_step = lambda: _actor_and_alpha(config, state, critic, batch, key_actor, key_alpha)  # noqa: E731
    if config.actor_update_every == 1:  # MEDAL: no cond, the graph of the original learner
        actor, log_alpha, actor_aux = actor_step()
    else:
        skipped = (state.actor, state.log_alpha, {"loss": jnp.zeros(()), "entropy": jnp.zeros(())})
        actor, log_alpha, actor_aux = jax.lax.cond(state.updates % config.actor_update_every == 0,
                                                   actor_step, lambda: skipped)
    polyak = jax.tree.map(lambda t, p: (1 - config.tau) * t + config.tau * p, critic.target, critic.params)
    if config.target_update_every > 1:
        polyak = jax.tree.map(lambda new, old: jnp.where(state.updates % config.target_update_every == 0,
                                                         new, old), polyak, critic.target)
    new_state = SACState(actor, critic.replace(target=polyak), log_alpha, state.updates + 1)
    metrics = {"sac/critic_loss": critic_aux["loss"], "sac/actor_loss": actor_aux["loss"],
               "sac/q": critic_aux["q"], "sac/target": critic_aux["target"],
               "sac/entropy": actor_aux["entropy"], "sac/alpha": jnp.exp(log_alpha.params)}
    return new_state, metrics


def _actor_and_alpha(config: SACConfig, state: SACState, critic: NetState, batch: SACBatch, key_actor,
                     key_alpha) -> tuple[NetState, NetState, dict]:
    """The actor step on the updated critic, then the temperature step: MEDAL's Adam on log alpha with a
    fresh sample of the updated actor, or IBC's clipped plain step on alpha with the actor step's log pi."""
    optimizer = _optimizer(config)
    alpha = jnp.exp(state.log_alpha.params)
    actor, actor_aux, _ = gradient_update(
        state.actor, lambda p: actor_loss(config, p, critic.params, alpha, batch.obs, key_actor), optimizer)
    entropy_target = target_entropy(config, batch.action.shape[-1])
    log_pi = actor_aux.pop("log_pi")
    if config.alpha_update == "clipped_step":
        step = config.alpha_step_size * jnp.mean(-log_pi - entropy_target)
        new_alpha = jnp.clip(alpha - step, *config.alpha_bounds)
        return actor, state.log_alpha.replace(params=jnp.log(new_alpha)), actor_aux
    _, fresh_log_pi = squashed_sample(*policy(config, actor.params, batch.obs), key_alpha)
    log_alpha, _, _ = gradient_update(state.log_alpha, lambda p: alpha_loss(p, fresh_log_pi, entropy_target),
                                      optimizer)
    return actor, log_alpha, actor_aux
