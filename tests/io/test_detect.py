"""Format detection by first bytes and extension."""

from __future__ import annotations

import pytest

from evtrack.errors import EventFileError, UnknownFormatError
from evtrack.io import detect_format, read_events, write_events


def test_content_decides_over_extension(tmp_path, events_factory):
    ev = events_factory(20)
    write_events(tmp_path / "a.h5", ev)
    (tmp_path / "a.h5").rename(tmp_path / "renamed.dat")
    assert detect_format(tmp_path / "renamed.dat") == "hdf5"
    assert read_events(tmp_path / "renamed.dat") == ev
    write_events(tmp_path / "b.txt", ev)
    (tmp_path / "b.txt").rename(tmp_path / "b.events")
    assert detect_format(tmp_path / "b.events") == "text"
    write_events(tmp_path / "c.npz", ev)
    (tmp_path / "c.npz").rename(tmp_path / "c.zip")
    assert detect_format(tmp_path / "c.zip") == "npz"


def test_signatures(tmp_path):
    cases = {
        "x.bin": (b"\x89HDF\r\n\x1a\n" + b"\0" * 100, "hdf5"),
        "y.bin": (b"#!AER-DAT4.0\r\n<xml/>", "aedat4"),
        "z.bin": (b"% date today\n% evt 3.0\n\x00\x01", "evt3"),
        "w.bin": (b"% evt 2.0\n\x00\x00\x00\x00", "evt2"),
        "v.bin": (b"% format EVT3;height=720;width=1280\n", "evt3"),
        "u.bin": (b"0.1 1 2 1\n0.2 3 4 0\n", "text"),
    }
    for name, (data, fmt) in cases.items():
        (tmp_path / name).write_bytes(data)
        assert detect_format(tmp_path / name) == fmt, name


def test_unknown_format_lists_supported(tmp_path):
    (tmp_path / "m.bin").write_bytes(b"\x00\x01garbage")
    with pytest.raises(UnknownFormatError, match=r"m.bin: unknown event file format.*"
                                                 r"hdf5 \(.h5/.hdf5/.hdf\).*evt3 \(.raw\)"):
        detect_format(tmp_path / "m.bin")
    (tmp_path / "empty.bin").write_bytes(b"")
    with pytest.raises(UnknownFormatError):
        read_events(tmp_path / "empty.bin")


def test_extension_without_matching_content(tmp_path):
    for name, what in [("a.h5", "HDF5 signature"), ("b.aedat4", "AER-DAT4.0"),
                       ("c.npz", "zip signature"), ("d.raw", "'% ' header")]:
        (tmp_path / name).write_bytes(b"\x00garbage")
        with pytest.raises(EventFileError, match=f"{name}: the extension .*{what}"):
            detect_format(tmp_path / name)
    (tmp_path / "e.h5").write_bytes(b"")
    with pytest.raises(EventFileError, match="is empty"):
        detect_format(tmp_path / "e.h5")


def test_empty_text_file_has_no_events(tmp_path):
    (tmp_path / "e.txt").write_bytes(b"")
    assert detect_format(tmp_path / "e.txt") == "text"
    assert len(read_events(tmp_path / "e.txt")) == 0


def test_missing_file(tmp_path):
    with pytest.raises(EventFileError, match="nope.h5: no such file"):
        read_events(tmp_path / "nope.h5")
    with pytest.raises(EventFileError, match="not a regular file"):
        detect_format(tmp_path)


def test_raw_headers_that_cannot_be_read(tmp_path):
    (tmp_path / "a.raw").write_bytes(b"% plugin_name hal_plugin_gen41_evk3\n\x00\x00")
    with pytest.raises(EventFileError, match="no '% evt' or '% format' line"):
        detect_format(tmp_path / "a.raw")
    (tmp_path / "b.raw").write_bytes(b"% evt 2.1\n\x00\x00\x00\x00")
    with pytest.raises(EventFileError, match="'evt21' is not supported"):
        detect_format(tmp_path / "b.raw")
    (tmp_path / "c.raw").write_bytes(b"% evt 3.0")  # no newline: expelliarmus would hang
    with pytest.raises(EventFileError, match="not terminated"):
        read_events(tmp_path / "c.raw")
