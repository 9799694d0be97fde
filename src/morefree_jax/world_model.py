"""The world model: encoder, RSSM, decoder and embed head; observe, loss and update (PEG, state input).

Loss = KL-balanced posterior/prior KL (balance 0.8, free nats after averaging) + decoder NLL (Normal(., 1),
constant dropped) + embed-head NLL. The embed head learns to predict the (stop-gradient) encoder output from
stop-gradient features; it embeds imagined states for the goal reward, the encoder embeds goals.

`observe` runs only the recurrent part (deter step + posterior) inside `lax.scan`; the embedding's share of
the posterior layer and the prior statistics are computed batched over all B*T steps outside the scan.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from morefree_jax.learner_config import WorldModelConfig
from morefree_jax.networks import (
    MLP,
    RSSM,
    Gaussian,
    Latent,
    NetState,
    feature,
    gaussian_kl,
    gradient_update,
    zero_latent,
)


class Batch(NamedTuple):
    """A replay batch, batch-major: obs (B, T, O), action (B, T, A) (led to obs), is_first (B, T)."""

    obs: jax.Array
    action: jax.Array
    is_first: jax.Array


class Posterior(NamedTuple):
    """What the world-model update hands to the other learners, time-major (T, B, ...)."""

    latent: Latent
    embed: jax.Array  # encoder output of the batch observations (T, B, E)


class WorldModel(NamedTuple):
    """The world model's modules; params is a dict with the same keys."""

    encoder: MLP
    rssm: RSSM
    decoder: MLP
    embed_head: MLP
    config: WorldModelConfig

    @property
    def embed_size(self) -> int:
        return self.config.encoder_layers[-1]

    def feat_size(self) -> int:
        return self.config.deter + self.config.stoch


def make_world_model(cfg: WorldModelConfig, obs_size: int, precision: str = "f32") -> WorldModel:
    return WorldModel(
        encoder=MLP(cfg.encoder_layers, precision=precision),
        rssm=RSSM(cfg.deter, cfg.hidden, cfg.stoch, cfg.min_std, cfg.encoder_layers[-1], cfg.gru_bias,
                  precision),
        decoder=MLP(cfg.decoder_layers, out=obs_size, precision=precision),
        embed_head=MLP(cfg.embed_head_layers, out=cfg.encoder_layers[-1], precision=precision),
        config=cfg,
    )


def init_world_model(wm: WorldModel, key: jax.Array, obs_size: int, action_size: int) -> dict:
    key_enc, key_rssm, key_dec, key_head = jax.random.split(key, 4)
    cfg = wm.config
    embed = jnp.zeros((1, wm.embed_size))
    feat = jnp.zeros((1, cfg.deter + cfg.stoch))
    prev = zero_latent(cfg.deter, cfg.stoch, (1,))
    return {
        "encoder": wm.encoder.init(key_enc, jnp.zeros((1, obs_size))),
        "rssm": wm.rssm.init(key_rssm, prev, jnp.zeros((1, action_size)), embed, jnp.zeros((1, cfg.stoch))),
        "decoder": wm.decoder.init(key_dec, feat),
        "embed_head": wm.embed_head.init(key_head, feat),
    }


def encode(wm: WorldModel, params: dict, obs: jax.Array) -> jax.Array:
    return wm.encoder.apply(params["encoder"], obs)


def observe(wm: WorldModel, params: dict, embed, action, is_first, key) -> tuple[Latent, Gaussian, Gaussian]:
    """Filters a time-major sequence: embed (T, B, E), action (T, B, A), is_first (T, B).

    Where is_first, the previous state and action are zeroed. Returns posterior latents, posterior and
    prior statistics, all (T, B, ...).
    """
    rssm, p, cfg = wm.rssm, params["rssm"], wm.config
    projection = rssm.apply(p, embed, method=RSSM.embed_projection)
    noise = jax.random.normal(key, (*embed.shape[:-1], cfg.stoch))

    def step(prev: Latent, inputs):
        action_t, is_first_t, projection_t, noise_t = inputs
        keep = 1.0 - is_first_t.astype(action_t.dtype)[..., None]
        prev = Latent(prev.deter * keep, prev.stoch * keep)
        deter = rssm.apply(p, prev, action_t * keep, method=RSSM.deter_step)
        post = rssm.apply(p, deter, projection_t, method=RSSM.posterior_stats)
        latent = Latent(deter, post.mean + post.std * noise_t)
        return latent, (latent, post)

    start = zero_latent(cfg.deter, cfg.stoch, embed.shape[1:-1])
    _, (latents, post) = jax.lax.scan(step, start, (action, is_first, projection, noise),
                                      unroll=min(cfg.unroll, embed.shape[0]))
    prior = rssm.apply(p, latents.deter, method=RSSM.prior_stats)
    return latents, post, prior


def kl_balance_loss(post: Gaussian, prior: Gaussian, balance: float, free: float):
    """0.2 * max(mean KL(post || sg prior), free) + 0.8 * max(mean KL(sg post || prior), free)."""
    sg = jax.lax.stop_gradient
    kl_post = jnp.mean(gaussian_kl(post, Gaussian(sg(prior.mean), sg(prior.std))))
    kl_prior = jnp.mean(gaussian_kl(Gaussian(sg(post.mean), sg(post.std)), prior))
    loss = (1.0 - balance) * jnp.maximum(kl_post, free) + balance * jnp.maximum(kl_prior, free)
    return loss, kl_prior


def world_model_loss(wm: WorldModel, params: dict, batch: Batch, key: jax.Array):
    """-> (loss, (Posterior, metrics)). All terms are means over B and T."""
    sg = jax.lax.stop_gradient
    cfg = wm.config
    obs = jnp.swapaxes(batch.obs, 0, 1)
    embed = encode(wm, params, obs)
    latents, post, prior = observe(
        wm, params, embed, jnp.swapaxes(batch.action, 0, 1), jnp.swapaxes(batch.is_first, 0, 1), key
    )
    feat = feature(latents)
    recon = wm.decoder.apply(params["decoder"], feat)
    recon_loss = jnp.mean(0.5 * jnp.sum(jnp.square(recon - obs), -1))
    embed_pred = wm.embed_head.apply(params["embed_head"], sg(feat))
    embed_loss = jnp.mean(0.5 * jnp.sum(jnp.square(embed_pred - sg(embed)), -1))
    kl_loss, kl = kl_balance_loss(post, prior, cfg.kl_balance, cfg.kl_free)
    loss = cfg.kl_scale * kl_loss + recon_loss + embed_loss
    metrics = {
        "wm/loss": loss, "wm/recon_loss": recon_loss, "wm/embed_loss": embed_loss, "wm/kl": kl,
        "wm/prior_std": jnp.mean(prior.std), "wm/post_std": jnp.mean(post.std),
    }
    return loss, (Posterior(sg(latents), sg(embed)), metrics)


def world_model_update(wm: WorldModel, optimizer: optax.GradientTransformation, state: NetState,
                       batch: Batch, key: jax.Array) -> tuple[NetState, Posterior, dict]:
    """One gradient step of the world model -> (state, posterior of the batch, metrics)."""
    state, (posterior, metrics), grad_norm = gradient_update(
        state, lambda p: world_model_loss(wm, p, batch, key), optimizer)
    return state, posterior, {**metrics, "wm/grad_norm": grad_norm}
