"""The tracker's clock and input queues: the stream time, the frames waiting for the clock and
one typed queue of the measurements waiting until they are available to the filters.

Every queue is ordered by time and, at equal times, by arrival, so a stream gives the same
order however it was chunked.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from evtrack.errors import EventsError
from evtrack.tracking.pose_sources import PoseMeasurement

__all__ = [
    "DepthFrame",
    "FrameInput",
    "FrameQueue",
    "Measurement",
    "MeasurementQueue",
    "PendingPoseCall",
    "PoseMiss",
    "RgbFrame",
    "StreamClock",
    "TwistMeasurement",
]

FrameInput = np.ndarray | Callable[[], np.ndarray] | None
"""An RGB or depth frame: an array, a zero-argument callable returning one, or ``None``."""


@dataclass
class PoseMiss:
    """A pose-source call on the frame at ``t_us`` (µs) that found nothing."""

    t_us: int


@dataclass
class PendingPoseCall:
    """A pose-source call on the frame at ``t_us`` (µs) running in the tracker's worker thread;
    its result is taken when it becomes available to the filter (``TrackerConfig.pose_async``)."""

    t_us: int
    result: Future


@dataclass
class DepthFrame:
    """A sensor depth frame at ``t_us`` (µs): (H, W) metres in the depth source's camera,
    waiting for the depth fusions (``depth_fusion.range``, ``depth_fusion.icp``)."""

    t_us: int
    depth: np.ndarray


@dataclass
class RgbFrame:
    """An RGB frame at ``t_us`` (µs) waiting for the appearance alignment (``appearance``):
    ``image()`` gives it, (H, W, 3) uint8, read only when it is aligned."""

    t_us: int
    image: Callable[[], np.ndarray]


@dataclass
class TwistMeasurement:
    """A twist measured between two frames (frame-flow): ``twist`` (1, 6) ``[v_o, ω]`` and its
    covariance ``cov`` (1, 6, 6), event camera frame, at ``t_us`` (µs)."""

    t_us: int
    twist: Tensor
    cov: Tensor


Measurement = (PoseMeasurement | PoseMiss | PendingPoseCall | DepthFrame | RgbFrame
               | TwistMeasurement)


class MeasurementQueue:
    """Measurements waiting until they are available (µs), earliest first, then in the order
    they were pushed."""

    def __init__(self) -> None:
        self._heap: list[tuple[int, int, Measurement]] = []
        self._pushed = 0

    def __len__(self) -> int:
        return len(self._heap)

    @property
    def next_due_us(self) -> int | None:
        """When the earliest measurement becomes available (µs); ``None`` when empty."""
        return self._heap[0][0] if self._heap else None

    def push(self, available_us: int, item: Measurement) -> None:
        """Queue ``item``, available at ``available_us``."""
        self._pushed += 1
        heapq.heappush(self._heap, (int(available_us), self._pushed, item))

    def pop_due(self, t_now: int) -> tuple[int, Measurement] | None:
        """The earliest measurement available at or before ``t_now`` and its availability
        time, taken off the queue; ``None`` when none is due."""
        if not self._heap or self._heap[0][0] > t_now:
            return None
        available, _, item = heapq.heappop(self._heap)
        return available, item

    def replace_pending_calls(
            self, settle: Callable[[int, PendingPoseCall], tuple[int, Measurement]]) -> None:
        """Replace each queued :class:`PendingPoseCall` by ``settle(available, call)`` ->
        ``(available, measurement)``, in its place of the arrival order."""
        calls = [entry for entry in self._heap if isinstance(entry[2], PendingPoseCall)]
        if not calls:
            return
        self._heap = [entry for entry in self._heap if not isinstance(entry[2], PendingPoseCall)]
        for available, seq, call in calls:
            new_available, item = settle(available, call)
            self._heap.append((new_available, seq, item))
        heapq.heapify(self._heap)


class FrameQueue:
    """RGB-D frames waiting for the clock, earliest first, then in the order they were pushed."""

    def __init__(self) -> None:
        self._heap: list[tuple[int, int, FrameInput, FrameInput]] = []
        self._pushed = 0

    def __len__(self) -> int:
        return len(self._heap)

    @property
    def next_us(self) -> int | None:
        """Time of the earliest queued frame (µs); ``None`` when empty."""
        return self._heap[0][0] if self._heap else None

    def push(self, t_us: int, rgb: FrameInput, depth: FrameInput) -> None:
        """Queue the frame taken at ``t_us``."""
        self._pushed += 1
        heapq.heappush(self._heap, (t_us, self._pushed, rgb, depth))

    def pop_before(self, t_before: int) -> Iterator[tuple[int, FrameInput, FrameInput]]:
        """Take the frames taken before ``t_before`` off the queue, earliest first, one at a
        time (a frame pushed while one is processed is taken in its turn)."""
        while self._heap and self._heap[0][0] < t_before:
            t_us, _, rgb, depth = heapq.heappop(self._heap)
            yield t_us, rgb, depth


class StreamClock:
    """The stream's time: the end of the last closed velocity step (``now``, µs), the latest time
    known to be complete (``horizon``), the last event's time, and which input call last moved
    it (named in errors).

    Args:
        step_us: the velocity step (µs); the clock starts at a multiple of it.
    """

    def __init__(self, step_us: int) -> None:
        self.step_us = int(step_us)
        self.now: int | None = None
        self.horizon = -(1 << 62)
        self.last_event_us: int | None = None
        self.moved_by = "reset"

    def start(self, t_us: int) -> int:
        """Start at the step containing ``t_us``; returns the start (µs)."""
        self.now = (int(t_us) // self.step_us) * self.step_us
        return self.now

    def check_events(self, t_first: int, t_last: int) -> None:
        """Events from ``t_first`` to ``t_last`` (µs) may be pushed next.

        Raises:
            EventsError: they start before the last event pushed or before the clock.
        """
        if self.last_event_us is not None and t_first < self.last_event_us:
            raise EventsError(f"push_events: events start at t={t_first} µs, before the last "
                              f"event pushed (t={self.last_event_us} µs)")
        if self.now is not None and t_first < self.now:
            raise EventsError(f"push_events: events start at t={t_first} µs, before the "
                              f"tracker's clock ({self.now} µs, moved there by "
                              f"{self.moved_by}); push events and frames in time order, "
                              "all on the stream's clock")
