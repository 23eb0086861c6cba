"""The tracker's counters (:class:`TrackerStats`) and the per-stage timer."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

__all__ = ["StageTimer", "TrackerStats", "count_reason"]


@dataclass
class TrackerStats:
    """Counters of one run (since the last :meth:`Tracker.reset`).

    Attributes:
        steps: velocity steps processed.
        events: events pushed.
        events_denoised: of those, events removed as background activity by ``denoise.method``;
            events_on_hot_pixels: removed on hot pixels (``denoise.hot_pixels``); hot_pixels:
            distinct pixels found hot (see :mod:`evtrack.denoise`).
        events_on_object: events inside the predicted silhouette.
        events_in_bursts: of those, events of burst steps (not used); burst_steps: steps
            found to be event bursts (see :mod:`evtrack.tracking.tracker`).
        events_thinned: events of the cells beyond a group's ``load.max_events_per_step`` budget
            (not used; see :mod:`evtrack.tracking.tracker`).
        events_unsearched: events given to the flow but, beyond a RoI window's
            ``load.search_per_roi_window``, not searched for candidates (they still serve the
            searched events' triplets; see :mod:`evtrack.tracking.tracker`).
        roi_flows: RoI flows given to the velocity filter.
        velocity_updates: steps with at least one RoI flow (or GE row).
        depth_fallbacks: RoIs that took the fallback depth (see :mod:`evtrack.tracking.tracker`).
        frames: frames pushed; frames_without_depth: of those, without a depth frame.
        pose_calls: pose-source calls; poses: measurements returned; poses_late: dropped
            because older than ``history_ms``; pose_misses: calls that returned nothing or a
            pose below ``pose_gate.min_confidence``.
        poses_rejected: poses rejected by the gate; reinitialisations: filter re-inits after
            rejections; lost: times the object was declared lost.
        poses_implausible: poses dropped before the filter because the sensor depth of their
            frame contradicts them (``TrackerConfig.pose_gate.depth_min_share``).
        poses_from_alternatives: poses that failed that check and were replaced by one of
            their :attr:`~evtrack.tracking.pose_sources.PoseMeasurement.alternatives` that passed it
            (``TrackerConfig.pose_gate.alternatives``; not counted as implausible).
        poses_half_turned: poses replaced by their half turn about one of
            ``TrackerConfig.pose_gate.half_turn_axes``, which lay nearer the filter's pose;
            half_turn_reinits: poses that re-initialised the filter instead, the
            ``pose_gate.half_turn_reinit_after``-th in a row to need the turn.
        poses_depth_aligned: poses moved along their viewing ray onto the sensor depth
            (``TrackerConfig.pose_gate.depth_align``); pose_alignments_skipped: poses that were not,
            by reason (:class:`~evtrack.tracking.pose_alignment.RayAlignment`).
        search_budget_min: with ``TrackerConfig.load.realtime``, the lowest search budget per
            step it set (0: it never lowered it); event_budget_min: the lowest event budget
            per step it set (0: it never shed events); groups_over_load: step groups whose
            processing took longer than ``load.realtime`` of their stream time.
        twist_measurements: frame-flow twist measurements fused; twists_replayed: of those,
            measured on kept frame pairs when a late pose started the track.
        steps_remeasured: velocity steps measured again, with RoI flows, once a late pose
            started the track (``remeasure.on_pose``); remeasures_skipped: late first poses
            whose steps were not measured again, the pose not explaining the events
            (``remeasure.min_inside``).
        depth_ranges: range measurements from depth frames given to the pose filter
            (``depth_fusion.range``); depth_ranges_skipped: depth frames without one, by reason
            (:class:`~evtrack.tracking.depth_range.RangeResult`).
        depth_alignments: poses aligned with depth frames given to the pose filter
            (``depth_fusion.icp``); depth_alignments_skipped: aligned frames without one, by reason
            (``"few depth pixels"``, ``"few fit"``: too few depth pixels fit the mesh,
            ``"correction too large"``).
        appearance_alignments: poses aligned with RGB frames given to the pose filter
            (``appearance``); appearance_alignments_skipped: aligned frames without one, by
            reason (:class:`~evtrack.models.AppearanceResult`'s ``refusal``: ``"not visible"``,
            ``"few pixels"``, ``"low correlation"``, ``"correction too large"``,
            ``"diverged"``).
        time_s: processing time per stage (flow, velocity, pose, frames, other).
    """

    steps: int = 0
    events: int = 0
    events_denoised: int = 0
    events_on_hot_pixels: int = 0
    hot_pixels: int = 0
    events_on_object: int = 0
    events_in_bursts: int = 0
    burst_steps: int = 0
    events_thinned: int = 0
    events_unsearched: int = 0
    roi_flows: int = 0
    velocity_updates: int = 0
    depth_fallbacks: int = 0
    frames: int = 0
    frames_without_depth: int = 0
    pose_calls: int = 0
    poses: int = 0
    poses_late: int = 0
    pose_misses: int = 0
    poses_rejected: int = 0
    poses_implausible: int = 0
    poses_from_alternatives: int = 0
    poses_half_turned: int = 0
    half_turn_reinits: int = 0
    poses_depth_aligned: int = 0
    pose_alignments_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    search_budget_min: int = 0
    event_budget_min: int = 0
    groups_over_load: int = 0
    reinitialisations: int = 0
    lost: int = 0
    twist_measurements: int = 0
    twists_replayed: int = 0
    steps_remeasured: int = 0
    remeasures_skipped: int = 0
    depth_ranges: int = 0
    depth_ranges_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    depth_alignments: int = 0
    depth_alignments_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    appearance_alignments: int = 0
    appearance_alignments_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    time_s: dict[str, float] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class StageTimer:
    """``with StageTimer(totals, "flow"): ...`` adds the block's wall time (s) to
    ``totals["flow"]``."""

    def __init__(self, totals: dict[str, float], name: str) -> None:
        self.totals, self.name = totals, name

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.totals[self.name] = self.totals.get(self.name, 0.0) + time.perf_counter() - self.t0


def count_reason(counts: dict[str, int], reason: str) -> None:
    """Add one to ``counts[reason]`` (the stats' skipped-by-reason tables)."""
    counts[reason] = counts.get(reason, 0) + 1
