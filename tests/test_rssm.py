"""RSSM cell and observe: shapes, is_first resets, KL facts, the GRU bias."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.learner_config import preset
from morefree_jax.networks import RSSM, Gaussian, Latent, gaussian_kl
from morefree_jax.world_model import init_world_model, kl_balance_loss, make_world_model, observe

OBS, ACT, T, B = 4, 2, 6, 3


@functools.cache
def model():
    wm = make_world_model(preset("debug").wm, OBS)
    return wm, init_world_model(wm, jax.random.PRNGKey(0), OBS, ACT)


@functools.cache
def jitted_observe():
    wm, _ = model()
    return jax.jit(functools.partial(observe, wm))


def test_observe_shapes():
    wm, params = model()
    cfg = wm.config
    embed = jnp.ones((T, B, wm.embed_size))
    latents, post, prior = jitted_observe()(params, embed, jnp.ones((T, B, ACT)), jnp.zeros((T, B), bool),
                                            jax.random.PRNGKey(1))
    assert latents.deter.shape == (T, B, cfg.deter) and latents.stoch.shape == (T, B, cfg.stoch)
    assert post.mean.shape == post.std.shape == prior.std.shape == (T, B, cfg.stoch)
    assert float(jnp.min(post.std)) >= cfg.min_std and float(jnp.min(prior.std)) >= cfg.min_std


def test_posterior_ignores_previous_state_where_is_first():
    wm, params = model()
    key_a, key_b, key_e = jax.random.split(jax.random.PRNGKey(2), 3)
    embed = jax.random.normal(key_e, (T, B, wm.embed_size))
    actions_a = jax.random.uniform(key_a, (T, B, ACT), minval=-1, maxval=1)
    # Same inputs from t=3 on, different history before; is_first at t=3 must erase the difference.
    actions_b = actions_a.at[:3].set(jax.random.uniform(key_b, (3, B, ACT), minval=-1, maxval=1))
    embed_b = embed.at[:3].set(-embed[:3])
    is_first = jnp.zeros((T, B), bool).at[0].set(True).at[3].set(True)
    key = jax.random.PRNGKey(3)
    lat_a, post_a, _ = jitted_observe()(params, embed, actions_a, is_first, key)
    lat_b, post_b, _ = jitted_observe()(params, embed_b, actions_b, is_first, key)
    assert float(jnp.max(jnp.abs(lat_a.deter[:3] - lat_b.deter[:3]))) > 1e-3  # history matters before
    np.testing.assert_allclose(np.asarray(lat_a.deter[3:]), np.asarray(lat_b.deter[3:]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(post_a.mean[3:]), np.asarray(post_b.mean[3:]), atol=1e-6)
    # Without the reset the history leaks into t=3.
    lat_c, _, _ = jitted_observe()(params, embed_b, actions_b, is_first.at[3].set(False), key)
    assert float(jnp.max(jnp.abs(lat_a.deter[3] - lat_c.deter[3]))) > 1e-3


def test_kl_zero_for_identical_distributions_and_positive_otherwise():
    wm, params = model()
    deter = jax.random.normal(jax.random.PRNGKey(4), (5, wm.config.deter))
    stats_a = wm.rssm.apply(params["rssm"], deter, method=RSSM.prior_stats)
    stats_b = wm.rssm.apply(params["rssm"], deter, method=RSSM.prior_stats)
    np.testing.assert_allclose(np.asarray(gaussian_kl(stats_a, stats_b)), 0.0, atol=1e-6)
    loss, kl = kl_balance_loss(stats_a, stats_b, balance=0.8, free=0.0)
    assert abs(float(loss)) < 1e-6 and abs(float(kl)) < 1e-6
    # Closed form in 1-D: KL(N(0,1) || N(1,2)) = log 2 + (1 + 1) / 8 - 0.5.
    one_d = gaussian_kl(Gaussian(jnp.zeros(1), jnp.ones(1)), Gaussian(jnp.ones(1), 2 * jnp.ones(1)))
    np.testing.assert_allclose(float(one_d), np.log(2) + 2 / 8 - 0.5, rtol=1e-5)
    # Free nats clamp the loss after averaging.
    loss_free, _ = kl_balance_loss(stats_a, stats_b, balance=0.8, free=1.0)
    np.testing.assert_allclose(float(loss_free), 1.0, rtol=1e-6)


def test_img_step_matches_obs_step_deter():
    wm, params = model()
    prev = Latent(jnp.ones((2, wm.config.deter)), jnp.ones((2, wm.config.stoch)))
    action, noise = jnp.zeros((2, ACT)), jnp.zeros((2, wm.config.stoch))
    prior_latent, prior = wm.rssm.apply(params["rssm"], prev, action, noise, method=RSSM.img_step)
    post_latent, _, prior2 = wm.rssm.apply(params["rssm"], prev, action, jnp.zeros((2, wm.embed_size)), noise)
    np.testing.assert_allclose(np.asarray(prior_latent.deter), np.asarray(post_latent.deter), atol=1e-6)
    np.testing.assert_allclose(np.asarray(prior_latent.stoch), np.asarray(prior.mean), atol=1e-6)
    np.testing.assert_allclose(np.asarray(prior.std), np.asarray(prior2.std), atol=1e-6)


def test_the_gru_input_layer_has_dreamers_bias_unless_turned_off():
    _, params = model()
    assert params["rssm"]["params"]["gru"]["Dense_0"]["bias"].shape == (3 * preset("debug").wm.deter,)
    no_bias = make_world_model(dataclasses.replace(preset("debug").wm, gru_bias=False), OBS)
    no_bias_params = init_world_model(no_bias, jax.random.PRNGKey(0), OBS, ACT)["rssm"]["params"]
    assert "bias" not in no_bias_params["gru"]["Dense_0"]
