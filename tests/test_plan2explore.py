"""Plan2Explore disagreement: 0 when all members share parameters, > 0 otherwise; the ensemble learns."""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.learner_config import ExploreConfig, OptimizerConfig
from morefree_jax.networks import Latent
from morefree_jax.plan2explore import (
    disagreement,
    ensemble_predict,
    ensemble_update,
    init_ensemble,
    make_ensemble,
)

F, A, S = 10, 2, 4


def test_disagreement_zero_iff_members_share_parameters():
    ens = make_ensemble(ExploreConfig(members=4, layers=(16, 16)), S)
    state = init_ensemble(ens, jax.random.PRNGKey(0), F + A)
    feat = jax.random.normal(jax.random.PRNGKey(1), (7, 3, F))
    action = jax.random.uniform(jax.random.PRNGKey(2), (7, 3, A))
    shared = jax.tree.map(lambda x: jnp.broadcast_to(x[:1], x.shape), state.params)
    np.testing.assert_allclose(np.asarray(disagreement(ens, shared, feat, action)), 0.0, atol=1e-6)
    distinct = disagreement(ens, state.params, feat, action)
    assert distinct.shape == (7, 3) and float(jnp.min(distinct)) > 1e-3
    inputs = jnp.concatenate([feat, action], -1)
    member_by_member = jax.vmap(ens.member.apply, in_axes=(0, None))(state.params, inputs)
    np.testing.assert_allclose(np.asarray(ensemble_predict(ens, state.params, inputs)),
                               np.asarray(member_by_member), atol=1e-5)


def test_ensemble_update_lowers_loss_and_keeps_members_distinct():
    ens = make_ensemble(ExploreConfig(members=3, layers=(32,), opt=OptimizerConfig(lr=3e-3)), S)
    state = init_ensemble(ens, jax.random.PRNGKey(0), F + A)
    key_d, key_s, key_a = jax.random.split(jax.random.PRNGKey(3), 3)
    latent = Latent(jax.random.normal(key_d, (6, 5, F - S)), jax.random.normal(key_s, (6, 5, S)))
    action = jax.random.uniform(key_a, (6, 5, A))

    @jax.jit
    def train(state):
        return jax.lax.scan(lambda s, _: ensemble_update(ens, s, latent, action), state, None, length=100)

    state, metrics = train(state)
    losses = np.asarray(metrics["explore/ensemble_loss"])
    assert losses[-1] < 0.5 * losses[0]
    feat = jnp.concatenate([latent.stoch, latent.deter], -1)
    assert float(jnp.min(disagreement(ens, state.params, feat, action))) > 0.0
