"""run.codegen: a run's programs at XLA's backend optimisation level 0, for debug runs and tests."""

from __future__ import annotations

import types

import pytest

import envs_mjx
from morefree_jax.checkpoint import ConfigMismatchError, config_differences, refuse_config_change
from morefree_jax.config_run import ConfigError, config_to_dict, resolve_config
from morefree_jax.programs import compiler_options
from morefree_jax.run_fns import compiled_settings


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


def test_run_dirs_from_before_the_key_resume_optimized_and_a_change_is_refused():
    current = config_to_dict(_config())
    stored = {**current, "run": {k: v for k, v in current["run"].items() if k != "codegen"}}
    assert config_differences(stored, current) == []  # they compiled with XLA's defaults
    fast = config_to_dict(_config("codegen=fast"))
    assert config_differences(stored, fast) == ["run.codegen"]
    with pytest.raises(ConfigMismatchError, match="run.codegen: 'optimized' -> 'fast'"):
        refuse_config_change(stored, fast, "run dir")  # the numbers round differently: not resumable
