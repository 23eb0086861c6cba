"""Event file readers and writers.

Formats (:func:`detect_format` tells them apart by first bytes and extension):

========  =====================  ==========  ===============================================
name      extensions             access      notes
========  =====================  ==========  ===============================================
hdf5      .h5 .hdf5 .hdf         read/write  native; ms index for time-window reads
text      .txt                   read/write  ``t x y p`` lines, t in seconds (exact to 1 µs)
npz       .npz                   read/write  arrays x, y, t, p, sensor_size; loaded whole
aedat4    .aedat4                read        iniVation, via ``aedat``
evt2      .raw                   read        Prophesee EVT 2.0, via ``expelliarmus``
evt3      .raw                   read        Prophesee EVT 3.0, via ``expelliarmus``
========  =====================  ==========  ===============================================

Example::

    from evtrack.io import read_events, iter_events, open_events, write_events

    ev = read_events("recording.raw")                   # Events, validated
    for win in iter_events("big.h5", window_us=10_000):  # streamed, 10 ms windows
        ...
    with open_events("big.h5") as r:
        part = r.read(t0_us=1_000_000, t1_us=1_050_000)  # only that window is read
    write_events("copy.h5", ev, compression="lzf")
"""

from __future__ import annotations

from evtrack.io.aedat4 import Aedat4Reader
from evtrack.io.api import (
    WRITABLE_FORMATS,
    Writer,
    iter_events,
    open_events,
    open_writer,
    read_events,
    write_events,
)
from evtrack.io.formats import FORMATS, FormatInfo, detect_format, formats_help
from evtrack.io.hdf5 import EventWriter, Hdf5Reader
from evtrack.io.npz import NpzReader, NpzWriter
from evtrack.io.prophesee import RawReader
from evtrack.io.reader import DEFAULT_WINDOW_COUNT, EventReader
from evtrack.io.text import TextReader, TextWriter, parse_seconds_to_us

__all__ = [
    "DEFAULT_WINDOW_COUNT",
    "FORMATS",
    "WRITABLE_FORMATS",
    "Aedat4Reader",
    "EventReader",
    "EventWriter",
    "FormatInfo",
    "Hdf5Reader",
    "NpzReader",
    "NpzWriter",
    "RawReader",
    "TextReader",
    "TextWriter",
    "Writer",
    "detect_format",
    "formats_help",
    "iter_events",
    "open_events",
    "open_writer",
    "parse_seconds_to_us",
    "read_events",
    "write_events",
]
