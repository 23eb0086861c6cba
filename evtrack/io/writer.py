"""The lifecycle every streaming event writer shares: atomic close, discard on failure."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from evtrack.errors import EventsError, EvtrackError
from evtrack.events import Events
from evtrack.io.reader import quick_valid

__all__ = ["StreamingWriter"]


class StreamingWriter:
    """Base of the streaming writers (HDF5, text, npz), used as context managers.

    A subclass writes into a temporary file, counts events in ``self._n``, sets
    ``self._closed = False`` when it opens, and implements :meth:`close` (which makes the file
    appear at its path, atomically) and :meth:`_discard` (which removes every trace of it).
    Leaving the ``with`` block by an exception, or calling :meth:`abort`, discards.
    """

    path: Path
    sensor_size: tuple[int, int] | None
    _n: int
    _closed: bool
    _last_t: int | None

    def _checked_chunk(self, events: Events) -> Events | None:
        """The chunk to append, with the file's sensor size, or ``None`` if it is empty.

        Raises:
            EvtrackError: the writer is closed.
            EventsError: a sensor size other than the file's, invalid events (unsorted,
                outside the sensor, bad polarity), or a chunk that starts before the last one
                ended.
        """
        if self._closed:
            raise EvtrackError(f"{self.path}: write() after close()")
        if not len(events):
            return None
        if (events.sensor_size is not None and self.sensor_size is not None
                and tuple(events.sensor_size) != self.sensor_size):
            raise EventsError(
                f"{self.path}: chunk has sensor_size {events.sensor_size}, the file "
                f"{self.sensor_size}"
            )
        size = self.sensor_size if self.sensor_size is not None else events.sensor_size
        ev = Events(events.x, events.y, events.t, events.p, size)
        if not quick_valid(ev):
            raise EventsError(f"{self.path}: cannot write invalid events: {ev.validate()}")
        t0 = int(ev.t[0])
        if self._last_t is not None and t0 < self._last_t:
            raise EventsError(
                f"{self.path}: chunks must be written in time order: chunk starts at "
                f"t={t0} µs after {self._last_t} µs (event {self._n})"
            )
        return ev

    def close(self) -> None:  # pragma: no cover - every subclass overrides it
        raise NotImplementedError

    def _discard(self) -> None:  # pragma: no cover - every subclass overrides it
        raise NotImplementedError

    def _abort_quietly(self) -> None:
        self._closed = True
        self._discard()

    def abort(self) -> None:
        """Discard everything written; no file is created (idempotent)."""
        if not self._closed:
            self._abort_quietly()

    @property
    def num_events(self) -> int:
        """Events written so far."""
        return self._n

    def __enter__(self) -> Any:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
