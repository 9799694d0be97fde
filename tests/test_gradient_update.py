"""networks.gradient_update: the one update step of every learner (loss -> grads -> clip -> Adam -> decay)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.learner_config import OptimizerConfig
from morefree_jax.networks import gradient_update, init_net_state, make_optimizer


def test_one_step_matches_the_hand_computed_adam_step_with_clipping_and_decay():
    config = OptimizerConfig(lr=0.1, eps=1e-5, clip=1.0, weight_decay=0.01)
    optimizer = make_optimizer(config)
    params = {"w": jnp.array([3.0, -4.0])}
    state = init_net_state(params, optimizer)

    def loss_fn(p):  # gradient 2 w = (6, -8): norm 10, clipped to norm 1 -> (0.6, -0.8)
        loss = jnp.sum(jnp.square(p["w"]))
        return loss, {"loss": loss}

    new_state, aux, grad_norm = gradient_update(state, loss_fn, optimizer)
    assert float(grad_norm) == 10.0 and float(aux["loss"]) == 25.0  # the norm is taken before clipping
    # Adam's first step moves each entry by lr * g / (|g| + eps) = 0.1 * sign(g); then p <- p - 0.01 p
    # (decoupled, multiplicative, not scaled by lr: DreamerV2's optimiser), applied to the moved params.
    clipped = np.array([0.6, -0.8])
    moved = np.array([3.0, -4.0]) - 0.1 * clipped / (np.abs(clipped) + 1e-5)
    expected = moved - 0.01 * np.array([3.0, -4.0])
    np.testing.assert_allclose(np.asarray(new_state.params["w"]), expected, rtol=1e-5)
    assert jax.tree.structure(new_state.opt_state) == jax.tree.structure(state.opt_state)
