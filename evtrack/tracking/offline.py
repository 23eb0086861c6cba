"""Offline tracking of a recorded :class:`~evtrack.Sequence`: its events and frames pushed into
a tracker in time order, as they would arrive live, with the frames read ahead in a worker
thread."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from evtrack.events import Events

if TYPE_CHECKING:
    from evtrack.tracking.tracker import Tracker

__all__ = ["EVENTS_CHUNK_US", "PreparedDepth", "Prefetched", "push_sequence"]

EVENTS_CHUNK_US = 50_000
"""Offline tracking reads the events in windows of this length (µs)."""


@dataclass
class PreparedDepth:
    """A sensor depth frame as read (for a pose source that uses depth) and its event-camera
    map, made by :meth:`~evtrack.tracking.depth_sources.SensorDepth.prepare` in the reader
    thread."""

    raw: np.ndarray
    event_map: np.ndarray


class Prefetched:
    """``read(i)`` for frames read in increasing order: each call also starts reading the
    next ``ahead`` frames in a worker thread (OpenCV's decoders release the GIL), so that
    later calls usually find them ready. A read's exception is raised by the call that asks
    for that frame.

    Reading one frame ahead left the tracker waiting ~0.25 s per 2 s sequence for its depth
    frames on 2 busy cores (the worker starts a frame only when the one before is taken);
    three ahead, ~0.02 s (the mustard bottle `faster`, 2 cores of an AMD EPYC with up to 50 %
    steal time).

    Args:
        read: ``read(i) -> frame``, safe to call from another thread.
        count: frames there are (``0 .. count - 1``).
        ahead: frames read ahead (>= 1).
    """

    def __init__(self, read: Callable[[int], Any], count: int, ahead: int = 3) -> None:
        self._read = read
        self._count = count
        self._lookahead = max(1, int(ahead))
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evtrack-frames")
        self._ahead: dict[int, Future] = {}
        self._closed = False

    def __call__(self, index: int) -> Any:
        pending = self._ahead.pop(index, None)
        for other in [k for k in self._ahead if k < index]:  # skipped: not wanted any more
            self._ahead.pop(other).cancel()
        frame = pending.result() if pending is not None else self._read(index)
        if not self._closed:
            for later in range(index + 1, min(self._count, index + 1 + self._lookahead)):
                if later not in self._ahead:
                    self._ahead[later] = self._pool.submit(self._read, later)
        return frame

    def close(self) -> None:
        """Stop the worker (a read in flight finishes; its frame is dropped). Later calls
        read in the caller's thread."""
        self._closed = True
        for pending in self._ahead.values():
            pending.cancel()
        self._ahead.clear()
        self._pool.shutdown(wait=True)


class _EventPusher:
    """Pushes a sequence's event windows into the tracker up to a time, keeping the rest of
    the window that crosses it for the next call."""

    def __init__(self, tracker: Tracker, events: Iterator[Events]) -> None:
        self.tracker = tracker
        self.events = events
        self.carry: Events | None = None
        self.last_event_us: int | None = None

    def _push(self, chunk: Events) -> None:
        self.tracker.push_events(chunk)
        if len(chunk):
            self.last_event_us = chunk.t_end

    def skip_before(self, t_start: int) -> None:
        """Leave out the events before ``t_start`` (the stream starts there)."""
        self.until(t_start, push=False)

    def until(self, t_stop: int | None, push: bool = True) -> None:
        """Push the events before ``t_stop`` (``None``: all the rest); with ``push`` False,
        drop them instead."""
        while True:
            chunk = self.carry if self.carry is not None else next(self.events, None)
            self.carry = None
            if chunk is None:
                return
            if t_stop is None:
                if push:
                    self._push(chunk)
                continue
            k = int(torch.searchsorted(chunk.t, torch.tensor([t_stop]))[0])
            if k and push:
                self._push(chunk[:k])
            if k < len(chunk):
                self.carry = chunk[k:]
                return


def push_sequence(tracker: Tracker, sequence: Any, prepare_depth: Callable | None,
                  progress: bool, start_us: int | None = None) -> None:
    """Push every event and frame of ``sequence`` into ``tracker`` in time order, then flush.

    Args:
        prepare_depth: ``(t_us, raw) -> event map`` run in a reader thread ahead of time (the
            tracker's sensor depth), or ``None`` (depth frames read when processed).
        progress: show a progress bar over the frames.
        start_us: push only the events and frames from this time on (the track starts
            there); ``None``: all.
    """
    rgb_t = sequence.rgb_times_us.tolist()
    depth_t = sequence.depth_times_us.tolist()
    depth_index = {t: i for i, t in enumerate(depth_t)}
    rgb_index = {t: i for i, t in enumerate(rgb_t)}
    frame_times = sorted(t for t in set(rgb_t) | set(depth_t)
                         if start_us is None or t >= start_us)
    pusher = _EventPusher(tracker, sequence.iter_events(window_us=EVENTS_CHUNK_US))
    if start_us is not None:
        pusher.skip_before(start_us)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(frame_times), unit="frame", desc=f"track {tracker.method}")

    def read_prepared(index: int) -> PreparedDepth:
        raw = sequence.depth(index)
        return PreparedDepth(raw, prepare_depth(depth_t[index], raw))

    # the sensor depth is read at every depth frame: decode and prepare the next one in a
    # worker thread while this one is used (same frames and maps, made sooner)
    read_depth = (Prefetched(read_prepared, len(depth_t))
                  if prepare_depth is not None and len(depth_t) > 1 else sequence.depth)
    try:
        for t in frame_times:
            pusher.until(t)
            i_rgb, i_d = rgb_index.get(t), depth_index.get(t)
            rgb = (lambda i=i_rgb: sequence.rgb(i)) if i_rgb is not None else None
            depth = (lambda i=i_d: read_depth(i)) if i_d is not None else None
            tracker.push_frame(t, rgb, depth)
            if bar is not None:
                bar.update(1)
        # frames are read when the steps reach them: the last ones only in the final step
        # groups, so the reader stays open until the stream is done
        pusher.until(None)
        if pusher.last_event_us is not None:
            tracker.advance(pusher.last_event_us + 1)
        tracker.flush()
    finally:
        if isinstance(read_depth, Prefetched):
            read_depth.close()
        if bar is not None:
            bar.close()
