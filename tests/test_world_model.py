"""World model learns a fixed batch of task data: 200 updates lower the reconstruction loss >= 5x."""

import functools

import jax
import numpy as np

from morefree_jax.learner_config import preset
from morefree_jax.networks import init_net_state, make_optimizer
from morefree_jax.world_model import init_world_model, make_world_model, world_model_update
from tests.core_helpers import fixed_batch


def test_world_model_fits_fixed_batch_of_task_data():
    cfg = preset("debug")
    batch = fixed_batch(cfg.replay.batch, cfg.replay.length)
    obs_size, act_size = batch.obs.shape[-1], batch.action.shape[-1]
    wm = make_world_model(cfg.wm, obs_size)
    optimizer = make_optimizer(cfg.wm.opt)
    state = init_net_state(init_world_model(wm, jax.random.PRNGKey(0), obs_size, act_size), optimizer)
    update = functools.partial(world_model_update, wm, optimizer)

    @jax.jit
    def train(state, key):
        def body(state, key):
            state, _, metrics = update(state, batch, key)
            return state, metrics

        return jax.lax.scan(body, state, jax.random.split(key, 200))

    _, metrics = train(state, jax.random.PRNGKey(1))
    recon = np.asarray(metrics["wm/recon_loss"])
    for name, values in metrics.items():
        assert np.all(np.isfinite(np.asarray(values))), name
    first, last = recon[0], recon[-5:].mean()
    print("recon", first, "->", last)
    assert last * 5 <= first, (first, last)
    assert np.asarray(metrics["wm/embed_loss"])[-5:].mean() < np.asarray(metrics["wm/embed_loss"])[0]
