"""Fusing the queued measurements into the pose filter when they become available: poses
(through the pose gate), pose-source misses (which lose the object after
``lost_after_misses`` in a row), sensor depth frames (the depth fusions), frame-flow twists,
and the results of the pose source's worker thread."""

from __future__ import annotations

from functools import singledispatchmethod
from typing import TYPE_CHECKING, Any

from evtrack.tracking.inputs import (
    DepthFrame,
    Measurement,
    PendingPoseCall,
    PoseMiss,
    RgbFrame,
    TwistMeasurement,
)
from evtrack.tracking.pose_sources import PoseMeasurement
from evtrack.tracking.pose_timeline import pose_measurement_value

if TYPE_CHECKING:
    from evtrack.tracking.tracker import Tracker

__all__ = ["MeasurementFusion"]


class MeasurementFusion:
    """Applies the tracker's due measurements (an internal part of :class:`~evtrack.Tracker`:
    it reads the tracker's queue, filter and parts).

    Attributes:
        misses: pose-source misses in a row.
    """

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker
        self.misses = 0

    def reset(self) -> None:
        self.misses = 0

    def schedule(self, available_us: int, item: Measurement) -> None:
        """Queue a measurement and apply what is due at the clock."""
        self.tracker.measurements.push(available_us, item)
        self.apply_due(self.tracker.stream.now)

    def apply_due(self, t_now: int) -> None:
        """Apply every queued measurement available at or before ``t_now``, in order."""
        queue = self.tracker.measurements
        while (due := queue.pop_due(t_now)) is not None:
            available, item = due
            self._apply(item, available, t_now)

    @singledispatchmethod
    def _apply(self, item: Any, available: int, t_now: int) -> None:
        raise TypeError(f"no handler for a queued {type(item).__name__}")

    @_apply.register
    def _(self, item: PoseMeasurement, available: int, t_now: int) -> None:
        self.fuse_pose(item)

    @_apply.register
    def _(self, item: DepthFrame, available: int, t_now: int) -> None:
        tr = self.tracker
        if tr.initialized:
            tr.depth_fusion.fuse_range(item)
        if tr.initialized:
            tr.depth_fusion.fuse_alignment(item)

    @_apply.register
    def _(self, item: RgbFrame, available: int, t_now: int) -> None:
        tr = self.tracker
        if tr.initialized and tr.appearance is not None:
            tr.appearance.fuse(item)

    @_apply.register
    def _(self, item: PoseMiss, available: int, t_now: int) -> None:
        self.on_miss(t_now)

    @_apply.register
    def _(self, item: TwistMeasurement, available: int, t_now: int) -> None:
        tr = self.tracker
        if tr.initialized and tr.timeline.add(item.t_us, "twist", (item.twist,), item.cov):
            tr.stats.twist_measurements += 1

    @_apply.register
    def _(self, item: PendingPoseCall, available: int, t_now: int) -> None:
        """A worker's pose-source result, due at ``available`` (<= ``t_now``): handled as the
        synchronous path's pose or miss, scheduled for ``available`` at the frame's turn,
        would be now."""
        calls = self.tracker.pose_calls
        m = calls.result(item.result)  # a pose source's exception is raised here
        if not calls.accepted(m):
            self.on_miss(t_now)
            return
        due = max(m.t_us, available)
        if due <= t_now:
            self.fuse_pose(m)
        else:  # a measurement time after the frame's (not from the built-in sources)
            self.tracker.measurements.push(due, m)

    def settled(self, available: int, call: PendingPoseCall) -> tuple[int, Measurement]:
        """A worker's pose-source call not due yet, waited for and left pending as the
        synchronous path would have (the pose or the miss scheduled for its time): the end of
        a stream then leaves the same state and statistics either way."""
        calls = self.tracker.pose_calls
        m = calls.result(call.result)
        if calls.accepted(m):
            return max(m.t_us, available), m
        return available, PoseMiss(call.t_us)

    def on_miss(self, t_now: int) -> None:
        """A pose-source call found nothing; the object is lost after enough in a row."""
        tr = self.tracker
        self.misses += 1
        limit = tr.config.lost_after_misses
        if limit and self.misses >= limit and tr.initialized:
            tr._lose(t_now)

    def fuse_pose(self, m: PoseMeasurement) -> None:
        """Gate a pose (:mod:`~evtrack.tracking.pose_gate`) and fuse it at its own time."""
        tr = self.tracker
        gate = tr.pose_gate
        checked = gate.checked(m)
        if checked is None:
            return
        m = checked
        self.misses = 0
        was_init = tr.initialized
        if tr.motion.poses_only_initialise and was_init:
            return  # poses only (re-)initialise
        turned_back = False  # the track deemed half a turn off: re-initialise on m
        if gate.half_turns is not None and was_init:
            m, turned_back = gate.nearer_half_turn(m, tr._past_pose(m.t_us))
        ukf = tr.ukf
        rejected, reinit = int(ukf.rejected[0]), int(ukf.reinitialised[0])
        t, q = pose_measurement_value(m.pose, ukf.t.dtype, tr.device)
        cov = None if m.cov is None else m.cov.to(ukf.t.dtype).to(tr.device).unsqueeze(0)
        if m.t_us > tr.timeline.now:  # pragma: no cover - apply_due never lets it happen
            raise RuntimeError(f"pose at {m.t_us} µs applied before the clock reached it")
        agrees = was_init and gate.agrees_with_rejected(m.t_us, m.pose)
        kind = "pose_reinit" if turned_back or agrees else "pose"
        if not tr.timeline.add(m.t_us, kind, (t, q), cov):
            tr.stats.poses_late += 1
            return
        newly_rejected = int(ukf.rejected[0]) - rejected
        newly_reinit = int(ukf.reinitialised[0]) - reinit
        tr.stats.poses_rejected += max(0, newly_rejected)
        tr.stats.reinitialisations += max(0, newly_reinit)
        gate.fused(m, rejected=newly_rejected > 0 and newly_reinit <= 0)
        if tr.initialized and not was_init:
            tr.view.out_of_view_us = 0
            tr.motion.track_started(m.t_us)
