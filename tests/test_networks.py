"""Network building blocks: the ELU with the output-reusing derivative, the Glorot-uniform initial kernels."""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.actor_critic import init_actor_critic, make_actor_critic
from morefree_jax.distance import init_distance, make_distance
from morefree_jax.learner_config import ActorCriticConfig, DistanceConfig
from morefree_jax.networks import MLP, RSSM, Latent, elu, glorot_uniform


def test_elu_matches_jax_elu_in_value_and_gradient():
    x = jnp.concatenate([jnp.linspace(-20.0, 5.0, 1001), jnp.array([0.0, -1e-7, 1e-7, -88.0])])
    np.testing.assert_allclose(np.asarray(elu(x)), np.asarray(jax.nn.elu(x)), rtol=1e-6, atol=1e-7)
    ours = jax.vmap(jax.grad(elu))(x)
    reference = jax.vmap(jax.grad(jax.nn.elu))(x)
    np.testing.assert_allclose(np.asarray(ours), np.asarray(reference), rtol=1e-5, atol=1e-7)
    # Second derivative (used by nothing here, but jvp-of-jvp must still be right): exp(x) below 0.
    second = jax.vmap(jax.grad(jax.grad(elu)))(jnp.array([-1.0, -0.5, 2.0]))
    np.testing.assert_allclose(np.asarray(second), [np.exp(-1.0), np.exp(-0.5), 0.0], rtol=1e-5)


def assert_glorot(kernel, fan_in, fan_out):
    """Uniform on +-sqrt(6 / (fan_in + fan_out)): nothing beyond the limit, the extremes near it (a kernel of
    >= 1,000 entries all below 0.95 of it has probability < 1e-22), and the uniform's std."""
    kernel = np.asarray(kernel)
    limit = np.sqrt(6.0 / (fan_in + fan_out))
    assert kernel.size >= 1000
    assert np.abs(kernel).max() <= limit
    assert np.abs(kernel).max() >= 0.95 * limit
    np.testing.assert_allclose(kernel.std(), limit / np.sqrt(3.0), rtol=0.1)


def test_mlp_kernels_are_glorot_uniform_and_biases_zero():
    params = MLP((128, 128), out=8).init(jax.random.PRNGKey(0), jnp.zeros((1, 8)))["params"]
    assert_glorot(params["Dense_0"]["kernel"], 8, 128)
    assert_glorot(params["Dense_1"]["kernel"], 128, 128)
    assert_glorot(params["Dense_2"]["kernel"], 128, 8)
    assert all(not np.any(np.asarray(layer["bias"])) for layer in params.values())


def test_split_first_layers_keep_the_limit_of_the_concatenated_layer():
    config = ActorCriticConfig(actor_layers=(64, 64), critic_layers=(64, 64))
    actor_critic = make_actor_critic(config, 2, use_context=True)
    actor, critic = init_actor_critic(actor_critic, jax.random.PRNGKey(1), feat_size=160, context_size=96)
    for params in (actor.params["params"], critic.params["params"]):
        assert_glorot(params["first"]["kernel"], 160 + 96, 64)
        assert_glorot(params["context"]["kernel"], 160 + 96, 64)
    # the actor's mean and std come from one (H, 2A) layer standing for PEG's two (H, A) layers
    assert actor_critic.actor.head_fan_out == 2 and actor_critic.critic.head_fan_out is None
    assert_glorot(glorot_uniform(fan_out=2)(jax.random.PRNGKey(4), (400, 4)), 400, 2)
    distance = init_distance(make_distance(DistanceConfig(layers=(64, 64))), jax.random.PRNGKey(2), 96)
    assert_glorot(distance.params["params"]["first"]["kernel"], 2 * 96, 64)
    rssm = RSSM(deter=64, hidden=32, stoch=16, embed_size=96)
    prev = Latent(jnp.zeros((1, 64)), jnp.zeros((1, 16)))
    rssm_params = rssm.init(jax.random.PRNGKey(3), prev, jnp.zeros((1, 2)), jnp.zeros((1, 96)),
                            jnp.zeros((1, 16)))["params"]
    assert_glorot(rssm_params["obs_deter"]["kernel"], 64 + 96, 32)
    assert_glorot(rssm_params["obs_embed"]["kernel"], 64 + 96, 32)


def test_the_entropy_constant_is_the_float32_one_jax_computes():
    # a Python float since it must not start JAX at import; in float32 it is jnp's value, bit for bit
    from morefree_jax.networks import HALF_LOG_2PI_E

    assert np.float32(HALF_LOG_2PI_E) == 0.5 * jnp.log(2.0 * jnp.pi * jnp.e)
