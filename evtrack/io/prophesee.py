"""Prophesee RAW files (EVT 2.0 and EVT 3.0), read through the PyPI ``expelliarmus`` package.

The encoding comes from the ``% evt 2.0``/``% evt 3.0`` (or ``% format EVT3;...``) header line.
The sensor size, in order of preference:

1. ``sensor_size=`` given by the caller;
2. a ``% geometry W x H`` header line, or the ``width``/``height`` of a ``% format`` line;
3. the sensor generation, from a ``% sensor_generation`` line or the ``% plugin_name``
   (e.g. ``hal_plugin_gen41_evk3``), looked up in :data:`SENSOR_SIZES_BY_GENERATION`
   (gen3/gen31 → 640x480, gen4/gen41/imx636 → 1280x720). Caveat: the older Gen3 *ATIS* sensor
   is 480x360; events outside the looked-up size are reported, never dropped;
4. otherwise opening raises :class:`EventFileError` asking for ``sensor_size=(W, H)``.

Streaming uses ``Wizard.read_chunk``. expelliarmus stops silently on data it cannot decode;
this reader checks the decoder reached the end of the file and raises otherwise. Polarity 1 is
ON (+1), 0 is OFF (-1).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evtrack.errors import EventFileError
from evtrack.events import Events
from evtrack.io.formats import MAX_RAW_HEADER_BYTES, RawHeader, parse_raw_header
from evtrack.io.reader import EventReader, Locator, check_events


def _wizard(path: Path, **kwargs):
    """An expelliarmus ``Wizard``; imported here so that ``import evtrack`` works without it."""
    try:
        from expelliarmus import Wizard
    except ImportError as exc:
        raise EventFileError(path, "reading Prophesee RAW files needs the expelliarmus package "
                                   f"(pip install expelliarmus): {exc}") from exc
    return Wizard(**kwargs)

__all__ = ["RawReader", "SENSOR_SIZES_BY_GENERATION", "sensor_size_from_header", "CHUNK_EVENTS"]

CHUNK_EVENTS = 1 << 18  # events per chunk requested from expelliarmus when streaming
SENSOR_SIZES_BY_GENERATION: dict[str, tuple[int, int]] = {
    "gen3": (640, 480),
    "gen31": (640, 480),
    "gen4": (1280, 720),
    "gen41": (1280, 720),
    "imx636": (1280, 720),
}
_WORD_BYTES = {"evt2": 4, "evt3": 2}
_GEN_RE = re.compile(r"(gen\d+|imx\d+)", re.IGNORECASE)


def sensor_size_from_header(header: RawHeader) -> tuple[tuple[int, int], str] | None:
    """``((width, height), where_from)`` from a RAW header, or ``None`` (see module docstring)."""
    if header.geometry is not None:
        return header.geometry, "the header's geometry"
    gen = header.fields.get("sensor_generation", "").strip()
    if gen:
        key = "gen" + gen.replace(".", "")
        if key in SENSOR_SIZES_BY_GENERATION:
            return SENSOR_SIZES_BY_GENERATION[key], f"sensor_generation {gen}"
    plugin = header.fields.get("plugin_name", "")
    for m in _GEN_RE.finditer(plugin):
        key = m.group(1).lower()
        if key in SENSOR_SIZES_BY_GENERATION:
            return SENSOR_SIZES_BY_GENERATION[key], f"plugin_name {plugin}"
    return None


class RawReader(EventReader):
    """Reader of Prophesee RAW EVT 2.0/3.0 files (see the module docstring).

    Args:
        path: the file.
        sensor_size: ``(width, height)``; overrides what the header says.
        chunk_events: events per streamed chunk.
    """

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        chunk_events: int = CHUNK_EVENTS,
    ) -> None:
        super().__init__(path, sensor_size)
        self._chunk = int(chunk_events)
        self._tmpdir: Path | None = None
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as fh:
                header = parse_raw_header(fh.read(MAX_RAW_HEADER_BYTES))
        except OSError as exc:
            raise EventFileError(self.path, f"cannot read: {exc}") from exc
        if header is None:
            raise EventFileError(
                self.path, "not a Prophesee RAW file, or its '%' header is truncated (no newline "
                "after the last header line)"
            )
        if header.encoding not in _WORD_BYTES:
            raise EventFileError(
                self.path, f"RAW encoding {header.encoding or 'not stated in the header'} is not "
                "supported (EVT 2.0 and EVT 3.0 are)"
            )
        self.format = header.encoding
        self.header = header
        self._data_bytes = size - header.length
        word = _WORD_BYTES[header.encoding]
        if self._data_bytes % word:
            raise EventFileError(
                self.path, f"the data after the header ({self._data_bytes} bytes) is not a whole "
                f"number of {word}-byte {header.encoding.upper()} words: truncated"
            )
        if sensor_size is None:
            found = sensor_size_from_header(header)
            if found is None:
                raise EventFileError(
                    self.path, "the sensor size is unknown: the header has no '% geometry' line "
                    f"and plugin_name {header.fields.get('plugin_name', '(absent)')!r} is not in "
                    f"the table {sorted(SENSOR_SIZES_BY_GENERATION)}; pass sensor_size=(W, H)"
                )
            self.sensor_size = found[0]

    def _decoder_path(self) -> Path:
        """expelliarmus insists on a name ending '.raw' (after resolving symlinks).

        Other names get a hard link named ``events.raw`` in a temporary folder, or a copy when
        the temporary folder is on another file system.
        """
        real = self.path.resolve()
        if real.suffix == ".raw":
            return real
        if self._tmpdir is None:
            self._tmpdir = Path(tempfile.mkdtemp(prefix="evtrack-raw-"))
            target = self._tmpdir / "events.raw"
            try:
                os.link(real, target)
            except OSError:
                shutil.copyfile(real, target)
        return self._tmpdir / "events.raw"

    def _to_events(self, arr: np.ndarray) -> Events:
        return Events(
            np.ascontiguousarray(arr["x"]),
            np.ascontiguousarray(arr["y"]),
            np.ascontiguousarray(arr["t"]),
            (arr["p"].astype(np.int8) * 2 - 1).astype(np.int8),
            self.sensor_size,
        )

    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        if self._data_bytes == 0:
            return
        wizard = _wizard(self.path, encoding=self.format, fpath=self._decoder_path(),
                         chunk_size=self._chunk)
        decoded = 0
        try:
            for arr in wizard.read_chunk():
                decoded += len(arr)
                yield self._to_events(arr), None
        except (RuntimeError, ValueError) as exc:
            raise EventFileError(
                self.path, f"expelliarmus failed after {decoded} events: {exc}"
            ) from exc
        # read_chunk ends silently on undecodable data; 'finished' is set only at end of file.
        if not wizard.cargo.events_info.finished:
            raise EventFileError(
                self.path, f"the {self.format.upper()} decoder stopped before the end of the "
                f"file, having given {decoded} events (it decodes in chunks of {self._chunk}: "
                "a chunk holding corrupt or unsupported data words gives none)"
            )

    def _read_all(self) -> Events:
        if self._data_bytes == 0:
            return Events.empty(self.sensor_size)
        try:
            arr = _wizard(self.path, encoding=self.format).read(self._decoder_path())
        except (RuntimeError, ValueError) as exc:
            raise EventFileError(self.path, f"expelliarmus failed: {exc}") from exc
        if arr is None:  # no events, or a decode failure: the chunked pass tells which
            return super()._read_all()
        ev = self._to_events(arr)
        check_events(ev, self.path)
        self._num_events, self._scanned = len(ev), True
        self._t_start, self._t_end = int(ev.t[0]), int(ev.t[-1])
        return ev

    def close(self) -> None:
        if self._tmpdir is not None:
            with contextlib.suppress(OSError):
                shutil.rmtree(self._tmpdir)
            self._tmpdir = None
