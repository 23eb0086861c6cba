"""The ``pose`` baseline's motion source: none. The pose filter (``pose_only_ukf``, random-walk
process noise) runs on the poses alone."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.filters import PoseUKF
from evtrack.tracking.motion.base import MotionContext, MotionSource
from evtrack.tracking.silhouette import SilhouettePolygon

__all__ = ["PoseOnlyMotion"]


class PoseOnlyMotion(MotionSource):
    """No motion measurement: a zero twist every step (``method: pose``)."""

    def __init__(self, context: MotionContext) -> None:
        super().__init__(context)
        self._zero_twist = torch.zeros(1, 6, dtype=torch.float64, device=self.device)

    def pose_filter(self) -> PoseUKF:
        return PoseUKF(1, self.config.pose_only_ukf, device=self.device)

    def step(self, k: int, dt: float, pose: np.ndarray | None,
             poly: SilhouettePolygon | None, usable: bool) -> Tensor:
        return self._zero_twist
