"""``create(name, weights=...)`` and ``load_model(path)``: build a registered network, load weights.

Every network returned carries three attributes:

* ``arch_name``: its registered name,
* ``arch_kwargs``: the hyper-parameter overrides it was built with,
* ``weights_record``: the :class:`~evtrack.models.weights.WeightsRecord` of its weights, or
  ``None`` for a randomly initialised network.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torch import nn

from evtrack.models._registry import model_entrypoint
from evtrack.models.weights import (
    WeightsError,
    WeightsRecord,
    find_default_weights,
    load_weights_file,
)

__all__ = ["create", "load_model"]


def _build(name: str, kwargs: dict[str, Any]) -> nn.Module:
    entry = model_entrypoint(name)
    net = entry(**kwargs)
    net.arch_name = name
    net.arch_kwargs = dict(kwargs)
    net.weights_record = None
    return net


def _config_of(net: nn.Module) -> Any:
    cfg = getattr(net, "config", None)
    return cfg.to_dict() if hasattr(cfg, "to_dict") else None


def _load_into(net: nn.Module, state: dict, path: Path, name: str) -> None:
    try:
        result = net.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # tensors of the wrong shape
        first = str(exc).strip().splitlines()
        raise WeightsError(path, f"weights do not fit {name}: {' '.join(first[:3])}") from exc
    if result.missing_keys or result.unexpected_keys:
        raise WeightsError(
            path,
            f"weights do not fit {name}: {len(result.missing_keys)} missing tensor(s) "
            f"(e.g. {result.missing_keys[:3]}), {len(result.unexpected_keys)} unexpected "
            f"(e.g. {result.unexpected_keys[:3]})",
        )


def create(
    name: str,
    weights: str | Path | None = None,
    *,
    object_name: str | None = None,
    **kwargs: Any,
) -> nn.Module:
    """Build the registered model ``name``, optionally with weights.

    Args:
        name: a name from :func:`evtrack.models.list_models`.
        weights: ``None`` (random initialisation), ``"default"`` (the shipped weights for
            ``name``, and ``object_name`` if given) or a path to a weights file or an
            ``evtrack train`` checkpoint.
        object_name: when given with weights, the object they must have been trained on.
        **kwargs: hyper-parameter overrides; with weights they must agree with the record.

    Returns:
        The network in eval mode when weights were loaded, train mode otherwise.

    Raises:
        ConfigError: unknown model name or hyper-parameter.
        WeightsError: unreadable weights, or weights of another architecture, another object,
            or other hyper-parameters.
    """
    if weights is None:
        return _build(name, kwargs)
    model_entrypoint(name)  # unknown names fail before any file is read
    path = find_default_weights(name, object_name) if weights == "default" else Path(weights)
    record, state = load_weights_file(path)
    if record.arch != name:
        raise WeightsError(path, f"holds weights of architecture {record.arch!r}, not {name!r}")
    if object_name is not None and record.object_name != object_name:
        raise WeightsError(
            path, f"holds weights for object {record.object_name!r}, not {object_name!r}"
        )
    merged = {**record.arch_kwargs, **kwargs}
    net = _build(name, merged)
    if kwargs:
        reference = _build(name, dict(record.arch_kwargs))
        if _config_of(reference) != _config_of(net):
            raise WeightsError(
                path, f"hyper-parameters {kwargs} differ from those of the weights "
                      f"({record.arch_kwargs or 'defaults'})"
            )
    _load_into(net, state, path, name)
    net.weights_record = record
    return net.eval()


def load_model(
    path: str | Path, *, arch: str | None = None, object_name: str | None = None
) -> tuple[nn.Module, WeightsRecord]:
    """Build the network a weights file describes and load it.

    Args:
        path: weights file or ``evtrack train`` checkpoint.
        arch: when given, the architecture the file must hold.
        object_name: when given, the object the file must have been trained on.

    Returns:
        ``(net in eval mode, record)``.
    """
    record, _ = load_weights_file(path)
    net = create(arch or record.arch, weights=path, object_name=object_name)
    return net, record
