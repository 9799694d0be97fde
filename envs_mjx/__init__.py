"""Reset-free tasks in MuJoCo MJX: a registry over the task API of `envs_mjx.base`.

    env = envs_mjx.make("point_umaze")                   # defaults of the paper
    env = envs_mjx.make("ant", hard_reset_every=100_000)  # overrides are constructor arguments
"""

from __future__ import annotations

import importlib
import inspect

from envs_mjx.base import ResetFreeEnv

# name -> "module:Class"; modules are imported on first use so that importing the registry is cheap.
_REGISTRY: dict[str, str] = {
    "point_umaze": "envs_mjx.point_umaze:PointUMaze",
    "ant": "envs_mjx.ant:Ant",
    "tabletop": "envs_mjx.tabletop:Tabletop",
    "sawyer_door": "envs_mjx.sawyer_door:SawyerDoor",
    "push": "envs_mjx.fetch:FetchPush",
    "pick_place": "envs_mjx.fetch:FetchPickPlace",
    "push_hard": "envs_mjx.fetch:FetchPushHard",
    "pick_place_hard": "envs_mjx.fetch:FetchPickPlaceHard",
}

ALL_ENVS: tuple[str, ...] = tuple(_REGISTRY)


def env_class(name: str) -> type[ResetFreeEnv]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown env {name!r}; valid envs: {', '.join(ALL_ENVS)}")
    module_name, class_name = _REGISTRY[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def valid_overrides(name: str) -> tuple[str, ...]:
    """The keyword arguments `make(name, ...)` accepts."""
    params = inspect.signature(env_class(name).__init__).parameters
    return tuple(p for p in params if p != "self")


def make(name: str, **overrides) -> ResetFreeEnv:
    """Builds task `name`; overrides are the task's constructor arguments (see `valid_overrides`)."""
    cls = env_class(name)
    valid = valid_overrides(name)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(
            f"unknown override(s) {unknown} for env {name!r}; valid overrides: {', '.join(valid)}"
        )
    return cls(**overrides)


__all__ = ["ALL_ENVS", "ResetFreeEnv", "env_class", "make", "valid_overrides"]
