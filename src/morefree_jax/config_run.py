"""The root config of a run and the generic tools for trees of frozen dataclasses.

    config = resolve_config(["env=point_umaze", "agent=morefree", "preset=cpu", "wm.deter=64"], ALL_ENVS)
    config.run / config.agent / config.planner / config.schedule     # RunConfig, AgentConfig (config.py),
                                                                     # PlannerConfig, ScheduleConfig
    json.dumps(config_to_dict(config))  ->  config_from_dict(Config, loaded)

`Config` is the ONE config a run has and writes to config.json: the run settings (RunConfig, here), the
learner (AgentConfig and its presets, config.py), the goal search (PlannerConfig, planner.py) and the goal
schedule (ScheduleConfig, go_explore.py); each part stays next to the code it configures. `resolve_config`
layers defaults < preset < the task's own defaults (its `default_config()`, next to the task's class in
envs_mjx) < the variant (variants.py) < the user's keys.

The tools (apply_overrides, config_to_dict / config_from_dict, valid_keys) work on any frozen-dataclass
tree. Values are parsed by the field's annotated type: int, float, bool, str, tuple[X, ...] / tuple[X, Y],
X | None, Literal[...], and nested dataclasses. Every error is a one-line ConfigError saying what was
wrong and what is valid.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Any, Literal

from morefree_jax.baselines.config import ModelFreeConfig
from morefree_jax.config import AgentConfig
from morefree_jax.go_explore import ScheduleConfig
from morefree_jax.planner import PlannerConfig

MAX_SEED = 2**32 - 1  # jax.random.PRNGKey keeps the low 32 bits: larger seeds would collide


class ConfigError(ValueError):
    """A bad override or config value (one-line message)."""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """One training run. Step counts are env steps of the single reset-free stream.

    Task-dependent fields (None here) are filled from the task's `default_config()` by resolve_config:
    total_steps (the task's budget), train_every (env steps per gradient update: the paper's train ratio),
    subgoal_threshold (learned distance, env steps, under which the go phase switches to exploring).
    prefill: random-action steps before learning (PEG point maze: 50 episodes x 50 = 2500 steps).
    eval_every: PEG point maze evaluates every 1e4 steps. run_dir: None = runs/<env>/<agent>/seed<seed>.
    pretrain: gradient updates right after the prefill (PEG: 100), rounded up to whole chunks of updates.
    hard_reset_every: None = the task's own period.
    visitation_bins: bins per axis of the replay's xy visitation histogram logged at each evaluation.
    checkpoint_minutes: also checkpoint after this much wall-clock time (slow machines); results do not
    depend on where checkpoints fall, so it may change on resume.
    seed_axis: how the seeds of a multi-seed run share one program (programs.py): "map" (a loop inside the
    program, bit-exact single-seed numbers), "vmap" (batched, for accelerators), "auto" (map on CPU, vmap
    on GPU/TPU); it may change on resume.
    codegen: how XLA compiles a run's programs: "optimized" (XLA's default) or "fast", XLA's backend
    optimisation level 0 for every program (LLVM unoptimised): they compile in about half the time, run
    more slowly (MJX physics many times slower) and round differently (README, Training and evaluation).
    For short debug runs and the tests; it may not change on resume (the numbers do).
    """

    env: str = "point_umaze"
    agent: str = "morefree"
    preset: str = "cpu"
    seed: int = 0
    total_steps: int | None = None
    prefill: int = 2_500
    train_every: int | None = None
    eval_every: int = 10_000
    eval_episodes: int = 10
    checkpoint_every: int = 10_000
    keep_checkpoints: int = 3
    log_every: int = 1_000
    run_dir: str | None = None
    pretrain: int = 100
    hard_reset_every: int | None = None
    subgoal_threshold: float | None = None
    visitation_bins: int = 50
    checkpoint_minutes: float = 10.0
    seed_axis: Literal["auto", "map", "vmap"] = "auto"
    codegen: Literal["optimized", "fast"] = "optimized"

    def __post_init__(self):
        if self.total_steps is not None and self.total_steps <= 0:  # None: the task's budget
            raise ConfigError(f"run.total_steps must be > 0, got {self.total_steps}")
        if not 0 <= self.seed <= MAX_SEED:
            raise ConfigError(f"run.seed must be in 0..{MAX_SEED} (JAX keys keep 32 bits), got {self.seed}")
        positive = ("eval_every", "eval_episodes", "checkpoint_every", "keep_checkpoints",
                    "log_every", "visitation_bins")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"run.{name} must be > 0, got {getattr(self, name)}")
        for name in ("prefill", "pretrain"):
            if getattr(self, name) < 0:
                raise ConfigError(f"run.{name} must be >= 0, got {getattr(self, name)}")
        if self.checkpoint_minutes <= 0:
            raise ConfigError(f"run.checkpoint_minutes must be > 0, got {self.checkpoint_minutes}")
        for name in ("train_every", "hard_reset_every", "subgoal_threshold"):
            if getattr(self, name) is not None and getattr(self, name) <= 0:
                raise ConfigError(f"run.{name} must be > 0 or none, got {getattr(self, name)}")

    @property
    def resolved_run_dir(self) -> str:
        return self.run_dir or f"runs/{self.env}/{self.agent}/seed{self.seed}"


def check_choice(what: str, value: str, valid) -> None:
    """One-line error for an unknown name: "unknown env 'x'; valid envs: a, b"."""
    if value not in valid:
        raise ConfigError(f"unknown {what} {value!r}; valid {what}s: {', '.join(valid)}")


# ---- dataclass-tree tools ----------------------------------------------------------------------

@functools.cache
def _field_types(cls) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _is_optional(tp) -> tuple[bool, Any]:
    """(allows None, the type without None)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return True, args[0]
    return False, tp


def _type_name(tp) -> str:
    optional, inner = _is_optional(tp)
    if optional:
        return f"{_type_name(inner)} or none"
    if typing.get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if typing.get_origin(tp) is tuple:
        return "tuple of " + ", ".join(_type_name(a) for a in typing.get_args(tp) if a is not Ellipsis)
    return getattr(tp, "__name__", str(tp))


def _parse_scalar(text: str, tp, key: str):
    text = text.strip()
    try:
        if tp is bool:
            lowered = text.lower()
            if lowered in ("true", "1", "yes", "on"):
                return True
            if lowered in ("false", "0", "no", "off"):
                return False
            raise ValueError
        if tp is int:
            try:
                return int(text)
            except ValueError:
                number = float(text)  # accepts 1e6 for an int field when it is a whole number
                if not number.is_integer():
                    raise
                return int(number)
        if tp is float:
            number = float(text)
        elif tp is str:
            return text
    except (ValueError, OverflowError):
        raise ConfigError(f"{key} expects {_type_name(tp)}, got {text!r}") from None
    if tp is float:
        if not math.isfinite(number):
            raise ConfigError(f"{key} must be a finite number, got {text!r}")
        return number
    raise ConfigError(f"{key} has type {_type_name(tp)}, which overrides do not support")


def parse_value(text: str, tp, key: str):
    """Parses override text by the annotated type `tp`; `key` names the field in errors."""
    optional, inner = _is_optional(tp)
    if optional and text.strip().lower() in ("none", "null"):
        return None
    origin = typing.get_origin(inner)
    if origin is Literal:
        valid = typing.get_args(inner)
        value = parse_value(text, type(valid[0]), key)
        if value not in valid:
            raise ConfigError(f"{key} must be {_type_name(inner)}, got {text!r}")
        return value
    if origin is tuple:
        body = text.strip().strip("()[]").strip()
        items = [item for item in body.split(",") if item.strip()] if body else []
        args = typing.get_args(inner)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(parse_value(item, args[0], key) for item in items)
        if len(items) != len(args):
            raise ConfigError(f"{key} expects {len(args)} comma-separated values, got {text!r}")
        return tuple(parse_value(item, arg, key) for item, arg in zip(items, args, strict=True))
    if dataclasses.is_dataclass(inner):
        valid = ", ".join(f.name for f in dataclasses.fields(inner))
        raise ConfigError(f"{key} is a group; set one of its keys ({key}.<key>, valid: {valid})")
    return _parse_scalar(text, inner, key)


def _with_value(config, path: list[str], text: str, prefix: str):
    name, rest = path[0], path[1:]
    key = f"{prefix}{name}"
    types_by_field = _field_types(type(config))
    if name not in types_by_field:
        where = f"at '{prefix[:-1]}'" if prefix else "at top level"
        raise ConfigError(f"unknown key {key!r}; valid keys {where}: {', '.join(types_by_field)}")
    if rest:
        child = getattr(config, name)
        if not dataclasses.is_dataclass(child):
            raise ConfigError(f"{key} is a value, not a group; did you mean {key}=...?")
        return dataclasses.replace(config, **{name: _with_value(child, rest, text, key + ".")})
    return dataclasses.replace(config, **{name: parse_value(text, types_by_field[name], key)})


def apply_overrides(config, overrides) -> Any:
    """A copy of the frozen-dataclass tree `config` with "dotted.key=value" overrides applied in order.
    Errors from a field's own validation (__post_init__) are re-raised as one-line ConfigErrors."""
    for override in overrides:
        key, sep, text = override.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"override {override!r} must look like key=value (e.g. wm.deter=64)")
        try:
            config = _with_value(config, key.split("."), text, "")
        except ConfigError:
            raise
        except (ValueError, TypeError) as error:
            raise ConfigError(f"{key}={text}: {error}") from None
    return config


def valid_keys(config_cls, prefix: str = "") -> list[str]:
    """Every dotted leaf key of a dataclass tree type."""
    keys = []
    for name, tp in _field_types(config_cls).items():
        _, inner = _is_optional(tp)
        if dataclasses.is_dataclass(inner):
            keys.extend(valid_keys(inner, f"{prefix}{name}."))
        else:
            keys.append(f"{prefix}{name}")
    return keys


def config_to_dict(config) -> dict:
    """Nested plain dict of a dataclass tree (tuples kept; json.dumps writes them as lists)."""
    return dataclasses.asdict(config)


def _from_json(value, tp, key: str):
    optional, inner = _is_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{key} may not be null")
    if dataclasses.is_dataclass(inner):
        if not isinstance(value, dict):
            raise ConfigError(f"{key} must be a mapping, got {value!r}")
        return config_from_dict(inner, value, key + ".")
    origin = typing.get_origin(inner)
    if origin is tuple:
        args = typing.get_args(inner)
        element_types = [args[0]] * len(value) if args[-1] is Ellipsis else list(args)
        if len(element_types) != len(value):
            raise ConfigError(f"{key} expects {len(args)} values, got {value!r}")
        return tuple(_from_json(v, t, key) for v, t in zip(value, element_types, strict=True))
    if origin is Literal or inner in (int, float, bool, str):
        return value if isinstance(value, str) and inner is str else parse_value(str(value), inner, key)
    return value


def config_from_dict(config_cls, data: dict, prefix: str = ""):
    """Builds `config_cls` from a nested dict (e.g. a loaded config.json); unknown keys are errors,
    missing keys take their defaults."""
    types_by_field = _field_types(config_cls)
    unknown = sorted(set(data) - set(types_by_field))
    if unknown:
        where = f"at '{prefix[:-1]}'" if prefix else "at top level"
        raise ConfigError(f"unknown key(s) {unknown}; valid keys {where}: {', '.join(types_by_field)}")
    values = {name: _from_json(data[name], types_by_field[name], prefix + name) for name in data}
    return config_cls(**values)


# ---- the root config of a run -------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Config:
    """Everything a run depends on, written to <run_dir>/config.json: the training run, the learner
    (core presets), the goal search and the goal schedule (set by the variant, `variants.py`), and the
    model-free baselines' learners (baselines/config.py; only oracle_sac and r3l read them, and they read
    nothing of agent, planner and schedule)."""

    run: RunConfig = dataclasses.field(default_factory=RunConfig)
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)
    planner: PlannerConfig = dataclasses.field(default_factory=PlannerConfig)
    schedule: ScheduleConfig = dataclasses.field(default_factory=ScheduleConfig)
    baseline: ModelFreeConfig = dataclasses.field(default_factory=ModelFreeConfig)


# CLI names of the run's identity; every other key is dotted: run.*, agent.*, planner.*, schedule.*, or a
# group of the learner without the "agent." prefix (wm.deter=64).
SHORT_KEYS = {"env": "env", "agent": "agent", "preset": "preset", "seed": "seed", "steps": "total_steps"}
# Keys that may change when a run dir is resumed: they change nothing computed (where the dir is, the step
# budget, the cadence of logs, evaluations and checkpoints, how seeds share a program). A change is recorded
# in the run dir's provenance.jsonl.
RESUMABLE_KEYS = ("run.run_dir", "run.total_steps", "run.checkpoint_minutes", "run.seed_axis",
                  "run.checkpoint_every", "run.keep_checkpoints", "run.log_every", "run.eval_every")
# Filled from the task's default_config(); a run needs them resolved (resolve_config does it).
TASK_RUN_KEYS = ("total_steps", "train_every", "subgoal_threshold")


def _full_key(key: str) -> str:
    """Maps CLI shorthands to dotted keys of Config (wm.deter -> agent.wm.deter, eval_every -> run.*)."""
    head = key.split(".")[0]
    if head in _field_types(Config):
        return key
    if "." in key and head in _field_types(AgentConfig):
        return "agent." + key
    if "." not in key and key in _field_types(RunConfig):
        return "run." + key
    if key == "alpha":
        raise ConfigError("alpha is ambiguous; set agent.alpha (imagination) or schedule.alpha (collection)")
    run_keys = [name for name in _field_types(RunConfig) if name not in SHORT_KEYS.values()]
    shown = ", ".join([*SHORT_KEYS, *run_keys, "agent.<key>", "planner.<key>", "schedule.<key>",
                       "baseline.<key>",
                       *(f"{name}.<key>" for name, tp in _field_types(AgentConfig).items()
                         if dataclasses.is_dataclass(tp))])
    raise ConfigError(f"unknown key {key!r}; valid keys: {shown}")


def split_arguments(arguments) -> tuple[dict[str, str], list[str]]:
    """CLI words "key=value" -> (the short identity keys, the other overrides with full dotted keys)."""
    short, overrides, seen = {}, [], {}
    for argument in arguments:
        key, sep, value = argument.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"argument {argument!r} must look like key=value (e.g. env=point_umaze)")
        full = f"run.{SHORT_KEYS[key]}" if key in SHORT_KEYS else _full_key(key)
        if full in seen:  # "last wins" would silently drop one of them
            raise ConfigError(f"{full} is given twice ({seen[full]} and {argument}); give it once")
        seen[full] = argument
        if key in SHORT_KEYS:
            short[SHORT_KEYS[key]] = value.strip()
        else:
            overrides.append(f"{full}={value}")
    return short, overrides


def task_overrides(env: str) -> list[str]:
    """The task's default_config() as "dotted.key=value" overrides (values parsed by the field types)."""
    from envs_mjx import env_class

    def text(value) -> str:
        return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)

    return [f"{key}={text(value)}" for key, value in env_class(env).default_config().items()]


def resolve_config(arguments, valid_envs) -> Config:
    """The root config of `train env=... agent=... preset=... seed=... steps=... key=value ...`.

    Layers, later wins: defaults; the preset (learner sizes); the task's default_config() (PEG's per-task
    values, train ratio, budget, prefill, planner); the variant (schedule and imagination goals); the
    user's keys (steps, seed and the dotted overrides). Errors are one-line ConfigErrors."""
    from morefree_jax.config import PRESETS, preset
    from morefree_jax.variants import AGENTS, apply_variant

    short, overrides = split_arguments(arguments)
    identity = {key: short.pop(key) for key in ("env", "agent", "preset") if key in short}
    for override in list(overrides):  # identity keys given dotted (run.env=ant) choose the layers too
        key, _, value = override.partition("=")
        if key in ("run.env", "run.agent", "run.preset"):
            identity[key[4:]] = value
            overrides.remove(override)
    run = apply_overrides(RunConfig(), [f"{key}={value}" for key, value in identity.items()])
    check_choice("env", run.env, valid_envs)
    check_choice("agent", run.agent, AGENTS)
    check_choice("preset", run.preset, PRESETS)
    config = Config(run=run, agent=preset(run.preset))
    config = apply_overrides(config, task_overrides(run.env))
    config = apply_variant(config, run.agent)
    try:
        config = apply_overrides(config, [f"run.{key}={value}" for key, value in short.items()])
    except ConfigError as error:  # speak of the CLI name "steps", not the field
        message = str(error).replace("run.total_steps", "steps").replace("total_steps", "steps")
        raise ConfigError(message) from None
    config = apply_overrides(config, overrides)
    missing = [key for key in TASK_RUN_KEYS if getattr(config.run, key) is None]
    if missing:
        raise ConfigError(f"{', '.join(missing)} may not be none (the task's defaults fill them)")
    if config.run.total_steps <= config.run.prefill:
        raise ConfigError(f"steps ({config.run.total_steps}) must be larger than the prefill "
                          f"({config.run.prefill} random steps before learning); lower prefill or raise it")
    return config
