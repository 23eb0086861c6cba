"""The reader interface shared by every format, and the streaming machinery behind it.

Each format implements :meth:`EventReader._raw_chunks`, a generator of event chunks in file
order. This module validates those chunks on the fly (time order across chunks, coordinates
against the sensor, polarity), cuts them into exactly consecutive windows of a duration or an
event count, and answers ``num_events``/``t_start``/``t_end`` by a streaming pass when a format
has no index. Formats with an index (HDF5) override :meth:`EventReader.read` and the metadata.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from evtrack.errors import EventFileError
from evtrack.events import Events, concatenate

__all__ = [
    "DEFAULT_WINDOW_COUNT",
    "EventReader",
    "Locator",
    "check_events",
    "quick_valid",
    "rewindow",
]

# Window size used by iter_events/iter_windows when neither window_us nor count is given.
DEFAULT_WINDOW_COUNT = 1_000_000

Locator = Callable[[int], str]
"""Maps an index inside a chunk to a human description of where it is in the file."""


def _where(index: int, locate: Locator | None) -> str:
    return f"index {index}" + (f" ({locate(index)})" if locate is not None else "")


def check_events(
    ev: Events,
    path: str | Path,
    *,
    offset: int = 0,
    prev_t: int | None = None,
    locate: Locator | None = None,
    scope: str = "",
) -> None:
    """Raise :class:`EventFileError` naming ``path`` if ``ev`` breaks the event invariants.

    Uses :meth:`Events.validate` (order, coordinates in the sensor, polarity ±1) and also checks
    that the chunk starts no earlier than ``prev_t``, the last timestamp of the chunk before.

    Args:
        ev: the chunk.
        path: the file it came from (for the message).
        offset: index of the chunk's first event in the file; messages give file indices.
        prev_t: last timestamp (µs) before this chunk, or ``None``.
        locate: optional map from a chunk index to a place in the file (e.g. a line number).
        scope: optional words appended to counts (e.g. ``" in events 0..99"``).
    """
    if (prev_t is None or not len(ev) or int(ev.t[0]) >= prev_t) and quick_valid(ev):
        return
    problems: list[str] = []
    if prev_t is not None and len(ev) and int(ev.t[0]) < prev_t:
        problems.append(
            f"timestamp goes backwards at {_where(offset, _shift(locate, offset))}: "
            f"t={int(ev.t[0])} µs after {prev_t} µs"
        )
    report = ev.validate()
    if report.unsorted:
        i = report.first_unsorted
        problems.append(
            f"{report.unsorted} timestamps go backwards{scope}, first at "
            f"{_where(offset + i, _shift(locate, offset))} (t={int(ev.t[i])} µs after "
            f"{int(ev.t[i - 1])} µs)"
        )
    if report.outside:
        i = report.first_outside
        problems.append(
            f"{report.outside} events outside the sensor {ev.sensor_size}{scope}, first at "
            f"{_where(offset + i, _shift(locate, offset))} (x={int(ev.x[i])}, y={int(ev.y[i])})"
        )
    if report.bad_polarity:
        i = report.first_bad_polarity
        problems.append(
            f"{report.bad_polarity} events with polarity other than ±1{scope}, first at "
            f"{_where(offset + i, _shift(locate, offset))} (p={int(ev.p[i])})"
        )
    if problems:
        raise EventFileError(path, "invalid events: " + "; ".join(problems))


def quick_valid(ev: Events) -> bool:
    """Whether :meth:`Events.validate` would find no problem, computed with numpy.

    Same conditions (time order, ``0 <= x < width``, ``0 <= y < height``, polarity ±1), about
    ten times faster on CPU than the torch implementation; readers call ``validate`` only to
    describe a problem this finds.
    """
    if not len(ev):
        return True
    d = ev.numpy()
    t, x, y, p = d["t"], d["x"], d["y"], d["p"]
    if t.size > 1 and bool((t[1:] < t[:-1]).any()):
        return False
    if int(x.min()) < 0 or int(y.min()) < 0:
        return False
    if ev.sensor_size is not None:
        w, h = ev.sensor_size
        if int(x.max()) >= w or int(y.max()) >= h:
            return False
    return bool((np.abs(p) == 1).all())  # abs(-128) stays -128 in int8: still rejected


def _shift(locate: Locator | None, offset: int) -> Locator | None:
    """Turn a chunk-local locator into one taking file indices."""
    if locate is None:
        return None
    return lambda i: locate(i - offset)


def rewindow(
    chunks: Iterator[Events],
    *,
    window_us: int | None = None,
    count: int | None = None,
    t_start_us: int | None = None,
    include_empty: bool = False,
    sensor_size: tuple[int, int] | None = None,
) -> Iterator[Events]:
    """Cut a time-ordered stream of chunks into consecutive windows.

    Same semantics as :meth:`Events.windows` applied to the concatenated stream: time windows
    are half-open ``[t_start + k·window_us, t_start + (k+1)·window_us)`` with ``t_start`` the
    first event's time unless ``t_start_us`` is given; empty time windows are skipped unless
    ``include_empty``; count windows hold exactly ``count`` events (the last one fewer).
    The windows concatenate to exactly the input events, in order.

    Args:
        chunks: event chunks in non-decreasing time order (validated by the caller).
        window_us: window duration in µs (> 0), or ``None``.
        count: events per window (> 0), or ``None``; exactly one of the two is given.
        t_start_us: start of the first time window; must not be after the first event.
        include_empty: also yield empty windows between events (time windows only).
        sensor_size: sensor size given to empty windows.
    """
    if (window_us is None) == (count is None):
        raise ValueError("give exactly one of window_us and count")
    if count is not None:
        if int(count) <= 0:
            raise ValueError(f"count must be positive, got {count}")
        return _count_windows(chunks, int(count), sensor_size)
    if int(window_us) <= 0:
        raise ValueError(f"window_us must be positive, got {window_us}")
    return _time_windows(chunks, int(window_us), t_start_us, include_empty, sensor_size)


def _count_windows(
    chunks: Iterator[Events], count: int, sensor_size: tuple[int, int] | None
) -> Iterator[Events]:
    pending: list[Events] = []
    have = 0
    for ch in chunks:
        while len(ch):
            take = min(count - have, len(ch))
            pending.append(ch[:take])
            have += take
            ch = ch[take:]
            if have == count:
                yield _join(pending, sensor_size)
                pending, have = [], 0
    if have:
        yield _join(pending, sensor_size)


def _time_windows(
    chunks: Iterator[Events],
    window_us: int,
    t_start_us: int | None,
    include_empty: bool,
    sensor_size: tuple[int, int] | None,
) -> Iterator[Events]:
    start: int | None = None  # start time of window 0 of the current chunk
    pending: list[Events] = []  # pieces of the window being filled (window 0)
    for ch in chunks:
        if not len(ch):
            continue
        t = ch.t.cpu().numpy()
        if start is None:
            first = int(t[0])
            if t_start_us is not None and int(t_start_us) > first:
                raise ValueError(
                    f"t_start_us={t_start_us} is after the first event (t={first} µs); "
                    "windows must contain every event"
                )
            start = first if t_start_us is None else int(t_start_us)
        bounds = _window_bounds(t, start, window_us)
        current = 0
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            w = (int(t[s]) - start) // window_us
            if w != current:  # the window being filled is complete
                if pending or include_empty:
                    yield _join(pending, sensor_size)
                pending = []
                if include_empty:
                    for _ in range(w - current - 1):
                        yield Events.empty(sensor_size)
                current = w
            pending.append(ch[s:e])
        start += current * window_us
    if pending:
        yield _join(pending, sensor_size)


def _window_bounds(t: np.ndarray, start: int, window_us: int) -> list[int]:
    """Indices ``[0, ..., len(t)]`` where the window ``(t - start) // window_us`` of the sorted
    timestamps ``t`` changes: the cuts between consecutive non-empty windows.

    Binary search of the window edges the chunk spans (no per-event division: ~7x faster on
    17 M events), unless the chunk spans more windows than it has events (a long gap), where
    one pass over the events' window indices is cheaper.
    """
    n = len(t)
    w_first = (int(t[0]) - start) // window_us
    w_last = (int(t[-1]) - start) // window_us
    if w_last - w_first > n:
        widx = (t - start) // window_us
        cuts = np.flatnonzero(widx[1:] != widx[:-1]) + 1
    else:
        edges = start + window_us * np.arange(w_first + 1, w_last + 1, dtype=np.int64)
        cuts = np.unique(np.searchsorted(t, edges, side="left"))  # empty windows: repeats
        cuts = cuts[cuts < n]
    return [0, *cuts.tolist(), n]


def _join(pieces: list[Events], sensor_size: tuple[int, int] | None) -> Events:
    """Concatenate CPU chunks with numpy (several times faster than torch.cat here)."""
    if not pieces:
        return Events.empty(sensor_size)
    if len(pieces) == 1:
        return pieces[0]
    if any(pc.device.type != "cpu" for pc in pieces):
        return concatenate(pieces)
    arrays = [pc.numpy() for pc in pieces]
    coord = np.int32 if any(a["x"].dtype == np.int32 for a in arrays) else arrays[0]["x"].dtype
    cat = {k: np.concatenate([a[k] for a in arrays]) for k in ("t", "p")}
    return Events(
        np.concatenate([a["x"].astype(coord, copy=False) for a in arrays]),
        np.concatenate([a["y"].astype(coord, copy=False) for a in arrays]),
        cat["t"], cat["p"], pieces[0].sensor_size,
    )


class EventReader(ABC):
    """An open event file: metadata, windowed reads and streaming.

    Use :func:`evtrack.io.open_events` to get one. Readers are context managers.

    Attributes:
        path: the file.
        format: the format name (``'hdf5'``, ``'text'``, ...).
        sensor_size: ``(width, height)`` in pixels, or ``None`` when the file does not say and
            none was given.

    Every event a reader returns has passed :func:`check_events`: timestamps non-decreasing
    (also across chunks), coordinates inside the sensor, polarity ±1. A problem raises
    :class:`EventFileError` naming the file, the problem, the count and the first offending
    index; a reader never drops or reorders events.
    """

    format: str = ""

    def __init__(self, path: str | Path, sensor_size: tuple[int, int] | None = None) -> None:
        self.path = Path(path)
        self.sensor_size: tuple[int, int] | None = (
            None if sensor_size is None else (int(sensor_size[0]), int(sensor_size[1]))
        )
        self._num_events: int | None = None
        self._t_start: int | None = None
        self._t_end: int | None = None
        self._scanned = False

    # ----------------------------------------------------------------- to implement
    @abstractmethod
    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        """Yield ``(chunk, locator)`` in file order, unvalidated, with ``self.sensor_size``."""

    def _expected_count(self) -> int | None:
        """Number of events the file claims to hold (checked after a full pass), if any."""
        return None

    # ----------------------------------------------------------------- streaming
    def iter_chunks(self) -> Iterator[Events]:
        """Validated chunks in file order (sizes as stored; use :meth:`iter_windows` to choose)."""
        offset = 0
        prev_t: int | None = None
        t_first: int | None = None
        for ch, locate in self._raw_chunks():
            if not len(ch):
                continue
            check_events(ch, self.path, offset=offset, prev_t=prev_t, locate=locate,
                         scope=f" in events {offset}..{offset + len(ch) - 1}")
            if t_first is None:
                t_first = int(ch.t[0])
            prev_t = int(ch.t[-1])
            offset += len(ch)
            yield ch
        expected = self._expected_count()
        if expected is not None and expected != offset:
            raise EventFileError(
                self.path, f"the file says it holds {expected} events but {offset} were read: "
                "truncated or corrupt"
            )
        self._num_events, self._t_start, self._t_end = offset, t_first, prev_t
        self._scanned = True

    def iter_windows(
        self,
        window_us: int | None = None,
        count: int | None = None,
        *,
        t_start_us: int | None = None,
        include_empty: bool = False,
    ) -> Iterator[Events]:
        """Stream the file in consecutive windows without loading it whole.

        Args:
            window_us: window duration in µs; windows are ``[t_start + k·window_us,
                t_start + (k+1)·window_us)`` from the first event (or ``t_start_us``).
            count: events per window instead (the last window may hold fewer).
            t_start_us: start of the first time window (at or before the first event).
            include_empty: yield empty time windows too (skipped by default, as in
                :meth:`Events.windows`).

        With neither ``window_us`` nor ``count``, windows of :data:`DEFAULT_WINDOW_COUNT`
        events. The windows concatenate to exactly :meth:`read`'s result.
        """
        if window_us is None and count is None:
            count = DEFAULT_WINDOW_COUNT
        return rewindow(
            self.iter_chunks(), window_us=window_us, count=count, t_start_us=t_start_us,
            include_empty=include_empty, sensor_size=self.sensor_size,
        )

    # ----------------------------------------------------------------- reading
    def read(self, t0_us: int | None = None, t1_us: int | None = None) -> Events:
        """Events with ``t0_us <= t < t1_us`` (``None``: unbounded), validated.

        The base implementation streams the file and keeps only the window (memory bounded by
        the window; time proportional to the file up to ``t1_us``). Indexed formats (HDF5)
        read only the window.
        """
        if t0_us is None and t1_us is None:
            return self._read_all()
        pieces: list[Events] = []
        for ch in self.iter_chunks():
            if t1_us is not None and int(ch.t[0]) >= t1_us:
                break
            lo = 0 if t0_us is None else _searchsorted(ch.t, t0_us)
            hi = len(ch) if t1_us is None else _searchsorted(ch.t, t1_us)
            if hi > lo:
                pieces.append(ch[lo:hi])
        return _join(pieces, self.sensor_size)

    def _read_all(self) -> Events:
        ev = _join(list(self.iter_chunks()), self.sensor_size)
        return ev

    # ----------------------------------------------------------------- metadata
    def _scan(self) -> None:
        if not self._scanned:
            for _ in self.iter_chunks():
                pass

    @property
    def num_events(self) -> int:
        """Number of events (a streaming pass over the file for formats without an index)."""
        self._scan()
        return int(self._num_events or 0)

    @property
    def t_start(self) -> int | None:
        """First timestamp in µs, or ``None`` for a file without events."""
        self._scan()
        return self._t_start

    @property
    def t_end(self) -> int | None:
        """Last timestamp in µs, or ``None`` for a file without events."""
        self._scan()
        return self._t_end

    @property
    def indexed(self) -> bool:
        """Whether metadata and time-window reads avoid a pass over the whole file."""
        return False

    # ----------------------------------------------------------------- lifetime
    def close(self) -> None:  # noqa: B027 (formats without open handles keep this no-op)
        """Release the file (idempotent)."""

    def __enter__(self) -> EventReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, sensor_size={self.sensor_size})"


def _searchsorted(t: torch.Tensor, value: int) -> int:
    return int(torch.searchsorted(t, torch.tensor([int(value)], dtype=torch.int64))[0])

