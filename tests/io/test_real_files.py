"""The real camera files in ../shared/data/formats (AEDAT4, Prophesee EVT2/EVT3)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from evtrack.errors import EventFileError
from evtrack.events import concatenate
from evtrack.io import (
    Aedat4Reader,
    RawReader,
    detect_format,
    iter_events,
    open_events,
    read_events,
    write_events,
)
from evtrack.io.formats import parse_raw_header

EVT3_COUNT = 219_596
EVT2_COUNT = 539_481
AEDAT4_COUNT = 111_954


def test_evt3_equals_reference_decode(evt3_file, evt3_reference):
    assert detect_format(evt3_file) == "evt3"
    ev = read_events(evt3_file)
    assert len(ev) == EVT3_COUNT == len(evt3_reference)
    assert ev.sensor_size == (1280, 720)  # plugin gen41, no geometry line
    assert np.array_equal(ev.t.numpy(), evt3_reference["t"])
    assert np.array_equal(ev.x.numpy(), evt3_reference["x"])
    assert np.array_equal(ev.y.numpy(), evt3_reference["y"])
    assert np.array_equal(ev.p.numpy(), evt3_reference["p"].astype(np.int8) * 2 - 1)


def test_evt2_sample(evt2_file):
    assert detect_format(evt2_file) == "evt2"
    ev = read_events(evt2_file)
    assert len(ev) == EVT2_COUNT
    assert ev.sensor_size == (640, 480)  # plugin gen3
    assert int(ev.x.max()) < 640 and int(ev.y.max()) < 480
    assert (ev.t_start, ev.t_end) == (1_317_888, 1_367_888)
    assert set(ev.p.unique().tolist()) == {-1, 1}


def test_aedat4_sample(aedat4_file):
    assert detect_format(aedat4_file) == "aedat4"
    ev = read_events(aedat4_file)
    assert len(ev) == AEDAT4_COUNT
    assert ev.sensor_size == (320, 240)
    assert int(ev.x.max()) < 320 and int(ev.y.max()) < 240
    assert (ev.t_start, ev.t_end) == (1_605_537_493_718_345, 1_605_537_494_308_262)


@pytest.mark.parametrize("name", ["evt3_file", "evt2_file", "aedat4_file"])
def test_windows_concatenate_to_the_full_read(request, name):
    path = request.getfixturevalue(name)
    full = read_events(path)
    windows = list(iter_events(path, window_us=3_000))
    assert all(len(w) for w in windows)
    assert concatenate(windows) == full
    assert [len(w) for w in windows] == [len(w) for w in full.windows(3_000)]
    counted = list(iter_events(path, count=100_000))
    assert concatenate(counted) == full and all(len(w) == 100_000 for w in counted[:-1])
    with open_events(path) as r:
        assert r.num_events == len(full)
        assert (r.t_start, r.t_end) == (full.t_start, full.t_end)
        a, b = full.t_start + 10_000, full.t_start + 13_000
        assert r.read(a, b) == full.between(a, b)


def test_small_raw_chunks_and_other_names(tmp_path, evt3_file, evt3_reference):
    with RawReader(evt3_file, chunk_events=5_000) as r:
        assert np.array_equal(concatenate(list(r.iter_chunks())).t.numpy(), evt3_reference["t"])
    other = tmp_path / "recording.bin"
    other.write_bytes(evt3_file.read_bytes())  # expelliarmus itself wants a .raw name
    assert detect_format(other) == "evt3"
    assert len(read_events(other)) == EVT3_COUNT


def test_convert_real_files_to_hdf5(tmp_path, evt2_file, aedat4_file):
    for src in (evt2_file, aedat4_file):
        ev = read_events(src)
        write_events(tmp_path / "x.h5", ev)
        assert read_events(tmp_path / "x.h5") == ev


def _corrupt_word(src, dst, word_bytes, event_type):
    data = bytearray(src.read_bytes())
    header = parse_raw_header(bytes(data[:4096]))
    pos = header.length + word_bytes * ((len(data) - header.length) // word_bytes // 2)
    word = int.from_bytes(data[pos : pos + word_bytes], "little")
    shift = 8 * word_bytes - 4
    word = (word & ((1 << shift) - 1)) | (event_type << shift)
    data[pos : pos + word_bytes] = word.to_bytes(word_bytes, "little")
    dst.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("name", "word", "bad_type"), [("evt3_file", 2, 0x1), ("evt2_file", 4, 0x5)]
)
def test_undecodable_raw_data_raises(request, tmp_path, name, word, bad_type):
    bad = tmp_path / "bad.raw"
    _corrupt_word(request.getfixturevalue(name), bad, word, bad_type)
    with pytest.raises(EventFileError, match="bad.raw: the EVT. decoder stopped"):
        read_events(bad)
    with pytest.raises(EventFileError, match="decoder stopped"):
        list(iter_events(bad, window_us=1000))


def test_truncated_raw(tmp_path, evt3_file, evt2_file):
    data = evt3_file.read_bytes()
    (tmp_path / "odd.raw").write_bytes(data[:100_001])
    with pytest.raises(EventFileError, match="not a whole number of 2-byte EVT3 words"):
        read_events(tmp_path / "odd.raw")
    data2 = evt2_file.read_bytes()
    (tmp_path / "odd2.raw").write_bytes(data2[:100_002])
    with pytest.raises(EventFileError, match="4-byte EVT2 words: truncated"):
        read_events(tmp_path / "odd2.raw")
    header_only = data[: parse_raw_header(data[:4096]).length]
    (tmp_path / "h.raw").write_bytes(header_only)
    assert len(read_events(tmp_path / "h.raw")) == 0


def test_raw_sensor_size_sources(tmp_path, evt3_file):
    body = evt3_file.read_bytes()[parse_raw_header(evt3_file.read_bytes()[:4096]).length :]
    (tmp_path / "g.raw").write_bytes(b"% evt 3.0\n% geometry 1280 x 720\n" + body)
    assert read_events(tmp_path / "g.raw").sensor_size == (1280, 720)
    (tmp_path / "f.raw").write_bytes(b"% format EVT3;height=800;width=1400\n" + body)
    assert read_events(tmp_path / "f.raw").sensor_size == (1400, 800)
    (tmp_path / "s.raw").write_bytes(b"% evt 3.0\n% sensor_generation 4.1\n" + body)
    assert read_events(tmp_path / "s.raw").sensor_size == (1280, 720)
    (tmp_path / "u.raw").write_bytes(b"% evt 3.0\n% plugin_name hal_plugin_mystery\n" + body)
    with pytest.raises(EventFileError, match="sensor size is unknown.*pass sensor_size"):
        read_events(tmp_path / "u.raw")
    assert read_events(tmp_path / "u.raw", sensor_size=(1280, 720)).sensor_size == (1280, 720)
    (tmp_path / "small.raw").write_bytes(b"% evt 3.0\n% geometry 640x480\n" + body)
    with pytest.raises(EventFileError, match="events outside the sensor \\(640, 480\\)"):
        read_events(tmp_path / "small.raw")


def test_truncated_aedat4(tmp_path, aedat4_file):
    data = aedat4_file.read_bytes()
    (tmp_path / "cut.aedat4").write_bytes(data[: len(data) // 2])
    with pytest.raises(EventFileError, match="cut.aedat4: the AEDAT4 decoder failed after"):
        read_events(tmp_path / "cut.aedat4")
    (tmp_path / "hdr.aedat4").write_bytes(data[:40])
    with pytest.raises(EventFileError, match="hdr.aedat4"):
        read_events(tmp_path / "hdr.aedat4")


def test_aedat4_stream_choice(aedat4_file):
    with Aedat4Reader(aedat4_file, stream_id=0) as r:
        assert r.num_events == AEDAT4_COUNT
    with pytest.raises(EventFileError, match="stream 2 is not an event stream"):
        Aedat4Reader(aedat4_file, stream_id=2)  # the IMU stream


def test_raw_without_expelliarmus_is_a_clear_error(evt3_file, monkeypatch):
    """``import evtrack`` works without the decoder; reading a RAW file then names it."""
    monkeypatch.setitem(sys.modules, "expelliarmus", None)  # makes the import fail
    with pytest.raises(EventFileError, match="needs the expelliarmus package"):
        read_events(evt3_file)
