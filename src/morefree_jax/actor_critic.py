"""Actor-critic in imagination (DreamerV2/LEXA inside PEG), shared by the goal-conditioned and the
exploration learner.

Actor: trunc-normal head, dynamics gradients through the imagined trajectory,
  loss = -mean(weight[:-2] * (target[1:] + entropy_scale * entropy[:-1])).
Critic: Normal(., 1) on stop-gradient features, loss = mean(weight[:-1] * 0.5 * (v - sg(target))^2).
Targets: TD(lambda) with the target critic, constant discount, bootstrapped from the last state.
The target critic is a hard copy of the critic every `target_every` updates (the first update copies).
The goal-conditioned learner feeds the goal embedding as the networks' context; its projection through
the first layer is computed once per trajectory (networks.ContextMLP).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from morefree_jax.imagination import Trajectory, imagine
from morefree_jax.learner_config import ActorCriticConfig
from morefree_jax.networks import (
    RSSM,
    ContextMLP,
    Latent,
    NetState,
    TruncNormal,
    actor_distribution,
    gradient_update,
    init_net_state,
    make_optimizer,
)
from morefree_jax.returns import discount_weights, lambda_return


class ActorCritic(NamedTuple):
    actor: ContextMLP
    critic: ContextMLP
    config: ActorCriticConfig
    actor_opt: optax.GradientTransformation
    critic_opt: optax.GradientTransformation


class Imagined(NamedTuple):
    """Stop-gradient products of the actor's pass, reused by the critic and the other learners."""

    trajectory: Trajectory
    target: jax.Array  # (H, N)
    weight: jax.Array  # (H+1, N)
    reward_extras: object  # whatever the reward function returned besides the reward


def make_actor_critic(cfg: ActorCriticConfig, action_size: int, use_context: bool,
                      precision: str = "f32") -> ActorCritic:
    return ActorCritic(
        actor=ContextMLP(cfg.actor_layers, 2 * action_size, use_context, head_fan_out=action_size,
                         precision=precision),
        critic=ContextMLP(cfg.critic_layers, 1, use_context, precision=precision),
        config=cfg,
        actor_opt=make_optimizer(cfg.actor_opt),
        critic_opt=make_optimizer(cfg.critic_opt),
    )


def init_actor_critic(ac: ActorCritic, key, feat_size: int, context_size: int) -> tuple[NetState, NetState]:
    key_actor, key_critic = jax.random.split(key)
    feat = jnp.zeros((1, feat_size))
    context = jnp.zeros((1, context_size)) if ac.actor.use_context else None
    input_size = feat_size + (context_size if ac.actor.use_context else 0)
    actor_params = ac.actor.clone(input_size=input_size).init(key_actor, feat, context)
    critic_params = ac.critic.clone(input_size=input_size).init(key_critic, feat, context)
    return (init_net_state(actor_params, ac.actor_opt),
            init_net_state(critic_params, ac.critic_opt, with_target=True))


def project(net: ContextMLP, params, context: jax.Array | None) -> jax.Array | None:
    """The context's first-layer projection (N, hidden), or None for context-free networks."""
    return None if context is None else net.apply(params, context, method=ContextMLP.project)


def policy(ac: ActorCritic, actor_params, feat: jax.Array, projection) -> TruncNormal:
    raw = ac.actor.apply(actor_params, feat, projection, method=ContextMLP.from_projection)
    return actor_distribution(raw, ac.config.actor_min_std)


def value(ac: ActorCritic, critic_params, feat: jax.Array, projection) -> jax.Array:
    return ac.critic.apply(critic_params, feat, projection, method=ContextMLP.from_projection)[..., 0]


# Trajectory -> (reward (H, N) of states 0..H-1, extras). The last state's reward never enters a
# lambda-return, so reward functions skip it (saves 1/(H+1) of the reward networks' forward and backward),
# and they evaluate the start state through `start_without_gradient`.
RewardFn = Callable[[Trajectory], tuple[jax.Array, object]]


def start_without_gradient(fn: Callable, *inputs: jax.Array):
    """fn(*inputs) on time-major inputs (T, N, ...), with no backward pass through time step 0.

    fn maps each time step independently and returns a time-major array or pytree of them.

    In the actor loss, the start state's reward and the first successor's value enter only target[0],
    which the loss does not use (it starts at target[1]), so their gradient is zero; evaluated in one
    batch with the other steps they would still be back-propagated. Splitting step 0 off under
    stop_gradient gives the same values and gradients and saves 1/T of the network's backward pass.
    """
    first = fn(*(jax.lax.stop_gradient(x[:1]) for x in inputs))
    rest = fn(*(x[1:] for x in inputs))
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b], 0), first, rest)


def imagine_with(ac: ActorCritic, actor_params, rssm: RSSM, rssm_params, start: Latent,
                 context: jax.Array | None, key: jax.Array) -> Trajectory:
    """The learner's policy rolled out in the model for `config.horizon` steps from `start` (N, ...)."""
    actor_projection = project(ac.actor, actor_params, context)
    return imagine(rssm, rssm_params, lambda f: policy(ac, actor_params, f, actor_projection), start,
                   ac.config.horizon, key, min(ac.config.unroll, ac.config.horizon))


def returns_of(ac: ActorCritic, target_params, trajectory: Trajectory, reward: jax.Array,
               context: jax.Array | None) -> tuple[jax.Array, jax.Array]:
    """TD(lambda) targets (H, N) and weights (H+1, N) of a trajectory under the target critic.

    reward (H, N) holds the rewards of states 0..H-1; values bootstrap from the target critic.
    """
    cfg = ac.config
    projection = _time_broadcast(project(ac.critic, target_params, context))
    next_value = start_without_gradient(lambda feat: value(ac, target_params, feat, projection),
                                        trajectory.feat[1:])
    discount = jnp.full(trajectory.feat.shape[:1], cfg.discount)  # constant: no discount head (PEG)
    target = lambda_return(reward, next_value, discount[:-1, None], cfg.lambda_)
    # Weights from the (H+1,) discounts, broadcast over N (a (H+1, N) cumprod is slow to constant-fold).
    weight = jnp.broadcast_to(discount_weights(discount)[:, None], trajectory.feat.shape[:2])
    return target, weight


def _time_broadcast(projection):
    return None if projection is None else projection[None]


def actor_loss(ac: ActorCritic, actor_params, target_params, rssm: RSSM, rssm_params, reward_fn: RewardFn,
               start: Latent, context: jax.Array | None, key: jax.Array):
    """Imagines from `start` (N, ...) with the actor and returns (loss, (Imagined, metrics))."""
    sg = jax.lax.stop_gradient
    trajectory = imagine_with(ac, actor_params, rssm, rssm_params, start, context, key)
    reward, extras = reward_fn(trajectory)
    target, weight = returns_of(ac, target_params, trajectory, reward, context)
    entropy = trajectory.policy.entropy()  # (H, N) at states 0..H-1
    objective = target[1:] + ac.config.entropy * entropy[:-1]
    loss = -jnp.mean(sg(weight[:-2]) * objective)
    metrics = {
        "actor_loss": loss, "actor_entropy": jnp.mean(entropy), "reward": jnp.mean(reward),
        "target": jnp.mean(target), "action_abs": jnp.mean(jnp.abs(trajectory.action[1:])),
    }
    imagined = Imagined(sg(trajectory), sg(target), sg(weight), sg(extras))
    return loss, (imagined, metrics)


def critic_loss(ac: ActorCritic, critic_params, imagined: Imagined, context: jax.Array | None):
    v = value(ac, critic_params, imagined.trajectory.feat[:-1],
              _time_broadcast(project(ac.critic, critic_params, context)))
    loss = jnp.mean(imagined.weight[:-1] * 0.5 * jnp.square(v - imagined.target))
    return loss, {"critic_loss": loss, "value": jnp.mean(v)}


def actor_critic_update(ac: ActorCritic, actor: NetState, critic: NetState, updates: jax.Array,
                        rssm: RSSM, rssm_params, reward_fn: RewardFn, start: Latent,
                        context: jax.Array | None, key: jax.Array, prefix: str):
    """One actor and one critic step, then the periodic target copy.

    -> (actor, critic, Imagined, metrics). `updates` counts previous updates (copy when divisible).
    """
    actor, (imagined, actor_metrics), actor_norm = gradient_update(
        actor, lambda p: actor_loss(ac, p, critic.target, rssm, rssm_params, reward_fn, start, context, key),
        ac.actor_opt)
    critic, critic_metrics, critic_norm = gradient_update(
        critic, lambda p: critic_loss(ac, p, imagined, context), ac.critic_opt)
    copy = (updates % ac.config.target_every) == 0
    target = jax.tree.map(lambda new, old: jnp.where(copy, new, old), critic.params, critic.target)
    critic = critic.replace(target=target)
    metrics = {**actor_metrics, **critic_metrics, "actor_grad_norm": actor_norm,
               "critic_grad_norm": critic_norm}
    return actor, critic, imagined, {f"{prefix}/{k}": v for k, v in metrics.items()}
