"""Learned rewards as pure functions: the VICE-style goal classifier (R3L's forward reward, MEDAL's
discriminator) and random network distillation (R3L's backward exploration reward).
Settings and sources: baselines/baseline_config.py.

    classifier = init_classifier(cfg, obs_size, key)
    classifier, loss = update_classifier(cfg, classifier, goal_examples, visited, key)
    r = classifier_reward(cfg, classifier, next_obs)              # high near the goal examples

    rnd = init_rnd(cfg, obs_size, key)
    rnd = observe(rnd, obs)                                       # running whitening statistics
    rnd, loss = update_rnd(cfg, rnd, obs_batch)
    r = rnd_reward(cfg, rnd, next_obs_batch)                      # in [0, 1]: high where novel
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from morefree_jax.baselines.baseline_config import ClassifierConfig, RNDConfig
from morefree_jax.networks import NetState, gradient_update, init_net_state


def _torch_linear_init(fan_in: int):
    """PyTorch's default nn.Linear initialisation, U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and bias
    (kaiming_uniform with a = sqrt(5)): MEDAL's discriminator and DI-engine's RND networks keep it."""
    limit = 1.0 / math.sqrt(fan_in)

    def init(key: jax.Array, shape: Sequence[int], dtype=jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, -limit, limit)

    return init


class _MLP(nn.Module):
    """PyTorch-initialised Linear layers with a ReLU after each but the last; relu_output: after the last
    too, as DI-engine's FCEncoder (the RND target and predictor) applies its activation after every layer."""

    widths: Sequence[int]
    relu_output: bool = False

    @nn.compact
    def __call__(self, x):
        for index, width in enumerate(self.widths):
            init = _torch_linear_init(x.shape[-1])
            x = nn.Dense(width, kernel_init=init, bias_init=init)(x)
            if self.relu_output or index < len(self.widths) - 1:
                x = nn.relu(x)
        return x


# ---- the goal classifier (VICE, on MEDAL's discriminator template) ------------------------------

def _classifier(cfg: ClassifierConfig) -> _MLP:
    return _MLP((cfg.hidden, 1))


def init_classifier(cfg: ClassifierConfig, obs_size: int, key: jax.Array) -> NetState:
    return init_net_state(_classifier(cfg).init(key, jnp.zeros((1, obs_size))), optax.adam(cfg.lr))


def classifier_logits(cfg: ClassifierConfig, params, obs: jax.Array) -> jax.Array:
    return _classifier(cfg).apply(params, obs)[..., 0]


def classifier_reward(cfg: ClassifierConfig, state: NetState, obs: jax.Array) -> jax.Array:
    """-log(1 - sigmoid(D(s)) + eps): ~0 far from the goal examples, large on them."""
    return -jnp.log(1.0 - jax.nn.sigmoid(classifier_logits(cfg, state.params, obs)) + cfg.eps)


def mixup(inputs: jax.Array, labels: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each sample and its label mixed with a random partner's by lambda ~ Beta(1, 1) (MEDAL's mixup)."""
    key_lambda, key_partner = jax.random.split(key)
    lam = jax.random.beta(key_lambda, 1.0, 1.0, labels.shape)
    partner = jax.random.permutation(key_partner, labels.shape[0])
    mixed = lam[:, None] * inputs + (1 - lam[:, None]) * inputs[partner]
    return mixed, lam * labels + (1 - lam) * labels[partner]


def classifier_loss(cfg: ClassifierConfig, params, positives, negatives, key):
    inputs = jnp.concatenate([positives, negatives])
    labels = jnp.concatenate([jnp.ones(len(positives)), jnp.zeros(len(negatives))])
    if cfg.mixup:
        inputs, labels = mixup(inputs, labels, key)
    loss = jnp.mean(optax.sigmoid_binary_cross_entropy(classifier_logits(cfg, params, inputs), labels))
    return loss, loss


def update_classifier(cfg: ClassifierConfig, state: NetState, positives, negatives, key):
    """One Adam step of BCE: goal examples (label 1) against visited states (label 0) -> (state, the
    loss before the step)."""
    return gradient_update(state, lambda p: classifier_loss(cfg, p, positives, negatives, key),
                           optax.adam(cfg.lr))[:2]


# ---- random network distillation (DI-engine's settings) -----------------------------------------

@struct.dataclass
class RNDState:
    predictor: NetState
    target: dict  # frozen at its random initialisation
    mean: jax.Array  # running statistics of the observations (whitening)
    var: jax.Array
    count: jax.Array


def init_rnd(cfg: RNDConfig, obs_size: int, key: jax.Array) -> RNDState:
    key_predictor, key_target = jax.random.split(key)
    net, dummy = _MLP(cfg.hidden, relu_output=True), jnp.zeros((1, obs_size))
    return RNDState(predictor=init_net_state(net.init(key_predictor, dummy), optax.adam(cfg.lr)),
                    target=net.init(key_target, dummy), mean=jnp.zeros(obs_size), var=jnp.ones(obs_size),
                    count=jnp.asarray(1e-4))  # DI-engine's RunningMeanStd epsilon


def observe(state: RNDState, obs: jax.Array) -> RNDState:
    """Adds one observation (O,) to the running mean and variance (the parallel-variance update)."""
    count = state.count + 1.0
    delta = obs - state.mean
    mean = state.mean + delta / count
    var = (state.var * state.count + delta**2 * state.count / count) / count
    return state.replace(mean=mean, var=var, count=count)


def _errors(cfg: RNDConfig, predictor_params, state: RNDState, obs: jax.Array) -> jax.Array:
    """Per-sample squared prediction error averaged over the features, on whitened, clipped inputs."""
    whitened = jnp.clip((obs - state.mean) / jnp.sqrt(state.var + 1e-8), -cfg.clip, cfg.clip)
    net = _MLP(cfg.hidden, relu_output=True)
    target = jax.lax.stop_gradient(net.apply(state.target, whitened))
    return jnp.mean((net.apply(predictor_params, whitened) - target) ** 2, axis=-1)


def update_rnd(cfg: RNDConfig, state: RNDState, obs: jax.Array) -> tuple[RNDState, jax.Array]:
    """One Adam step of the predictor towards the frozen target on a batch (B, O) -> (state, the loss
    before the step)."""
    def loss_fn(params):
        loss = jnp.mean(_errors(cfg, params, state, obs))
        return loss, loss

    predictor, loss, _ = gradient_update(state.predictor, loss_fn, optax.adam(cfg.lr))
    return state.replace(predictor=predictor), loss


def rnd_reward(cfg: RNDConfig, state: RNDState, obs: jax.Array) -> jax.Array:
    """The prediction errors of a batch (B, O), min-max normalised to [0, 1] within it (DI-engine)."""
    errors = _errors(cfg, state.predictor.params, state, obs)
    low, high = jnp.min(errors), jnp.max(errors)
    return (errors - low) / (high - low + 1e-8)
