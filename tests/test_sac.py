"""The SAC learner of the model-free baselines (baselines/sac/learner.py) against hand-computed quantities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from morefree_jax.baselines.sac import learner as sac

CONFIG = sac.SACConfig(feature_dim=8, hidden_dim=16, batch_size=4)
OBS, ACT = 5, 2


def tiny_batch(not_done):
    key_obs, key_next, key_act = jax.random.split(jax.random.PRNGKey(7), 3)
    return sac.SACBatch(obs=jax.random.normal(key_obs, (4, OBS)),
                        next_obs=jax.random.normal(key_next, (4, OBS)),
                        action=jax.random.uniform(key_act, (4, ACT), minval=-1, maxval=1),
                        reward=jnp.array([0.0, 1.0, 0.0, 1.0]), not_done=jnp.asarray(not_done, jnp.float32))


def log_prob_by_hand(mean, log_std, key):
    """log pi of the squashed sample, from the change of variables written out in numpy."""
    noise = np.asarray(jax.random.normal(key, mean.shape))
    mean, std = np.asarray(mean, np.float64), np.exp(np.asarray(log_std, np.float64))
    u = mean + std * noise
    gaussian = -0.5 * ((u - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    return np.tanh(u), np.sum(gaussian - np.log(1 - np.tanh(u) ** 2), axis=-1)


def test_squashed_sample_log_prob_is_the_change_of_variables():
    mean, log_std, key = jnp.array([[0.3, -1.2]]), jnp.array([[-0.5, 0.2]]), jax.random.PRNGKey(3)
    action, log_pi = sac.squashed_sample(mean, log_std, key)
    expected_action, expected_log_pi = log_prob_by_hand(mean, log_std, key)
    np.testing.assert_allclose(action, expected_action, rtol=1e-5)
    np.testing.assert_allclose(log_pi, expected_log_pi, rtol=1e-4)


def test_critic_target_scales_the_reward_and_masks_the_bootstrap():
    state = sac.init(CONFIG, OBS, ACT, jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(11)
    batch = tiny_batch([1.0, 0.0, 1.0, 0.0])
    target = sac.critic_target(CONFIG, state, batch, key)
    mean, log_std = sac.policy(CONFIG, state.actor.params, batch.next_obs)
    next_action, next_log_pi = log_prob_by_hand(mean, log_std, key)
    q1, q2 = sac.q_values(CONFIG, state.critic.target, batch.next_obs, jnp.asarray(next_action, jnp.float32))
    soft = np.minimum(q1, q2) - 1.0 * next_log_pi  # initial alpha 1
    expected = 10.0 * np.asarray(batch.reward) + 0.99 * np.asarray(batch.not_done) * soft
    np.testing.assert_allclose(target, expected, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.asarray(target)[[1, 3]], [10.0, 10.0])  # done: 10 r, no bootstrap


def test_actor_and_temperature_losses():
    state = sac.init(CONFIG, OBS, ACT, jax.random.PRNGKey(0))
    batch, key, alpha = tiny_batch([1.0] * 4), jax.random.PRNGKey(5), 0.3
    loss, aux = sac.actor_loss(CONFIG, state.actor.params, state.critic.params, alpha, batch.obs, key)
    mean, log_std = sac.policy(CONFIG, state.actor.params, batch.obs)
    action, log_pi = log_prob_by_hand(mean, log_std, key)
    q1, q2 = sac.q_values(CONFIG, state.critic.params, batch.obs, jnp.asarray(action, jnp.float32))
    assert float(loss) == pytest.approx(np.mean(alpha * log_pi - np.minimum(q1, q2)), rel=1e-4)
    assert float(aux["entropy"]) == pytest.approx(-np.mean(log_pi), rel=1e-4)
    # Entropy below the target (log pi high) -> the gradient step raises alpha; above it -> lowers alpha.
    grad_low = jax.grad(lambda a: sac.alpha_loss(a, jnp.full(4, 3.0), -1.0)[0])(0.0)
    grad_high = jax.grad(lambda a: sac.alpha_loss(a, jnp.full(4, -3.0), -1.0)[0])(0.0)
    assert grad_low < 0 < grad_high
    assert sac.target_entropy(CONFIG, ACT) == -1.0


def test_log_std_is_clipped_and_actions_stay_in_range():
    state = sac.init(CONFIG, OBS, ACT, jax.random.PRNGKey(0))
    huge = jnp.full((3, OBS), 1e4)
    _, log_std = sac.policy(CONFIG, state.actor.params, huge)
    assert float(log_std.min()) >= -20.0 and float(log_std.max()) <= 2.0
    deterministic = sac.act(CONFIG, state.actor.params, huge, jax.random.PRNGKey(1), deterministic=True)
    mean, _ = sac.policy(CONFIG, state.actor.params, huge)
    np.testing.assert_allclose(deterministic, np.tanh(mean), rtol=1e-6)
    sampled = sac.act(CONFIG, state.actor.params, huge, jax.random.PRNGKey(1))
    assert float(jnp.abs(sampled).max()) <= 1.0


def test_update_polyak_averages_the_target_and_fits_a_fixed_batch():
    config = sac.SACConfig(feature_dim=8, hidden_dim=16, lr=1e-2)  # a larger step: fits in a few hundred
    state = sac.init(config, OBS, ACT, jax.random.PRNGKey(0))
    batch = tiny_batch([0.0] * 4)  # every step terminal: fixed targets 10 r, which the critic must fit
    step = jax.jit(lambda s, k: sac.update(config, s, batch, k))
    new, metrics = step(state, jax.random.PRNGKey(1))
    expected = jax.tree.map(lambda t, p: 0.995 * t + 0.005 * p, state.critic.target, new.critic.params)
    for got, want in zip(jax.tree.leaves(new.critic.target), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert int(new.updates) == 1 and all(np.isfinite(float(v)) for v in metrics.values())
    first = float(metrics["sac/critic_loss"])
    for i in range(300):
        new, metrics = step(new, jax.random.PRNGKey(i + 2))
    assert float(metrics["sac/critic_loss"]) < 0.05 * first


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="tau must be in"):
        sac.SACConfig(tau=1.5)
    with pytest.raises(ValueError, match="hidden_dim must be > 0"):
        sac.SACConfig(hidden_dim=0)
