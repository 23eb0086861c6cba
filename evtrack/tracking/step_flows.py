"""The RoI flows of one step group, split by velocity step."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.flow import FlowResult

__all__ = ["SEGMENT_STEPS", "StepFlows"]

SEGMENT_STEPS = 10
"""The filters take the pose, its silhouette and the velocity filter's pivot afresh every this
many velocity steps of a step group (its segments), whatever ``flow_batch_steps`` is: a group
of 40 steps makes one flow call but four segments. With the group's first pose for all of
its 40 steps, the coded box of ``evtrack demo`` (320x240, seeds 0-5) erred 6 % more in
position than with groups of 10."""


class StepFlows:
    """The RoI flows of one step group, split by velocity step.

    The rows are put in time order once (the flow reports its windows in time order; the sort
    is stable and costs nothing then), so each step's rows are one contiguous slice: views,
    not the per-step masks over every field of the result.

    Args:
        res: the group's flow result.
        t0: start of the group (µs). step: the velocity step (µs). n_steps: steps in the group.
        dtype, device: of the velocity filter's inputs.

    Attributes:
        uv: (N, 2) float64 RoI centres (px); flow: (N, 2) px/s; normal: (N,) bool normal-flow
            flags; support: (N,) events with candidates in each RoI window; bounds:
            (n_steps + 1,) step ``k``'s rows are ``bounds[k]:bounds[k + 1]``.
        depth_cache: kept by :meth:`evtrack.tracking.roi_depth.RoiDepth.run` (the depths of
            the group's remaining rows while the depth map and silhouette stay the same).
    """

    def __init__(self, res: FlowResult, t0: int, step: int, n_steps: int, dtype: torch.dtype,
                 device: torch.device) -> None:
        t = res.t.cpu().numpy()
        order = np.argsort(t, kind="stable")
        self.uv = res.xy.detach().cpu().numpy()[order].astype(np.float64)
        order_t = torch.from_numpy(order).to(res.flow.device)
        self.flow = res.flow[order_t].to(dtype=dtype, device=device)
        self.normal = res.normal[order_t].to(device)
        self.support = res.support.detach().cpu().numpy()[order]
        edges = t0 + step * np.arange(n_steps + 1, dtype=np.int64)
        self.bounds = np.searchsorted(t[order], edges, side="left")
        self.depth_cache: tuple[np.ndarray | None, int, np.ndarray, Any, Any] | None = None

    def step(self, k: int) -> tuple[np.ndarray, Tensor, Tensor]:
        """Step ``k``'s RoI centres (N, 2) float64 px, flows (N, 2) px/s and normal flags (N,)."""
        lo, hi = int(self.bounds[k]), int(self.bounds[k + 1])
        return self.uv[lo:hi], self.flow[lo:hi], self.normal[lo:hi]
