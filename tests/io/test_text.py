"""Text reader: exact seconds → µs, block boundaries, and errors that name the line."""

from __future__ import annotations

from decimal import ROUND_HALF_UP, Decimal

import numpy as np
import pytest

from evtrack.errors import EventFileError
from evtrack.events import concatenate
from evtrack.io import TextReader, iter_events, parse_seconds_to_us, read_events, write_events


def _decimal_us(token: str) -> int:
    """Independent reference: Decimal arithmetic, half away from zero."""
    return int((Decimal(token) * 1_000_000).quantize(Decimal(1), rounding=ROUND_HALF_UP))


@pytest.mark.parametrize(
    ("token", "us"),
    [
        ("0", 0),
        ("0.000001", 1),
        ("0.0000015", 2),  # a tie rounds away from zero
        ("0.0000014999", 1),
        ("0.0000025", 3),
        ("1.", 1_000_000),
        (".5", 500_000),
        ("3600.123456789", 3_600_123_457),
        ("86399.999999", 86_399_999_999),
        ("0.9999995", 1_000_000),  # rounding carries into the seconds
        ("1e-6", 1),
        ("1.5E-3", 1_500),
        ("2e3", 2_000_000_000),
        ("-0.5", -500_000),
        ("+7.25", 7_250_000),
        ("1e-40", 0),
        ("0e99", 0),
    ],
)
def test_parse_seconds_exact(token, us):
    assert parse_seconds_to_us(token) == us
    assert parse_seconds_to_us(token) == _decimal_us(token)


@pytest.mark.parametrize("token", ["", ".", "abc", "nan", "inf", "1.2.3", "1e", "0x10", "1_000"])
def test_parse_seconds_rejects(token):
    with pytest.raises(ValueError):
        parse_seconds_to_us(token)


def _write_lines(path, lines, newline="\n"):
    path.write_bytes(newline.join(lines).encode() + newline.encode())


def test_fast_path_matches_decimal_reference_for_hours_of_timestamps(tmp_path):
    """Random timestamps up to 10 h, 0 to 12 decimals: each µs equals the Decimal reference.

    float64 parsing would also get most of these; the ties (digit 7 = 5, then zeros) and the
    12-digit fractions are where a float path rounds the wrong way.
    """
    rng = np.random.default_rng(0)
    n = 3000
    secs = np.sort(rng.integers(0, 36_000, n))
    tokens = []
    for s in secs.tolist():
        nd = int(rng.integers(0, 13))
        if nd == 0:
            tokens.append(f"{s}.0")
            continue
        frac = "".join(str(d) for d in rng.integers(0, 10, nd))
        if nd >= 7 and rng.random() < 0.3:  # exact tie at the 7th digit
            frac = frac[:6] + "5" + "0" * (nd - 7)
        tokens.append(f"{s}.{frac}")
    expected = np.array([_decimal_us(t) for t in tokens])
    order = np.argsort(expected, kind="stable")
    tokens = [tokens[i] for i in order]
    _write_lines(tmp_path / "e.txt", [f"{t} 1 2 1" for t in tokens])
    ev = read_events(tmp_path / "e.txt")
    assert np.array_equal(ev.t.numpy(), expected[order])


def test_ecd_style_file_without_header(tmp_path):
    _write_lines(tmp_path / "events.txt", [
        "0.000000000 33 39 1", "0.000011001 158 145 1", "0.000050000 88 143 0",
        "0.000055000 174 154 0",
    ])
    ev = read_events(tmp_path / "events.txt")
    assert ev.sensor_size is None
    assert ev.t.tolist() == [0, 11, 50, 55]
    assert ev.x.tolist() == [33, 158, 88, 174]
    assert ev.p.tolist() == [1, 1, -1, -1]
    assert read_events(tmp_path / "events.txt", sensor_size=(240, 180)).sensor_size == (240, 180)


def test_slow_path_variants_read_the_same(tmp_path):
    """CRLF, tabs, extra blanks, comments, -1 polarity, exponents, no final newline."""
    text = (
        "# a comment\r\n\r\n0.5\t1  2 1\r\n  0.75e0 3 4 -1\r\n# mid comment\r\n1 5 6 0"
    )
    (tmp_path / "v.txt").write_bytes(text.encode())
    ev = read_events(tmp_path / "v.txt")
    assert ev.t.tolist() == [500_000, 750_000, 1_000_000]
    assert ev.x.tolist() == [1, 3, 5]
    assert ev.p.tolist() == [1, -1, -1]


def test_small_blocks_give_the_same_events(tmp_path, events_factory):
    ev = events_factory(2000, seed=3)
    write_events(tmp_path / "b.txt", ev)
    for block in (40, 97, 1000):
        chunks = list(TextReader(tmp_path / "b.txt", block_bytes=block).iter_chunks())
        assert concatenate(chunks) == ev
    windows = list(iter_events(tmp_path / "b.txt", window_us=50))
    assert concatenate(windows) == ev


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("0.3 1 2", "line 6: expected 4 fields 't x y p', got 3"),
        ("0.3 1 2 1 9", "line 6: expected 4 fields 't x y p', got 5"),
        ("0.3 a 2 1", "line 6: x must be an integer, got 'a'"),
        ("0.3 1 2.5 1", "line 6: y must be an integer"),
        ("zz 1 2 1", "line 6: not a decimal number of seconds: 'zz'"),
        ("nan 1 2 1", "line 6: not a decimal number"),
        ("0.3 1 2 2", "polarity other than 1/0 .* first at line 6 \\(p=2\\)"),
        ("0.3 1 2 1\xe9", "line 6: non-ASCII"),
        ("1e30 1 2 1", "line 6: timestamp .* too large"),
    ],
)
def test_bad_lines_name_the_line(tmp_path, line, message):
    lines = ["# header", "0.1 1 2 1", "", "0.2 1 2 0", "0.25 3 3 1", line, "0.4 1 1 1"]
    (tmp_path / "bad.txt").write_bytes("\n".join(lines).encode("latin-1"))
    with pytest.raises(EventFileError, match=message) as info:
        read_events(tmp_path / "bad.txt")
    assert "bad.txt" in str(info.value)
    with pytest.raises(EventFileError, match=message):
        list(iter_events(tmp_path / "bad.txt", window_us=100))


def test_unsorted_and_outside_name_index_and_line(tmp_path):
    _write_lines(tmp_path / "u.txt", ["# sensor_size 10 10", "0.1 1 1 1", "0.3 1 1 1",
                                     "0.2 1 1 1", "0.25 1 1 1", "0.4 1 1 1"])
    with pytest.raises(EventFileError, match=r"1 timestamps go backwards.*index 2 \(line 4\)"):
        read_events(tmp_path / "u.txt")
    _write_lines(tmp_path / "o.txt", ["# sensor_size 10 10", "0.1 1 1 1", "0.2 10 1 1",
                                     "0.3 1 12 1"])
    with pytest.raises(EventFileError, match=r"2 events outside the sensor \(10, 10\).*"
                                             r"index 1 \(line 3\) \(x=10, y=1\)"):
        read_events(tmp_path / "o.txt")
    _write_lines(tmp_path / "n.txt", ["0.1 -1 1 1"])
    with pytest.raises(EventFileError, match="outside the sensor"):
        read_events(tmp_path / "n.txt")


def test_unsorted_across_blocks_is_caught(tmp_path):
    lines = [f"0.{i:06d} 1 1 1" for i in range(100, 200)] + ["0.000050 1 1 1"]
    _write_lines(tmp_path / "x.txt", lines)
    with pytest.raises(EventFileError, match=r"backwards.* index 100 \(line 101\)"):
        list(TextReader(tmp_path / "x.txt", block_bytes=64).iter_chunks())


def test_truncation_is_detected_through_the_trailer(tmp_path, events_factory):
    ev = events_factory(100, seed=5)
    write_events(tmp_path / "t.txt", ev)
    data = (tmp_path / "t.txt").read_bytes()
    assert data.endswith(b"# num_events 100\n")
    cut = data[: data.rfind(b"\n", 0, len(data) - 40) + 1]  # whole lines only
    (tmp_path / "cut.txt").write_bytes(cut)
    with pytest.raises(EventFileError, match="trailer .* missing: the file is truncated"):
        read_events(tmp_path / "cut.txt")
    lines = data.split(b"\n")
    (tmp_path / "drop.txt").write_bytes(b"\n".join(lines[:5] + lines[6:]))  # one event removed
    with pytest.raises(EventFileError, match="says it holds 100 events but 99 were read"):
        read_events(tmp_path / "drop.txt")


def test_overlong_line_is_rejected(tmp_path):
    (tmp_path / "long.txt").write_bytes(b"0.1 1 1 1\n" + b"1" * 200_000 + b"\n0.2 1 1 1\n")
    with pytest.raises(EventFileError, match="longer than"):
        list(TextReader(tmp_path / "long.txt", block_bytes=1 << 12).iter_chunks())
    with pytest.raises(EventFileError, match="line 2"):
        read_events(tmp_path / "long.txt")


@pytest.mark.parametrize("header", ["# sensor_size 10 abc", "# sensor_size 640", "#sensor_size"])
def test_a_malformed_sensor_size_header_is_an_error_not_a_comment(tmp_path, header):
    path = tmp_path / "ev.txt"
    path.write_text(f"{header}\n0.001 1 1 1\n")
    with pytest.raises(EventFileError, match="line 1: bad sensor_size header"):
        read_events(path)
    path.write_text("# sensor_sizes are given below\n0.001 1 1 1\n")  # a word, not the header
    assert len(read_events(path)) == 1
