"""The model registry: ``@register_model`` entry points, :func:`list_models`, lookup.

Entry points are small functions that only choose hyper-parameters and return an
``nn.Module``; :func:`evtrack.models.create` (in :mod:`evtrack.models.factory`) calls them and
loads weights. This mirrors timm's ``register_model`` / ``create_model`` / ``list_models``.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from typing import Any

from torch import nn

from evtrack.errors import ConfigError

__all__ = ["register_model", "list_models", "model_entrypoint", "is_model"]

_ENTRYPOINTS: dict[str, Callable[..., nn.Module]] = {}
_FAMILY: dict[str, str] = {}


def register_model(fn: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
    """Register ``fn`` under its function name.

    The function takes keyword hyper-parameters (overrides of its defaults) and returns the
    network. Registering the same name twice is an error, so two families cannot shadow each
    other silently.
    """
    name = fn.__name__
    if name in _ENTRYPOINTS:
        raise ValueError(f"model {name!r} is already registered (by {_FAMILY[name]})")
    _ENTRYPOINTS[name] = fn
    _FAMILY[name] = fn.__module__
    return fn


def list_models(pattern: str = "*") -> list[str]:
    """Sorted names of the registered models matching the shell-style ``pattern``."""
    return sorted(n for n in _ENTRYPOINTS if fnmatch.fnmatchcase(n, pattern))


def is_model(name: str) -> bool:
    """Whether ``name`` is a registered model."""
    return name in _ENTRYPOINTS


def model_entrypoint(name: str) -> Callable[..., Any]:
    """The entry point of ``name``.

    Raises:
        ConfigError: naming the unknown model and listing the known ones.
    """
    try:
        return _ENTRYPOINTS[name]
    except KeyError:
        raise ConfigError(
            f"unknown model {name!r}; registered models: {', '.join(list_models()) or 'none'}"
        ) from None
