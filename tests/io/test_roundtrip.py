"""Every writable format gives back exactly what was written, streamed or whole."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.errors import EventFileError, EventsError
from evtrack.events import Events, concatenate
from evtrack.io import (
    detect_format,
    iter_events,
    open_events,
    open_writer,
    read_events,
    write_events,
)

WRITABLE = {"hdf5": "h5", "text": "txt", "npz": "npz"}


def _single(sensor=(640, 480)) -> Events:
    return Events([3], [4], [123_456_789], [-1], sensor)


def _cases(factory):
    return {
        "empty": Events.empty((640, 480)),
        "single": _single(),
        "int16": factory(1000, seed=1, coord_dtype=np.int16),
        "int32": factory(1000, seed=2, coord_dtype=np.int32),
        "wide_sensor_int32": factory(500, seed=3, sensor_size=(40_000, 35_000),
                                     coord_dtype=np.int32),
        # absolute camera clocks (~50 years in µs) and close to the int64 limit
        "large_t": factory(300, seed=4, t0=1_605_537_493_718_345),
        "huge_t": factory(50, seed=5, t0=9_000_000_000_000_000_000),
        "same_t": Events([1, 2, 3], [1, 2, 3], [5, 5, 5], [1, -1, 1], (640, 480)),
    }


@pytest.mark.parametrize("fmt", list(WRITABLE))
def test_round_trip_every_case(tmp_path, events_factory, fmt):
    for name, ev in _cases(events_factory).items():
        path = tmp_path / f"{name}.{WRITABLE[fmt]}"
        write_events(path, ev)
        assert detect_format(path) == fmt
        back = read_events(path)
        assert back == ev, name
        assert back.t.dtype == torch.int64 and back.p.dtype == torch.int8
        windows = list(iter_events(path, window_us=997))
        assert concatenate(windows) == ev if windows else len(ev) == 0
        counted = list(iter_events(path, count=7))
        assert all(len(w) == 7 for w in counted[:-1])
        assert sum(len(w) for w in counted) == len(ev)


@pytest.mark.parametrize("fmt", list(WRITABLE))
def test_streaming_writer_equals_whole_write(tmp_path, events_factory, fmt):
    ev = events_factory(5000, seed=7)
    path = tmp_path / f"s.{WRITABLE[fmt]}"
    with open_writer(path, ev.sensor_size) as w:
        for part in ev.windows(count=333):
            w.write(part)
        assert not path.exists()  # appears only on close
    assert path.exists()
    assert read_events(path) == ev


@pytest.mark.parametrize("fmt", list(WRITABLE))
def test_writer_failure_leaves_nothing(tmp_path, events_factory, fmt):
    ev = events_factory(100, seed=8)
    path = tmp_path / f"f.{WRITABLE[fmt]}"
    with pytest.raises(RuntimeError), open_writer(path, ev.sensor_size) as w:
        w.write(ev)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt", list(WRITABLE))
def test_writers_refuse_invalid_or_out_of_order_chunks(tmp_path, events_factory, fmt):
    ev = events_factory(100, seed=9)
    path = tmp_path / f"bad.{WRITABLE[fmt]}"
    unsorted = Events(ev.x, ev.y, ev.t.flip(0), ev.p, ev.sensor_size)
    with pytest.raises(EventsError, match="backwards"):
        write_events(path, unsorted)
    outside = Events(ev.x + 1000, ev.y, ev.t, ev.p, ev.sensor_size)
    with pytest.raises(EventsError, match="outside the sensor"):
        write_events(path, outside)
    with pytest.raises(EventsError, match="time order"), open_writer(path, ev.sensor_size) as w:
        w.write(ev[50:])
        w.write(ev[:50])
    assert list(tmp_path.iterdir()) == []


def test_overwrite_is_atomic_and_keeps_old_file_on_failure(tmp_path, events_factory):
    path = tmp_path / "a.h5"
    first = events_factory(100, seed=10)
    write_events(path, first)
    bad = Events(first.x, first.y, first.t.flip(0), first.p, first.sensor_size)
    with pytest.raises(EventsError):
        write_events(path, bad)
    assert read_events(path) == first
    second = events_factory(50, seed=11)
    write_events(path, second)
    assert read_events(path) == second
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"]


def test_unwritable_formats_give_a_clear_error(tmp_path, events_factory):
    ev = events_factory(10)
    for name in ("out.raw", "out.aedat4"):
        with pytest.raises(EventFileError, match="not supported.*writable formats: hdf5"):
            write_events(tmp_path / name, ev)
    with pytest.raises(EventFileError, match="cannot tell the output format"):
        write_events(tmp_path / "out.bin", ev)
    write_events(tmp_path / "out.bin", ev, format="npz")
    assert read_events(tmp_path / "out.bin") == ev


def test_hdf5_needs_a_sensor_size(tmp_path):
    ev = Events([1], [2], [3], [1], None)
    with pytest.raises(EventsError, match="sensor_size"):
        write_events(tmp_path / "a.h5", ev)
    write_events(tmp_path / "a.h5", ev, sensor_size=(8, 8))
    assert read_events(tmp_path / "a.h5").sensor_size == (8, 8)
    # text and npz keep an unknown sensor size unknown
    for ext in ("txt", "npz"):
        write_events(tmp_path / f"a.{ext}", ev)
        assert read_events(tmp_path / f"a.{ext}") == ev


@pytest.mark.parametrize("compression", ["lzf", "gzip"])
def test_hdf5_compression_round_trip(tmp_path, events_factory, compression):
    ev = events_factory(3000, seed=12)
    path = tmp_path / "c.h5"
    write_events(path, ev, compression=compression, chunk_events=512)
    assert read_events(path) == ev
    with open_events(path) as r:
        assert r.read(ev.t_start + 500, ev.t_start + 900) == ev.between(
            ev.t_start + 500, ev.t_start + 900)


def test_npz_compressed_round_trip(tmp_path, events_factory):
    ev = events_factory(2000, seed=13)
    write_events(tmp_path / "c.npz", ev, compress=True)
    assert read_events(tmp_path / "c.npz") == ev


def test_sensor_size_argument_overrides_the_file(tmp_path, events_factory):
    ev = events_factory(200, seed=14, sensor_size=(64, 48))
    for ext in WRITABLE.values():
        path = tmp_path / f"o.{ext}"
        write_events(path, ev)
        assert read_events(path, sensor_size=(100, 100)).sensor_size == (100, 100)
        with pytest.raises(EventFileError, match="outside the sensor"):
            read_events(path, sensor_size=(10, 10))


def test_iter_events_checks_arguments_and_file_at_call(tmp_path, events_factory):
    with pytest.raises(EventFileError, match="no such file"):
        iter_events(tmp_path / "missing.h5", window_us=10)
    write_events(tmp_path / "a.h5", events_factory(10))
    for kwargs in ({"window_us": 10, "count": 5}, {"window_us": 0}, {"count": -1}):
        with pytest.raises(ValueError):
            iter_events(tmp_path / "a.h5", **kwargs)
    default = list(iter_events(tmp_path / "a.h5"))  # default: runs of DEFAULT_WINDOW_COUNT
    assert len(default) == 1 and len(default[0]) == 10
    with pytest.raises(ValueError, match="after the first event"):
        list(iter_events(tmp_path / "a.h5", window_us=10, t_start_us=10**12))
