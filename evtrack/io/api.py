"""The format-independent entry points: open, read, stream and write event files."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

from evtrack.errors import EventFileError
from evtrack.events import Events
from evtrack.io.aedat4 import Aedat4Reader
from evtrack.io.formats import FORMATS, detect_format, format_from_extension
from evtrack.io.hdf5 import EventWriter, Hdf5Reader, write_hdf5
from evtrack.io.npz import NpzReader, NpzWriter, write_npz
from evtrack.io.prophesee import RawReader
from evtrack.io.reader import EventReader
from evtrack.io.text import TextReader, TextWriter, write_text

__all__ = [
    "open_events",
    "read_events",
    "iter_events",
    "write_events",
    "open_writer",
    "Writer",
    "WRITABLE_FORMATS",
]

_READERS: dict[str, type[EventReader]] = {
    "hdf5": Hdf5Reader,
    "text": TextReader,
    "npz": NpzReader,
    "aedat4": Aedat4Reader,
    "evt2": RawReader,
    "evt3": RawReader,
}
_WRITE_FUNCTIONS = {"hdf5": write_hdf5, "text": write_text, "npz": write_npz}
WRITABLE_FORMATS = tuple(f.name for f in FORMATS.values() if f.writable)


class Writer(Protocol):
    """What :func:`open_writer` returns: a streaming writer with an atomic close."""

    def write(self, events: Events) -> None: ...

    def close(self) -> None: ...

    def abort(self) -> None: ...

    def __enter__(self) -> Writer: ...

    def __exit__(self, *exc: object) -> None: ...


def open_events(
    path: str | Path, *, sensor_size: tuple[int, int] | None = None, format: str | None = None
) -> EventReader:
    """Open an event file of any readable format.

    Args:
        path: the file.
        sensor_size: ``(width, height)``; overrides the size the file states (needed for text
            files without a ``# sensor_size`` line, and RAW files of unknown sensors).
        format: skip detection and read as this format.

    Returns:
        An :class:`EventReader` (context manager) with ``sensor_size``, ``num_events``,
        ``t_start``/``t_end`` (µs), ``read(t0_us, t1_us)`` and ``iter_windows(...)``.

    Raises:
        UnknownFormatError: unrecognised content and extension.
        EventFileError: missing, truncated or corrupt file.
    """
    fmt = format or detect_format(path)
    if fmt not in _READERS:
        raise ValueError(f"unknown format {fmt!r}; readable formats: {sorted(_READERS)}")
    return _READERS[fmt](path, sensor_size)


def read_events(path: str | Path, *, sensor_size: tuple[int, int] | None = None) -> Events:
    """Read a whole event file, validated.

    Returns all events (x, y int; t int64 µs non-decreasing; p int8 ±1; sensor size), or
    raises :class:`EventFileError` naming the file and the problem (unsorted timestamps,
    events outside the sensor, bad polarity, truncated or corrupt data); never a subset.
    """
    with open_events(path, sensor_size=sensor_size) as reader:
        return reader.read()


def iter_events(
    path: str | Path,
    *,
    window_us: int | None = None,
    count: int | None = None,
    sensor_size: tuple[int, int] | None = None,
    t_start_us: int | None = None,
    include_empty: bool = False,
) -> Iterator[Events]:
    """Stream an event file in consecutive windows without loading it whole.

    Windows are ``[t_start + k·window_us, t_start + (k+1)·window_us)`` from the first event (or
    ``t_start_us``), or runs of ``count`` events; with neither, runs of
    :data:`evtrack.io.reader.DEFAULT_WINDOW_COUNT` events. Empty time windows are skipped
    unless ``include_empty``. The windows concatenate to exactly :func:`read_events`'s result.
    Memory: one window plus one decoder chunk, except ``.npz`` (loaded whole).

    The file is opened (and its format detected) when this is called, so a missing or
    unrecognised file raises here; the file is closed when the iteration ends.
    """
    reader = open_events(path, sensor_size=sensor_size)
    try:
        windows = reader.iter_windows(
            window_us, count, t_start_us=t_start_us, include_empty=include_empty
        )
    except BaseException:
        reader.close()
        raise
    return _closing(reader, windows)


def _closing(reader: EventReader, windows: Iterator[Events]) -> Iterator[Events]:
    with reader:
        yield from windows


def _writable_format(path: Path, format: str | None) -> str:
    fmt = format or format_from_extension(path)
    if fmt in WRITABLE_FORMATS:
        return fmt
    names = ", ".join(f"{n} ({'/'.join(FORMATS[n].extensions)})" for n in WRITABLE_FORMATS)
    if fmt in ("raw", "evt2", "evt3", "aedat4"):
        raise EventFileError(
            path, f"writing {fmt.upper()} is not supported (evtrack reads it only); "
            f"writable formats: {names}"
        )
    raise EventFileError(
        path, f"cannot tell the output format from the name (extension '{path.suffix}'); "
        f"writable formats: {names}, or pass format=..."
    )


def open_writer(
    path: str | Path,
    sensor_size: tuple[int, int] | None,
    *,
    format: str | None = None,
    **options: Any,
) -> Writer:
    """A streaming writer for ``path``'s format (by extension unless ``format`` is given).

    Options: hdf5 — those of :class:`EventWriter` (``compression``, ``compression_opts``,
    ``chunk_events``, ``checksum``, ``t0_us``); npz — ``compress``; text — none.
    The file appears atomically when the writer is closed without error.
    """
    path = Path(path)
    fmt = _writable_format(path, format)
    if fmt == "hdf5":
        return EventWriter(path, sensor_size, **options)
    if options:
        allowed = {"npz": {"compress"}, "text": set()}[fmt]
        unknown = set(options) - allowed
        if unknown:
            raise TypeError(f"unknown {fmt} writer options {sorted(unknown)}")
    if fmt == "npz":
        return NpzWriter(path, sensor_size, **options)
    return TextWriter(path, sensor_size)


def write_events(path: str | Path, events: Events, **format_options: Any) -> None:
    """Write events to ``path`` atomically (temporary file, then rename).

    The format comes from the extension (``.h5``/``.hdf5``, ``.txt``, ``.npz``) or
    ``format=...``. Other options go to the format's writer (see :func:`open_writer`);
    ``sensor_size=(W, H)`` supplies a size when ``events.sensor_size`` is ``None``.

    Raises:
        EventsError: the events are invalid (unsorted, outside the sensor, bad polarity), or
            HDF5 is asked for without a sensor size.
        EventFileError: the format cannot be written (AEDAT4, RAW) or is unknown.
    """
    path = Path(path)
    fmt = _writable_format(path, format_options.pop("format", None))
    _WRITE_FUNCTIONS[fmt](path, events, **format_options)
