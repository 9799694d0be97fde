"""Lambda-returns and discount weights against hand-computed values."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from morefree_jax.returns import discount_weights, lambda_return


def hand_lambda_return(reward, value, discount, bootstrap, lam):
    """Straightforward Python recursion written independently of the library."""
    targets = [0.0] * len(reward)
    nxt_target, nxt_value = bootstrap, bootstrap
    for t in reversed(range(len(reward))):
        nv = value[t + 1] if t + 1 < len(reward) else bootstrap
        targets[t] = reward[t] + discount[t] * ((1 - lam) * nv + lam * nxt_target)
        nxt_target = targets[t]
    del nxt_value
    return np.array(targets)


@pytest.mark.parametrize("jit", [False, True])
def test_lambda_return_three_steps_by_hand(jit):
    reward = jnp.array([1.0, 2.0, 3.0])
    # value = [10, 20, 30]: value_0 is never used by a lambda-return.
    discount = jnp.array([0.5, 0.5, 0.5])
    fn = jax.jit(lambda_return, static_argnums=3) if jit else lambda_return
    next_value = jnp.array([20.0, 30.0, 40.0])  # value[1:] then the bootstrap
    got = fn(reward, next_value, discount, 0.5)
    # t=2: 3 + 0.5*(0.5*40 + 0.5*40) = 23; t=1: 2 + 0.5*(0.5*30 + 0.5*23) = 15.25;
    # t=0: 1 + 0.5*(0.5*20 + 0.5*15.25) = 9.8125
    np.testing.assert_allclose(np.asarray(got), [9.8125, 15.25, 23.0], rtol=1e-6)


@pytest.mark.parametrize("lam", [0.0, 1.0, 0.95])
def test_lambda_return_limits_and_random(lam):
    rng = np.random.default_rng(0)
    reward, value = rng.normal(size=5), rng.normal(size=5)
    discount = np.full(5, 0.9)
    next_value = jnp.asarray(np.append(value[1:], 2.0))
    got = np.asarray(lambda_return(jnp.asarray(reward), next_value, jnp.asarray(discount), lam))
    np.testing.assert_allclose(got, hand_lambda_return(reward, value, discount, 2.0, lam), rtol=1e-5)
    if lam == 0.0:  # one-step TD targets
        np.testing.assert_allclose(got, reward + 0.9 * np.append(value[1:], 2.0), rtol=1e-5)
    if lam == 1.0:  # discounted Monte-Carlo with bootstrap
        mc = [sum(0.9**k * reward[t + k] for k in range(5 - t)) + 0.9 ** (5 - t) * 2.0 for t in range(5)]
        np.testing.assert_allclose(got, mc, rtol=1e-5)


def test_lambda_return_batched_trailing_axis():
    reward = jnp.arange(8.0).reshape(4, 2)
    value = jnp.ones((4, 2))
    discount = jnp.full((4, 2), 0.99)
    next_value = jnp.concatenate([value[1:], jnp.zeros((1, 2))])
    got = lambda_return(reward, next_value, discount, 0.95)
    for n in range(2):
        np.testing.assert_allclose(
            np.asarray(got[:, n]),
            hand_lambda_return(np.asarray(reward[:, n]), np.ones(4), np.full(4, 0.99), 0.0, 0.95), rtol=1e-5)


@pytest.mark.parametrize("jit", [False, True])
def test_discount_weights_by_hand(jit):
    fn = jax.jit(discount_weights) if jit else discount_weights
    got = fn(jnp.array([0.5, 0.9, 0.8, 0.7]))
    np.testing.assert_allclose(np.asarray(got), [1.0, 0.5, 0.45, 0.36], rtol=1e-6)
