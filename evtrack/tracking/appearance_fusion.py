"""Poses from the RGB frames and the textured mesh (``appearance``, part of ``pose_source:
model``): the mesh rendered at the filter's pose of a frame's time, the frame aligned with the
render (:class:`~evtrack.models.AppearanceRefiner`), the aligned pose fused there with the
fit's covariance (:meth:`~evtrack.filters.PoseUKF.update_aligned`), at most
``appearance.rate_hz``; refused fits are counted by reason in
``TrackerStats.appearance_alignments_skipped``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.models.appearance_refine import AppearanceRefineConfig, AppearanceRefiner
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.inputs import RgbFrame
from evtrack.tracking.observability import RotationObservability
from evtrack.tracking.occlusion import Occluders
from evtrack.tracking.pose_timeline import PoseTimeline, pose_measurement_value
from evtrack.tracking.stats import StageTimer, TrackerStats, count_reason

__all__ = ["AppearanceFusion", "fit_covariance"]


def fit_covariance(information: np.ndarray, variance: float, scale: float, std_m: float,
                   std_rad: float) -> np.ndarray:
    """(6, 6) tangent covariance ``[δt, δθ]`` (m², rad²) of a least-squares fit:
    ``scale · variance · information⁻¹`` plus the floors ``std_m²``, ``std_rad²``. The
    information is regularised by 1e-9 of its largest eigenvalue, so a direction the fit did
    not see gets a variance that large rather than an infinite one."""
    w, V = np.linalg.eigh(0.5 * (information + information.T))
    w = np.maximum(w, 1e-9 * max(float(w.max()), 1e-30))
    cov = (V / w) @ V.T * (scale * max(variance, 1e-12))
    return cov + np.diag([std_m ** 2] * 3 + [std_rad ** 2] * 3)


class AppearanceFusion:
    """Appearance measurements from RGB frames.

    Args:
        config: the tracker's config (``appearance``).
        mesh: the object's textured :class:`~evtrack.sim.objects.ObjectMesh`.
        rgb_camera: the camera of the RGB frames.
        T_event_rgb: (4, 4) RGB camera -> event camera.
        timeline: the pose filter's timeline (the measurements are added at their times).
        past_pose: ``t_us -> (4, 4) or None``, the filter's pose at a kept past time.
        refiner: the aligner (default: an :class:`~evtrack.models.AppearanceRefiner` of the
            mesh and camera with ``config.appearance``'s settings).

    Attributes:
        stats: the counters it adds to.
        observability: the rotational information of the fused alignments (source
            ``"appearance"``) is added to it.
    """

    def __init__(self, config: TrackerConfig, mesh: Any, rgb_camera: PinholeCamera,
                 T_event_rgb: np.ndarray, timeline: PoseTimeline,
                 past_pose: Callable[[int], np.ndarray | None],
                 refiner: AppearanceRefiner | None = None) -> None:
        self.config = config
        self.timeline = timeline
        self.past_pose = past_pose
        self.rgb_camera = rgb_camera
        self.occluders: Callable[[], Occluders] = Occluders
        """The nearer tracked objects whose pixels the alignment leaves out (set by the
        tracker; none by default)."""
        self.T_event_rgb = np.asarray(T_event_rgb, np.float64)
        self.T_rgb_event = np.linalg.inv(self.T_event_rgb)
        a = config.appearance
        self.refiner = refiner or AppearanceRefiner(mesh, rgb_camera, AppearanceRefineConfig(
            levels=tuple(a.levels), iterations=a.iterations, max_pixels=a.max_pixels,
            min_correlation=a.min_correlation, max_rotation_deg=a.max_rotation_deg,
            max_translation_m=a.max_translation_m))
        self.stats = TrackerStats()
        self.observability = RotationObservability()
        self.reset()

    def reset(self) -> None:
        """Forget the last alignment's time."""
        self.last_alignment_us: int | None = None

    def due(self, t_us: int) -> bool:
        """Whether a frame at ``t_us`` is to be aligned (``appearance.rate_hz``)."""
        last = self.last_alignment_us
        period_us = 1e6 / self.config.appearance.rate_hz
        return last is None or not 0 <= t_us - last < 0.9 * period_us

    def fuse(self, frame: RgbFrame) -> None:
        """Align the mesh's render with an RGB frame from the filter's pose of the frame's time
        and fuse the aligned pose there with the fit's covariance."""
        if not self.due(frame.t_us):
            return
        a = self.config.appearance
        with StageTimer(self.stats.time_s, "appearance"):
            T_ev = self.past_pose(frame.t_us)
            if T_ev is None:
                return
            self.last_alignment_us = frame.t_us
            occluders = self.occluders()
            hidden = (occluders.mask(frame.t_us, self.rgb_camera, self.T_rgb_event)
                      if occluders else None)
            res = self.refiner.refine(self.T_rgb_event @ T_ev, frame.image(), ignore=hidden)
            if not res.refined:
                count_reason(self.stats.appearance_alignments_skipped, res.refusal)
                return
            cov_rgb = fit_covariance(res.information, res.residual_std ** 2, a.cov_scale,
                                     a.std_m, math.radians(a.std_deg))
            A = self.T_event_rgb
            Ra = np.kron(np.eye(2), A[:3, :3])  # both tangent blocks rotate with the frame
            ukf = self.timeline.filter
            kw = {"dtype": ukf.t.dtype, "device": ukf.t.device}
            value = pose_measurement_value(torch.from_numpy(A @ res.pose), kw["dtype"],
                                           kw["device"])
            cov = torch.as_tensor(Ra @ cov_rgb @ Ra.T, **kw).reshape(1, 6, 6)
            if self.timeline.add(frame.t_us, "aligned", value, cov):
                self.stats.appearance_alignments += 1
                self.observability.add("appearance", res.information, res.residual_std ** 2,
                                       res.pose[:3, :3])
