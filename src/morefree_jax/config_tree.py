"""Tools for trees of frozen dataclasses: dotted overrides, JSON round trips, the valid keys.

    config = apply_overrides(config, ["agent.wm.deter=64", "run.seed=3"])
    json.dumps(config_to_dict(config))  ->  config_from_dict(type(config), loaded)

Values are parsed by the field's annotated type: int, float, bool, str, tuple[X, ...] / tuple[X, Y],
X | None, Literal[...], and nested dataclasses. Every error is a one-line ConfigError saying what was
wrong and what is valid. The root config of a run, built with these, is config.Config.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Any, Literal


class ConfigError(ValueError):
    """A bad override or config value (one-line message)."""



def check_choice(what: str, value: str, valid) -> None:
    """One-line error for an unknown name: "unknown env 'x'; valid envs: a, b"."""
    if value not in valid:
        raise ConfigError(f"unknown {what} {value!r}; valid {what}s: {', '.join(valid)}")


@functools.cache
def field_types(cls) -> dict[str, Any]:
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
    types_by_field = field_types(type(config))
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
    for name, tp in field_types(config_cls).items():
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
    types_by_field = field_types(config_cls)
    unknown = sorted(set(data) - set(types_by_field))
    if unknown:
        where = f"at '{prefix[:-1]}'" if prefix else "at top level"
        raise ConfigError(f"unknown key(s) {unknown}; valid keys {where}: {', '.join(types_by_field)}")
    values = {name: _from_json(data[name], types_by_field[name], prefix + name) for name in data}
    return config_cls(**values)
