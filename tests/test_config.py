"""Dotted overrides and dict round trip on a small frozen-dataclass tree; RunConfig checks."""

from __future__ import annotations

import dataclasses
import json
from typing import Literal

import pytest

from morefree_jax.config import (
    ConfigError,
    RunConfig,
    apply_overrides,
    check_choice,
    config_from_dict,
    config_to_dict,
    valid_keys,
)


@dataclasses.dataclass(frozen=True)
class WorldModel:
    deter: int = 200
    free_nats: float = 1.0
    layers: tuple[int, ...] = (400, 400, 400)
    activation: str = "elu"
    layer_norm: bool = True


@dataclasses.dataclass(frozen=True)
class Planner:
    method: Literal["mppi", "cem"] = "mppi"
    iterations: int = 5
    use_last_steps: int | None = 10
    bounds: tuple[float, float] = (0.0, 10.0)

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"planner.iterations must be >= 1, got {self.iterations}")


@dataclasses.dataclass(frozen=True)
class Tree:
    wm: WorldModel = dataclasses.field(default_factory=WorldModel)
    planner: Planner = dataclasses.field(default_factory=Planner)
    run: RunConfig = dataclasses.field(default_factory=RunConfig)
    alpha: float = 0.2


def test_overrides_parse_by_field_type():
    tree = apply_overrides(Tree(), [
        "wm.deter=64", "wm.free_nats=0.5", "wm.layers=(32, 32)", "wm.activation=silu", "wm.layer_norm=false",
        "planner.method=cem", "planner.iterations=3", "planner.use_last_steps=none", "planner.bounds=-2,8",
        "alpha=1", "run.total_steps=1e5", "run.train_every=5", "wm.deter=48",
    ])
    assert tree.wm == WorldModel(48, free_nats=0.5, layers=(32, 32), activation="silu", layer_norm=False)
    assert tree.planner == Planner(method="cem", iterations=3, use_last_steps=None, bounds=(-2.0, 8.0))
    assert tree.alpha == 1.0 and isinstance(tree.alpha, float)
    assert tree.run.total_steps == 100_000 and isinstance(tree.run.total_steps, int)
    assert Tree() == Tree()  # the original is untouched (frozen, copied)
    assert apply_overrides(Tree(), ["wm.layers=()"]).wm.layers == ()


@pytest.mark.parametrize("override, message", [
    ("wm.deterr=64", "unknown key 'wm.deterr'; valid keys at 'wm': deter, free_nats, layers, activation"),
    ("beta=1", "unknown key 'beta'; valid keys at top level: wm, planner, run, alpha"),
    ("wm.deter=abc", "wm.deter expects int, got 'abc'"),
    ("wm.deter=2.5", "wm.deter expects int, got '2.5'"),
    ("wm.free_nats=fast", "wm.free_nats expects float, got 'fast'"),
    ("wm.free_nats=nan", "wm.free_nats must be a finite number, got 'nan'"),
    ("wm.layer_norm=maybe", "wm.layer_norm expects bool, got 'maybe'"),
    ("wm.layers=(32,x)", "wm.layers expects int, got 'x'"),
    ("planner.method=random", "planner.method must be one of 'mppi', 'cem', got 'random'"),
    ("planner.bounds=1,2,3", "planner.bounds expects 2 comma-separated values, got '1,2,3'"),
    ("planner.iterations=0", "planner.iterations=0: planner.iterations must be >= 1, got 0"),
    ("run.total_steps=0", "run.total_steps must be > 0, got 0"),
    ("run.total_steps=-5", "run.total_steps must be > 0, got -5"),
    ("wm=3", "wm is a group; set one of its keys (wm.<key>, valid: deter, free_nats, layers"),
    ("alpha.x=3", "alpha is a value, not a group"),
    ("wm.deter", "override 'wm.deter' must look like key=value"),
])
def test_bad_overrides_are_one_line_errors(override, message):
    with pytest.raises(ConfigError) as error:
        apply_overrides(Tree(), [override])
    text = str(error.value)
    assert message in text and "\n" not in text


def test_dict_round_trip_through_json():
    tree = apply_overrides(Tree(), ["wm.layers=16,16", "planner.use_last_steps=none", "run.seed=7"])
    loaded = json.loads(json.dumps(config_to_dict(tree)))
    assert loaded["wm"]["layers"] == [16, 16] and loaded["planner"]["use_last_steps"] is None
    assert config_from_dict(Tree, loaded) == tree
    assert config_from_dict(Tree, {"alpha": 0.5}) == Tree(alpha=0.5)  # missing keys take defaults
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['deterr'\]; valid keys at 'wm': deter"):
        config_from_dict(Tree, {"wm": {"deterr": 1}})
    with pytest.raises(ConfigError, match="wm.deter expects int"):
        config_from_dict(Tree, {"wm": {"deter": 1.5}})


def test_valid_keys_and_choices():
    keys = valid_keys(Tree)
    assert keys[:5] == ["wm.deter", "wm.free_nats", "wm.layers", "wm.activation", "wm.layer_norm"]
    assert "run.train_every" in keys and "alpha" in keys and "wm" not in keys
    with pytest.raises(ConfigError, match="unknown env 'pointmaze'; valid envs: point_umaze, ant"):
        check_choice("env", "pointmaze", ("point_umaze", "ant"))


def test_run_config_dir_and_defaults():
    assert RunConfig(env="ant", agent="rf_peg", seed=2).resolved_run_dir == "runs/ant/rf_peg/seed2"
    assert RunConfig().eval_episodes == 10
