"""RGB-D frames into the tracker: queued until the clock reaches them, then the depth frame put
to use (RoI depth, the pose gate's memory, the depth fusions), the RGB frame handed to the
motion source where it uses images, and the pose source called on the frames of its slots."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.models.estimator import check_rgb
from evtrack.tracking.inputs import (
    DepthFrame,
    FrameInput,
    FrameQueue,
    PendingPoseCall,
    PoseMiss,
    RgbFrame,
)
from evtrack.tracking.offline import PreparedDepth
from evtrack.tracking.stats import StageTimer

if TYPE_CHECKING:
    from evtrack.tracking.tracker import Tracker

__all__ = ["FrameIntake", "checked_rgb"]


def checked_rgb(t_us: int, rgb: Any, camera: PinholeCamera) -> np.ndarray:
    """``rgb`` if it is a uint8 (H, W, 3) image of ``camera``'s size.

    Raises:
        ValueError: naming the frame's time, what it got and what was expected.
    """
    where = f"RGB frame at t={t_us} µs"
    try:
        check_rgb(rgb)  # the pose estimators' own check of the image's format
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if rgb.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"{where} is {rgb.shape[1]}x{rgb.shape[0]}, the RGB-D camera is "
                         f"{camera.width}x{camera.height}")
    return rgb


class FrameIntake:
    """Queues and processes the tracker's frames (an internal part of :class:`~evtrack.Tracker`:
    it reads the tracker's clock and parts)."""

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker
        self.queue = FrameQueue()

    def reset(self) -> None:
        self.queue = FrameQueue()

    @property
    def next_us(self) -> int | None:
        """Time of the earliest queued frame (µs); ``None`` when none is queued."""
        return self.queue.next_us

    def push(self, t_us: int, rgb: FrameInput, depth: FrameInput) -> None:
        self.queue.push(t_us, rgb, depth)

    def due(self, t_before: int) -> None:
        """Process the queued frames taken before ``t_before``."""
        stats = self.tracker.stats
        for t_us, rgb, depth in self.queue.pop_before(t_before):
            with StageTimer(stats.time_s, "frames"):
                try:
                    self._process(t_us, rgb, depth)
                except Exception as exc:
                    if hasattr(exc, "add_note"):  # Python >= 3.11
                        exc.add_note(f"(while processing the frame pushed for t={t_us} µs; "
                                     "the tracker goes on without it)")
                    raise

    def _process(self, t_us: int, rgb: FrameInput, depth: FrameInput) -> None:
        tr = self.tracker
        depth_map = self._take_depth(t_us, depth)
        if rgb is None:
            return
        get_rgb: Callable[[], np.ndarray] = functools.cache(
            (lambda: checked_rgb(t_us, rgb(), tr.rgb_camera)) if callable(rgb) else (lambda: rgb))
        image = tr.motion.on_rgb(t_us, get_rgb) if tr.motion.uses_rgb else None
        if tr.appearance is not None and tr.appearance.due(t_us):
            tr.fusion.schedule(t_us, RgbFrame(t_us, get_rgb))
        if not self._wants_pose(t_us):
            return
        tr.stats.pose_calls += 1
        calls = tr.pose_calls
        available = t_us + tr.config.pose_latency_us
        if depth_map is None and depth is not None and calls.uses_depth:
            depth_map = depth() if callable(depth) else depth
        depth_in = depth_map if calls.uses_depth else None
        prior = self._pose_prior(t_us)
        if calls.in_worker and available > tr.stream.now:
            # computed in the worker (the RGB frame read there too), taken at `available`:
            # the same result at the same moment for the filter
            future = calls.submit(t_us, image if image is not None else get_rgb, depth_in, prior)
            tr.measurements.push(available, PendingPoseCall(t_us, future))
            return
        m = calls.call(t_us, image if image is not None else get_rgb(), depth_in, prior)
        if calls.accepted(m):
            tr.push_pose(m, available_us=available)
        else:
            tr.stats.pose_misses += 1
            tr.fusion.schedule(max(available, tr.stream.now), PoseMiss(t_us))

    def _take_depth(self, t_us: int, depth: FrameInput) -> np.ndarray | None:
        """A sensor depth frame: in use for the RoIs (unless a newer one is), kept for the
        pose gate and measured by the depth fusions; returns it as read (``None``: none)."""
        tr = self.tracker
        if depth is None or not tr.roi_depth.sensor:
            return None
        source = tr.roi_depth.source
        depth_map = depth() if callable(depth) else depth
        if isinstance(depth_map, PreparedDepth):  # from track(): prepared ahead
            event_map, depth_map = depth_map.event_map, depth_map.raw
        else:
            event_map = source.prepare(t_us, depth_map)
        if source.t_us is None or t_us >= source.t_us:
            source.set_prepared(t_us, event_map)  # else the newer map stays in use
        tr.pose_gate.remember_depth(t_us, event_map)
        if tr.depth_fusion is not None:
            tr.fusion.schedule(t_us, DepthFrame(t_us, event_map))
        return depth_map

    def _wants_pose(self, t_us: int) -> bool:
        tr = self.tracker
        if tr.pose_source is None:
            return False
        if tr.motion.poses_only_initialise and tr.initialized:
            return False
        return tr.pose_calls.wants(t_us)

    def _pose_prior(self, t_us: int) -> np.ndarray | None:
        """(4, 4) the pose (event camera frame) handed to the pose source for the frame at
        ``t_us`` (``TrackerConfig.pose_prior``), or ``None``: no prior wanted, a source that
        takes none, or no track (before the first pose, after a loss)."""
        tr = self.tracker
        if not (tr.config.pose_prior and tr.initialized and tr.pose_calls.accepts_prior):
            return None
        return np.array(tr.pose(t_us), dtype=np.float64)
