"""TD(lambda) returns and the discount weights of imagined trajectories (DreamerV2 conventions).

Pure, time-major functions: the leading axis is time, any trailing axes broadcast (so one call handles
(T,) or (T, N)).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def lambda_return(reward: jax.Array, next_value: jax.Array, discount: jax.Array, lambda_: float) -> jax.Array:
    """TD(lambda) targets (T, ...), rlax style (`next_value[t]` is the value of the state after step t).

    target_t = reward_t + discount_t * ((1 - lambda) * next_value_t + lambda * target_{t+1}),
    bootstrapped with target_T = next_value_{T-1}. DreamerV2's call on an imagined sequence of H+1 states
    is lambda_return(reward[:-1], value[1:], discount[:-1], lambda_).
    """
    inputs = reward + discount * next_value * (1.0 - lambda_)

    def backward(target_next, step):
        step_input, step_discount = step
        target = step_input + step_discount * lambda_ * target_next
        return target, target

    _, targets = jax.lax.scan(backward, next_value[-1], (inputs, discount), reverse=True)
    return targets


def discount_weights(discount: jax.Array) -> jax.Array:
    """weight_t = prod_{k<t} discount_k (weight_0 = 1), the cumulative survival of imagined states."""
    shifted = jnp.concatenate([jnp.ones_like(discount[:1]), discount[:-1]], 0)
    return jnp.cumprod(shifted, 0)
