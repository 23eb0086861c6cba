"""One config value checked against the type of its field's default (YAML and CLI input)."""

from __future__ import annotations

from typing import Any

from evtrack.errors import ConfigError

__all__ = ["checked_scalar"]


def checked_scalar(name: str, value: Any, default: Any, source: str) -> Any:
    """``value`` for the field ``name`` whose default is ``default``: a bool for a bool, an
    integer (``5.0`` accepted) for an int, a number for a float (returned as ``float``), a
    string for a str; anything else passes unchanged.

    Raises:
        ConfigError: naming ``source`` and the field.
    """
    def bad(kind: str) -> ConfigError:
        return ConfigError(f"{source}: field {name!r} must be {kind}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise bad("an integer")
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    return value
