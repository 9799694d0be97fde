"""run.codegen: a run's programs at XLA's backend optimisation level 0, for debug runs and tests."""

from __future__ import annotations

import types

import jax
import pytest
from conftest import cached_env

import envs_mjx
from morefree_jax.checkpoint import ConfigMismatchError, config_differences, refuse_config_change
from morefree_jax.compile import compile_programs, compiler_options, jit_run_fns
from morefree_jax.config import ConfigError, config_to_dict, resolve_config
from morefree_jax.registry import make_run_fns
from morefree_jax.run import compiled_settings

PROGRAMS = ("init", "prefill", "collect", "train_updates", "evaluate", "visitation")


def _config(*extra: str):
    return resolve_config(["env=tabletop", "agent=morefree", *extra], envs_mjx.ALL_ENVS)


def test_fast_codegen_turns_llvm_optimisation_off():
    assert compiler_options(types.SimpleNamespace(config=_config("codegen=fast"))) == {
        "xla_backend_optimization_level": 0}
    assert compiler_options(types.SimpleNamespace(config=_config())) is None  # XLA's defaults
    assert compiled_settings(_config("codegen=fast")) != compiled_settings(_config())


def test_bad_codegen_is_a_one_line_error_naming_the_valid_ones():
    with pytest.raises(ConfigError, match="run.codegen must be one of 'optimized', 'fast', got 'quick'"):
        _config("codegen=quick")


def test_a_codegen_change_is_refused_on_resume():
    optimized, fast = config_to_dict(_config()), config_to_dict(_config("codegen=fast"))
    assert config_differences(optimized, fast) == ["run.codegen"]
    with pytest.raises(ConfigMismatchError, match="run.codegen: 'optimized' -> 'fast'"):
        refuse_config_change(optimized, fast, "run dir")  # the numbers round differently: not resumable


@pytest.mark.parametrize("agent", ["morefree", "r3l"])
@pytest.mark.parametrize(("codegen", "expected"), [("fast", {"xla_backend_optimization_level": 0}),
                                                   ("optimized", None)])
def test_every_program_of_a_run_gets_the_codegen_options(agent, codegen, expected, monkeypatch):
    """compile_programs and jit_run_fns pass compiler_options(fns) to the jit of each program."""
    config = resolve_config(["env=tabletop", f"agent={agent}", f"codegen={codegen}"], envs_mjx.ALL_ENVS)
    fns = make_run_fns(config, cached_env("tabletop"))
    given = []
    monkeypatch.setattr(jax, "jit", lambda fn, **kwargs: given.append(kwargs.get("compiler_options")) or fn)
    compile_programs(fns, num_seeds=1)
    jit_run_fns(fns)
    programs = sum(getattr(fns, name) is not None for name in PROGRAMS)  # model-free: no train_updates
    assert given == [expected] * (2 * programs)
