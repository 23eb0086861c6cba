"""Per-sample values along a trajectory: errors against ground truth and the object's pixel speed.

The pixel speed is the one of the benchmark's velocity CDF (:mod:`evtrack.sim.groundtruth`):
the mean image speed (px/s) of evenly picked mesh vertices moving with the ground-truth twist.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from evtrack.eval.metrics import position_errors, rotation_errors
from evtrack.tracking.trajectory import Trajectory

__all__ = ["SampleErrors", "sample_errors", "pixel_speed_at", "SPEED_VERTICES"]

SPEED_VERTICES = 256
"""Mesh vertices averaged for the pixel speed (the simulator's default ``velocity_samples``)."""


@dataclass
class SampleErrors:
    """Errors at the tracked samples of a trajectory.

    Attributes:
        t_us: (N,) int64 µs of the tracked samples.
        position_cm: (N,) float64 Euclidean position errors, centimetres.
        rotation_deg: (N,) float64 geodesic rotation errors, degrees.
    """

    t_us: np.ndarray
    position_cm: np.ndarray
    rotation_deg: np.ndarray


def sample_errors(trajectory: Trajectory, ground_truth) -> SampleErrors:
    """Errors of the tracked samples (status tracking, finite pose) against ground truth.

    Args:
        trajectory: the tracker's output.
        ground_truth: anything with ``pose_at(t_us (N,)) -> (N, 4, 4)``
            (:class:`~evtrack.sequence.GroundTruth`).
    """
    use = trajectory.tracked & torch.isfinite(trajectory.poses).flatten(1).all(1)
    t = trajectory.t_us[use]
    if t.numel() == 0:
        empty = np.zeros(0)
        return SampleErrors(np.zeros(0, np.int64), empty, empty.copy())
    est = trajectory.poses[use]
    true = torch.as_tensor(ground_truth.pose_at(t), dtype=torch.float64)
    return SampleErrors(t.numpy(), 100.0 * position_errors(est, true).numpy(),
                        np.rad2deg(rotation_errors(est, true).numpy()))


class _GroundTruthMotion:
    """A :class:`~evtrack.sequence.GroundTruth` seen through the simulator's trajectory
    interface (``pose(times_s)``, ``twist(times_s)``), as
    :func:`~evtrack.sim.groundtruth.pixel_speeds` reads it."""

    def __init__(self, ground_truth) -> None:
        self.gt = ground_truth

    @staticmethod
    def _us(times_s: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.round(np.asarray(times_s, np.float64) * 1e6).astype(np.int64))

    def pose(self, times_s: np.ndarray) -> np.ndarray:
        return self.gt.pose_at(self._us(times_s)).numpy()

    def twist(self, times_s: np.ndarray) -> np.ndarray:
        return self.gt.twist_at(self._us(times_s)).numpy()


def pixel_speed_at(t_us: np.ndarray, ground_truth, vertices: np.ndarray, camera,
                   count: int = SPEED_VERTICES) -> np.ndarray:
    """Mean pixel speed (px/s) of the object at times ``t_us`` (µs), from ground truth.

    Args:
        t_us: (N,) µs.
        ground_truth: a :class:`~evtrack.sequence.GroundTruth` (poses and twists).
        vertices: (V, 3) mesh vertices in the object frame, metres.
        camera: the event camera (:class:`~evtrack.PinholeCamera`; distortion ignored).
        count: vertices picked evenly from ``vertices``.

    Returns:
        (N,) float64 px/s.
    """
    from evtrack.sim.groundtruth import pixel_speeds

    t = np.asarray(t_us, np.int64).reshape(-1)
    if t.size == 0:
        return np.zeros(0)
    vertices = np.asarray(vertices, np.float64)
    idx = np.linspace(0, len(vertices) - 1, min(count, len(vertices))).astype(int)
    return pixel_speeds(_GroundTruthMotion(ground_truth), t * 1e-6, vertices[idx], camera)
