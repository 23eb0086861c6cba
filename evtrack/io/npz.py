"""NumPy ``.npz`` event files: arrays ``x``, ``y``, ``t`` (int64 µs), ``p`` (int8 ±1) and
``sensor_size`` (int64 ``[width, height]``, absent when unknown).

Reading loads the four arrays whole on first access (zip members are checked against their
CRC-32, so corrupted bytes raise); windows are then cut from memory. Prefer HDF5 for recordings
that do not fit in memory. Files from other tools that store ``p`` as 0/1 or bool are accepted
(0 → -1); ``t`` must be integer µs.

Writing streams: chunks go to temporary raw files beside the output, which are packed into the
archive (stored, or deflated with ``compress=True``) on close, without holding all events in
memory.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evtrack.errors import EventFileError, EvtrackError
from evtrack.events import Events
from evtrack.io.reader import EventReader, Locator, check_events
from evtrack.io.writer import StreamingWriter
from evtrack.utils import atomic_path

__all__ = ["NpzReader", "NpzWriter", "write_npz"]

_FIELDS = ("x", "y", "t", "p")
_DEFAULT_BLOCK = 1 << 20  # events per streamed chunk
_INT16_MAX_SIDE = 32767


class NpzReader(EventReader):
    """Reader of ``.npz`` event files (see the module docstring).

    Args:
        path: the file.
        sensor_size: overrides the file's ``sensor_size`` array.
        block_events: events per streamed chunk.
    """

    format = "npz"

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        block_events: int = _DEFAULT_BLOCK,
    ) -> None:
        super().__init__(path, sensor_size)
        self._block = int(block_events)
        self._arrays: dict[str, np.ndarray] | None = None
        self._z: Any = None
        try:
            self._z = np.load(self.path, allow_pickle=False)
            if not isinstance(self._z, np.lib.npyio.NpzFile):
                raise EventFileError(self.path, "not an .npz archive")
            self._inspect(sensor_size)
        except EvtrackError:
            self.close()
            raise
        except Exception as exc:  # zipfile/numpy raise many types on corrupt archives
            self.close()
            raise EventFileError(self.path, f"cannot read as .npz: {_describe(exc)}") from exc

    def _inspect(self, sensor_size: tuple[int, int] | None) -> None:
        names = set(self._z.files)
        missing = [k for k in _FIELDS if k not in names]
        if missing:
            have = sorted(names)
            listed = (f"{have[:6]} and {len(have) - 6} more" if len(have) > 6 else str(have))
            raise EventFileError(
                self.path, f"missing array(s) {missing} (has {listed}): not an event "
                ".npz or truncated"
            )
        shapes = {}
        for k in _FIELDS:
            shape, dtype = self._header(k)
            if len(shape) != 1 or dtype.kind not in ("iub" if k == "p" else "iu"):
                raise EventFileError(
                    self.path, f"array '{k}' must be 1-D integers, got shape {shape} dtype {dtype}"
                )
            shapes[k] = shape[0]
        if len(set(shapes.values())) != 1:
            raise EventFileError(
                self.path, "arrays have different lengths ("
                + ", ".join(f"{k}={n}" for k, n in shapes.items()) + "): truncated or corrupt"
            )
        self._n = shapes["t"]
        if sensor_size is None and "sensor_size" in names:
            size = self._load("sensor_size")
            if size.shape != (2,) or size.dtype.kind not in "iu" or (size <= 0).any():
                raise EventFileError(
                    self.path, f"'sensor_size' must hold two positive integers, got {size!r}"
                )
            self.sensor_size = (int(size[0]), int(size[1]))

    def _header(self, key: str) -> tuple[tuple[int, ...], np.dtype]:
        """Shape and dtype of a member, from its .npy header only (no data read)."""
        with self._z.zip.open(f"{key}.npy") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        return shape, dtype

    def _load(self, key: str) -> np.ndarray:
        try:
            return self._z[key]
        except Exception as exc:
            raise EventFileError(
                self.path, f"cannot read array '{key}': {_describe(exc)}"
            ) from exc

    def _load_all(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            a = {k: self._load(k) for k in _FIELDS}
            if len({v.shape[0] for v in a.values()}) != 1:
                raise EventFileError(self.path, "arrays have different lengths: corrupt")
            a["p"] = self._polarity(a["p"])
            for k, target in (("x", np.int32), ("y", np.int32), ("t", np.int64)):
                a[k] = self._fit(a[k], target, k)
            if a["x"].dtype != a["y"].dtype:
                a["x"], a["y"] = a["x"].astype(np.int32), a["y"].astype(np.int32)
            self._arrays = a
        return self._arrays

    def _fit(self, arr: np.ndarray, target: type, key: str) -> np.ndarray:
        if arr.dtype in (np.int16, np.int32) and key != "t" or arr.dtype == target:
            return arr
        info = np.iinfo(target)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            i = int(np.flatnonzero((arr < info.min) | (arr > info.max))[0])
            raise EventFileError(
                self.path, f"'{key}' value {arr[i]} at index {i} does not fit {np.dtype(target)}"
            )
        return arr.astype(target)

    def _polarity(self, p: np.ndarray) -> np.ndarray:
        if p.dtype == bool:
            return np.where(p, 1, -1).astype(np.int8)
        bad = (p != 1) & (p != 0) & (p != -1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise EventFileError(
                self.path, f"{int(bad.sum())} events with polarity other than ±1 (or 0/1), first "
                f"at index {i} (p={p[i]})"
            )
        if (p == 0).any() and (p == -1).any():
            i = int(np.flatnonzero(p == 0)[0])
            raise EventFileError(
                self.path, f"polarity mixes 0/1 and ±1 conventions, first 0 at index {i}"
            )
        return np.where(p == 1, 1, -1).astype(np.int8)

    def _raw_chunks(self) -> Iterator[tuple[Events, Locator | None]]:
        a = self._load_all()
        for i0 in range(0, self._n, self._block):
            sl = slice(i0, i0 + self._block)
            yield Events(a["x"][sl], a["y"][sl], a["t"][sl], a["p"][sl], self.sensor_size), None

    def _read_all(self) -> Events:
        a = self._load_all()
        ev = Events(a["x"], a["y"], a["t"], a["p"], self.sensor_size)
        check_events(ev, self.path)
        self._num_events = len(ev)
        self._t_start = int(ev.t[0]) if len(ev) else None
        self._t_end = int(ev.t[-1]) if len(ev) else None
        self._scanned = True
        return ev

    @property
    def num_events(self) -> int:
        return self._n

    def _expected_count(self) -> int | None:
        return self._n

    def close(self) -> None:
        if self._z is not None:
            with contextlib.suppress(Exception):
                self._z.close()
            self._z = None


class NpzWriter(StreamingWriter):
    """Stream events into an ``.npz`` file; the file appears atomically on :meth:`close`.

    Args:
        path: output file (``.npz``).
        sensor_size: stored as ``sensor_size`` when given.
        compress: deflate the members (smaller, slower to read); default False.

    Chunks must be valid and in time order across :meth:`write` calls (:class:`EventsError`).
    Coordinates are stored as int16 when the sensor is known and at most 32767 px a side,
    else int32.
    """

    def __init__(
        self,
        path: str | Path,
        sensor_size: tuple[int, int] | None = None,
        *,
        compress: bool = False,
    ) -> None:
        self.path = Path(path)
        self.sensor_size = None if sensor_size is None else tuple(int(v) for v in sensor_size)
        self._compress = bool(compress)
        small = self.sensor_size is not None and max(self.sensor_size) <= _INT16_MAX_SIDE
        coord = np.dtype(np.int16 if small else np.int32)
        self._dtypes = {"x": coord, "y": coord, "t": np.dtype(np.int64), "p": np.dtype(np.int8)}
        self._n = 0
        self._last_t: int | None = None
        self._closed = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(
            tempfile.mkdtemp(prefix=f".{self.path.name}.parts-", dir=self.path.parent)
        )
        self._parts = {k: open(self._tmpdir / f"{k}.bin", "wb") for k in _FIELDS}  # noqa: SIM115

    def write(self, events: Events) -> None:
        """Append a chunk (must follow the previous chunk in time)."""
        ev = self._checked_chunk(events)
        if ev is None:
            return
        d = ev.numpy()
        for k in _FIELDS:
            self._parts[k].write(d[k].astype(self._dtypes[k], copy=False).tobytes())
        self._n += len(ev)
        self._last_t = int(d["t"][-1])

    def close(self) -> None:
        """Pack the archive and move it into place (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            for fh in self._parts.values():
                fh.close()
            arrays: dict[str, np.ndarray] = {}
            for k in _FIELDS:
                if self._n:
                    arrays[k] = np.memmap(self._tmpdir / f"{k}.bin", dtype=self._dtypes[k],
                                          mode="r", shape=(self._n,))
                else:
                    arrays[k] = np.zeros(0, dtype=self._dtypes[k])
            if self.sensor_size is not None:
                arrays["sensor_size"] = np.asarray(self.sensor_size, dtype=np.int64)
            save = np.savez_compressed if self._compress else np.savez
            with atomic_path(self.path, suffix=".npz") as tmp:
                save(tmp, **arrays)
            del arrays
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)

    def _discard(self) -> None:
        for fh in self._parts.values():
            with contextlib.suppress(Exception):
                fh.close()
        shutil.rmtree(self._tmpdir, ignore_errors=True)


def write_npz(path: str | Path, events: Events, **options: Any) -> None:
    """Write ``events`` as ``.npz`` atomically (options: ``sensor_size``, ``compress``)."""
    unknown = set(options) - {"sensor_size", "compress"}
    if unknown:
        raise TypeError(f"unknown npz options {sorted(unknown)}")
    size = options.get("sensor_size") or events.sensor_size
    with NpzWriter(path, size, compress=options.get("compress", False)) as w:
        w.write(events)


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"
