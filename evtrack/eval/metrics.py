"""Tracking accuracy against ground truth, as in the method paper's tables.

* Position error: the Euclidean distance between the estimated and the true translation of the
  object-to-camera pose, reported in centimetres.
* Rotation error: the geodesic angle of ``R_trueᵀ R_est`` (the angle of the rotation vector of
  the relative rotation), reported in degrees.

Each table entry is the root mean square of the per-sample errors, with σ the (population)
standard deviation of the same per-sample errors, over the trajectory samples where the
tracker was tracking (status 1) — the samples before the first pose, or while the object was
lost, carry no estimate and are reported separately as the tracked fraction.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from evtrack.tracking.trajectory import Trajectory

__all__ = [
    "position_errors",
    "rotation_errors",
    "TrackingErrors",
    "error_summary",
    "tracking_errors",
]


def position_errors(T_est: Tensor, T_true: Tensor) -> Tensor:
    """(N, 4, 4), (N, 4, 4) -> (N,) Euclidean translation errors in metres."""
    return torch.linalg.vector_norm(T_est[..., :3, 3] - T_true[..., :3, 3], dim=-1)


def rotation_errors(T_est: Tensor, T_true: Tensor) -> Tensor:
    """(N, 4, 4), (N, 4, 4) -> (N,) geodesic rotation errors in radians, in [0, π].

    ``θ = atan2(|axis part|, (tr - 1) / 2)`` of ``R_trueᵀ R_est``: accurate near 0 and π,
    unlike ``arccos`` of the trace.
    """
    R = T_true[..., :3, :3].transpose(-1, -2) @ T_est[..., :3, :3]
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    axis = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = torch.linalg.vector_norm(axis, dim=-1) / 2.0
    return torch.atan2(sin, cos)


@dataclass
class TrackingErrors:
    """RMSE and σ of the position (cm) and rotation (deg) errors.

    Attributes:
        position_rmse_cm, position_std_cm: over the tracked samples.
        rotation_rmse_deg, rotation_std_deg: over the tracked samples.
        samples: tracked samples used; total: all samples of the trajectory.
    """

    position_rmse_cm: float
    position_std_cm: float
    rotation_rmse_deg: float
    rotation_std_deg: float
    samples: int
    total: int

    @property
    def tracked_fraction(self) -> float:
        return self.samples / self.total if self.total else 0.0

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    def __str__(self) -> str:
        return (f"{self.position_rmse_cm:.2f}({self.position_std_cm:.2f}) cm  "
                f"{self.rotation_rmse_deg:.2f}({self.rotation_std_deg:.2f}) deg  "
                f"[{self.samples}/{self.total} samples]")


def error_summary(position_m: Tensor, rotation_rad: Tensor, total: int | None = None
                  ) -> TrackingErrors:
    """RMSE and σ of per-sample errors (metres, radians) in the paper's units (cm, deg)."""
    p = position_m.to(torch.float64) * 100.0
    r = torch.rad2deg(rotation_rad.to(torch.float64))
    n = int(p.numel())
    if n == 0:
        nan = float("nan")
        return TrackingErrors(nan, nan, nan, nan, 0, int(total or 0))

    def rms(x: Tensor) -> float:
        return float(torch.sqrt(torch.mean(x * x)))

    return TrackingErrors(rms(p), float(p.std(unbiased=False)), rms(r),
                          float(r.std(unbiased=False)), n, int(total if total is not None else n))


def tracking_errors(trajectory: Trajectory, ground_truth, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> TrackingErrors:
    """Errors of a trajectory against ground truth at the trajectory's own times.

    Args:
        trajectory: the tracker's output.
        ground_truth: a :class:`~evtrack.sequence.GroundTruth` (``pose_at`` interpolates it on
            SE(3)) or any object with ``pose_at(t_us (N,)) -> (N, 4, 4)``.
        t_start_us, t_end_us: restrict to samples in ``[t_start_us, t_end_us]``.

    Returns:
        :class:`TrackingErrors` over the tracked samples of the window.
    """
    t = trajectory.t_us
    window = torch.ones_like(t, dtype=torch.bool)
    if t_start_us is not None:
        window &= t >= int(t_start_us)
    if t_end_us is not None:
        window &= t <= int(t_end_us)
    use = window & trajectory.tracked & torch.isfinite(trajectory.poses).flatten(1).all(1)
    total = int(window.sum())
    if not bool(use.any()):
        return error_summary(torch.zeros(0), torch.zeros(0), total)
    est = trajectory.poses[use]
    true = torch.as_tensor(ground_truth.pose_at(t[use]), dtype=torch.float64)
    return error_summary(position_errors(est, true), rotation_errors(est, true), total)
