"""Calls of the pose source: which frames it runs on (``pose_rate_hz``), the pose prior it is
given (``pose_prior``), and the worker thread it runs in during offline tracking
(``pose_async``), whose results are taken only when they would be available live."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from evtrack.tracking.pose_sources import PoseMeasurement, PoseSource
from evtrack.tracking.stats import StageTimer, TrackerStats

__all__ = ["FRAME_JITTER_US", "PoseCaller"]

FRAME_JITTER_US = 1000
"""A frame up to this much before a pose-source slot still takes that slot (frame timestamps
are rounded to µs, so 60 FPS frames fall a few µs either side of the 5 Hz grid)."""


class PoseCaller:
    """Runs a pose source on the frames of its slots.

    Args:
        source: the pose source, or ``None`` (no calls).
        period_us: one call per this many µs of frames (``1 / pose_rate_hz``).
        min_confidence: results below this confidence count as misses.

    Attributes:
        stats: the counters it adds to (``pose_calls``, ``poses``, ``pose_misses``; the time
            in ``pose_source`` and ``pose_wait``).
        in_worker: run the calls in the worker thread (:meth:`submit`), their results taken
            when they become available (``pose_async`` inside :meth:`evtrack.Tracker.track`).
    """

    def __init__(self, source: PoseSource | None, period_us: int, min_confidence: float) -> None:
        self.source = source
        self.period_us = period_us
        self.min_confidence = min_confidence
        self.stats = TrackerStats()
        self._pool: ThreadPoolExecutor | None = None
        self.in_worker = False
        self.reset()

    def reset(self) -> None:
        """Forget the slots."""
        self._next_slot: int | None = None

    @property
    def uses_depth(self) -> bool:
        """Whether the source takes the depth frame."""
        return bool(getattr(self.source, "uses_depth", False))

    @property
    def accepts_prior(self) -> bool:
        """Whether the source takes a pose prior."""
        return bool(getattr(self.source, "accepts_prior", False))

    def wants(self, t_us: int) -> bool:
        """Whether the frame at ``t_us`` takes a slot (and so a call); moves the slots on."""
        if self._next_slot is None:
            self._next_slot = t_us
        if t_us + FRAME_JITTER_US < self._next_slot:
            return False
        while self._next_slot <= t_us + FRAME_JITTER_US:
            self._next_slot += self.period_us
        return True

    def accepted(self, m: PoseMeasurement | None) -> bool:
        """Whether a result is a pose (not a miss)."""
        return m is not None and m.confidence >= self.min_confidence

    def call(self, t_us: int, image: np.ndarray | Callable[[], np.ndarray],
             depth: np.ndarray | None, prior: np.ndarray | None = None
             ) -> PoseMeasurement | None:
        """The pose source on one frame (``image`` may be a reader, called here), timed;
        ``prior`` (4, 4) is passed only when there is one."""
        with StageTimer(self.stats.time_s, "pose_source"):
            rgb = image() if callable(image) else image
            if prior is None:
                return self.source(t_us, rgb, depth)
            return self.source(t_us, rgb, depth, prior=prior)

    def submit(self, t_us: int, image: np.ndarray | Callable[[], np.ndarray],
               depth: np.ndarray | None, prior: np.ndarray | None) -> Future:
        """:meth:`call` in the one worker thread (calls run in submission order)."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evtrack-pose")
        return self._pool.submit(self.call, t_us, image, depth, prior)

    def result(self, future: Future) -> PoseMeasurement | None:
        """A worker's result (waiting for it, timed; a pose source's exception is raised
        here), counted as a pose or a miss."""
        with StageTimer(self.stats.time_s, "pose_wait"):
            m = future.result()
        if self.accepted(m):
            self.stats.poses += 1
        else:
            self.stats.pose_misses += 1
        return m
