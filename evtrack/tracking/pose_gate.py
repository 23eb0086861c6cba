"""The pose gate: what becomes of a pose from the pose source before the pose filter fuses it.

* **Ray alignment** (``pose_gate.depth_align``): the pose is moved along its viewing ray onto the
  sensor depth of its frame (:mod:`evtrack.tracking.pose_alignment`): an RGB network errs
  mostly in range, which the depth frame measures.
* **Depth check** (``pose_gate.depth_min_share``): a pose whose frame's sensor depth contradicts it
  (less than that share of the valid depths inside its silhouette lie in its depth range) is
  dropped: a network's gross errors, which can agree with each other, then never re-initialise
  the filter. Both read the sensor depth frame nearest the pose's own time (within
  ``depth.max_age_ms``): the maps of the last ``history_ms`` are kept, so a pose that arrives
  late is judged against the depth of its time, not the latest frame's.
* **Alternatives** (``pose_gate.alternatives``): a dropped pose gives way to the first of its
  ``alternatives`` (the detector's other poses of that image, most confident first) that the
  depth confirms.
* **Half turns** (``pose_gate.half_turn_axes``): a pose whose half turn about a symmetry axis lies
  nearer the filter's pose is turned (:mod:`evtrack.tracking.pose_flips`), unless it is the
  ``pose_gate.half_turn_reinit_after``-th in a row to need it: then the track is deemed half a turn
  off and re-initialises on the pose.
* **Agreement** (``pose_gate.reinit_on_agreement``): a pose that agrees with the previous, gated one
  re-initialises the filter (the filter has drifted off, the poses have not).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import Tensor

from evtrack.eval.metrics import position_errors, rotation_errors
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_sources import silhouette_depth_share
from evtrack.tracking.pose_alignment import PoseRayAligner
from evtrack.tracking.pose_flips import HalfTurnResolver
from evtrack.tracking.pose_sources import PoseMeasurement
from evtrack.tracking.silhouette import Silhouette
from evtrack.tracking.stats import TrackerStats, count_reason

__all__ = ["PoseGate"]

POSE_DEPTH_MIN_PIXELS = 16
"""Fewest valid depth pixels in a pose's silhouette to judge it (``pose_gate.depth_min_share``)."""


class PoseGate:
    """Aligns, checks and turns poses, and tells when one re-initialises the filter.

    Args:
        config: the tracker's config (the ``pose_*`` and ``reinit_*`` fields).
        silhouette: the object's silhouette in the camera of the sensor depth frames.
        sensor_depth: whether there are sensor depth frames (no checks without).
        aligner: the ray aligner (``pose_gate.depth_align``), or ``None``.
        half_turns: the half-turn resolver (``pose_gate.half_turn_axes``), or ``None``.
        to_depth, from_depth: (4, 4) event camera -> depth camera and back, ``None`` where
            the depth frames are in the event camera.

    Attributes:
        stats: the counters it adds to.
    """

    def __init__(self, config: TrackerConfig, silhouette: Silhouette, sensor_depth: bool,
                 aligner: PoseRayAligner | None, half_turns: HalfTurnResolver | None,
                 to_depth: np.ndarray | None = None,
                 from_depth: np.ndarray | None = None) -> None:
        self.config = config
        self.silhouette = silhouette
        self.aligner = aligner
        self.half_turns = half_turns
        self.to_depth, self.from_depth = to_depth, from_depth
        self.checks_depth = sensor_depth and bool(config.pose_gate.depth_min_share
                                                  or aligner is not None)
        self.stats = TrackerStats()
        self.depth_frames: dict[int, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """Forget the kept depth frames and the poses seen."""
        self.depth_frames = {}
        self.forget_track()

    def forget_track(self) -> None:
        """Forget what relates poses to the track (the object was lost)."""
        self.rejected: tuple[int, Tensor] | None = None
        self.half_turns_in_row = 0

    # ------------------------------------------------------------ depth frames
    def remember_depth(self, t_us: int, event_map: np.ndarray) -> None:
        """Keep the sensor depth map just taken (frame time ``t_us``) for the poses of its
        time, and forget the maps older than the kept past (``history_ms`` before the newest).
        Costs one map per depth frame of that past (640x480 float32: 1.2 MB each, ~37 MB at
        30 Hz and the default 1 s)."""
        if not self.checks_depth:
            return
        self.depth_frames[t_us] = event_map
        oldest = max(self.depth_frames) - self.config.history_ms * 1e3
        for t_old in [t for t in self.depth_frames if t < oldest]:
            del self.depth_frames[t_old]

    def frame_depth(self, t_us: int) -> np.ndarray | None:
        """The kept sensor depth map nearest in time to a pose at ``t_us`` (the earlier of two
        as near), within ``depth.max_age_ms`` of it; ``None`` without one."""
        max_age_us = self.config.depth.max_age_ms * 1e3
        fresh = [t for t in self.depth_frames if abs(t_us - t) <= max_age_us]
        if not fresh:
            return None
        return self.depth_frames[min(fresh, key=lambda t: (abs(t - t_us), t))]

    # ------------------------------------------------------------ checks
    def checked(self, m: PoseMeasurement) -> PoseMeasurement | None:
        """``m`` aligned and checked, or the first plausible alternative, or ``None``
        (counted in ``poses_implausible``)."""
        checked = self.depth_checked(m)
        if checked is None:
            checked = self.plausible_alternative(m)
        if checked is None:
            self.stats.poses_implausible += 1  # neither a found pose nor a miss
        return checked

    def depth_checked(self, m: PoseMeasurement) -> PoseMeasurement | None:
        """The pose aligned along its viewing ray with its frame's sensor depth (unchanged when
        it cannot be), or ``None`` when that depth contradicts it."""
        if not self.checks_depth:
            return m
        depth = self.frame_depth(m.t_us)
        if depth is None:
            return m
        pose = m.pose.detach().cpu().numpy()
        if self.to_depth is not None:
            pose = self.to_depth @ pose
        if self.aligner is not None:
            res = self.aligner.align(depth, pose)
            if res.ok:
                self.stats.poses_depth_aligned += 1
                pose = res.pose
                aligned = self.from_depth @ pose if self.from_depth is not None else pose
                m = dataclasses.replace(m, pose=torch.as_tensor(aligned, dtype=m.pose.dtype))
            else:
                count_reason(self.stats.pose_alignments_skipped, res.reason)
        share_min = self.config.pose_gate.depth_min_share
        if not share_min:
            return m
        poly = self.silhouette.polygon(pose)
        if poly is None:
            return m
        share, count = silhouette_depth_share(depth, poly, self.config.pose_gate.depth_tolerance_m)
        return None if count >= POSE_DEPTH_MIN_PIXELS and share < share_min else m

    def plausible_alternative(self, m: PoseMeasurement) -> PoseMeasurement | None:
        """The first of ``m``'s alternatives (most confident first) at or above
        ``pose_gate.min_confidence`` and ``pose_gate.alternatives_min_confidence`` that passes the
        depth
        check, aligned as it checked; ``None`` without one or with ``pose_gate.alternatives``
        off."""
        c = self.config
        if not c.pose_gate.alternatives:
            return None
        least = max(c.pose_gate.min_confidence, c.pose_gate.alternatives_min_confidence)
        for alt in m.alternatives:
            if alt.confidence < least:
                continue
            checked = self.depth_checked(alt)
            if checked is not None:
                self.stats.poses_from_alternatives += 1
                return checked
        return None

    def nearer_half_turn(self, m: PoseMeasurement, reference: np.ndarray | None
                         ) -> tuple[PoseMeasurement, bool]:
        """``m``, or its half turn about one of ``pose_gate.half_turn_axes`` where that lies nearer
        ``reference`` (4, 4) (the filter's pose at ``m.t_us``; ``None``: none); and whether
        the filter is to re-initialise on ``m`` as it is instead: the pose is the
        ``pose_gate.half_turn_reinit_after``-th in a row to need the turn, so the track, not the
        network, is deemed half a turn off (it started on a turned pose)."""
        if self.half_turns is None or reference is None:
            return m, False
        pose = m.pose.detach().cpu().numpy().astype(np.float64)
        chosen, axis = self.half_turns.resolve(pose, reference)
        if axis is None:
            self.half_turns_in_row = 0
            return m, False
        self.half_turns_in_row += 1
        limit = self.config.pose_gate.half_turn_reinit_after
        if limit and self.half_turns_in_row >= limit:
            self.half_turns_in_row = 0
            self.stats.half_turn_reinits += 1
            return m, True
        self.stats.poses_half_turned += 1
        return dataclasses.replace(m, pose=torch.as_tensor(chosen, dtype=m.pose.dtype)), False

    def agrees_with_rejected(self, t_us: int, pose: Tensor) -> bool:
        """Whether the previous pose was rejected by the filter's gate and ``pose`` lies within
        the motion the config allows since (``reinit_agree_*``): two poses that agree with
        each other but not with the filter mean the filter is off, so the second
        re-initialises it. Random outliers rarely agree with each other."""
        c = self.config
        if not c.pose_gate.reinit_on_agreement or self.rejected is None:
            return False
        t0, pose0 = self.rejected
        dt = max(0.0, (t_us - t0) * 1e-6)
        moved = float(position_errors(pose, pose0))
        turned = math.degrees(float(rotation_errors(pose, pose0)))
        return (moved <= c.pose_gate.reinit_agree_m + c.pose_gate.reinit_agree_m_per_s * dt
                and turned <= (c.pose_gate.reinit_agree_deg
                               + c.pose_gate.reinit_agree_deg_per_s * dt))

    def fused(self, m: PoseMeasurement, rejected: bool) -> None:
        """Note the filter's verdict on the fused pose ``m``: gated (``rejected``, and not
        re-initialised on), or taken."""
        self.rejected = (m.t_us, m.pose) if rejected else None
