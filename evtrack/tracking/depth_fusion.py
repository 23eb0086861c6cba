"""The RGB-D extensions (not in the paper): measurements of the pose from each sensor depth
frame, fused by the pose filter at the frame's time.

* ``depth_fusion.range``: the object's range along its viewing ray against the mesh's surface at the
  filter's pose of the frame's time (:mod:`evtrack.tracking.depth_range`; no renderer), a 1-D
  measurement (:meth:`~evtrack.filters.PoseUKF.update_range`); frames without one are counted
  by reason in ``depth_ranges_skipped``.
* ``depth_fusion.icp``: the mesh aligned with the depth frame from the filter's pose of the frame's
  time (:class:`~evtrack.models.DepthRefiner`), the aligned pose fused with the fit's
  covariance, at most ``depth_fusion.icp_rate_hz``; refused fits are counted by reason in
  ``depth_alignments_skipped``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.filters.lie import pivot_map

# evtrack.models is imported with this module, not where depth_icp is set up: it imports
# torch's flop counter, which imports Triton where installed (CUDA builds of torch), and
# Triton's LLVM crashes the process when Mesa's (the headless OpenGL of model depth) is
# already loaded.
from evtrack.models.depth_refine import DepthRefineConfig, DepthRefiner
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_range import DepthRange
from evtrack.tracking.inputs import DepthFrame
from evtrack.tracking.observability import RotationObservability
from evtrack.tracking.occlusion import Occluders
from evtrack.tracking.pose_timeline import PoseTimeline, pose_measurement_value
from evtrack.tracking.stats import StageTimer, TrackerStats, count_reason

__all__ = ["DepthFusion", "alignment_covariance"]


def alignment_covariance(res: Any, std_m: float, std_rad: float, radius_m: float = 0.0,
                         min_share: float = 0.0) -> np.ndarray:
    """(6, 6) tangent covariance ``[δt, δθ]`` (m², rad²; the pose filter's left perturbation
    about the object's origin) of a depth alignment (:class:`~evtrack.models.RefineResult`):
    the fit's ``rmse² · information⁻¹`` for its motion ``[δv, δω]`` about ``res.centre``, carried
    to the origin ``t`` (``δv = δt + (t − c) × δθ``), plus the floors ``std_m²``, ``std_rad²``.

    Directions the depth barely saw count as unseen: in the information measured in metres of
    surface motion (rotations times ``radius_m``, the object's radius), each eigen-direction
    below ``min_share`` of the best-seen one, and every direction below 1e-9 of it, gets a
    variance that large rather than a finite, overconfident one. A can's spin about its axis is
    such a direction: on the simulator's tomato soup can the fit claimed 0.4-0.75° about the
    axis (0.04-0.1° about the others) while leaving a 5° turn about it at 7°."""
    M = pivot_map(torch.from_numpy(res.pose[:3, 3] - res.centre)).numpy()
    info = M.T @ res.information @ M
    scale = np.r_[np.ones(3), np.full(3, radius_m if radius_m > 0 else 1.0)]
    info_s = info / np.outer(scale, scale)  # per metre of surface motion
    w, V = np.linalg.eigh(0.5 * (info_s + info_s.T))
    top = max(float(w.max()), 1e-30)
    w = np.where(w < max(min_share, 1e-9) * top, 1e-9 * top, w)
    cov = (V / w) @ V.T / np.outer(scale, scale) * max(res.rmse_m, 1e-6) ** 2
    return cov + np.diag([std_m ** 2] * 3 + [std_rad ** 2] * 3)


class DepthFusion:
    """Range and alignment measurements from sensor depth frames.

    Args:
        config: the tracker's config (``depth_range*``, ``depth_icp*``).
        mesh: the object's :class:`~evtrack.sim.objects.ObjectMesh`.
        depth_camera: the camera of the depth frames.
        T_depth_event: (4, 4) event camera -> depth camera.
        timeline: the pose filter's timeline (the measurements are added at their times).
        past_pose: ``t_us -> (4, 4) or None``, the filter's pose at a kept past time.

    Attributes:
        stats: the counters it adds to.
        observability: the rotational information of the fused alignments (source
            ``"depth"``) is added to it.
    """

    def __init__(self, config: TrackerConfig, mesh: Any, depth_camera: PinholeCamera,
                 T_depth_event: np.ndarray, timeline: PoseTimeline,
                 past_pose: Callable[[int], np.ndarray | None]) -> None:
        self.config = config
        self.timeline = timeline
        self.past_pose = past_pose
        self.depth_camera = depth_camera
        self.occluders: Callable[[], Occluders] = Occluders
        """The nearer tracked objects whose pixels the alignment leaves out (set by the
        tracker; none by default)."""
        self.T_depth_event = T_depth_event
        self.T_event_depth = np.linalg.inv(T_depth_event)
        self.stats = TrackerStats()
        self.observability = RotationObservability()
        self.depth_range: DepthRange | None = None
        if config.depth_fusion.range:
            self.depth_range = DepthRange(mesh, depth_camera, std_m=config.depth_fusion.range_std_m)
        self.depth_icp: DepthRefiner | None = None
        if config.uses_depth_icp:
            self.depth_icp = DepthRefiner.from_mesh(mesh, DepthRefineConfig(
                model_points=config.depth_fusion.icp_points,
                max_scene_points=config.depth_fusion.icp_scene_points))
            self._K = depth_camera.K().numpy()
            self._dist = None if depth_camera.dist is None else depth_camera.dist.numpy()
        self.reset()

    def reset(self) -> None:
        """Forget the last alignment's time."""
        self.last_alignment_us: int | None = None

    def _value_kw(self) -> dict[str, Any]:
        ukf = self.timeline.filter
        return {"dtype": ukf.t.dtype, "device": ukf.t.device}

    def fuse_range(self, frame: DepthFrame) -> None:
        """Measure the object's range on a depth frame at the filter's pose of the frame's
        time and fuse it there."""
        if self.depth_range is None:
            return
        with StageTimer(self.stats.time_s, "depth_range"):
            T_ev = self.past_pose(frame.t_us)
            if T_ev is None:
                return
            T_d = self.T_depth_event @ T_ev
            res = self.depth_range.measure(frame.depth, T_d)
            if not res.ok:
                count_reason(self.stats.depth_ranges_skipped, res.reason)
                return
            # uᵀ t_d = d with t_d = R t_ev + p  <=>  (Rᵀ u)ᵀ t_ev = d - uᵀ p
            R, p = self.T_depth_event[:3, :3], self.T_depth_event[:3, 3]
            u_ev = R.T @ res.direction
            d_ev = res.distance - float(res.direction @ p)
            kw = self._value_kw()
            value = (torch.as_tensor(u_ev, **kw).reshape(1, 3), torch.tensor([d_ev], **kw))
            if self.timeline.add(frame.t_us, "range", value,
                                 torch.tensor([res.variance], **kw)):
                self.stats.depth_ranges += 1

    def fuse_alignment(self, frame: DepthFrame) -> None:
        """Align the mesh with a depth frame from the filter's pose of the frame's time and
        fuse the aligned pose there with the fit's covariance."""
        if self.depth_icp is None:
            return
        cfg = self.config
        period_us = 1e6 / cfg.depth_fusion.icp_rate_hz
        last = self.last_alignment_us
        if last is not None and 0 <= frame.t_us - last < 0.9 * period_us:
            return
        with StageTimer(self.stats.time_s, "depth_icp"):
            T_ev = self.past_pose(frame.t_us)
            if T_ev is None:
                return
            self.last_alignment_us = frame.t_us
            T_d = self.T_depth_event @ T_ev
            depth = frame.depth
            occluders = self.occluders()
            if occluders:  # the nearer objects' pixels hold their depth, not this object's
                hidden = occluders.mask(frame.t_us, self.depth_camera, self.T_depth_event)
                depth = np.where(hidden, np.nan, depth).astype(frame.depth.dtype, copy=False)
            res = self.depth_icp.refine(T_d, depth, self._K, self._dist)
            if not res.refined:
                count_reason(self.stats.depth_alignments_skipped, res.refusal)
                return
            cov_d = alignment_covariance(res, cfg.depth_fusion.icp_std_m,
                                         math.radians(cfg.depth_fusion.icp_std_deg),
                                         self.depth_icp.radius,
                                         cfg.icp_min_information)
            A = self.T_event_depth
            T_meas = A @ res.pose
            Ra = np.kron(np.eye(2), A[:3, :3])  # both tangent blocks rotate with the frame
            kw = self._value_kw()
            value = pose_measurement_value(torch.from_numpy(T_meas), kw["dtype"], kw["device"])
            cov = torch.as_tensor(Ra @ cov_d @ Ra.T, **kw).reshape(1, 6, 6)
            if self.timeline.add(frame.t_us, "aligned", value, cov):
                self.stats.depth_alignments += 1
                self.observability.add("depth", res.information, res.rmse_m ** 2,
                                       res.pose[:3, :3])
