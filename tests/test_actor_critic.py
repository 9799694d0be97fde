"""The goal-conditioned actor-critic learns to reach random goals in a toy differentiable "world model".

The toy model is a linear point mass: deter = position (2,), pos' = pos + 0.2 * action; the reward is
-||pos - goal||. It plugs into the library's imagination through the same `apply(..., method=)` call as
the RSSM, so the real actor loss, dynamics gradients, lambda-returns and critic run unchanged.
"""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax.actor_critic import actor_critic_update, imagine_with, init_actor_critic, make_actor_critic
from morefree_jax.config import ActorCriticConfig, OptimizerConfig
from morefree_jax.networks import Latent

N, HORIZON = 256, 10


class LinearPointMass:
    def apply(self, params, latent, action, noise, method=None):
        return Latent(latent.deter + 0.2 * action, latent.stoch), None


def starts_and_goals(key):
    key_s, key_g = jax.random.split(key)
    start = Latent(jax.random.uniform(key_s, (N, 2), minval=-1, maxval=1), jnp.zeros((N, 1)))
    return start, jax.random.uniform(key_g, (N, 2), minval=-1, maxval=1)


def test_goal_conditioned_actor_reduces_distance_to_random_goals():
    opt = OptimizerConfig(lr=1e-3)
    cfg = ActorCriticConfig(actor_layers=(64, 64), critic_layers=(64, 64), horizon=HORIZON, entropy=1e-4,
                            target_every=10, actor_opt=opt, critic_opt=opt)
    ac = make_actor_critic(cfg, 2, use_context=True)
    model = LinearPointMass()
    actor, critic = init_actor_critic(ac, jax.random.PRNGKey(0), 3, 2)

    def final_distance(actor_params, key):
        start, goal = starts_and_goals(key)
        traj = imagine_with(ac, actor_params, model, None, start, goal, jax.random.PRNGKey(7))
        return jnp.mean(jnp.linalg.norm(traj.latent.deter[-1] - goal, axis=-1))

    @jax.jit
    def train(actor, critic, key):
        def body(carry, inputs):
            actor, critic = carry
            step, key = inputs
            key_data, key_update = jax.random.split(key)
            start, goal = starts_and_goals(key_data)

            def reward_fn(traj):
                return -jnp.linalg.norm(traj.latent.deter[:-1] - goal[None], axis=-1), None

            actor, critic, _, metrics = actor_critic_update(ac, actor, critic, step, model, None, reward_fn,
                                                            start, goal, key_update, "gc")
            return (actor, critic), metrics

        steps = jnp.arange(300)
        return jax.lax.scan(body, (actor, critic), (steps, jax.random.split(key, 300)))

    before = float(final_distance(actor.params, jax.random.PRNGKey(5)))
    (actor, critic), metrics = train(actor, critic, jax.random.PRNGKey(1))
    after = float(final_distance(actor.params, jax.random.PRNGKey(5)))
    for name, values in metrics.items():
        assert np.all(np.isfinite(np.asarray(values))), name
    print("final distance", before, "->", after)
    assert after < 0.5 * before, (before, after)
    assert np.asarray(metrics["gc/reward"])[-10:].mean() > np.asarray(metrics["gc/reward"])[:10].mean()


def test_trunc_normal_entropy_and_reparameterised_sample():
    from scipy import stats

    from morefree_jax.networks import TruncNormal

    loc, scale = np.array([0.3, -0.9, 0.0]), np.array([0.4, 0.2, 2.1])
    dist = TruncNormal(jnp.asarray(loc), jnp.asarray(scale))
    expected = sum(stats.truncnorm((-1 - m) / s, (1 - m) / s, loc=m, scale=s).entropy()
                   for m, s in zip(loc, scale, strict=True))
    np.testing.assert_allclose(float(dist.entropy()), expected, rtol=1e-4)

    def mean_sample(shift):
        dist = TruncNormal(jnp.full(20_000, shift), jnp.full(20_000, 0.3))
        return jnp.mean(dist.sample(jax.random.PRNGKey(0)))

    assert 0.9 < float(jax.grad(mean_sample)(0.0)) < 1.1  # d E[x] / d loc ~ 1 away from the bounds
    samples = TruncNormal(jnp.full(20_000, 0.9), jnp.full(20_000, 0.5)).sample(jax.random.PRNGKey(1))
    assert float(samples.max()) < 1.0 and float(samples.min()) > -1.0


def test_trunc_normal_sample_gradient_finite_when_uniform_draw_hits_a_saturated_bound(monkeypatch):
    """loc 0.5, scale 0.1: the lower bound is 15 std away, erf rounds it to -1 in float32; a uniform draw
    of exactly 0 used to give erf_inv(-1) = -inf and a NaN actor gradient (point_umaze run at ~6500 steps)."""
    from morefree_jax.networks import TruncNormal

    lowest_draw = lambda key, shape, minval, maxval: jnp.broadcast_to(minval, shape)  # noqa: E731
    monkeypatch.setattr(jax.random, "uniform", lowest_draw)

    def sample_sum(loc, scale):
        return jnp.sum(TruncNormal(loc, scale).sample(jax.random.PRNGKey(0)))

    loc, scale = jnp.array([0.5, -0.3]), jnp.array([0.1, 0.1])
    value = sample_sum(loc, scale)
    grads = jax.grad(sample_sum, argnums=(0, 1))(loc, scale)
    assert np.isfinite(float(value))
    assert np.all(np.isfinite(np.asarray(grads[0]))) and np.all(np.isfinite(np.asarray(grads[1])))
    # The lowest draw lands ~5.42 std below loc (the float32 limit of erf_inv; both bounds are further).
    np.testing.assert_allclose(np.asarray(TruncNormal(loc, scale).sample(jax.random.PRNGKey(0))),
                               [0.5 - 0.542, -0.3 - 0.542], atol=2e-3)
