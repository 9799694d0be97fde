"""The goal-conditioned actor-critic learns to reach random goals in a toy differentiable "world model".

The toy model is a linear point mass: deter = position (2,), pos' = pos + 0.2 * action; the reward is
-||pos - goal||. It plugs into the library's imagination through the same `apply(..., method=)` call as
the RSSM, so the real actor loss, dynamics gradients, lambda-returns and critic run unchanged.
"""

import jax
import jax.numpy as jnp
import numpy as np

from morefree_jax import actor_critic
from morefree_jax.actor_critic import (
    actor_critic_update,
    actor_loss,
    imagine_with,
    init_actor_critic,
    make_actor_critic,
    start_without_gradient,
)
from morefree_jax.learner_config import ActorCriticConfig, OptimizerConfig
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


def test_trunc_normal_sample_gradient_finite_when_uniform_draw_hits_a_saturated_bound():
    """loc 0.5, scale 0.1: the lower bound is 15 std away, erf rounds it to -1 in float32; a uniform draw
    of exactly 0 used to give erf_inv(-1) = -inf and a NaN actor gradient (point_umaze run at ~6500 steps)."""
    from morefree_jax.networks import TruncNormal

    def sample_sum(loc, scale):
        return jnp.sum(TruncNormal(loc, scale).sample_from_uniform(jnp.zeros_like(loc)))  # the lowest draw

    loc, scale = jnp.array([0.5, -0.3]), jnp.array([0.1, 0.1])
    value = sample_sum(loc, scale)
    grads = jax.grad(sample_sum, argnums=(0, 1))(loc, scale)
    assert np.isfinite(float(value))
    assert np.all(np.isfinite(np.asarray(grads[0]))) and np.all(np.isfinite(np.asarray(grads[1])))
    # The lowest draw lands ~5.42 std below loc (the float32 limit of erf_inv; both bounds are further).
    np.testing.assert_allclose(np.asarray(TruncNormal(loc, scale).sample_from_uniform(jnp.zeros(2))),
                               [0.5 - 0.542, -0.3 - 0.542], atol=2e-3)


def test_trunc_normal_sample_is_the_sample_of_its_uniform_draw():
    from morefree_jax.networks import TruncNormal

    actor = TruncNormal(jnp.array([0.5, -0.3, 0.0]), jnp.array([0.1, 0.4, 2.0]))
    key = jax.random.PRNGKey(3)
    unit = jax.random.uniform(key, (3,))
    np.testing.assert_array_equal(np.asarray(jax.jit(actor.sample)(key)),
                                  np.asarray(jax.jit(actor.sample_from_uniform)(unit)))
    # Monotone in the draw: the inverse CDF.
    low, high = actor.sample_from_uniform(jnp.full(3, 0.2)), actor.sample_from_uniform(jnp.full(3, 0.8))
    assert np.all(np.asarray(low) < np.asarray(high))


def test_start_without_gradient_keeps_values_and_drops_only_the_start_gradient():
    key_x, key_w, key_c = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(key_x, (5, 3, 4))
    w = jax.random.normal(key_w, (4, 4))
    cotangent = jax.random.normal(key_c, (5, 3))

    def fn(x):  # per time step, returns a pytree
        h = jnp.tanh(x @ w)
        return {"sum": h.sum(-1), "h": h}

    split = start_without_gradient(fn, x)
    np.testing.assert_allclose(split["sum"], fn(x)["sum"], rtol=1e-6)
    np.testing.assert_allclose(split["h"], fn(x)["h"], rtol=1e-6)

    def loss(fn_of_x, x):
        return jnp.sum(fn_of_x(x)["sum"] * cotangent)

    grad_split = jax.grad(lambda x: loss(lambda x: start_without_gradient(fn, x), x))(x)
    grad_plain = jax.grad(lambda x: loss(fn, x))(x)
    np.testing.assert_allclose(grad_split[1:], grad_plain[1:], rtol=1e-5)
    np.testing.assert_array_equal(grad_split[0], 0.0)
    assert np.abs(grad_plain[0]).sum() > 0  # the plain gradient at step 0 is not trivially zero


def test_actor_gradient_unchanged_by_splitting_off_the_start_state(monkeypatch):
    """The start's reward and the first successor's value enter no actor-loss term: the split (in the
    reward and in the lambda-return values) leaves the actor's gradient as it is without it."""
    cfg = ActorCriticConfig(actor_layers=(32, 32), critic_layers=(32, 32), horizon=6)
    ac = make_actor_critic(cfg, action_size=2, use_context=True)
    actor, critic = init_actor_critic(ac, jax.random.PRNGKey(1), feat_size=3, context_size=2)
    start, goals = starts_and_goals(jax.random.PRNGKey(2))

    def reward_fn(trajectory):
        distance = lambda f: jnp.linalg.norm(f[..., :2] - goals, axis=-1)  # noqa: E731
        return -actor_critic.start_without_gradient(distance, trajectory.feat[:-1]), None

    def actor_grad():
        return jax.grad(lambda p: actor_loss(ac, p, critic.params, LinearPointMass(), None, reward_fn, start,
                                             goals, jax.random.PRNGKey(3))[0])(actor.params)

    split = actor_grad()
    monkeypatch.setattr(actor_critic, "start_without_gradient", lambda fn, *inputs: fn(*inputs))
    plain = actor_grad()
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7), split, plain)
