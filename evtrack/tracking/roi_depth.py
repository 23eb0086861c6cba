"""RoI depth: the depth (m) of each RoI flow, from the sensor's depth frames or the mesh rendered
at the predicted pose, with a fallback.

Depth fallback: a RoI without a valid depth (no depth frame yet, a frame older than
``depth.max_age_ms``, a pushed frame without depth and no earlier one, or only missing or
out-of-range pixels in its patch) takes the predicted depth of the object's origin; each such
RoI is counted in :attr:`~evtrack.tracking.stats.TrackerStats.depth_fallbacks`.
"""

from __future__ import annotations

import math

import numpy as np

from evtrack.tracking.depth_sources import DepthSource, ModelDepth, SensorDepth
from evtrack.tracking.silhouette import SilhouettePolygon
from evtrack.tracking.stats import TrackerStats
from evtrack.tracking.step_flows import StepFlows

__all__ = ["DEPTH_TOLERANCE_M", "RoiDepth"]

DEPTH_TOLERANCE_M = 0.05
"""Depths within this distance outside the object's predicted depth range still count as the
object's (noise, pose error)."""

DepthSnapshot = tuple[np.ndarray | None, int | None]


class RoiDepth:
    """Depths of RoIs from a :class:`~evtrack.tracking.depth_sources.DepthSource`.

    Args:
        source: sensor depth frames or model depth.
        max_depth_age_ms: a sensor frame older than this is not used (the RoIs fall back).
        range_sigmas: the silhouette's depth range is widened by :data:`DEPTH_TOLERANCE_M` plus
            this many standard deviations of the pose's depth (:meth:`set_pose_uncertainty`).

    Attributes:
        stats: the counters it adds to (``depth_fallbacks``).
        range_margin_m: the widening of the depth range now (m).
    """

    def __init__(self, source: DepthSource, max_depth_age_ms: float,
                 range_sigmas: float = 0.0) -> None:
        self.source = source
        self.max_age_us = max_depth_age_ms * 1e3
        self.sensor = isinstance(source, SensorDepth)
        self.range_sigmas = range_sigmas
        self.range_margin_m = DEPTH_TOLERANCE_M
        self.stats = TrackerStats()

    def set_pose_uncertainty(self, depth_std_m: float) -> None:
        """Widen the depth range by ``range_sigmas`` times ``depth_std_m``, the pose filter's
        standard deviation (m) of the object origin's camera ``z`` (a non-finite one: the fixed
        margin)."""
        extra = self.range_sigmas * depth_std_m
        self.range_margin_m = DEPTH_TOLERANCE_M + (extra if math.isfinite(extra) else 0.0)

    def reset(self) -> None:
        """Forget the depth frame (sensor) or the rendering (model) and the pose's
        uncertainty."""
        self.range_margin_m = DEPTH_TOLERANCE_M
        if isinstance(self.source, SensorDepth):
            self.source.map, self.source.t_us = None, None
        elif isinstance(self.source, ModelDepth):
            self.source.invalidate()

    def snapshot(self) -> DepthSnapshot | None:
        """The sensor depth map in use and its time (``None`` for model depth)."""
        return (self.source.map, self.source.t_us) if self.sensor else None

    def restore(self, snapshot: DepthSnapshot | None) -> None:
        """Use a :meth:`snapshot`'s map again (sensor depth; ``None``: nothing to do)."""
        if snapshot is not None:
            self.source.map, self.source.t_us = snapshot

    def invalidate_model(self) -> None:
        """Model depth: render afresh at the next lookup (sensor depth: nothing to do)."""
        if isinstance(self.source, ModelDepth):
            self.source.invalidate()

    def expires_after_us(self) -> float | None:
        """The last time (µs) the sensor map in use may be read; ``None`` without one."""
        if self.source.map is None or self.source.t_us is None:
            return None
        return self.source.t_us + self.max_age_us

    def expire(self, t_now: int) -> None:
        """Drop a sensor depth frame older than ``depth.max_age_ms`` at ``t_now`` (lookups then
        fall back)."""
        if self.source.t_us is not None and t_now - self.source.t_us > self.max_age_us:
            self.source.map = None

    def unranged(self, uv: np.ndarray, t_now: int) -> np.ndarray:
        """(N,) sensor depths (m, NaN where missing) of the RoIs ``uv`` (N, 2) px: patch
        medians with no depth range (before the first pose), no fallback."""
        self.expire(t_now)
        return self.source.lookup(uv, None)

    def lookup(self, uv: np.ndarray, poly: SilhouettePolygon, pose: np.ndarray, t_now: int,
               patch: bool = True) -> np.ndarray:
        """(N,) depths (m) of the RoIs ``uv`` (N, 2) px at ``t_now``, within the silhouette's
        depth range widened by :attr:`range_margin_m`, the missing ones by the fallback
        (counted). Model depth renders at ``pose`` when due."""
        if isinstance(self.source, ModelDepth):
            self.source.update(t_now, pose)
        else:
            self.expire(t_now)  # too old: fall back
        z = self.source.lookup(uv, self.depth_range(poly), patch)
        self.stats.depth_fallbacks += int(self.fill_missing(z, pose).sum())
        return z

    def run(self, flows: StepFlows, k: int, end: int, poly: SilhouettePolygon,
            pose: np.ndarray, t_now: int) -> tuple[np.ndarray, np.ndarray]:
        """The sensor depths (m) of the RoIs of steps ``k..end-1`` of ``flows`` (the map read
        at ``t_now``, step ``k``'s start), the missing ones replaced by the fallback (not
        counted), and which were missing. One lookup serves the rows of every remaining step
        of the group while the depth map stays the same (the group's silhouette and pose are
        fixed; a new or expired map starts a new lookup): the same depths as step by step at a
        fraction of the per-call cost."""
        self.expire(t_now)
        lo, hi = int(flows.bounds[k]), int(flows.bounds[end])
        cache = flows.depth_cache
        z_range = self.depth_range(poly)
        if (cache is None or cache[0] is not self.source.map or cache[3] is not poly
                or cache[4] != z_range):
            cache = (self.source.map, lo, self.source.lookup(flows.uv[lo:], z_range), poly,
                     z_range)
            flows.depth_cache = cache
        z = cache[2][lo - cache[1]:hi - cache[1]].copy()
        return z, self.fill_missing(z, pose)

    def step(self, flows: StepFlows, k: int, poly: SilhouettePolygon, pose: np.ndarray,
             t_now: int) -> np.ndarray:
        """:meth:`run` for step ``k`` alone, its fallbacks counted."""
        z, missing = self.run(flows, k, k + 1, poly, pose, t_now)
        self.stats.depth_fallbacks += int(missing.sum())
        return z

    def depth_range(self, poly: SilhouettePolygon) -> tuple[float, float]:
        """The depths (m) that count as the object's: ``poly``'s range widened by
        :attr:`range_margin_m`."""
        z_lo, z_hi = poly.z_range
        return z_lo - self.range_margin_m, z_hi + self.range_margin_m

    @staticmethod
    def fill_missing(z: np.ndarray, pose: np.ndarray | None) -> np.ndarray:
        """Replace the missing depths (NaN) of ``z`` (N,) metres, in place, by the fallback
        (the depth of the origin of ``pose``); returns which were missing (N,)."""
        missing = ~np.isfinite(z)
        if missing.any():
            z[missing] = float(pose[2, 3]) if pose is not None else float("nan")
        return missing
