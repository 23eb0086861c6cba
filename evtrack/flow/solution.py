"""What every registration backend's per-group solve returns (:class:`GroupSolution`)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["GroupSolution"]


@dataclass
class GroupSolution:
    """Eq. 3 and the constraint-line fit of G groups, before the aperture test (see
    :mod:`evtrack.flow.registration`).

    Attributes:
        has: (G,) bool, the group has candidates.
        full: (G, 2) float32 arg-min candidate F in px/s (NaN without one).
        best_cost: (G,) int64 cost of F, in 1 / ``COST_SCALE`` px/s summed over the events.
        used_events: (G,) int64 events in the data term (after the cap).
        inliers: (G,) int64 events of the data term that agree with F.
        lines: (G,) int64 events that gave a constraint line.
        fit_flow: (G, 2) float32 IRLS intersection of the lines in px/s (F where it was not
            solvable).
        ratio: (G,) float64 eigenvalue ratio ``l_min / l_max`` of the lines' scatter (1 when
            undefined).
        major: (G, 2) float32 unit eigenvector of ``l_max`` (the dominant normal).
        normal_speed: (G,) float32 the lines' speed along ``major`` in px/s.
    """

    has: Tensor
    full: Tensor
    best_cost: Tensor
    used_events: Tensor
    inliers: Tensor
    lines: Tensor
    fit_flow: Tensor
    ratio: Tensor
    major: Tensor
    normal_speed: Tensor
