"""The one argument style of the command-line entry points: `key=value` words, as `make train` takes.

    args = parse_keys(argv, {"runs": REQUIRED, "out": "results", "quick": False, "reps": 3})

A value is parsed by the type of its default (bool: 1/0, true/false, yes/no; int; str; a None default
takes a string or "none"). A bad word is a KeyValueError whose one line names the valid keys.
"""

from __future__ import annotations

from typing import Any

REQUIRED = object()  # a key that has no default and must be given
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


class KeyValueError(ValueError):
    """A bad key=value argument (one-line message)."""


def _parse(key: str, text: str, default: Any) -> Any:
    if default is None or default is REQUIRED or isinstance(default, str):
        return None if default is None and text.lower() == "none" else text
    if isinstance(default, bool):
        if text.lower() in _TRUE + _FALSE:
            return text.lower() in _TRUE
        raise KeyValueError(f"{key} expects 1 or 0 (true or false), got {text!r}")
    try:
        return type(default)(text)
    except ValueError:
        raise KeyValueError(f"{key} expects {type(default).__name__}, got {text!r}") from None


def parse_keys(argv: list[str], spec: dict[str, Any]) -> dict[str, Any]:
    """The values of `spec`'s keys given as key=value words in `argv`, the defaults for the others."""
    values = {key: default for key, default in spec.items()}
    valid = ", ".join(spec)
    seen = set()
    for argument in argv:
        key, sep, text = argument.partition("=")
        key = key.strip()
        if not sep or key not in spec:
            raise KeyValueError(f"bad argument {argument!r}; valid keys: {valid} (key=value)")
        if key in seen:
            raise KeyValueError(f"{key} is given twice; give it once")
        seen.add(key)
        values[key] = _parse(key, text.strip(), spec[key])
    missing = [key for key, value in values.items() if value is REQUIRED]
    if missing:
        raise KeyValueError(f"{', '.join(f'{key}=...' for key in missing)} required; valid keys: {valid}")
    return values
