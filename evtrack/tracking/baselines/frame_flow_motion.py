"""The ``frame-flow`` baseline's motion source (ROFT-like): dense optical flow between
consecutive RGB frames (:mod:`evtrack.tracking.baselines.frame_flow`) -> a twist per frame pair
(``frame_flow_kf``) -> twist measurement of a constant-velocity pose UKF
(:class:`~evtrack.filters.PoseTwistUKF`), which is predicted every step and fused with the
poses.

While no pose has started the track, frame pairs are kept for ``history_ms`` (with the depth
frame of their time): the pose that starts it arrives ``pose_latency_ms`` after its frame was
taken, and the pairs since that frame are measured then, each at the pose the timeline gives
for its time, as the event flow carries a late first pose to the present in the full method.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.filters import PoseTwistUKF, VelocityKF
from evtrack.tracking.baselines.frame_flow import DenseFlow, grid_in_polygon, twist_adjoint
from evtrack.tracking.inputs import TwistMeasurement
from evtrack.tracking.motion.base import MotionContext, MotionSource
from evtrack.tracking.silhouette import Silhouette

__all__ = ["FrameFlowMotion"]


class FrameFlowMotion(MotionSource):
    """Dense RGB flow -> twist measurements of the pose filter (``method: frame-flow``).

    Attributes:
        rgb_silhouette: the object's silhouette in the RGB camera.
    """

    uses_rgb = True

    def __init__(self, context: MotionContext) -> None:
        super().__init__(context)
        cfg = self.config
        self.rgb_silhouette = Silhouette(context.vertices, context.rgb_camera)
        self.T_rgb_event = torch.linalg.inv(context.T_event_rgb)
        self.dense_flow = DenseFlow(cfg.frame_flow)
        self.frame_kf = VelocityKF(context.rgb_camera, 1, cfg.frame_flow_kf, device=self.device)
        self.rgb_to_event_twist = twist_adjoint(context.T_event_rgb)
        self._backlog: deque[tuple[Any, Any]] = deque()

    def sensing_camera(self) -> PinholeCamera:
        return self.context.rgb_camera

    def sensing_silhouette(self) -> Silhouette:
        return self.rgb_silhouette

    def depth_from_event(self) -> Tensor:
        return self.T_rgb_event

    def pose_filter(self) -> PoseTwistUKF:
        return PoseTwistUKF(1, self.config.pose_twist_ukf, device=self.device)

    def reset(self) -> None:
        self.dense_flow.reset()
        self._backlog = deque()

    def twist(self) -> np.ndarray:
        return np.array(self.services.timeline.filter.twist.tolist()[0], np.float64)

    def on_rgb(self, t_us: int, read: Callable[[], np.ndarray]) -> np.ndarray:
        """Dense flow from the previous frame -> one twist measurement (event camera frame),
        or the pair kept while no pose has started the track."""
        image = read()
        pair = self.dense_flow.push(t_us, image)
        if pair is None:
            return image
        services = self.services
        if not services.initialized():
            self._backlog.append((pair, services.depth.snapshot()))
            horizon = t_us - self.config.history_ms * 1e3
            while self._backlog and self._backlog[0][0].t0_us < horizon:
                self._backlog.popleft()
            return image
        measured = self._measure_pair(pair, services.pose(pair.t0_us), t_us)
        if measured is not None:
            dtype = services.timeline.filter.t.dtype
            V_ev, cov_ev = measured
            services.schedule(t_us, TwistMeasurement(pair.t_mid_us, V_ev.to(dtype),
                                                     cov_ev.to(dtype)))
        return image

    def _measure_pair(self, pair, pose_ev: np.ndarray, t_us: int
                      ) -> tuple[Tensor, Tensor] | None:
        """The twist (1, 6) and its covariance (1, 6, 6), event camera frame, that the dense
        flow of ``pair`` measures for the object at ``pose_ev`` (at the pair's first frame);
        ``None`` when no flow sample falls on the object."""
        if not np.isfinite(pose_ev).all():
            return None
        pose_rgb = (self.T_rgb_event @ torch.from_numpy(pose_ev)).numpy()
        poly = self.rgb_silhouette.polygon(pose_rgb)
        if poly is None:
            return None
        cfg = self.config.frame_flow
        pts = grid_in_polygon(poly, pair.flow.shape[:2], cfg.grid_px, cfg.max_samples)
        if len(pts) == 0:
            return None
        uv, flow = pair.sample(pts)
        z = self.services.depth.lookup(pts.astype(np.float64), poly, pose_rgb, t_now=t_us)
        kw = {"dtype": self.frame_kf.twist.dtype, "device": self.device}
        self.frame_kf.reset(1)
        V = self.frame_kf.update(torch.as_tensor(uv, **kw).unsqueeze(0),
                                 torch.as_tensor(z, **kw).unsqueeze(0),
                                 torch.as_tensor(flow, **kw).unsqueeze(0),
                                 torch.zeros(1, len(uv), dtype=torch.bool, device=self.device))
        A = self.rgb_to_event_twist.to(**kw)
        return (A @ V[0]).unsqueeze(0), (A @ self.frame_kf.cov[0] @ A.T).unsqueeze(0)

    def track_started(self, t_pose: int) -> None:
        """Measure the kept frame pairs from ``t_pose`` (the pose that started the track) to
        now, in order, each at the timeline's pose for its first frame."""
        services = self.services
        timeline = services.timeline
        dtype = timeline.filter.t.dtype
        backlog, self._backlog = self._backlog, deque()
        for pair, depth in backlog:
            if pair.t0_us < t_pose or pair.t_mid_us > timeline.now:
                continue
            pose_ev = services.past_pose(pair.t0_us)
            if pose_ev is None:
                continue
            saved = services.depth.snapshot() if depth is not None else None
            services.depth.restore(depth)
            try:
                measured = self._measure_pair(pair, pose_ev, pair.t1_us)
            finally:
                services.depth.restore(saved)
            if measured is not None and timeline.add(
                    pair.t_mid_us, "twist", (measured[0].to(dtype),), measured[1].to(dtype)):
                self.stats.twist_measurements += 1
                self.stats.twists_replayed += 1
