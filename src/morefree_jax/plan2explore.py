"""Plan2Explore: an ensemble of K one-step predictors of the next stochastic latent and its disagreement.

Members are one MLP with stacked parameters (leading axis K), initialised and applied with `jax.vmap`,
so the ensemble is a single batched computation. Input concat(feat_t, action_t) (action_t led to state t,
DreamerV2 convention) predicts stoch_{t+1} of the posterior (disag_offset 1); loss = sum over members of
the mean Normal(., 1) NLL (constant dropped); inputs and targets are stop-gradient. The intrinsic reward is
the std over members of the predicted means, averaged over the stoch dimensions.

The paper's appendix describes Plan2Explore as published: the variance over members of f(s_t), without the
action. The std and the action input are PEG's code (docs/learner.md, "Plan2Explore"), which the paper says
MoReFree extends with every other hyperparameter kept; where its prose summarises earlier methods we follow
the code it ran, and docs/fidelity.md, "Learner and schedule", says so.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from morefree_jax.learner_config import ExploreConfig
from morefree_jax.networks import (
    MLP,
    Latent,
    NetState,
    elu,
    feature,
    gradient_update,
    init_net_state,
    make_optimizer,
)
from morefree_jax.precision import matmul


class Ensemble(NamedTuple):
    member: MLP
    config: ExploreConfig
    optimizer: optax.GradientTransformation
    precision: str = "f32"  # of ensemble_predict's matmuls (precision.py)


def make_ensemble(cfg: ExploreConfig, stoch_size: int, precision: str = "f32") -> Ensemble:
    return Ensemble(MLP(cfg.layers, out=stoch_size, precision=precision), cfg, make_optimizer(cfg.opt),
                    precision)


def init_ensemble(ens: Ensemble, key: jax.Array, input_size: int) -> NetState:
    keys = jax.random.split(key, ens.config.members)
    params = jax.vmap(lambda k: ens.member.init(k, jnp.zeros((1, input_size))))(keys)
    return init_net_state(params, ens.optimizer)


def ensemble_predict(ens: Ensemble, params, inputs: jax.Array) -> jax.Array:
    """Predicted next stoch of every member: inputs (..., F + A) -> (K, ..., S).

    All members read the same input, so their first layers run as one matmul against the concatenated
    kernels (in, K * h); the remaining layers are vmapped over members. XLA on CPU runs a vmapped matmul
    with a shared input (batch dimension on one side only) far slower than either form
    (docs/performance.md, "What the runtime settings gain").
    """
    layers = [params["params"][f"Dense_{i}"] for i in range(len(ens.config.layers) + 1)]
    members, in_size, width = layers[0]["kernel"].shape
    flat = inputs.reshape(-1, in_size)
    kernel = jnp.transpose(layers[0]["kernel"], (1, 0, 2)).reshape(in_size, members * width)
    h = elu(matmul(flat, kernel, ens.precision) + layers[0]["bias"].reshape(-1))
    h = jnp.transpose(h.reshape(-1, members, width), (1, 0, 2))  # (K, M, h)

    def rest(member_layers, h):
        for i, layer in enumerate(member_layers):
            h = matmul(h, layer["kernel"], ens.precision) + layer["bias"]
            if i < len(member_layers) - 1:
                h = elu(h)
        return h

    out = jax.vmap(rest)(layers[1:], h)
    return out.reshape(members, *inputs.shape[:-1], out.shape[-1])


def disagreement(ens: Ensemble, params, feat: jax.Array, action: jax.Array) -> jax.Array:
    """Intrinsic reward (...,): std over members of the predictions, mean over stoch dimensions."""
    preds = ensemble_predict(ens, params, jnp.concatenate([feat, action], -1))
    return jnp.mean(jnp.std(preds, 0), -1)


def ensemble_loss(ens: Ensemble, params, latent: Latent, action: jax.Array):
    """latent (T, B, ...) posterior of the batch, action (T, B, A); inputs[:-1] predict stoch[1:]."""
    sg = jax.lax.stop_gradient
    inputs = sg(jnp.concatenate([feature(latent), action], -1))[:-1]
    target = sg(latent.stoch)[1:]
    preds = ensemble_predict(ens, params, inputs)
    per_member = jnp.mean(0.5 * jnp.sum(jnp.square(preds - target[None]), -1), axis=(1, 2))
    loss = jnp.sum(per_member)
    return loss, {"explore/ensemble_loss": loss}


def ensemble_update(ens: Ensemble, state: NetState, latent: Latent, action: jax.Array):
    state, metrics, grad_norm = gradient_update(state, lambda p: ensemble_loss(ens, p, latent, action),
                                                ens.optimizer)
    return state, {**metrics, "explore/ensemble_grad_norm": grad_norm}
