"""Event file formats: their names, extensions, and detection by extension and first bytes.

A format is named by a short string (``'hdf5'``, ``'text'``, ``'npz'``, ``'aedat4'``,
``'evt2'``, ``'evt3'``). :func:`detect_format` looks at the file's first bytes (signatures
and header lines) and at its extension; :func:`format_from_extension` is used for files that do
not exist yet (writing).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from evtrack.errors import EventFileError, UnknownFormatError

__all__ = [
    "FORMATS",
    "FormatInfo",
    "detect_format",
    "format_from_extension",
    "formats_help",
    "parse_raw_header",
    "RawHeader",
    "HDF5_SIGNATURE",
    "AEDAT4_SIGNATURE",
    "ZIP_SIGNATURE",
]

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
AEDAT4_SIGNATURE = b"#!AER-DAT4.0"
ZIP_SIGNATURE = b"PK\x03\x04"
EMPTY_ZIP_SIGNATURE = b"PK\x05\x06"  # an archive with no members (still a zip, still not events)
# HDF5 allows a user block before the superblock; the signature then sits at 512, 1024, ...
_HDF5_SIGNATURE_OFFSETS = (0, 512, 1024, 2048, 4096)
_SNIFF_BYTES = 8192
# Longest Prophesee RAW header accepted (real headers are well under 4 KiB).
MAX_RAW_HEADER_BYTES = 1 << 20


@dataclass(frozen=True)
class FormatInfo:
    """One event file format.

    Attributes:
        name: short name used throughout evtrack.
        extensions: file name endings that imply this format (lower case, with the dot).
        readable: whether evtrack reads it.
        writable: whether evtrack writes it.
        description: one line for ``--help`` and error messages.
    """

    name: str
    extensions: tuple[str, ...]
    readable: bool
    writable: bool
    description: str


FORMATS: dict[str, FormatInfo] = {
    f.name: f
    for f in (
        FormatInfo("hdf5", (".h5", ".hdf5", ".hdf"), True, True,
                   "evtrack native HDF5: events/{x,y,t,p} + ms_to_idx time index"),
        FormatInfo("text", (".txt",), True, True,
                   "lines 't x y p' (t in s, p 1/0), as in the Event Camera Dataset"),
        FormatInfo("npz", (".npz",), True, True,
                   "numpy arrays x, y, t (µs), p (±1), sensor_size (W, H)"),
        FormatInfo("aedat4", (".aedat4",), True, False,
                   "iniVation AEDAT 4.0, via the 'aedat' package"),
        FormatInfo("evt2", (".raw",), True, False,
                   "Prophesee RAW EVT 2.0, via 'expelliarmus'"),
        FormatInfo("evt3", (".raw",), True, False,
                   "Prophesee RAW EVT 3.0, via 'expelliarmus'"),
    )
}


def formats_help() -> str:
    """A multi-line table of the supported formats, for ``--help`` and error messages."""
    rows = []
    for f in FORMATS.values():
        mode = "read/write" if f.writable else "read only"
        rows.append(f"  {f.name:7s} {'/'.join(f.extensions):16s} {mode:10s} {f.description}")
    return "\n".join(rows)


def _supported_list() -> str:
    return ", ".join(f"{f.name} ({'/'.join(f.extensions)})" for f in FORMATS.values())


def format_from_extension(path: str | Path) -> str | None:
    """The format implied by ``path``'s extension, or ``None``.

    ``.raw`` is ambiguous (EVT 2.0 or 3.0) and maps to ``'raw'``; only the header tells which.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".raw":
        return "raw"
    for f in FORMATS.values():
        if suffix in f.extensions:
            return f.name
    return None


# ----------------------------------------------------------------------------- RAW headers
_GEOMETRY_RE = re.compile(r"(\d+)\s*[xX]\s*(\d+)")
_EVT_RE = re.compile(r"^\s*(\d+)\.(\d+)")


@dataclass(frozen=True)
class RawHeader:
    """The ``% key value`` header of a Prophesee RAW file.

    Attributes:
        fields: header keys (first word after ``%``) to values (rest of the line, stripped);
            for a repeated key the last line wins.
        length: bytes taken by the header; the binary event words start there.
        encoding: ``'evt2'``, ``'evt3'``, another ``'evtNN'`` string for versions that
            evtrack cannot decode (e.g. ``'evt21'``), or ``None`` when no line states it.
        geometry: ``(width, height)`` from a ``% geometry W x H`` line or from the width/height
            of a ``% format`` line, or ``None``.
    """

    fields: dict[str, str]
    length: int
    encoding: str | None
    geometry: tuple[int, int] | None


def parse_raw_header(data: bytes) -> RawHeader | None:
    """Parse the ``%`` header at the start of ``data`` (the file's first bytes).

    Returns ``None`` when ``data`` does not start with ``%`` or when the header is not
    complete within ``data`` (no newline after the last ``%`` line).
    """
    if not data.startswith(b"%"):
        return None
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(data) and data[pos : pos + 1] == b"%":
        end = data.find(b"\n", pos)
        if end < 0:
            return None
        line = data[pos + 1 : end].decode("latin-1").strip()
        key, _, value = line.partition(" ")
        if key:
            fields[key] = value.strip()
        pos = end + 1
    encoding = None
    geometry = None
    if "evt" in fields:
        m = _EVT_RE.match(fields["evt"])
        if m:
            major, minor = m.groups()
            encoding = f"evt{major}" if minor == "0" else f"evt{major}{minor}"
    if "format" in fields:  # e.g. "EVT3;height=720;width=1280" (Metavision 3 and later)
        parts = fields["format"].split(";")
        name = parts[0].strip().lower()
        if encoding is None and name.startswith("evt"):
            encoding = name
        kv = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
        if kv.get("width", "").strip().isdigit() and kv.get("height", "").strip().isdigit():
            geometry = (int(kv["width"]), int(kv["height"]))
    if "geometry" in fields:
        m = _GEOMETRY_RE.search(fields["geometry"])
        if m:
            geometry = (int(m.group(1)), int(m.group(2)))
    return RawHeader(fields, pos, encoding, geometry)


# ----------------------------------------------------------------------------- detection
def _looks_like_text(head: bytes) -> bool:
    """Whether ``head`` reads as ASCII lines whose first data line has 4 numeric fields."""
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    lines = text.splitlines()
    if len(head) == _SNIFF_BYTES and lines:
        lines = lines[:-1]  # the last line may be cut by the sniff window
    for line in lines:
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != 4:
            return False
        return all(re.fullmatch(r"[+-]?[\d.eE+-]+", f) for f in fields)
    # Only comments/blank lines (or nothing): text if printable.
    return all(c.isprintable() or c in "\r\n\t" for c in text)


def _sniff(head: bytes) -> str | None:
    """The format named by the first bytes, or ``None``."""
    for off in _HDF5_SIGNATURE_OFFSETS:
        if head[off : off + len(HDF5_SIGNATURE)] == HDF5_SIGNATURE:
            return "hdf5"
    if head.startswith(AEDAT4_SIGNATURE):
        return "aedat4"
    if head.startswith(ZIP_SIGNATURE) or head.startswith(EMPTY_ZIP_SIGNATURE):
        return "npz"
    if head.startswith(b"%"):
        return "raw"
    if head and _looks_like_text(head):
        return "text"
    return None


def detect_format(path: str | Path) -> str:
    """The format of an existing event file, from its first bytes and its extension.

    The content decides when it carries a signature (HDF5, ``#!AER-DAT4.0``, zip/npz, a
    Prophesee ``%`` header whose ``evt`` or ``format`` line names EVT 2.0 or 3.0) or reads as
    ``t x y p`` text lines. A ``*.txt`` file without another format's signature is ``'text'``
    (the text reader then reports any bad line by number; an empty file holds zero events).

    Args:
        path: the file.

    Returns:
        ``'hdf5'``, ``'text'``, ``'npz'``, ``'aedat4'``, ``'evt2'`` or ``'evt3'``.

    Raises:
        EventFileError: the file is missing, or its extension names a format but its content
            does not match it (truncated or mislabelled), or it is a RAW file whose header does
            not say EVT 2.0 or 3.0.
        UnknownFormatError: neither the content nor the extension is recognised; the message
            lists the supported formats.
    """
    path = Path(path)
    if not path.is_file():
        raise EventFileError(path, "no such file" if not path.exists() else "not a regular file")
    with open(path, "rb") as fh:
        head = fh.read(_SNIFF_BYTES)
    by_ext = format_from_extension(path)
    sniffed = _sniff(head)
    if sniffed == "raw":
        return _raw_encoding(path, head)
    if sniffed is not None:
        return sniffed
    if by_ext == "text":  # the text reader reports what is wrong, with the line number
        return "text"
    if by_ext is not None:
        expected = {
            "hdf5": "the HDF5 signature",
            "aedat4": "'#!AER-DAT4.0'",
            "npz": "the zip signature 'PK\\x03\\x04'",
            "raw": "a '% ' header line",
        }[by_ext]
        what = "is empty" if not head else "has other content"
        raise EventFileError(
            path,
            f"the extension '{path.suffix}' means {by_ext}, but the file {what} instead of "
            f"starting with {expected}: it is truncated, corrupt or mislabelled",
        )
    raise UnknownFormatError(
        path,
        "unknown event file format (neither the extension nor the first bytes match); "
        f"supported: {_supported_list()}",
    )


def _raw_encoding(path: Path, head: bytes) -> str:
    header = parse_raw_header(head)
    if header is None:  # header longer than the sniff window: read more
        with open(path, "rb") as fh:
            header = parse_raw_header(fh.read(MAX_RAW_HEADER_BYTES))
    if header is None:
        raise EventFileError(
            path, "Prophesee RAW header is not terminated (no newline after the last '%' line, "
            f"or longer than {MAX_RAW_HEADER_BYTES} bytes): truncated or not a RAW file"
        )
    if header.encoding in ("evt2", "evt3"):
        return header.encoding
    if header.encoding is None:
        raise EventFileError(
            path, "Prophesee RAW header has no '% evt' or '% format' line, so the encoding "
            "(EVT 2.0 or 3.0) is unknown"
        )
    raise EventFileError(
        path, f"Prophesee RAW encoding '{header.encoding}' is not supported "
        "(evtrack reads EVT 2.0 and EVT 3.0 through expelliarmus)"
    )
