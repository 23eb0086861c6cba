"""One config value checked against the type of its field's default (YAML and CLI input)."""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING, Any

from evtrack.errors import ConfigError

if TYPE_CHECKING:
    import torch

__all__ = ["checked_device", "checked_scalar", "number_from_text", "unknown_fields"]

_SCIENTIFIC = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")
"""A number in scientific notation. YAML 1.1 (PyYAML) reads ``1e-3`` as a string (it wants
``1.0e-3``), so number fields also take such strings; a quoted plain number (``"16"``) stays
a string, and an error."""


def number_from_text(value: Any) -> Any:
    """``value`` as a float if it is a string in scientific notation (``"1e-3"``, which YAML
    1.1 reads as a string), else ``value`` unchanged. Parsed, never evaluated."""
    if isinstance(value, str) and _SCIENTIFIC.fullmatch(value.strip()):
        return float(value)
    return value


def checked_scalar(name: str, value: Any, default: Any, source: str) -> Any:
    """``value`` for the field ``name`` whose default is ``default``: a bool for a bool, an
    integer (``5.0`` accepted) for an int, a number for a float (returned as ``float``), a
    string for a str; anything else passes unchanged. Number fields also take a string
    in scientific notation (``"1e-3"``: YAML 1.1 reads it without a dot as a string); it is
    parsed, never evaluated.

    Raises:
        ConfigError: naming ``source`` and the field.
    """
    def bad(kind: str) -> ConfigError:
        return ConfigError(f"{source}: field {name!r} must be {kind}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    number = number_from_text(value) if isinstance(default, int | float) else value
    if isinstance(default, int):
        if (isinstance(number, bool) or not isinstance(number, int | float)
                or not math.isfinite(number) or number != int(number)):
            raise bad("an integer")
        return int(number)
    if isinstance(default, float):
        if isinstance(number, bool) or not isinstance(number, int | float):
            raise bad("a number")
        return float(number)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    return value


def checked_device(device: Any, where: str) -> torch.device:
    """``device`` as a ``torch.device`` that this torch can use.

    Raises:
        ConfigError: naming ``where``: not a device name, or CUDA asked for where this torch
            has none (or not that many GPUs).
    """
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(f"{where}: {device!r} is not a torch device (cpu, cuda, cuda:1, "
                          f"...)") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"{where}: {device!r}, but this torch has no CUDA device (install "
                              "a CUDA build of torch, or use cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"{where}: {device!r}, but only {torch.cuda.device_count()} "
                              "CUDA device(s) are visible")
    return dev


def unknown_fields(unknown: Any, known: Any) -> str:
    """``unknown field(s) [...]`` with the nearest known name of each where one is close
    (``'metod': did you mean 'method'?``), else the list of the known names."""
    import difflib

    known = sorted(known)
    hints = []
    for name in sorted(unknown):
        close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.7)
        if close:
            hints.append(f"{name!r}: did you mean {close[0]!r}?")
    text = f"unknown field(s) {sorted(unknown)}"
    if hints:
        return f"{text} ({'; '.join(hints)})"
    return f"{text}; known: {known}"
