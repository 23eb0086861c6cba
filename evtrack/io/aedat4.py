"""iniVation AEDAT 4.0 files, read through the PyPI ``aedat`` package (read only).

The sensor size is the event stream's ``width``/``height`` from the file's description.
Packets are decoded one at a time (``aedat.Decoder`` iterates packets) and grouped into chunks
of about :data:`CHUNK_EVENTS` events, so a file is streamed without being loaded whole.
Timestamps are the camera's absolute µs (t u64 in the file, int64 here). IMU, trigger and frame
streams are skipped. A file with several event streams must be read with an explicit
``Aedat4Reader(path, stream_id=...)``; the other readers refuse it rather than drop a stream.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import aedat
import numpy as np

from evtrack.errors import EventFileError
from evtrack.events import Events
from evtrack.io.reader import EventReader, Locator

__all__ = ["Aedat4Reader", "CHUNK_EVENTS"]

CHUNK_EVENTS = 1 << 16  # packets are grouped into chunks of at least this many events
_INT16_MAX_SIDE = 32767
_INT64_MAX = np.iinfo(np.int64).max


class Aedat4Reader(EventReader):
    """Streaming AEDAT 4.0 reader.

    Args:
        path: the file.
        sensor_size: overrides the event stream's width/height.
        stream_id: the event stream to read; required when the file has more than one.

    Raises:
        EventFileError: the decoder cannot open the file, the file has no event stream, or the
            decoder fails part-way (truncated or corrupt packets); the message says how many
            events were decoded before the failure.
    """

    format = "aedat4"

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        stream_id: int | None = None,
    ) -> None:
        super().__init__(path, sensor_size)
        decoder = self._open()
        streams = decoder.id_to_stream()
        events = sorted(i for i, s in streams.items() if s.get("type") == "events")
        if not events:
            kinds = sorted({s.get("type", "?") for s in streams.values()})
            raise EventFileError(self.path, f"no event stream in the file (streams: {kinds})")
        if stream_id is not None:
            if stream_id not in events:
                raise EventFileError(
                    self.path, f"stream {stream_id} is not an event stream (those are {events})"
                )
            self._stream = stream_id
        elif len(events) > 1:
            raise EventFileError(
                self.path, f"the file has {len(events)} event streams {events}; choose one with "
                "Aedat4Reader(path, stream_id=...)"
            )
        else:
            self._stream = events[0]
        info = streams[self._stream]
        if sensor_size is None:
            w, h = int(info.get("width", 0)), int(info.get("height", 0))
            if w <= 0 or h <= 0:
                raise EventFileError(
                    self.path, f"event stream {self._stream} has no valid width/height ({w}x{h}); "
                    "pass sensor_size=(W, H)"
                )
            self.sensor_size = (w, h)

    def _open(self) -> aedat.Decoder:
        try:
            return aedat.Decoder(str(self.path))
        except Exception as exc:  # the Rust decoder raises RuntimeError/OSError/ValueError
            raise EventFileError(self.path, f"the AEDAT4 decoder cannot open it: {exc}") from exc

    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        decoder = self._open()
        pending: list[np.ndarray] = []
        have = 0
        decoded = 0
        while True:
            try:
                packet = next(decoder)
            except StopIteration:
                break
            except Exception as exc:
                raise EventFileError(
                    self.path, f"the AEDAT4 decoder failed after {decoded + have} events: {exc} "
                    "(truncated or corrupt)"
                ) from exc
            if packet.get("stream_id") != self._stream or "events" not in packet:
                continue
            arr = packet["events"]
            pending.append(arr)
            have += len(arr)
            if have >= CHUNK_EVENTS:
                yield self._to_events(pending), None
                decoded += have
                pending, have = [], 0
        if pending:
            yield self._to_events(pending), None

    def _to_events(self, packets: list[np.ndarray]) -> Events:
        arr = np.concatenate(packets) if len(packets) > 1 else packets[0]
        t = arr["t"]
        if t.size and int(t.max()) > _INT64_MAX:
            raise EventFileError(self.path, "timestamp beyond the int64 µs range: corrupt packet")
        x, y = arr["x"], arr["y"]
        small = x.size == 0 or max(int(x.max()), int(y.max())) <= _INT16_MAX_SIDE
        coord = np.int16 if small else np.int32  # never wrap a corrupt u16 into a valid value
        return Events(
            x.astype(coord),
            y.astype(coord),
            t.astype(np.int64),
            np.where(arr["on"], 1, -1).astype(np.int8),
            self.sensor_size,
        )
