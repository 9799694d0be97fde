"""Network building blocks: the ELU with the output-reusing derivative."""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.networks import elu


def test_elu_matches_jax_elu_in_value_and_gradient():
    x = jnp.concatenate([jnp.linspace(-20.0, 5.0, 1001), jnp.array([0.0, -1e-7, 1e-7, -88.0])])
    np.testing.assert_allclose(np.asarray(elu(x)), np.asarray(jax.nn.elu(x)), rtol=1e-6, atol=1e-7)
    ours = jax.vmap(jax.grad(elu))(x)
    reference = jax.vmap(jax.grad(jax.nn.elu))(x)
    np.testing.assert_allclose(np.asarray(ours), np.asarray(reference), rtol=1e-5, atol=1e-7)
    # Second derivative (used by nothing here, but jvp-of-jvp must still be right): exp(x) below 0.
    second = jax.vmap(jax.grad(jax.grad(elu)))(jnp.array([-1.0, -0.5, 2.0]))
    np.testing.assert_allclose(np.asarray(second), [np.exp(-1.0), np.exp(-0.5), 0.0], rtol=1e-5)
