"""Which registered RoI windows are reported, by their constraint lines (tensor code).

A RoI window's events give constraint lines (see :mod:`evtrack.flow.registration`) when their
candidates near the registered flow come from two non-parallel displacements. Without any, the
flow is one event's candidate that no other displacement confirms; with one, only the flow
across that line is measured. The rules (:class:`~evtrack.flow.config.FlowConfig`):

* ``min_lines``: a RoI window with fewer lines is refused;
* ``max_lineless_share``: a time window where more than this share of the RoI windows that pass
  the other report rules have no line is judged strictly: its line-less RoI windows are refused
  and its one-line RoI windows report their line's normal flow.

The compiled CPU report (:func:`evtrack.flow.registration_compiled._report_rows`) applies the
same rules in its own loop.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from evtrack.flow.registration import Registration

__all__ = ["line_report", "one_line_normal"]


def line_report(window: Tensor, passing: Tensor, lines: Tensor, min_lines: int,
                max_lineless_share: float) -> tuple[Tensor, Tensor]:
    """The reported RoI windows and those judged strictly.

    Args:
        window: (G,) int64 time window of each registered group, non-decreasing.
        passing: (G,) bool groups that pass the other report rules (support, consensus, a
            flow).
        lines: (G,) int64 constraint lines of each group.
        min_lines: the fewest lines of a reported group.
        max_lineless_share: above this share of line-less groups among a time window's
            passing ones, the window is judged strictly.

    Returns:
        ``(reported (G,) bool, strict (G,) bool)``: ``strict`` marks the groups of strictly
        judged time windows (their one-line groups report normal flow).
    """
    if window.numel() == 0 or max_lineless_share >= 1.0:
        strict = torch.zeros_like(passing)
    else:
        _, inverse = torch.unique_consecutive(window, return_inverse=True)
        n_windows = int(inverse.max()) + 1
        counts = torch.zeros(n_windows, dtype=torch.float64, device=window.device)
        lineless = torch.zeros_like(counts)
        counts.index_add_(0, inverse, passing.to(torch.float64))
        lineless.index_add_(0, inverse, (passing & (lines == 0)).to(torch.float64))
        strict = (lineless > float(max_lineless_share) * counts)[inverse]
    reported = passing & (lines >= min_lines) & ~(strict & (lines == 0))
    return reported, strict


def one_line_normal(reg: Registration, mask: Tensor) -> Registration:
    """``reg`` with the groups of ``mask`` (G,) bool, each with one constraint line, reported
    as that line's normal flow (a single line's eigenvalue ratio is 0: the aperture case)."""
    if not bool(mask.any()):
        return reg
    m = mask[:, None]
    return dataclasses.replace(
        reg, flow=torch.where(m, reg.line_flow, reg.flow), normal=reg.normal | mask,
        normal_dir=torch.where(m, reg.line_normal, reg.normal_dir),
        ratio=torch.where(mask, torch.zeros_like(reg.ratio), reg.ratio))
