"""agent.precision: bf16 matmul inputs with float32 accumulation, everything else float32; the f32 program is
the one from before the option existed; run dirs record the precision and a resume keeps it."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from morefree_jax import precision
from morefree_jax.agent import EnvSpec, make_agent
from morefree_jax.config import ConfigError, resolve_config
from morefree_jax.driver import settle_precision
from morefree_jax.imagination import GoalPools
from morefree_jax.learner_config import preset
from morefree_jax.registry import make_run_fns
from tests.core_helpers import fixed_batch
from tests.program_digest import program_digest

# program_digest of a debug point_umaze morefree run's collect and train_updates (update_cadence=chunk, the
# one cadence then) at the pinned jax and flax, made by the code before agent.precision existed (commit
# 8f10a47, same digests there): an f32 run traces to these same programs, so it computes the same numbers
# bit for bit. A change that alters the f32 computation on purpose updates them (and says so in its commit).
F32_PROGRAM_DIGESTS = {"collect": "29be1af2740616ed", "train_updates": "be4d15215c1bd786"}


def test_an_f32_run_traces_to_the_programs_before_the_precision_option():
    config = resolve_config(["env=point_umaze", "agent=morefree", "preset=debug", "agent.precision=f32",
                             "update_cadence=chunk"], envs_mjx.ALL_ENVS)
    fns = make_run_fns(config, envs_mjx.make("point_umaze"))
    state = jax.eval_shape(fns.init, jax.random.PRNGKey(0))
    digests = {name: program_digest(getattr(fns, name), state) for name in F32_PROGRAM_DIGESTS}
    assert digests == F32_PROGRAM_DIGESTS


def _equations(jaxpr):
    """Every equation of a jaxpr, inside scans, conds, custom_vjp and pjit bodies too."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from _equations(inner)


def _bf16_agent():
    config = dataclasses.replace(preset("debug"), precision="bf16")
    agent = make_agent(config, EnvSpec(4, 2, (0, 1)))
    pools = GoalPools(jnp.ones((4, 4)), jnp.zeros((1, 4)))
    batch = fixed_batch(config.replay.batch, config.replay.length)
    return agent, agent.init(jax.random.PRNGKey(0)), batch, pools


def test_under_bf16_every_matmul_takes_bfloat16_and_accumulates_in_float32():
    agent, state, batch, pools = _bf16_agent()
    jaxpr = jax.make_jaxpr(agent.train_step)(state, batch, pools, jax.random.PRNGKey(1)).jaxpr
    dots = [eqn for eqn in _equations(jaxpr) if eqn.primitive.name == "dot_general"]
    # forward (one per layer call) and both backward matmuls (custom vjp) of every layer: many dozens
    assert len(dots) > 50
    for eqn in dots:
        assert [v.aval.dtype for v in eqn.invars] == [jnp.bfloat16, jnp.bfloat16], eqn
        assert eqn.outvars[0].aval.dtype == jnp.float32, eqn


def test_under_bf16_parameters_optimizer_state_and_losses_stay_float32():
    agent, state, batch, pools = _bf16_agent()
    new_state, metrics = jax.jit(agent.train_step)(state, batch, pools, jax.random.PRNGKey(1))
    dtypes = {leaf.dtype for leaf in jax.tree.leaves(new_state) if jnp.issubdtype(leaf.dtype, jnp.inexact)}
    assert dtypes == {jnp.dtype(jnp.float32)}
    assert {jnp.asarray(value).dtype for value in metrics.values()} == {jnp.dtype(jnp.float32)}
    assert all(np.isfinite(float(value)) for value in metrics.values())


def _sin_loss(x, kernel, which):
    return jnp.sum(jnp.sin(precision.matmul(x, kernel, which)))


# (input width, output width): the weight gradient transposes the narrower side; under 8 columns it does not
WIDTHS = [(16, 8), (8, 24), (16, 4)]


@pytest.mark.parametrize(("width_in", "width_out"), WIDTHS)
def test_bf16_matmul_gradients_match_float32_to_bfloat16_rounding(width_in, width_out):
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 5, width_in))
    kernel = jax.random.normal(jax.random.PRNGKey(1), (width_in, width_out))
    grad = jax.jit(jax.grad(_sin_loss, argnums=(0, 1)), static_argnums=2)
    exact, mixed = grad(x, kernel, "f32"), grad(x, kernel, "bf16")
    for a, b in zip(exact, mixed, strict=True):
        assert b.dtype == jnp.float32 and b.shape == a.shape
        np.testing.assert_allclose(b, a, rtol=0.05, atol=0.05 * float(jnp.max(jnp.abs(a))))


def test_bf16_weight_gradients_contract_a_row_major_lhs_also_under_vmap():
    # XLA's CPU backend runs a dot whose lhs contracts over its major axis in float32 (precision.py)
    x = jax.random.normal(jax.random.PRNGKey(0), (4, 10, 16))  # 4 ensemble members
    kernels = jax.random.normal(jax.random.PRNGKey(1), (4, 16, 24))
    grad = jax.vmap(jax.grad(_sin_loss, argnums=(0, 1)), in_axes=(0, 0, None))
    jaxpr = jax.make_jaxpr(grad, static_argnums=2)(x, kernels, "bf16").jaxpr
    dots = [eqn for eqn in _equations(jaxpr) if eqn.primitive.name == "dot_general"]
    assert len(dots) == 3  # forward, input gradient, weight gradient
    for eqn in dots:
        (lhs_contract, _), (lhs_batch, _) = eqn.params["dimension_numbers"]
        assert tuple(lhs_contract) == (eqn.invars[0].aval.ndim - 1,), eqn
        assert tuple(lhs_batch) in ((), (0,)), eqn
    compiled = jax.jit(grad, static_argnums=2)
    exact, mixed = compiled(x, kernels, "f32"), compiled(x, kernels, "bf16")
    for a, b in zip(exact, mixed, strict=True):
        np.testing.assert_allclose(b, a, rtol=0.05, atol=0.05 * float(jnp.max(jnp.abs(a))))


def test_auto_resolves_to_a_concrete_precision_and_bad_values_name_the_valid_ones():
    assert precision.resolve_precision("auto") in precision.PRECISIONS
    assert precision.resolve_precision("f32") == "f32"
    with pytest.raises(ValueError, match="valid: auto, f32, bf16"):
        dataclasses.replace(preset("debug"), precision="fp16")
    with pytest.raises(ConfigError, match="f32, bf16"):
        resolve_config(["env=point_umaze", "agent.precision=half"], envs_mjx.ALL_ENVS)


def _config_in(run_dir, *extra):
    chosen = [] if any(a.startswith("agent.precision=") for a in extra) else ["agent.precision=auto"]
    arguments = ["env=point_umaze", "preset=debug", f"run_dir={run_dir}", *chosen, *extra]
    return resolve_config(arguments, envs_mjx.ALL_ENVS)


@pytest.mark.parametrize("stored", ["f32", "bf16"])
def test_a_resume_keeps_the_recorded_precision(tmp_path, stored):
    (tmp_path / "config.json").write_text(json.dumps({"agent": {"precision": stored}}))
    assert settle_precision(_config_in(tmp_path)).agent.precision == stored  # auto: the run dir's
    assert settle_precision(_config_in(tmp_path / "new")).agent.precision == precision.default_precision()
    given = settle_precision(_config_in(tmp_path, "agent.precision=f32"))
    assert given.agent.precision == "f32"  # explicit: as given (the driver then refuses a changed config)


def test_the_default_is_float32():
    assert resolve_config(["env=point_umaze"], envs_mjx.ALL_ENVS).agent.precision == "f32"


def test_a_run_dir_from_before_the_option_resumes_in_float32(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"agent": {"alpha": 0.2}}))
    assert settle_precision(_config_in(tmp_path)).agent.precision == "f32"


def test_seeds_of_a_group_with_different_precisions_are_refused(tmp_path):
    for seed, stored in ((0, "f32"), (1, "bf16")):
        (tmp_path / f"seed{seed}").mkdir()
        (tmp_path / f"seed{seed}" / "config.json").write_text(json.dumps({"agent": {"precision": stored}}))
    with pytest.raises(ConfigError, match="different precisions"):
        settle_precision(_config_in(tmp_path), seeds=(0, 1))
