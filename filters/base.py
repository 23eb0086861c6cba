"""What the filters share: a batch of tracks, checked time steps and inputs, saved state of
another batch size, and the choice of the backend that runs each stateful call.

A filter's ``backend`` attribute names its preferred backend (:mod:`backends`: ``"auto"``,
``"torch"``, ``"numpy"``, ``"numba"``); each stateful call asks :meth:`TrackFilter._single_track`
whether a single-track backend runs it or the filter's torch steps do.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from evtrack.filters.backend_base import FilterBackend
from evtrack.filters.backends import AUTO, TORCH, check_backend_name, resolve_backend
from evtrack.filters.compiled import CompilableSteps

__all__ = ["TrackFilter", "check_dt", "checked"]


class TrackFilter(CompilableSteps, nn.Module):
    """Base of the filters: B tracks whose state lives in buffers (first dimension B).

    Subclasses set :attr:`_STATE`, the names of the three state buffers a single-track backend
    reads (the first one's leading dimension is B), and call :meth:`_init_backend` in
    ``__init__``.
    """

    _STATE: ClassVar[tuple[str, ...]]
    backend: str

    def _init_backend(self, backend: str, fast_path: bool) -> None:
        """Set the preferred backend: ``backend`` (``"auto"`` or a registered name), or the
        torch steps where ``fast_path`` is False."""
        self.backend = check_backend_name(backend) if fast_path else TORCH

    @property
    def fast_path(self) -> bool:
        """Whether a single-track backend may run this filter's calls (``backend`` is not
        ``"torch"``); setting True restores ``"auto"`` where it was ``"torch"``."""
        return self.backend != TORCH

    @fast_path.setter
    def fast_path(self, enabled: bool) -> None:
        if not enabled:
            self.backend = TORCH
        elif self.backend == TORCH:
            self.backend = AUTO

    @property
    def batch_size(self) -> int:
        """Number of tracks B."""
        return self._buffers[self._STATE[0]].shape[0]

    def _single_track_allowed(self) -> bool:
        """Whether this filter's configuration has single-track forms at all."""
        return True

    def _single_track(self, inputs: tuple[object, ...]) -> FilterBackend | None:
        """The single-track backend that runs a stateful call with ``inputs``, or ``None``: the
        torch steps (another preference, compiled steps, a batch, another dtype or device,
        gradients, tracing; see :func:`~evtrack.filters.backends.resolve_backend`)."""
        preference = self.backend
        if (preference == TORCH or self.__dict__.get("_compiled_steps")
                or not self._single_track_allowed()):
            return None
        buf = self._buffers
        first, second, third = self._STATE
        return resolve_backend(preference, buf[first], (buf[second], buf[third], *inputs))

    def _dt(self, dt: float | Tensor) -> Tensor:
        """``dt`` (seconds, a float or (B,)) as a (B,) tensor of the state's dtype and device;
        raises ``ValueError`` for another shape, or a negative or non-finite step."""
        state = self._buffers[self._STATE[0]]
        d = torch.as_tensor(dt, dtype=state.dtype, device=state.device)
        check_dt(d)
        B = state.shape[0]
        if d.ndim == 0:
            return d.expand(B)
        if tuple(d.shape) != (B,):
            raise ValueError(
                f"{type(self).__name__}: dt must be a float or ({B},), got {tuple(d.shape)}"
            )
        return d

    def _single_dt(self, dt: float | Tensor) -> float:
        """``dt`` of one track as a float of seconds, checked as :meth:`_dt` does."""
        if isinstance(dt, Tensor) and dt.ndim > 0:
            self._dt(dt)  # raises unless (B,)
        value = float(dt)
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0, got {value}")
        return value

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):  # noqa: ANN001 - torch's signature
        # A saved filter may hold another number of tracks: take the saved batch size.
        key = prefix + self._STATE[0]
        if key in state_dict and state_dict[key].shape[0] != self.batch_size:
            self.reset(state_dict[key].shape[0])  # type: ignore[attr-defined]
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )


def check_dt(d: Tensor) -> None:
    """Raise ``ValueError`` unless the time step ``d`` (seconds, a scalar or (B,) tensor) is
    finite and >= 0; only on CPU (on a GPU the check would wait for the device)."""
    if d.is_cpu and d.numel() and not bool((torch.isfinite(d) & (d >= 0)).all()):
        raise ValueError(f"dt must be finite seconds >= 0, got {d.tolist()}")


def checked(
    t: Tensor, shape: tuple[int, ...], name: str, kw: dict[str, Any], copy: bool = True
) -> Tensor:
    """``t`` (a tensor, or anything :func:`torch.as_tensor` takes) moved to ``kw`` (dtype,
    device) and copied unless ``copy`` is False; raises ``ValueError`` unless its shape is
    ``shape``."""
    if not isinstance(t, Tensor):
        t = torch.as_tensor(t)
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    t = t.to(**kw)
    return t.clone() if copy else t
