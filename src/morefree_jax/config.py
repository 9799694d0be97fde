"""The root config of a run: `resolve_config(arguments, valid_envs) -> Config`.

    config = resolve_config(["env=point_umaze", "agent=morefree", "preset=cpu", "wm.deter=64"], ALL_ENVS)
    config.run / config.agent / config.planner / config.schedule / config.baseline
    # RunConfig (here), AgentConfig (learner_config.py), PlannerConfig (planner.py),
    # ScheduleConfig (goal_schedule.py), ModelFreeConfig (baselines/baseline_config.py)
    json.dumps(config_to_dict(config))  ->  config_from_dict(Config, loaded)

`Config` is the ONE config a run has and writes to config.json; each part stays next to the code it
configures. `resolve_config` layers defaults < preset < the task's own defaults (its `default_config()`,
next to the task's class in envs_mjx) < the agent's settings (its registry entry, registry.py) < the
user's keys. The tools it uses (overrides, JSON round trips, one-line ConfigErrors) are config_tree.py's.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from envs_mjx import env_class
from morefree_jax import registry, variants
from morefree_jax.baselines.baseline_config import ModelFreeConfig
from morefree_jax.config_tree import (
    ConfigError,
    apply_overrides,
    check_choice,
    config_from_dict,
    config_to_dict,
    field_types,
    valid_keys,
)
from morefree_jax.goal_schedule import ScheduleConfig
from morefree_jax.learner_config import PRESETS, AgentConfig, preset
from morefree_jax.planner import PlannerConfig

__all__ = ["Config", "ConfigError", "RunConfig", "apply_overrides", "config_from_dict", "config_to_dict",
           "resolve_config", "valid_keys"]

MAX_SEED = 2**32 - 1  # jax.random.PRNGKey keeps the low 32 bits: larger seeds would collide


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
    seed_axis: how the seeds of a multi-seed run share one program (compile.py): "map" (a loop inside the
    program, bit-exact single-seed numbers), "vmap" (batched, for accelerators), "auto" (map on CPU, vmap
    on GPU/TPU); it may change on resume.
    codegen: how XLA compiles a run's programs: "optimized" (XLA's default) or "fast", XLA's backend
    optimisation level 0 for every program (LLVM unoptimised): they compile in about half the time, run
    more slowly (MJX physics many times slower) and round differently (docs/training.md, "Codegen").
    For short debug runs and the tests; it may not change on resume (the numbers do).
    update_cadence: when the world-model agents' gradient updates run (docs/training.md, "Update cadence"):
    "interleaved" (the paper's "every n steps": one update after every train_every env steps, inside the
    chunk, so the next steps act with the updated policies and distance) or "chunk" (all of a chunk's
    updates after it, the policies fixed within the chunk). Model-free agents update every env step anyway.
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
    update_cadence: Literal["interleaved", "chunk"] = "interleaved"

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

    def require_task_defaults(self) -> None:
        """A ConfigError unless the task's defaults (TASK_RUN_KEYS) are filled, as resolve_config does."""
        unresolved = [key for key in TASK_RUN_KEYS if getattr(self, key) is None]
        if unresolved:
            raise ConfigError(f"run.{', run.'.join(unresolved)} unset: build the config with resolve_config, "
                              "which fills the task's defaults")

    @property
    def resolved_run_dir(self) -> str:
        return self.run_dir or f"runs/{self.env}/{self.agent}/seed{self.seed}"


# ---- the root config of a run -------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Config:
    """Everything a run depends on, written to <run_dir>/config.json: the training run, the learner
    (core presets), the goal search and the goal schedule (set by the variant, `variants.py`), and the
    model-free baselines' learners (baselines/baseline_config.py). Which sections an agent reads: its
    registry entry (registry.py)."""

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
# The paper's alpha (Sec. 4, Alg. 2: the back-and-forth probability and the imagination goal shares alpha/2,
# alpha/2, 1 - alpha): one CLI key for both schedule.alpha and agent.alpha, which stay separate for ablations.
PAPER_ALPHA = "alpha"
# Filled from the task's default_config(); a run needs them resolved (resolve_config does it).
TASK_RUN_KEYS = ("total_steps", "train_every", "subgoal_threshold")


def _full_key(key: str) -> str:
    """Maps CLI shorthands to dotted keys of Config (wm.deter -> agent.wm.deter, eval_every -> run.*)."""
    head = key.split(".")[0]
    if head in field_types(Config):
        return key
    if "." in key and head in field_types(AgentConfig):
        return "agent." + key
    if "." not in key and key in field_types(RunConfig):
        return "run." + key
    if key == PAPER_ALPHA:
        return PAPER_ALPHA
    run_keys = [name for name in field_types(RunConfig) if name not in SHORT_KEYS.values()]
    shown = ", ".join([*SHORT_KEYS, *run_keys, "agent.<key>", "planner.<key>", "schedule.<key>",
                       "baseline.<key>",
                       *(f"{name}.<key>" for name, tp in field_types(AgentConfig).items()
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


def _expand_paper_alpha(overrides: list[str], agent: str) -> list[str]:
    """`alpha=v` -> schedule.alpha=v and agent.alpha=v, for the agents whose two alphas are the paper's one;
    where they are not (rf_peg, the other ablations, the model-free baselines) it is a ConfigError."""
    given = [override for override in overrides if override.partition("=")[0] == PAPER_ALPHA]
    if not given:
        return overrides
    valid = variants.paper_alpha_agents()
    if agent not in valid:
        raise ConfigError(f"alpha= sets the paper's alpha of {', '.join(valid)}, not of agent {agent}; "
                          "set schedule.alpha (collection) or agent.alpha (imagination) instead")
    separate = ("schedule.alpha", "agent.alpha")
    both = [override for override in overrides if override.partition("=")[0] in separate]
    if both:
        raise ConfigError(f"alpha= sets schedule.alpha and agent.alpha; give it or them, not {both[0]} too")
    value = given[0].partition("=")[2]
    rest = [override for override in overrides if override not in given]
    return [*rest, f"schedule.alpha={value}", f"agent.alpha={value}"]


def task_overrides(env: str) -> list[str]:
    """The task's default_config() as "dotted.key=value" overrides (values parsed by the field types)."""
    def text(value) -> str:
        return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)

    return [f"{key}={text(value)}" for key, value in env_class(env).default_config().items()]


def resolve_config(arguments, valid_envs) -> Config:
    """The root config of `train env=... agent=... preset=... seed=... steps=... key=value ...`.

    Layers, later wins: defaults; the preset (learner sizes); the task's default_config() (PEG's per-task
    values, train ratio, budget, prefill, planner); the agent's registry entry (a variant's schedule and
    imagination goals, a model-free agent's seed phase as its prefill); the user's keys (steps, seed and the
    dotted overrides). Errors are one-line ConfigErrors."""

    short, overrides = split_arguments(arguments)
    identity = {key: short.pop(key) for key in ("env", "agent", "preset") if key in short}
    for override in list(overrides):  # identity keys given dotted (run.env=ant) choose the layers too
        key, _, value = override.partition("=")
        if key in ("run.env", "run.agent", "run.preset"):
            identity[key[4:]] = value
            overrides.remove(override)
    run = apply_overrides(RunConfig(), [f"{key}={value}" for key, value in identity.items()])
    check_choice("env", run.env, valid_envs)
    check_choice("agent", run.agent, registry.AGENTS)
    check_choice("preset", run.preset, PRESETS)
    config = Config(run=run, agent=preset(run.preset))
    config = apply_overrides(config, task_overrides(run.env))
    config = registry.configure(config, run.agent)
    try:
        config = apply_overrides(config, [f"run.{key}={value}" for key, value in short.items()])
    except ConfigError as error:  # speak of the CLI name "steps", not the field
        message = str(error).replace("run.total_steps", "steps").replace("total_steps", "steps")
        raise ConfigError(message) from None
    config = apply_overrides(config, _expand_paper_alpha(overrides, run.agent))
    missing = [key for key in TASK_RUN_KEYS if getattr(config.run, key) is None]
    if missing:
        raise ConfigError(f"{', '.join(missing)} may not be none (the task's defaults fill them)")
    if config.run.total_steps <= config.run.prefill:
        raise ConfigError(f"steps ({config.run.total_steps}) must be larger than the prefill "
                          f"({config.run.prefill} random steps before learning); lower prefill or raise it")
    return config
