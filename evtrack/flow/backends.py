"""The flow's backends: what a candidate search and a registration provide, and
:func:`resolve`, the one place that chooses them for a config and a device.

``FlowConfig.backend`` and the device choose (search / registration, the backend's name):

* ``"torch"``, any device: tensors / tensors (``torch``);
* ``"auto"`` on CPU: numba / numba (``compiled``) where numba is installed, else ``torch``;
* ``"auto"`` on CUDA: tensors / Triton (``triton``) where Triton is installed, else
  ``torch``; on other devices ``torch``;
* ``"compiled"``: ``compiled`` on CPU, ``triton`` on CUDA, an error where that cannot run
  (without numba, without Triton, or on another device).

All give the same candidates and the same RoIs with the same Eq. 3 solutions, costs and
inlier counts, bit for bit; the refined flows agree to float rounding.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from evtrack.errors import ConfigError
from evtrack.flow import numba_support, registration_triton
from evtrack.flow.candidates import Candidates, CandidateSearch
from evtrack.flow.compiled import CompiledSearch
from evtrack.flow.config import FlowConfig
from evtrack.flow.registration_compiled import CompiledRegistration
from evtrack.flow.registration_tensor import TensorRegistration
from evtrack.flow.registration_triton import TritonRegistration
from evtrack.flow.solution import GroupSolution

__all__ = ["CandidateSearchBackend", "RegistrationBackend", "FlowBackend", "resolve"]


class CandidateSearchBackend(Protocol):
    """What a candidate search provides (:class:`~evtrack.flow.candidates.CandidateSearch`,
    :class:`~evtrack.flow.compiled.CompiledSearch`).

    Attributes:
        device: where its state lives.
        next_seq: the stream index of the next event (events seen since the last reset).
        runs_ahead: whether a caller may search the next batch in a worker thread while it
            registers the current one (the search releases the GIL).
    """

    device: torch.device
    next_seq: int
    runs_ahead: bool

    def __call__(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor,
                 search: Tensor | None = None) -> Candidates:
        """The candidates of the next events of the stream ((n,) pixel coordinates, int64 µs
        timestamps, polarities, optional (n,) bool of the events searched); they enter the
        history."""

    def reset(self) -> None:
        """Forget every event seen."""

    def continue_bursts(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor) -> None:
        """Make each given event (one per pixel) the continuation of a burst."""

    def moved(self, config: FlowConfig, device: torch.device) -> CandidateSearchBackend | None:
        """This search with its state on ``device``, or None where the state cannot move
        (the caller then starts a fresh search, if no event was seen yet)."""


class RegistrationBackend(Protocol):
    """What a registration backend provides
    (:class:`~evtrack.flow.registration_tensor.TensorRegistration`,
    :class:`~evtrack.flow.registration_compiled.CompiledRegistration`,
    :class:`~evtrack.flow.registration_triton.TritonRegistration`).

    Attributes:
        reports_rows: whether it also has ``register_closed(...)``, which registers a flow's
            closed windows and makes their reported rows in one compiled call (see
            :meth:`CompiledRegistration.register_closed
            <evtrack.flow.registration_compiled.CompiledRegistration.register_closed>`).
    """

    reports_rows: bool

    def solve(self, group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
              max_events: int, max_hypotheses: int, pair_budget: int, line_gate: float,
              refine_iters: int, n_ordinals: int) -> GroupSolution:
        """The caps, Eq. 3 and the line fit of ``g_count`` groups (arguments as
        :func:`evtrack.flow.registration.register_groups`)."""


@dataclass(frozen=True)
class FlowBackend:
    """The backend :func:`resolve` chose.

    Attributes:
        name: ``"torch"`` (tensors), ``"compiled"`` (numba, CPU) or ``"triton"`` (tensor
            search, Triton registration; CUDA).
        search: makes the candidate search, ``search(config, device)``.
        registration: solves the registration's groups.
    """

    name: str
    search: Callable[[FlowConfig, torch.device], CandidateSearchBackend]
    registration: RegistrationBackend


_TORCH = FlowBackend("torch", CandidateSearch, TensorRegistration())
_COMPILED = FlowBackend("compiled", CompiledSearch, CompiledRegistration())
_TRITON = FlowBackend("triton", CandidateSearch, TritonRegistration())


def resolve(config: FlowConfig, device: torch.device | str) -> FlowBackend:
    """The backend of a flow with ``config`` on ``device`` (the table of the module
    docstring).

    Raises:
        ConfigError: ``backend="compiled"`` where it cannot run: on a device other than CPU
            and CUDA, on CPU without numba, on CUDA without Triton.
    """
    device_type = torch.device(device).type
    wanted = config.backend
    if wanted == "compiled" and device_type not in ("cpu", "cuda"):
        raise ConfigError(f"flow config field 'backend': 'compiled' runs on CPU (numba) "
                          f"and CUDA (Triton), not {device_type}; use 'auto' or 'torch'")
    if wanted == "torch":
        return _TORCH
    if device_type == "cuda":
        if registration_triton.available(device_type):
            return _TRITON
        if wanted == "compiled":
            raise ConfigError("flow config field 'backend': 'compiled' on CUDA needs triton "
                              "(it comes with PyTorch's CUDA builds); use 'auto' or 'torch'")
        return _TORCH
    if device_type != "cpu":
        return _TORCH
    if numba_support.available():
        return _COMPILED
    if wanted == "compiled":
        raise ConfigError("flow config field 'backend': 'compiled' needs numba "
                          "(pip install numba); use 'auto' or 'torch'")
    return _TORCH
