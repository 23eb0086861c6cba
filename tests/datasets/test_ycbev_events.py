"""YCB-Ev event streams: written by ycbev-toolkit's own writer, read back by evtrack."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evtrack.datasets.ycbev import read_ycbev_events, unpack_events
from evtrack.errors import EventFileError


def _write(path: Path, t, x, y, p) -> None:
    import ycbev

    ycbev.write_event_data(path, *(np.asarray(a, np.int32) for a in (t, x, y, p)))


def test_toolkit_writer_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    n = 5000
    t = np.sort(rng.integers(0, 2**31 - 1, n))
    x, y, p = rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n)
    x[:2], y[:2], p[:2] = (0, 1279), (719, 0), (1, 0)  # the corners of the sensor
    path = tmp_path / "01_events.int32.zst"
    _write(path, t, x, y, p)
    ev = read_ycbev_events(path, (1280, 720))
    np.testing.assert_array_equal(ev.t.numpy(), t)
    np.testing.assert_array_equal(ev.x.numpy(), x)
    np.testing.assert_array_equal(ev.y.numpy(), y)
    np.testing.assert_array_equal(ev.p.numpy(), p * 2 - 1)


def test_unpack_layout() -> None:
    """x in bits 0-13, y in 14-27, polarity in 28-31, after the timestamp word."""
    word = 1279 | (719 << 14) | (1 << 28)
    data = np.array([[123456, word]], np.uint32).tobytes()
    t, x, y, p = unpack_events(data)
    assert (t[0], x[0], y[0], p[0]) == (123456, 1279, 719, 1)
    with pytest.raises(ValueError, match="multiple of 8"):
        unpack_events(data[:-4])


def test_unsorted_and_bad_polarity(tmp_path: Path) -> None:
    path = tmp_path / "e.int32.zst"
    _write(path, [10, 5], [1, 2], [1, 2], [1, 0])
    with pytest.raises(EventFileError, match=r"e.int32.zst: .*timestamps go backwards"):
        read_ycbev_events(path, (1280, 720))
    _write(path, [1, 5], [1, 2], [1, 2], [1, 3])
    with pytest.raises(EventFileError, match=r"e.int32.zst: event 1: polarity 3"):
        read_ycbev_events(path, (1280, 720))


def test_not_zstd(tmp_path: Path) -> None:
    path = tmp_path / "e.int32.zst"
    path.write_bytes(b"not a zstd frame at all")
    with pytest.raises(EventFileError, match=r"e.int32.zst: corrupt or truncated zstd"):
        read_ycbev_events(path, (1280, 720))
    with pytest.raises(EventFileError, match="not found"):
        read_ycbev_events(tmp_path / "missing.zst", (1280, 720))
