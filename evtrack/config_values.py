"""Value checks of the configs that are not yet read by :mod:`evtrack.configs`.

:func:`number_from_text`, :func:`unknown_fields` and :func:`checked_device` are
:mod:`evtrack.configs`'s; :func:`checked_scalar` applies its scalar rules to one value by the
type of the field's default. New code uses :mod:`evtrack.configs` directly.
"""

from __future__ import annotations

from typing import Any

from evtrack.configs import (
    SCALAR_KINDS,
    checked_device,
    convert_value,
    number_from_text,
    unknown_fields,
)
from evtrack.errors import ConfigError

__all__ = ["checked_device", "checked_scalar", "number_from_text", "unknown_fields"]


def checked_scalar(name: str, value: Any, default: Any, source: str) -> Any:
    """``value`` for the field ``name`` whose default is ``default``, by the rules of
    :mod:`evtrack.configs` for the default's type (bool, int, float or str); a field of any
    other type passes unchanged.

    Raises:
        ConfigError: ``<source>: field '<name>' must be <kind>, got <value>``.
    """
    kind = next((k for k in SCALAR_KINDS if isinstance(default, k)), None)
    if kind is None:
        return value
    try:
        return convert_value(value, kind, source)
    except ConfigError:
        raise ConfigError(f"{source}: field {name!r} must be {SCALAR_KINDS[kind]}, "
                          f"got {value!r}") from None
