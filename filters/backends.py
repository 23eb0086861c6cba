"""The registry of the filters' backends and the one place that picks the backend of a call.

Backends, by name:

* ``"torch"``: the specification, the filters' own torch steps (any batch, device and dtype,
  gradients, ``torch.compile``, ONNX export);
* ``"numpy"``: one float64 CPU track in NumPy and Python floats (:mod:`fast_path`);
* ``"numba"``: the NumPy backend with its velocity update and pose predict compiled, and runs
  of many steps per call (:mod:`fast_compiled`).

A filter holds a preference (its ``backend`` attribute, ``"auto"`` by default) and asks
:func:`resolve_backend` at every stateful call which backend runs it: the preferred
single-track backend where the call is one float64 CPU track that needs no gradients and
nothing is being traced, exported or compiled, else the torch steps (``None``). ``"auto"``
means the process-wide default (:func:`set_default_backend`), itself ``"auto"`` unless set:
numba where it is installed, else NumPy; a named backend that cannot run here (numba
missing) falls back the same way.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor

from evtrack.filters.backend_base import FilterBackend
from evtrack.filters.fast_compiled import NumbaBackend
from evtrack.filters.fast_path import NumpyBackend
from evtrack.filters.linalg import use_portable

__all__ = [
    "AUTO",
    "TORCH",
    "applies",
    "as_array",
    "as_bool_array",
    "backend_names",
    "check_backend_name",
    "default_backend",
    "get_backend",
    "register_backend",
    "resolve_backend",
    "set_default_backend",
    "single_track_backends",
]

TORCH = "torch"
AUTO = "auto"

# Single-track backends by name, in the order "auto" tries them.
_REGISTRY: dict[str, FilterBackend] = {}
_DEFAULT = [AUTO]  # the process-wide preference that "auto" stands for


def register_backend(backend: FilterBackend) -> None:
    """Register a single-track backend under ``backend.name`` (``"auto"`` tries the backends in
    the order they were registered)."""
    if backend.name in (TORCH, AUTO):
        raise ValueError(f"backend name {backend.name!r} is reserved")
    _REGISTRY[backend.name] = backend


register_backend(NumbaBackend())
register_backend(NumpyBackend())


def backend_names() -> tuple[str, ...]:
    """The registered backends: ``"torch"`` (the specification) and the single-track ones."""
    return (TORCH, *_REGISTRY)


def single_track_backends() -> tuple[FilterBackend, ...]:
    """The registered single-track backends, available here or not, in registration order."""
    return tuple(_REGISTRY.values())


def check_backend_name(name: str) -> str:
    """``name`` if it is a registered backend or ``"auto"``; raises ``ValueError`` otherwise."""
    if name != AUTO and name not in backend_names():
        raise ValueError(f"unknown filter backend {name!r}; one of {(AUTO, *backend_names())}")
    return name


def set_default_backend(name: str) -> None:
    """Set the backend that ``"auto"`` stands for in this process (``"auto"``: numba where it is
    installed, else NumPy)."""
    _DEFAULT[0] = check_backend_name(name)


def default_backend() -> str:
    """The backend that ``"auto"`` stands for in this process (see :func:`set_default_backend`)."""
    return _DEFAULT[0]


def get_backend(name: str) -> FilterBackend | None:
    """The single-track backend that runs for the preference ``name`` (``"auto"``, or a named
    backend that cannot run here: the first registered one that can), or ``None`` for the
    torch steps."""
    if name == AUTO:
        name = _DEFAULT[0]
    backend = _REGISTRY.get(name)
    if backend is not None and backend.available():
        return backend
    if name == TORCH:
        return None
    for backend in _REGISTRY.values():  # "auto", or a backend missing here
        if backend.available():
            return backend
    return None


def resolve_backend(
    preference: str, state: Tensor, others: Iterable[object]
) -> FilterBackend | None:
    """The backend that runs a filter's stateful call.

    Args:
        preference: the filter's backend name (``"auto"``, ``"torch"`` or a registered one).
        state: the filter's first state tensor (B, ...).
        others: its other state tensors and the call's inputs.

    Returns:
        The single-track backend for ``preference`` (see :func:`get_backend`) where
        :func:`applies`, else ``None``: the filter's torch steps run.
    """
    if preference == TORCH or not applies(state, others):
        return None
    return get_backend(preference)


def applies(state: Tensor, others: Iterable[object]) -> bool:
    """Whether a stateful call may run on a single-track backend.

    Args:
        state: the filter's first state tensor (B, ...).
        others: its other state tensors and the call's inputs.

    Returns:
        True when ``state`` is one track (B = 1) of float64 on CPU, every other entry is a
        tensor, a number or ``None`` (anything else goes to the torch steps, which report it),
        none needs gradients, and nothing is being exported, traced or compiled.
    """
    if state.shape[0] != 1 or state.dtype is not torch.float64 or not state.is_cpu:
        return False
    if use_portable() or torch.compiler.is_compiling():
        return False
    grad = torch.is_grad_enabled()
    if grad and state.requires_grad:
        return False
    for x in others:
        if isinstance(x, Tensor):
            if grad and x.requires_grad:
                return False
        elif x is not None and not isinstance(x, float | int):
            return False
    return True


def as_array(x: Tensor) -> np.ndarray:
    """A CPU float64 NumPy view (or copy, for another dtype or device) of a tensor."""
    if x.dtype is not torch.float64 or not x.is_cpu:
        x = x.to(dtype=torch.float64, device="cpu")
    return (x.detach() if x.requires_grad else x).numpy()


def as_bool_array(x: Tensor) -> np.ndarray:
    """A CPU NumPy view (or copy) of a bool tensor."""
    if not x.is_cpu:
        x = x.cpu()
    return (x.detach() if x.requires_grad else x).numpy()
