"""The lifecycle every streaming event writer shares: atomic close, discard on failure."""

from __future__ import annotations

from typing import Any

__all__ = ["StreamingWriter"]


class StreamingWriter:
    """Base of the streaming writers (HDF5, text, npz), used as context managers.

    A subclass writes into a temporary file, counts events in ``self._n``, sets
    ``self._closed = False`` when it opens, and implements :meth:`close` (which makes the file
    appear at its path, atomically) and :meth:`_discard` (which removes every trace of it).
    Leaving the ``with`` block by an exception, or calling :meth:`abort`, discards.
    """

    _n: int
    _closed: bool

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
