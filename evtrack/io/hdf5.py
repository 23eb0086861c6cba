"""evtrack's native HDF5 event files: a streaming writer and an indexed reader.

Layout (``format_version`` 1)::

    events/x   (N,) int16 (int32 when the sensor is wider or taller than 32767 px)
    events/y   (N,) same dtype as x
    events/t   (N,) int64, µs, non-decreasing
    events/p   (N,) int8, +1 (ON) / -1 (OFF)
    ms_to_idx  (K+1,) int64: ms_to_idx[k] = index of the first event with t >= t0_us + k·1000
               (K = (t_last - t0_us) // 1000 + 1, so the last entry is N; [0] for no events)
    attributes: sensor_width, sensor_height (px), t0_us (µs), num_events, format_version

Datasets are chunked (:data:`DEFAULT_CHUNK_EVENTS` events per chunk), resizable, with a
Fletcher-32 checksum by default so that corrupted bytes raise instead of reading as valid
events; ``compression='lzf'`` or ``'gzip'`` (built-in h5py filters, with byte shuffling) shrink
files about 3x at a read-speed cost (see ``benchmarks/bench_io.py``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from evtrack.errors import EventFileError, EventsError, EvtrackError
from evtrack.events import Events
from evtrack.io.reader import EventReader, Locator, check_events
from evtrack.io.writer import StreamingWriter
from evtrack.utils import atomic_path

__all__ = [
    "EventWriter",
    "Hdf5Reader",
    "write_hdf5",
    "FORMAT_VERSION",
    "DEFAULT_CHUNK_EVENTS",
    "DEFAULT_READ_BLOCK",
]

FORMAT_VERSION = 1
US_PER_MS = 1000
DEFAULT_CHUNK_EVENTS = 1 << 16  # HDF5 chunk length (events) of each dataset
DEFAULT_READ_BLOCK = 1 << 20  # events per block when streaming
_WRITE_BUFFER_CHUNKS = 8  # writer flushes after this many HDF5 chunks of buffered events
_MAX_CHUNK_BYTES = 64 << 20  # larger chunks than this are taken as corruption
# Longest span the ms index may cover (2**28 ms, about 74.5 hours; 2 GiB of index).
MAX_INDEX_ENTRIES = 1 << 28
_INT16_MAX_SIDE = 32767
_COMPRESSIONS = (None, "lzf", "gzip")
# HDF5 filter ids that keep the stored size at least the raw size: shuffle, fletcher32.
_SIZE_PRESERVING_FILTERS = {h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_FLETCHER32}
_FIELDS = ("x", "y", "t", "p")


def _coord_dtype(sensor_size: tuple[int, int]) -> np.dtype:
    return np.dtype(np.int16 if max(sensor_size) <= _INT16_MAX_SIDE else np.int32)


def _check_sensor_size(sensor_size: Any) -> tuple[int, int]:
    if sensor_size is None:
        raise EventsError(
            "the HDF5 format stores the sensor size: give sensor_size=(width, height) "
            "(events read from text files without a header have none)"
        )
    w, h = (int(v) for v in sensor_size)
    if w <= 0 or h <= 0:
        raise EventsError(f"sensor_size must be positive (width, height), got {sensor_size}")
    return w, h


class EventWriter(StreamingWriter):
    """Stream events into a native HDF5 file; the file appears atomically on :meth:`close`.

    Args:
        path: output file (``.h5``); replaced if it exists, only once writing succeeded.
        sensor_size: ``(width, height)`` in pixels.
        compression: ``None`` (default, fastest reads), ``'lzf'`` or ``'gzip'``.
        compression_opts: gzip level 0-9 (default 4); ``None`` otherwise.
        chunk_events: HDF5 chunk length in events (default 65536).
        checksum: store Fletcher-32 checksums so that corruption is detected (default True).
        t0_us: origin of the ms index (µs); default: the first event's timestamp. Must not be
            after the first event.

    Chunks passed to :meth:`write` must be valid (see :meth:`Events.validate`) and in time
    order across calls, else :class:`EventsError` is raised. If the ``with`` block raises, or
    :meth:`abort` is called, no file is left behind.

    Example:
        >>> with EventWriter(path, (640, 480)) as w:  # doctest: +SKIP
        ...     for chunk in chunks:
        ...         w.write(chunk)
    """

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int],
        *,
        compression: str | None = None,
        compression_opts: int | None = None,
        chunk_events: int = DEFAULT_CHUNK_EVENTS,
        checksum: bool = True,
        t0_us: int | None = None,
    ) -> None:
        self.path = Path(path)
        self.sensor_size = _check_sensor_size(sensor_size)
        if compression == "none":
            compression = None
        if compression not in _COMPRESSIONS:
            raise ValueError(f"compression must be one of {_COMPRESSIONS}, got {compression!r}")
        if compression == "gzip" and compression_opts is None:
            compression_opts = 4
        if int(chunk_events) <= 0:
            raise ValueError(f"chunk_events must be positive, got {chunk_events}")
        self._chunk = int(chunk_events)
        self._coord = _coord_dtype(self.sensor_size)
        self._t0 = None if t0_us is None else int(t0_us)
        self._n = 0
        self._last_t: int | None = None
        self._ms: list[np.ndarray] = []
        self._next_k = 0
        self._buf: list[tuple[np.ndarray, ...]] = []
        self._buf_n = 0
        self._closed = False
        self._stack = contextlib.ExitStack()
        try:
            tmp = self._stack.enter_context(atomic_path(self.path, suffix=".h5"))
            self._file = h5py.File(tmp, "w")
            grp = self._file.create_group("events")
            dtypes = {"x": self._coord, "y": self._coord, "t": np.int64, "p": np.int8}
            self._ds = {
                k: grp.create_dataset(
                    k, shape=(0,), maxshape=(None,), dtype=dt, chunks=(self._chunk,),
                    compression=compression, compression_opts=compression_opts,
                    shuffle=compression is not None, fletcher32=bool(checksum),
                )
                for k, dt in dtypes.items()
            }
            self._ms_ds = self._file.create_dataset(
                "ms_to_idx", shape=(0,), maxshape=(None,), dtype=np.int64,
                chunks=(self._chunk,), fletcher32=bool(checksum),
            )
        except BaseException:
            self._abort_quietly()
            raise

    # ----------------------------------------------------------------- writing
    def write(self, events: Events) -> None:
        """Append a chunk (must follow the previous chunk in time)."""
        ev = self._checked_chunk(events)
        if ev is None:
            return
        t = ev.t.cpu().numpy()
        if self._t0 is None:
            self._t0 = int(t[0])
        elif self._n == 0 and self._t0 > int(t[0]):
            raise EventsError(
                f"{self.path}: t0_us={self._t0} is after the first event (t={int(t[0])} µs)"
            )
        self._index(t)
        self._buf.append((
            ev.x.cpu().numpy().astype(self._coord, copy=False),
            ev.y.cpu().numpy().astype(self._coord, copy=False),
            t,
            ev.p.cpu().numpy().astype(np.int8, copy=False),
        ))
        self._buf_n += len(t)
        self._n += len(t)
        self._last_t = int(t[-1])
        if self._buf_n >= self._chunk * _WRITE_BUFFER_CHUNKS:
            self._flush()

    def _index(self, t: np.ndarray) -> None:
        """Resolve the ms boundaries up to this chunk's last event (see the module layout)."""
        k_hi = (int(t[-1]) - self._t0) // US_PER_MS
        if k_hi < self._next_k:
            return
        if k_hi + 2 > MAX_INDEX_ENTRIES:
            raise EventsError(
                f"{self.path}: the events span {k_hi} ms from t0_us={self._t0}; the ms index is "
                f"limited to {MAX_INDEX_ENTRIES} entries (about 74 hours): split the recording"
            )
        ks = np.arange(self._next_k, k_hi + 1, dtype=np.int64)
        bounds = self._t0 + ks * US_PER_MS
        self._ms.append(self._n + np.searchsorted(t, bounds, side="left").astype(np.int64))
        self._next_k = k_hi + 1

    def _flush(self) -> None:
        if not self._buf_n:
            return
        start = self._ds["t"].shape[0]
        stop = start + self._buf_n
        for j, k in enumerate(_FIELDS):
            data = np.concatenate([b[j] for b in self._buf])
            self._ds[k].resize((stop,))
            self._ds[k][start:stop] = data
        self._buf, self._buf_n = [], 0
        self._append_ms(self._ms)
        self._ms = []

    def _append_ms(self, parts: list[np.ndarray]) -> None:
        if not parts:
            return
        table = np.concatenate(parts)
        start = self._ms_ds.shape[0]
        self._ms_ds.resize((start + table.shape[0],))
        self._ms_ds[start:] = table

    # ----------------------------------------------------------------- finishing
    def close(self) -> None:
        """Write the index and attributes, then move the file into place (idempotent)."""
        if self._closed:
            return
        try:
            self._flush()
            self._append_ms([np.array([self._n], dtype=np.int64)])  # end sentinel ([0] if empty)
            attrs = self._file.attrs
            attrs["sensor_width"], attrs["sensor_height"] = self.sensor_size
            attrs["t0_us"] = np.int64(self._t0 if self._t0 is not None else 0)
            attrs["num_events"] = np.int64(self._n)
            attrs["format_version"] = FORMAT_VERSION
            self._file.close()
        except BaseException:
            self._abort_quietly()
            raise
        self._closed = True
        self._stack.close()  # renames the temporary file onto self.path

    def _discard(self) -> None:
        with contextlib.suppress(Exception):
            self._file.close()
        self._stack.__exit__(EvtrackError, EvtrackError("aborted"), None)


def write_hdf5(path: str | Path, events: Events, **options: Any) -> None:
    """Write ``events`` to a native HDF5 file atomically (options as for :class:`EventWriter`).

    ``sensor_size`` may be given as an option when ``events.sensor_size`` is ``None``.
    """
    sensor_size = options.pop("sensor_size", None) or events.sensor_size
    with EventWriter(path, sensor_size, **options) as w:
        w.write(events)


# ============================================================================ reading
def _as_int(arr: np.ndarray, target: type, what: str, path: Path) -> np.ndarray:
    """Convert an integer array to ``target``, raising if a value does not fit."""
    if arr.dtype == target:
        return arr
    info = np.iinfo(target)
    if arr.size and (arr.min() < info.min or arr.max() > info.max):
        raise EventFileError(path, f"{what} holds values outside the {np.dtype(target)} range")
    return arr.astype(target)


class Hdf5Reader(EventReader):
    """Reader of the native HDF5 layout (see the module docstring).

    Opening checks the layout (datasets present, 1-D integers of one length, index table
    consistent with ``events/t``, sizes plausible for the file) without reading events.
    :meth:`read` with a time window reads only that window, located through ``ms_to_idx``;
    files without ``ms_to_idx`` fall back to a binary search on ``events/t``.

    Args:
        path: the file.
        sensor_size: overrides the file's ``sensor_width``/``sensor_height`` attributes.
        block_events: events per block when streaming.
    """

    format = "hdf5"

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        block_events: int = DEFAULT_READ_BLOCK,
    ) -> None:
        super().__init__(path, sensor_size)
        self._block = int(block_events)
        self._f: h5py.File | None = None
        try:
            self._f = h5py.File(self.path, "r")
            self._inspect(sensor_size)
        except EventFileError:
            self.close()
            raise
        except Exception as exc:  # h5py/libhdf5 raise many types on corrupt files
            self.close()
            raise EventFileError(
                self.path, f"cannot read as HDF5 events: {_describe(exc)}"
            ) from exc

    # ----------------------------------------------------------------- layout checks
    def _fail(self, problem: str) -> EventFileError:
        return EventFileError(self.path, problem)

    def _inspect(self, sensor_size: tuple[int, int] | None) -> None:
        f = self._f
        grp = f.get("events")
        if not isinstance(grp, h5py.Group):
            raise self._fail("missing group 'events' (not an evtrack HDF5 event file)")
        self._ds = {}
        for k in _FIELDS:
            ds = grp.get(k)
            if not isinstance(ds, h5py.Dataset):
                raise self._fail(f"missing dataset 'events/{k}': truncated or not an event file")
            if ds.ndim != 1 or ds.dtype.kind not in "iu":
                raise self._fail(
                    f"dataset 'events/{k}' must be a 1-D integer array, got shape {ds.shape} "
                    f"dtype {ds.dtype}"
                )
            self._ds[k] = ds
        version = f.attrs.get("format_version")
        if version is not None and int(version) > FORMAT_VERSION:
            raise self._fail(
                f"format_version {int(version)} is newer than this evtrack reads "
                f"({FORMAT_VERSION}): update evtrack"
            )
        lengths = {k: ds.shape[0] for k, ds in self._ds.items()}
        if len(set(lengths.values())) != 1:
            raise self._fail(
                "datasets have different lengths ("
                + ", ".join(f"{k}={n}" for k, n in lengths.items())
                + "): truncated or corrupt"
            )
        n = lengths["t"]
        claimed = f.attrs.get("num_events")
        if claimed is not None and int(claimed) != n:
            raise self._fail(f"attribute num_events={int(claimed)} but the datasets hold {n}")
        self._check_storage(n)
        if sensor_size is None:
            w, h = f.attrs.get("sensor_width"), f.attrs.get("sensor_height")
            if w is not None and h is not None:
                if int(w) <= 0 or int(h) <= 0:
                    raise self._fail(f"sensor size attributes must be positive, got {w}x{h}")
                self.sensor_size = (int(w), int(h))
        self._n = n
        self._t_first = self._t_last = None
        if n:
            ends = self._ds["t"][[0, n - 1]] if n > 1 else self._ds["t"][0:1].repeat(2)
            self._t_first, self._t_last = int(ends[0]), int(ends[1])
        self._t0 = int(f.attrs.get("t0_us", self._t_first if self._t_first is not None else 0))
        self._ms = f.get("ms_to_idx")
        if self._ms is not None:
            self._check_ms_table()

    def _check_storage(self, n: int) -> None:
        file_size = self.path.stat().st_size
        for k, ds in self._ds.items():
            if ds.chunks is not None and ds.chunks[0] * ds.dtype.itemsize > _MAX_CHUNK_BYTES:
                raise self._fail(f"dataset 'events/{k}' has an implausible chunk size {ds.chunks}")
            stored = ds.id.get_storage_size()
            if stored > file_size:
                raise self._fail(
                    f"dataset 'events/{k}' claims {stored} bytes of storage in a {file_size}-byte "
                    "file: truncated or corrupt"
                )
            plist = ds.id.get_create_plist()
            filters = {plist.get_filter(i)[0] for i in range(plist.get_nfilters())}
            if filters <= _SIZE_PRESERVING_FILTERS and stored < n * ds.dtype.itemsize:
                raise self._fail(
                    f"dataset 'events/{k}' claims {n} events but stores only {stored} bytes: "
                    "truncated or corrupt"
                )

    def _check_ms_table(self) -> None:
        ms = self._ms
        if not isinstance(ms, h5py.Dataset) or ms.ndim != 1 or ms.dtype.kind not in "iu":
            raise self._fail("'ms_to_idx' must be a 1-D integer dataset")
        if self._n == 0:
            expected = 1
        else:
            if self._t0 > self._t_first:
                raise self._fail(
                    f"attribute t0_us={self._t0} is after the first event (t={self._t_first} µs)"
                )
            expected = (self._t_last - self._t0) // US_PER_MS + 2
        if ms.shape[0] != expected:
            raise self._fail(
                f"'ms_to_idx' has {ms.shape[0]} entries, but the events from t0_us={self._t0} to "
                f"t={self._t_last} µs need {expected}: corrupt index"
            )
        first, last = (int(v) for v in ms[[0, expected - 1]]) if expected > 1 else (int(ms[0]),) * 2
        if first != 0 or last != self._n:
            raise self._fail(
                f"'ms_to_idx' must start at 0 and end at {self._n}, got {first} and {last}"
            )

    # ----------------------------------------------------------------- metadata
    @property
    def num_events(self) -> int:
        return self._n

    @property
    def t_start(self) -> int | None:
        return self._t_first

    @property
    def t_end(self) -> int | None:
        return self._t_last

    @property
    def indexed(self) -> bool:
        return True

    def _expected_count(self) -> int | None:
        return self._n

    # ----------------------------------------------------------------- reading
    def _slice(self, i0: int, i1: int) -> Events:
        """Events ``[i0, i1)`` as stored (unvalidated)."""
        d = {k: self._ds[k][i0:i1] for k in _FIELDS}
        coord = np.int16 if d["x"].dtype == np.int16 and d["y"].dtype == np.int16 else np.int32
        return Events(
            _as_int(d["x"], coord, "events/x", self.path),
            _as_int(d["y"], coord, "events/y", self.path),
            _as_int(d["t"], np.int64, "events/t", self.path),
            _as_int(d["p"], np.int8, "events/p", self.path),
            self.sensor_size,
        )

    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        for i0 in range(0, self._n, self._block):
            yield self._guard(self._slice, i0, min(self._n, i0 + self._block)), None

    def _guard(self, fn: Any, *args: Any) -> Any:
        try:
            return fn(*args)
        except EvtrackError:
            raise
        except Exception as exc:
            raise EventFileError(self.path, f"cannot read events: {_describe(exc)}") from exc

    def _read_all(self) -> Events:
        ev = self._guard(self._slice, 0, self._n)
        check_events(ev, self.path)
        if self._ms is not None and self._n:
            self._verify_ms_table(self._guard(lambda: self._ms[()]), ev.t.numpy())
        return ev

    def _verify_ms_table(self, table: np.ndarray, t: np.ndarray) -> None:
        """Check every entry: t[ms[k] - 1] < t0 + k·1000 <= t[ms[k]] (edges excepted)."""
        n = self._n
        bounds = self._t0 + np.arange(table.shape[0], dtype=np.int64) * US_PER_MS
        inside = (table >= 0) & (table <= n)
        at = np.clip(table, 0, n - 1)
        before = np.clip(table - 1, 0, n - 1)
        ok = inside & ((table == n) | (t[at] >= bounds)) & ((table == 0) | (t[before] < bounds))
        bad = np.flatnonzero(~ok)
        if bad.size:
            k = int(bad[0])
            raise self._fail(
                f"'ms_to_idx' disagrees with events/t at {bad.size} entries, first at k={k} "
                f"(index {int(table[k])} for t >= {int(bounds[k])} µs)"
            )

    def read(self, t0_us: int | None = None, t1_us: int | None = None) -> Events:
        """Events with ``t0_us <= t < t1_us``; only that window is read from disk."""
        if t0_us is None and t1_us is None:
            return self._read_all()
        i0 = 0 if t0_us is None else self._guard(self._index_of, int(t0_us))
        i1 = self._n if t1_us is None else self._guard(self._index_of, int(t1_us))
        i1 = max(i0, i1)
        ev = self._guard(self._slice, i0, i1)
        check_events(ev, self.path, offset=i0)
        self._guard(self._check_bounds, i0, i1, t0_us, t1_us, ev)
        return ev

    def _index_of(self, t: int) -> int:
        """Index of the first event with timestamp ``>= t`` (µs)."""
        n = self._n
        if n == 0 or t <= self._t_first:
            return 0
        if t > self._t_last:
            return n
        tds = self._ds["t"]
        if self._ms is not None:
            k = (t - self._t0) // US_PER_MS
            lo, hi = (int(v) for v in self._ms[k : k + 2])
            if not 0 <= lo <= hi <= n:
                raise self._fail(f"'ms_to_idx' entries {k}..{k + 1} ({lo}, {hi}) are invalid")
        else:
            lo, hi = 0, n
            while hi - lo > self._block:  # bisect with single reads, then one block
                mid = (lo + hi) // 2
                if int(tds[mid]) < t:
                    lo = mid + 1
                else:
                    hi = mid
        return lo + int(np.searchsorted(tds[lo:hi], t, side="left"))

    def _check_bounds(
        self, i0: int, i1: int, t0: int | None, t1: int | None, ev: Events
    ) -> None:
        """Check that [i0, i1) is exactly the window, so a corrupt index cannot go unseen."""
        tds = self._ds["t"]
        ok = True
        if t0 is not None:
            ok &= (len(ev) == 0 or int(ev.t[0]) >= t0) and (i0 == 0 or int(tds[i0 - 1]) < t0)
        if t1 is not None:
            ok &= (len(ev) == 0 or int(ev.t[-1]) < t1) and (i1 == self._n or int(tds[i1]) >= t1)
        if not ok:
            raise self._fail(
                f"'ms_to_idx' points to events [{i0}, {i1}) that are not the window "
                f"[{t0}, {t1}) µs: corrupt index or unsorted events"
            )

    def close(self) -> None:
        if self._f is not None:
            with contextlib.suppress(Exception):
                self._f.close()
            self._f = None


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"
