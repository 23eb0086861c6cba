"""Text event files: one event per line, ``t x y p``, as in the Event Camera Dataset.

``t`` is in seconds (decimal, e.g. ``1.000123456``), ``x``/``y`` are integer pixels, ``p`` is 1
(ON) or 0 (OFF); -1 is also read as OFF. Fields are separated by spaces or tabs; blank lines and
lines starting with ``#`` are skipped.

Seconds are converted to integer µs *exactly* from the decimal digits (no float on the way):
digits beyond the sixth decimal are rounded half away from zero, so ``0.0000015`` is 2 µs and
``3600.123456789`` is 3,600,123,457 µs at any magnitude that fits int64 µs.

Files written by evtrack start with a header and end with a trailer::

    # evtrack events text 1
    # columns: t[s] x[px] y[px] p(1=ON,0=OFF)
    # sensor_size 640 480
    0.000010 12 7 1
    ...
    # num_events 123456

When the header is present the trailer is required and its count checked, so a file cut at a
line boundary is reported as truncated. Files without the header (other tools) have no count to
check; ``# sensor_size W H`` may still give the sensor size.

Reading is streamed in blocks of :data:`BLOCK_BYTES`. Each block is parsed by a vectorised
numpy path when it has the common shape (only digits, one ``.`` inside the first field, four
fields per line); otherwise, and to report errors with line numbers, by an exact pure-Python
path.
"""

from __future__ import annotations

import contextlib
import re
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from evtrack.errors import EventFileError, EvtrackError
from evtrack.events import Events
from evtrack.io.reader import EventReader, Locator
from evtrack.io.writer import StreamingWriter
from evtrack.utils import atomic_path

__all__ = [
    "TextReader",
    "TextWriter",
    "write_text",
    "parse_seconds_to_us",
    "BLOCK_BYTES",
]

BLOCK_BYTES = 4 << 20  # bytes parsed per block when streaming
MAX_LINE_BYTES = 1 << 16  # a longer line is taken as corruption (real lines are < 100 bytes)
_HEADER_SCAN_BYTES = 1 << 16  # leading comment lines are looked for within this many bytes
_TRAILER_SCAN_BYTES = 256
HEADER_MAGIC = "# evtrack events text 1"
_SENSOR_RE = re.compile(r"#\s*sensor_size\s+(\d+)\s+(\d+)\s*$")
_TRAILER_RE = re.compile(rb"#\s*num_events\s+(\d+)\s*$")
US_PER_S = 1_000_000
_US_DIGITS = 6
_MAX_FAST_DIGITS = 18  # int64 parses of up to 18 digits cannot overflow
_MAX_SECONDS = (np.iinfo(np.int64).max - US_PER_S) // US_PER_S
_INT64 = np.iinfo(np.int64)
_INT32 = np.iinfo(np.int32)
_POW10 = 10 ** np.arange(_MAX_FAST_DIGITS + 1, dtype=np.int64)

# Byte classes for the vectorised parser: 0 blank, 1 digit, 2 '.', 3 newline, 255 other.
_BLANK, _DIGIT, _DOT, _NEWLINE, _OTHER = 0, 1, 2, 3, 255
_CLASS = np.full(256, _OTHER, dtype=np.uint8)
_CLASS[ord("0") : ord("9") + 1] = _DIGIT
_CLASS[ord(".")] = _DOT
_CLASS[[ord(" "), ord("\t"), ord("\r")]] = _BLANK
_CLASS[ord("\n")] = _NEWLINE

_SECONDS_RE = re.compile(r"([+-]?)(\d*)(?:\.(\d*))?(?:[eE]([+-]?\d{1,6}))?")
_INT_RE = re.compile(r"[+-]?\d+")
_MAX_EXPONENT = 30  # |10-exponent| beyond this cannot give an int64 µs timestamp


# ============================================================================ parsing
def parse_seconds_to_us(token: str) -> int:
    """Convert a decimal seconds string to integer µs exactly.

    Accepts an optional sign, digits with an optional fraction, and an optional exponent
    (``1.5e-3``). Digits beyond the µs are rounded half away from zero.

    Raises:
        ValueError: not a finite decimal number.
    """
    m = _SECONDS_RE.fullmatch(token)
    if m is None or not (m.group(2) or m.group(3)):
        raise ValueError(f"not a decimal number of seconds: {token!r}")
    sign, ipart, fpart, exp = m.group(1), m.group(2), m.group(3) or "", m.group(4)
    digits = int((ipart or "0") + fpart)
    shift = (int(exp) if exp else 0) - len(fpart) + _US_DIGITS  # value_us = digits * 10**shift
    if shift > _MAX_EXPONENT:
        if digits:
            raise ValueError(f"timestamp {token!r} s is too large for int64 µs")
        value = 0
    elif shift >= 0:
        value = digits * 10**shift
    elif -shift > len(str(digits)) + 1:
        value = 0  # below half a µs
    else:
        q, r = divmod(digits, 10**-shift)
        value = q + (2 * r >= 10**-shift)
    return -value if sign == "-" else value


def _parse_fast(block: bytes) -> tuple[np.ndarray, ...] | None:
    """Vectorised parse of a block of complete lines, or ``None`` if the block is unusual.

    Returns ``(t_us, x, y, p, line_index)`` (int64 arrays; ``line_index`` counts the block's
    lines from 0) when every byte is a digit, ``.``, blank or newline, every non-blank line has
    four fields and exactly one ``.`` strictly inside the first, and no field exceeds 18 digits.
    """
    b = np.frombuffer(block, dtype=np.uint8)
    cls = _CLASS[b]
    if cls.max() == _OTHER:
        return None
    tok = np.subtract(cls, 1, dtype=np.uint8) <= 1  # digit or dot (blank wraps to 255)
    edge = np.diff(tok.view(np.int8), prepend=np.int8(0), append=np.int8(0))
    starts = np.flatnonzero(edge == 1)
    ends = np.flatnonzero(edge == -1)  # exclusive
    newlines = np.flatnonzero(cls == _NEWLINE)
    per_line = np.diff(np.searchsorted(starts, newlines), prepend=0)
    nonblank = per_line != 0
    if not np.all(per_line[nonblank] == 4):
        return None
    lines = np.flatnonzero(nonblank)
    n = lines.size
    if n == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, empty, empty
    starts = starts.reshape(n, 4)
    ends = ends.reshape(n, 4)
    if int((ends - starts).max()) > _MAX_FAST_DIGITS:
        return None
    dots = np.flatnonzero(cls == _DOT)
    if dots.size != n or not np.all((dots > starts[:, 0]) & (dots < ends[:, 0] - 1)):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            vals = np.fromstring(block.replace(b".", b" "), dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
    if vals.size != 5 * n:
        return None
    vals = vals.reshape(n, 5)
    sec = vals[:, 0]
    if int(sec.max()) > _MAX_SECONDS:
        return None
    ndig = ends[:, 0] - dots - 1
    frac = vals[:, 1]
    us = np.empty(n, dtype=np.int64)
    short = ndig <= _US_DIGITS
    us[short] = frac[short] * _POW10[_US_DIGITS - ndig[short]]
    long_ = ~short
    if long_.any():
        div = _POW10[ndig[long_] - _US_DIGITS]
        q, r = np.divmod(frac[long_], div)
        us[long_] = q + (2 * r >= div)
    return sec * US_PER_S + us, vals[:, 2], vals[:, 3], vals[:, 4], lines


def _parse_slow(block: bytes, path: Path, first_line: int) -> tuple[np.ndarray, ...]:
    """Exact line-by-line parse; raises :class:`EventFileError` naming the line at fault."""
    t: list[int] = []
    x: list[int] = []
    y: list[int] = []
    p: list[int] = []
    where: list[int] = []
    for i, raw in enumerate(block.split(b"\n")[:-1]):
        lineno = first_line + i
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise EventFileError(path, f"line {lineno}: non-ASCII bytes: {raw[:60]!r}") from None
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 4:
            raise EventFileError(
                path, f"line {lineno}: expected 4 fields 't x y p', got {len(fields)}: "
                f"{line[:80]!r}"
            )
        try:
            tv = parse_seconds_to_us(fields[0])
        except ValueError as exc:
            raise EventFileError(path, f"line {lineno}: {exc}") from None
        if not _INT64.min <= tv <= _INT64.max:
            raise EventFileError(path, f"line {lineno}: timestamp {fields[0]} s overflows int64 µs")
        ints = []
        for name, tok in zip(("x", "y", "p"), fields[1:], strict=True):
            if _INT_RE.fullmatch(tok) is None:
                raise EventFileError(path, f"line {lineno}: {name} must be an integer, got {tok!r}")
            v = int(tok)
            if not _INT32.min <= v <= _INT32.max:
                raise EventFileError(path, f"line {lineno}: {name}={tok} is out of range")
            ints.append(v)
        t.append(tv)
        x.append(ints[0])
        y.append(ints[1])
        p.append(ints[2])
        where.append(i)
    return tuple(np.asarray(a, dtype=np.int64) for a in (t, x, y, p, where))


# ============================================================================ reading
class TextReader(EventReader):
    """Streaming reader of ``t x y p`` text files (see the module docstring).

    Args:
        path: the file.
        sensor_size: overrides a ``# sensor_size`` header line; without either the events have
            ``sensor_size=None`` and only negative coordinates are rejected.
        block_bytes: bytes parsed per block.
    """

    format = "text"

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        block_bytes: int = BLOCK_BYTES,
    ) -> None:
        super().__init__(path, sensor_size)
        self._block = int(block_bytes)
        try:
            self._size = self.path.stat().st_size
            with open(self.path, "rb") as fh:
                head = fh.read(_HEADER_SCAN_BYTES)
                fh.seek(max(0, self._size - _TRAILER_SCAN_BYTES))
                tail = fh.read()
        except OSError as exc:
            raise EventFileError(self.path, f"cannot read: {exc}") from exc
        self._parse_header(head, sensor_size)
        self._parse_trailer(tail)

    def _parse_header(self, head: bytes, sensor_size: tuple[int, int] | None) -> None:
        pos = 0
        lines = 0
        # Written by evtrack (even if cut inside the first line): the trailer is then required.
        self._magic = head.startswith(HEADER_MAGIC.encode())
        while True:
            end = head.find(b"\n", pos)
            if end < 0:
                break
            line = head[pos:end].decode("latin-1").strip()
            if (line and not line.startswith("#")) or _TRAILER_RE.fullmatch(line.encode()):
                break
            m = _SENSOR_RE.match(line)
            if m is None and re.match(r"#\s*sensor_size\b", line):
                raise EventFileError(self.path, f"line {lines + 1}: bad sensor_size header "
                                                f"{line!r} (expected '# sensor_size W H')")
            if m and sensor_size is None:
                w, h = int(m.group(1)), int(m.group(2))
                if w <= 0 or h <= 0:
                    raise EventFileError(
                        self.path, f"line {lines + 1}: sensor size must be positive"
                    )
                self.sensor_size = (w, h)
            pos = end + 1
            lines += 1
        self._data_start = pos
        self._header_lines = lines

    def _parse_trailer(self, tail: bytes) -> None:
        self._claimed: int | None = None
        self._data_end = self._size
        stripped = tail.rstrip()
        cut = stripped.rfind(b"\n") + 1
        last = stripped[cut:]
        m = _TRAILER_RE.fullmatch(last.strip())
        start_of_last = self._size - len(tail) + cut
        if m and start_of_last >= self._data_start:
            self._claimed = int(m.group(1))
            self._data_end = start_of_last
        elif self._magic:
            raise EventFileError(
                self.path, "the '# num_events N' trailer written by evtrack is missing: "
                "the file is truncated"
            )

    def _expected_count(self) -> int | None:
        return self._claimed

    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        line_base = self._header_lines + 1  # 1-based number of the block's first line
        carry = b""
        with open(self.path, "rb") as fh:
            fh.seek(self._data_start)
            pos = self._data_start
            while pos < self._data_end:
                want = min(self._block, self._data_end - pos)
                data = fh.read(want)
                if len(data) != want:
                    raise EventFileError(self.path, "the file shrank while being read")
                pos += want
                buf = carry + data
                if pos < self._data_end:
                    cut = buf.rfind(b"\n") + 1
                    if cut == 0:
                        if len(buf) > MAX_LINE_BYTES:
                            raise EventFileError(
                                self.path, f"line {line_base} is longer than {MAX_LINE_BYTES} "
                                "bytes: not an event text file"
                            )
                        carry = buf
                        continue
                    block, carry = buf[:cut], buf[cut:]
                else:
                    block = buf if buf.endswith(b"\n") else buf + b"\n"
                    carry = b""
                yield self._events(block, line_base)
                line_base += block.count(b"\n")

    def _events(self, block: bytes, line_base: int) -> tuple[Events, Locator]:
        parsed = _parse_fast(block)
        if parsed is None:
            parsed = _parse_slow(block, self.path, line_base)
        t, x, y, p, where = parsed
        lines = where + line_base
        bad = (p != 0) & (p != 1) & (p != -1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise EventFileError(
                self.path, f"{int(bad.sum())} events with polarity other than 1/0 (or -1) in "
                f"lines {int(lines[0])}..{int(lines[-1])}, first at line {int(lines[i])} "
                f"(p={int(p[i])})"
            )
        for name, v in (("x", x), ("y", y)):
            if v.size and (v.max() > _INT32.max or v.min() < _INT32.min):
                i = int(np.flatnonzero((v > _INT32.max) | (v < _INT32.min))[0])
                raise EventFileError(self.path, f"line {int(lines[i])}: {name} is out of range")
        ev = Events(
            x.astype(np.int32), y.astype(np.int32), t,
            np.where(p == 1, 1, -1).astype(np.int8), self.sensor_size,
        )
        return ev, lambda i: f"line {int(lines[i])}"


# ============================================================================ writing
def _format_lines(t: np.ndarray, x: np.ndarray, y: np.ndarray, p01: np.ndarray) -> str:
    """Lines ``'<s>.<us> x y p'`` with exactly six decimals (exact µs)."""
    sec, us = np.divmod(np.abs(t), US_PER_S)
    cols = [sec.tolist(), us.tolist(), x.tolist(), y.tolist(), p01.tolist()]
    if not (t < 0).any():
        return "".join(map("%d.%06d %d %d %d\n".__mod__, zip(*cols, strict=True)))
    sign = np.where(t < 0, "-", "").tolist()
    return "".join(map("%s%d.%06d %d %d %d\n".__mod__, zip(sign, *cols, strict=True)))


class TextWriter(StreamingWriter):
    """Stream events into a ``t x y p`` text file; the file appears atomically on :meth:`close`.

    Args:
        path: output file (``.txt``).
        sensor_size: written as a ``# sensor_size W H`` header line when given.

    Chunks must be valid and in time order across :meth:`write` calls (:class:`EventsError`).
    """

    def __init__(self, path: str | Path, sensor_size: tuple[int, int] | None = None) -> None:
        self.path = Path(path)
        self.sensor_size = None if sensor_size is None else tuple(int(v) for v in sensor_size)
        self._n = 0
        self._last_t: int | None = None
        self._closed = False
        self._stack = contextlib.ExitStack()
        try:
            tmp = self._stack.enter_context(atomic_path(self.path, suffix=".txt"))
            self._fh: TextIO = open(tmp, "w", encoding="ascii", newline="\n")  # noqa: SIM115
            self._fh.write(HEADER_MAGIC + "\n# columns: t[s] x[px] y[px] p(1=ON,0=OFF)\n")
            if self.sensor_size is not None:
                self._fh.write(f"# sensor_size {self.sensor_size[0]} {self.sensor_size[1]}\n")
        except BaseException:
            self._abort_quietly()
            raise

    def write(self, events: Events) -> None:
        """Append a chunk (must follow the previous chunk in time)."""
        ev = self._checked_chunk(events)
        if ev is None:
            return
        d = ev.numpy()
        self._fh.write(_format_lines(d["t"], d["x"], d["y"], (d["p"] > 0).astype(np.int8)))
        self._n += len(ev)
        self._last_t = int(d["t"][-1])

    def close(self) -> None:
        """Write the trailer and move the file into place (idempotent)."""
        if self._closed:
            return
        try:
            self._fh.write(f"# num_events {self._n}\n")
            self._fh.close()
        except BaseException:
            self._abort_quietly()
            raise
        self._closed = True
        self._stack.close()

    def _discard(self) -> None:
        with contextlib.suppress(Exception):
            self._fh.close()
        self._stack.__exit__(EvtrackError, EvtrackError("aborted"), None)


def write_text(path: str | Path, events: Events, **options: Any) -> None:
    """Write ``events`` as a text file atomically (option: ``sensor_size``)."""
    if set(options) - {"sensor_size"}:
        raise TypeError(f"unknown text options {sorted(set(options) - {'sensor_size'})}")
    size = options.get("sensor_size") or events.sensor_size
    with TextWriter(path, size) as w:
        w.write(events)
