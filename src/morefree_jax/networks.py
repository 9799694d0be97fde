"""Networks of the agent as Flax linen modules: MLPs, the LayerNorm GRU, the RSSM cell, the actor head.

Modules are used through `init`/`apply` (state holds only parameter pytrees). Two structural choices keep
the math of PEG/DreamerV2 and remove redundant work:
- A network whose input is concat(x, context) (actor/critic on feat+goal, distance on state+goal, the
  posterior on deter+embed) has its first layer split into Dense(x) + Dense(context, no bias): the same
  function class, but the context projection is computed once per goal / per embedding instead of at every
  imagined step.
- Every kernel starts from Keras' default, Glorot-uniform, with which DreamerV2/PEG build every Dense layer
  (Flax's default, LeCun-normal, draws a first layer on 6 raw inputs about 6x wider); a layer split in two
  above keeps the limit of the one layer it replaces (`glorot_uniform`'s fan_in).
- The RSSM exposes its pieces (`deter_step`, `prior_stats`, `posterior_stats`) so sequence code can run
  only the recurrent part inside `lax.scan` and the rest batched over all time steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from morefree_jax.learner_config import OptimizerConfig
from morefree_jax.precision import dot_general_for

# A Python float, not jnp: a jnp constant starts JAX's backend on import, too early for runtime.configure()
HALF_LOG_2PI_E = 0.5 * math.log(2.0 * math.pi * math.e)  # float32(.) equals the jnp.log value
SQRT2 = 2.0**0.5
ERF_INV_LIMIT = 1.0 - 2.0**-24  # the largest float32 below 1: erf_inv stays finite (~3.83)


class Latent(NamedTuple):
    """RSSM state: deter (..., D), stoch (..., S)."""

    deter: jax.Array
    stoch: jax.Array


class Gaussian(NamedTuple):
    """Diagonal Gaussian statistics (..., S)."""

    mean: jax.Array
    std: jax.Array


@jax.custom_jvp
def elu(x: jax.Array) -> jax.Array:
    """ELU (alpha 1), the activation of every network here: x where x > 0, else exp(x) - 1.

    exp(x) - 1 is what TensorFlow's Elu kernel (the original agent's) computes; `jax.nn.elu` uses expm1,
    which differs by at most ~1e-7 absolute and costs twice as much on CPU (XLA evaluates expm1 with
    both a polynomial and exp; docs/performance.md, "What the runtime settings gain").
    Its derivative is written with the output (1 where x > 0, else y + 1 = exp(x)), so the backward pass
    reuses y instead of evaluating exp(x) again: ELU passes over (N, 400) activations are a large share of
    a train step on CPU.
    """
    return jnp.where(x > 0, x, jnp.exp(jnp.minimum(x, 0.0)) - 1.0)


@elu.defjvp
def _elu_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    y = elu(x)
    return y, dx * jnp.where(x > 0, 1.0, y + 1.0)


def feature(latent: Latent) -> jax.Array:
    """feat = concat(stoch, deter) (..., S + D)."""
    return jnp.concatenate([latent.stoch, latent.deter], -1)


def sigmoid2_std(x: jax.Array, min_std: float) -> jax.Array:
    """DreamerV2 "sigmoid2" std transform: 2 * sigmoid(x / 2) + min_std."""
    return 2.0 * jax.nn.sigmoid(x / 2.0) + min_std


def gaussian_kl(lhs: Gaussian, rhs: Gaussian) -> jax.Array:
    """KL(lhs || rhs) of diagonal Gaussians, summed over the last axis."""
    var_ratio = jnp.square(lhs.std / rhs.std)
    mahalanobis = jnp.square((lhs.mean - rhs.mean) / rhs.std)
    return 0.5 * jnp.sum(var_ratio + mahalanobis - 1.0 - jnp.log(var_ratio), -1)


def glorot_uniform(fan_in: int | None = None, fan_out: int | None = None):
    """Keras' default kernel initializer: U(+-sqrt(6 / (fan_in + fan_out))), both taken from the kernel's
    shape unless given: a layer split in two here (ContextMLP, the posterior) passes the fan-in of the
    concatenated input, the actor's merged mean-and-std head the fan-out of each of PEG's two heads."""

    def init(key: jax.Array, shape: Sequence[int], dtype=jnp.float32) -> jax.Array:
        limit = (6.0 / ((fan_in or shape[0]) + (fan_out or shape[-1]))) ** 0.5
        return jax.random.uniform(key, shape, dtype, -limit, limit)

    return init


def dense(features: int, use_bias: bool = True, fan_in: int | None = None, fan_out: int | None = None,
          precision: str = "f32") -> nn.Dense:
    """A Dense layer as DreamerV2 builds it: Glorot-uniform kernel, zero bias; its matmul at `precision`
    (precision.py: "bf16" multiplies bfloat16 copies with float32 accumulation, parameters stay float32)."""
    return nn.Dense(features, use_bias=use_bias, kernel_init=glorot_uniform(fan_in, fan_out),
                    dot_general=dot_general_for(precision))


class MLP(nn.Module):
    """ELU MLP; optional linear output layer. precision: of every matmul (precision.py)."""

    layers: Sequence[int]
    out: int | None = None
    precision: str = "f32"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.layers:
            x = elu(dense(width, precision=self.precision)(x))
        if self.out is not None:
            x = dense(self.out, precision=self.precision)(x)
        return x


class ContextMLP(nn.Module):
    """ELU MLP on concat(x, context) with the context's share of the first layer computed separately.

    `project(context)` once, then `from_projection(x, projection)` for every x that shares the context.
    With `use_context=False` it is a plain MLP on x (the exploration actor and critic).
    input_size: the size of concat(x, context), for the first layer's initial scale (init_* sets it).
    head_fan_out: the initial scale's fan-out of the output layer, where it stands for several (the actor).
    precision: of every matmul (precision.py).
    """

    layers: Sequence[int]
    out: int
    use_context: bool = True
    input_size: int | None = None
    head_fan_out: int | None = None
    precision: str = "f32"

    def setup(self):
        precision = self.precision
        self.first = dense(self.layers[0], fan_in=self.input_size, precision=precision)
        if self.use_context:
            self.context = dense(self.layers[0], use_bias=False, fan_in=self.input_size, precision=precision)
        self.hidden = [dense(width, precision=precision) for width in self.layers[1:]]
        self.head = dense(self.out, fan_out=self.head_fan_out, precision=precision)

    def project(self, context: jax.Array) -> jax.Array:
        return self.context(context)

    def from_projection(self, x: jax.Array, projection: jax.Array | None) -> jax.Array:
        h = self.first(x)
        if projection is not None:
            h = h + projection
        h = elu(h)
        for layer in self.hidden:
            h = elu(layer(h))
        return self.head(h)

    def __call__(self, x: jax.Array, context: jax.Array | None = None) -> jax.Array:
        projection = self.project(context) if self.use_context else None
        return self.from_projection(x, projection)


class LayerNormGRU(nn.Module):
    """GRU with LayerNorm over the 3*deter pre-activations and update bias -1 (DreamerV2). DreamerV2's input
    layer has a bias (`use_bias=norm is not None`, true for its boolean norm); use_bias=False builds the
    layer of run dirs made before that was found (config `wm.gru_bias`)."""

    size: int
    use_bias: bool = True
    precision: str = "f32"

    @nn.compact
    def __call__(self, x: jax.Array, state: jax.Array) -> jax.Array:
        layer = dense(3 * self.size, use_bias=self.use_bias, precision=self.precision)
        parts = layer(jnp.concatenate([x, state], -1))  # LayerNorm and gates in float32
        parts = nn.LayerNorm(epsilon=1e-3)(parts)
        reset, cand, update = jnp.split(parts, 3, -1)
        cand = jnp.tanh(jax.nn.sigmoid(reset) * cand)
        update = jax.nn.sigmoid(update - 1.0)
        return update * cand + (1.0 - update) * state


class RSSM(nn.Module):
    """Recurrent state-space model with a Gaussian stochastic state (PEG: deter 200, hidden 200, stoch 50).
    embed_size: the encoder's output size, for the initial scale of the posterior's split first layer.
    gru_bias: the GRU input layer's bias (LayerNormGRU). precision: of every matmul (precision.py); the
    state carried across steps (deter, stoch) and the statistics stay float32."""

    deter: int
    hidden: int
    stoch: int
    min_std: float = 0.1
    embed_size: int | None = None
    gru_bias: bool = True
    precision: str = "f32"

    def setup(self):
        precision = self.precision
        self.img_in = dense(self.hidden, precision=precision)
        self.gru = LayerNormGRU(self.deter, self.gru_bias, precision)
        self.img_out = dense(self.hidden, precision=precision)
        self.img_stats = dense(2 * self.stoch, precision=precision)
        posterior_fan_in = self.deter + self.embed_size if self.embed_size else None
        self.obs_deter = dense(self.hidden, fan_in=posterior_fan_in, precision=precision)
        self.obs_embed = dense(self.hidden, use_bias=False, fan_in=posterior_fan_in, precision=precision)
        self.obs_stats = dense(2 * self.stoch, precision=precision)

    def _stats(self, raw: jax.Array) -> Gaussian:
        mean, std = jnp.split(raw, 2, -1)
        return Gaussian(mean, sigmoid2_std(std, self.min_std))

    def deter_step(self, prev: Latent, action: jax.Array) -> jax.Array:
        """The recurrent part of img_step: new deter from (prev stoch, prev deter, action)."""
        x = elu(self.img_in(jnp.concatenate([prev.stoch, action], -1)))
        return self.gru(x, prev.deter)

    def prior_stats(self, deter: jax.Array) -> Gaussian:
        return self._stats(self.img_stats(elu(self.img_out(deter))))

    def embed_projection(self, embed: jax.Array) -> jax.Array:
        """The embedding's share of the posterior's first layer (computable for all steps at once)."""
        return self.obs_embed(embed)

    def posterior_stats(self, deter: jax.Array, embed_projection: jax.Array) -> Gaussian:
        return self._stats(self.obs_stats(elu(self.obs_deter(deter) + embed_projection)))

    def img_step(self, prev: Latent, action: jax.Array, noise: jax.Array) -> tuple[Latent, Gaussian]:
        """Prior step; noise (..., S) standard normal gives the reparameterised sample."""
        deter = self.deter_step(prev, action)
        prior = self.prior_stats(deter)
        return Latent(deter, prior.mean + prior.std * noise), prior

    def obs_step(self, prev: Latent, action: jax.Array, embed: jax.Array, noise: jax.Array):
        """Posterior step -> (posterior latent, posterior stats, prior stats)."""
        deter = self.deter_step(prev, action)
        post = self.posterior_stats(deter, self.embed_projection(embed))
        return Latent(deter, post.mean + post.std * noise), post, self.prior_stats(deter)

    def __call__(self, prev: Latent, action: jax.Array, embed: jax.Array, noise: jax.Array):
        return self.obs_step(prev, action, embed, noise)


def zero_latent(deter: int, stoch: int, batch_shape: tuple[int, ...] = ()) -> Latent:
    return Latent(jnp.zeros((*batch_shape, deter)), jnp.zeros((*batch_shape, stoch)))


class TruncNormal(NamedTuple):
    """Normal(loc, scale) truncated to [-1, 1] (the DreamerV2/PEG `trunc_normal` actor distribution)."""

    loc: jax.Array
    scale: jax.Array

    def _bounds(self):
        alpha = (-1.0 - self.loc) / self.scale
        beta = (1.0 - self.loc) / self.scale
        return alpha, beta

    def sample(self, key: jax.Array) -> jax.Array:
        """Reparameterised inverse-CDF sample, clipped to [-1+1e-6, 1-1e-6] with a straight-through grad."""
        return self.sample_from_uniform(jax.random.uniform(key, self.loc.shape))

    def sample_from_uniform(self, unit: jax.Array) -> jax.Array:
        """The sample for `unit` ~ U[0, 1) of the batch shape (so one draw can serve several samplers)."""
        alpha, beta = self._bounds()
        # Inverse CDF by hand instead of jax.random.truncated_normal: when a bound is beyond ~5.5 std,
        # erf(bound) rounds to +-1 in float32, and a uniform draw of exactly 0 then gives u = -1,
        # erf_inv(u) = -inf; the output clip hides it in the forward pass, but the backward pass
        # computes 0 * inf = NaN (this NaN'd the exploration actor of a point_umaze run at ~6500 steps).
        # Keeping u strictly inside (-1, 1) keeps erf_inv and its derivative finite.
        a = jax.scipy.special.erf(alpha / SQRT2)
        b = jax.scipy.special.erf(beta / SQRT2)
        u = jnp.maximum(a, unit * (b - a) + a)  # what jax.random.uniform(minval=a, maxval=b) computes
        u = jnp.clip(u, -ERF_INV_LIMIT, ERF_INV_LIMIT)
        z = jnp.clip(SQRT2 * jax.scipy.special.erfinv(u), alpha, beta)
        x = self.loc + self.scale * z
        clipped = jnp.clip(x, -1.0 + 1e-6, 1.0 - 1e-6)
        return x + jax.lax.stop_gradient(clipped - x)

    def mode(self) -> jax.Array:
        return self.loc

    def entropy(self) -> jax.Array:
        """Entropy summed over action dimensions (closed form of the truncated normal)."""
        alpha, beta = self._bounds()
        mass = jax.scipy.special.ndtr(beta) - jax.scipy.special.ndtr(alpha)
        pdf = jax.scipy.stats.norm.pdf
        per_dim = (
            HALF_LOG_2PI_E + jnp.log(self.scale * mass) + (alpha * pdf(alpha) - beta * pdf(beta)) / (2 * mass)
        )
        return jnp.sum(per_dim, -1)


def actor_distribution(raw: jax.Array, min_std: float) -> TruncNormal:
    """Actor head output (..., 2A) -> TruncNormal(tanh(mean), 2*sigmoid(std/2) + min_std)."""
    mean, std = jnp.split(raw, 2, -1)
    return TruncNormal(jnp.tanh(mean), sigmoid2_std(std, min_std))


@flax.struct.dataclass
class NetState:
    """Parameters, optimiser state and (for critics) the target copy of one learner."""

    params: Any
    opt_state: Any
    target: Any = None


def make_optimizer(cfg: OptimizerConfig) -> optax.GradientTransformation:
    """DreamerV2's optimiser: global-norm clip, Adam(lr, eps), then decoupled decay p <- p - wd * p.

    The decay is multiplicative and not scaled by the learning rate, applied to every parameter (PEG).
    optax adds eps to the bias-corrected sqrt(v); TF's Adam, which PEG ran, adds it to the uncorrected one,
    so PEG's eps acts 1 / sqrt(1 - beta2^t) times larger early in training; the two converge as t grows.
    """
    return optax.chain(
        optax.clip_by_global_norm(cfg.clip),
        optax.adam(cfg.lr, eps=cfg.eps),
        optax.add_decayed_weights(-cfg.weight_decay),
    )


def init_net_state(params, optimizer: optax.GradientTransformation, with_target: bool = False) -> NetState:
    return NetState(params, optimizer.init(params), params if with_target else None)


def gradient_update(state: NetState, loss_fn, optimizer: optax.GradientTransformation):
    """The one update step every learner uses: loss -> gradients -> clip + optimiser step (make_optimizer).

    loss_fn(params) -> (loss, aux). Returns (new state, aux, pre-clip gradient norm)."""
    (_, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
    state, grad_norm = apply_gradients(state, grads, optimizer)
    return state, aux, grad_norm


def apply_gradients(state: NetState, grads, optimizer: optax.GradientTransformation) -> tuple[NetState, dict]:
    """One optimiser step; returns the new state and the pre-clip gradient norm."""
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    return state.replace(params=params, opt_state=opt_state), optax.global_norm(grads)
