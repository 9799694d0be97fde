"""TD(lambda) returns and the discount weights of imagined trajectories (DreamerV2 conventions).

Pure, time-major functions: the leading axis is time, any trailing axes broadcast (so one call handles
(T,) or (T, N)).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def lambda_return(
    reward: jax.Array, value: jax.Array, discount: jax.Array, bootstrap: jax.Array, lambda_: float
) -> jax.Array:
    """TD(lambda) targets (T, ...).

    target_t = reward_t + discount_t * ((1 - lambda) * value_{t+1} + lambda * target_{t+1}),
    with value_T = target_T = bootstrap. `value` (T, ...) holds value_t; only value_1.. are used.
    """
    next_value = jnp.concatenate([value[1:], bootstrap[None]], 0)
    inputs = reward + discount * next_value * (1.0 - lambda_)

    def backward(target_next, step):
        step_input, step_discount = step
        target = step_input + step_discount * lambda_ * target_next
        return target, target

    _, targets = jax.lax.scan(backward, bootstrap, (inputs, discount), reverse=True)
    return targets


def discount_weights(discount: jax.Array) -> jax.Array:
    """weight_t = prod_{k<t} discount_k (weight_0 = 1), the cumulative survival of imagined states."""
    shifted = jnp.concatenate([jnp.ones_like(discount[:1]), discount[:-1]], 0)
    return jnp.cumprod(shifted, 0)
