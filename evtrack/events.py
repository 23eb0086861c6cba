"""The event container: a structure of arrays ``x, y, t, p`` with its sensor size.

Conventions (docs/architecture.md): ``t`` is int64 microseconds and non-decreasing, ``p`` is
int8 in {+1, -1}, ``x``/``y`` are integer pixel coordinates (int16 or int32).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.errors import EventsError
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["Events", "EventsValidationReport", "concatenate"]

_COORD_DTYPES = (torch.int16, torch.int32, torch.int64)


def _as_tensor(value: object, dtype: torch.dtype, name: str) -> Tensor:
    if isinstance(value, Tensor):
        tensor = value
    else:
        tensor = torch.as_tensor(np.ascontiguousarray(value))
    if tensor.ndim != 1:
        raise EventsError(f"Events.{name} must be 1-D, got shape {tuple(tensor.shape)}")
    if tensor.dtype == torch.bool or tensor.is_complex():
        raise EventsError(f"Events.{name} must hold integers, got dtype {tensor.dtype}")
    if tensor.is_floating_point() and dtype != tensor.dtype:
        if not torch.isfinite(tensor).all():
            raise EventsError(f"Events.{name} contains NaN or infinite values")
        if not torch.equal(tensor, torch.round(tensor)):
            raise EventsError(f"Events.{name} must hold integers, got fractional values")
    if dtype != tensor.dtype and tensor.numel() and not _fits(tensor.dtype, dtype):
        info = torch.iinfo(dtype)
        low, high = tensor.min().item(), tensor.max().item()  # Python numbers: no promotion
        if low < info.min or high > info.max:
            bad = low if low < info.min else high
            raise EventsError(f"Events.{name} holds {bad}, outside the {dtype} range "
                              f"[{info.min}, {info.max}] it is stored in")
    return tensor.to(dtype)


def _checked_sensor_size(sensor_size: Any) -> tuple[int, int]:
    """``(width, height)`` as positive ints.

    Raises:
        EventsError: not two positive whole numbers.
    """
    try:
        values = [float(v) for v in sensor_size]
    except (TypeError, ValueError) as exc:
        raise EventsError(f"sensor_size must be (width, height), got {sensor_size!r}") from exc
    if len(values) != 2 or not all(math.isfinite(v) and v > 0 and v == int(v) for v in values):
        raise EventsError(f"sensor_size must be two positive whole numbers (width, height), "
                          f"got {tuple(sensor_size)!r}")
    return int(values[0]), int(values[1])


def _fits(source: torch.dtype, target: torch.dtype) -> bool:
    """Whether every value of the integer dtype ``source`` fits in ``target`` (no check
    needed before the cast)."""
    if source.is_floating_point:
        return False
    s, t = torch.iinfo(source), torch.iinfo(target)
    return t.min <= s.min and s.max <= t.max


@dataclass(frozen=True)
class EventsValidationReport:
    """What :meth:`Events.validate` found. Each count has the index of its first offender.

    Attributes:
        num_events: number of events checked.
        unsorted: number of events whose timestamp is smaller than the previous one.
        first_unsorted: index of the first such event, or -1.
        outside: number of events with x or y outside ``[0, width) x [0, height)``.
        first_outside: index of the first such event, or -1.
        bad_polarity: number of events whose polarity is neither +1 nor -1.
        first_bad_polarity: index of the first such event, or -1.
    """

    num_events: int
    unsorted: int = 0
    first_unsorted: int = -1
    outside: int = 0
    first_outside: int = -1
    bad_polarity: int = 0
    first_bad_polarity: int = -1
    problems: tuple[str, ...] = field(default=())

    @property
    def ok(self) -> bool:
        return not self.problems

    def __str__(self) -> str:
        if self.ok:
            return f"{self.num_events} events, no problems"
        return f"{self.num_events} events: " + "; ".join(self.problems)


def _first_true(mask: Tensor | np.ndarray) -> int:
    """Index of the first True of a 1-D mask (numpy or torch), or -1."""
    if isinstance(mask, np.ndarray):
        return int(mask.argmax()) if mask.any() else -1
    idx = torch.nonzero(mask, as_tuple=False)
    return int(idx[0, 0]) if idx.numel() else -1


class Events:
    """A batch of events from one sensor, as a structure of 1-D tensors.

    Args:
        x: (N,) column in pixels, int16/int32 (other integer types are converted to int32).
        y: (N,) row in pixels, same dtype rules as ``x``.
        t: (N,) timestamps in microseconds, converted to int64. Non-decreasing by convention;
            :meth:`validate` checks it.
        p: (N,) polarity, +1 (ON) or -1 (OFF), converted to int8. A 0/1 polarity is *not*
            accepted silently here; use :meth:`from_unsigned_polarity`.
        sensor_size: ``(width, height)`` in pixels, or ``None`` when unknown.

    The constructor checks shapes and dtypes only (cheap); call :meth:`validate` or
    :meth:`check` to verify ordering, coordinates and polarity.

    Example:
        >>> ev = Events(x=[1, 2], y=[3, 4], t=[10, 20], p=[1, -1], sensor_size=(640, 480))
        >>> len(ev), ev.duration_us
        (2, 10)
    """

    __slots__ = ("x", "y", "t", "p", "sensor_size")

    def __init__(
        self,
        x: Tensor | np.ndarray | Sequence[int],
        y: Tensor | np.ndarray | Sequence[int],
        t: Tensor | np.ndarray | Sequence[int],
        p: Tensor | np.ndarray | Sequence[int],
        sensor_size: tuple[int, int] | None = None,
    ) -> None:
        if not isinstance(x, Tensor):
            x = torch.as_tensor(np.ascontiguousarray(x))
        coord_dtype = x.dtype if x.dtype in (torch.int16, torch.int32) else torch.int32
        self.x = _as_tensor(x, coord_dtype, "x")
        self.y = _as_tensor(y, coord_dtype, "y")
        self.t = _as_tensor(t, torch.int64, "t")
        self.p = _as_tensor(p, torch.int8, "p")
        n = self.x.shape[0]
        for name in ("y", "t", "p"):
            if getattr(self, name).shape[0] != n:
                raise EventsError(
                    f"Events fields differ in length: x has {n}, {name} has "
                    f"{getattr(self, name).shape[0]}"
                )
        if sensor_size is not None:
            sensor_size = _checked_sensor_size(sensor_size)
        self.sensor_size = sensor_size

    # ------------------------------------------------------------------ constructors
    @classmethod
    def empty(cls, sensor_size: tuple[int, int] | None = None, device: str | torch.device = "cpu"):
        """An empty container (N = 0)."""
        z = torch.zeros(0, dtype=torch.int32, device=device)
        return cls(z, z.clone(), z.to(torch.int64), z.to(torch.int8), sensor_size)

    @classmethod
    def from_unsigned_polarity(cls, x, y, t, p01, sensor_size=None) -> Events:
        """Build from a 0/1 (OFF/ON) polarity, as most camera formats store it."""
        p = p01 if isinstance(p01, Tensor) else torch.as_tensor(np.ascontiguousarray(p01))
        p = p.to(torch.int8)
        if p.numel() and (p.min() < 0 or p.max() > 1):
            bad = _first_true((p < 0) | (p > 1))
            raise EventsError(f"0/1 polarity expected, got {int(p[bad])} at index {bad}")
        return cls(x, y, t, p * 2 - 1, sensor_size)

    @classmethod
    def from_structured(cls, arr: np.ndarray, sensor_size: tuple[int, int] | None = None) -> Events:
        """Build from a numpy structured array with fields ``t, x, y, p`` (p as 0/1 or ±1)."""
        names = arr.dtype.names or ()
        missing = [f for f in ("t", "x", "y", "p") if f not in names]
        if missing:
            raise EventsError(f"structured array lacks fields {missing} (has {list(names)})")
        p = np.asarray(arr["p"]).astype(np.int8)
        if p.size and p.min() >= 0:
            return cls.from_unsigned_polarity(arr["x"], arr["y"], arr["t"], p, sensor_size)
        return cls(arr["x"], arr["y"], arr["t"], p, sensor_size)

    # ------------------------------------------------------------------ basic properties
    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        span = f", t=[{self.t_start}, {self.t_end}] µs" if len(self) else ""
        return (
            f"Events(n={len(self)}{span}, sensor_size={self.sensor_size}, "
            f"device={self.device})"
        )

    @property
    def device(self) -> torch.device:
        return self.t.device

    @property
    def t_start(self) -> int:
        """First timestamp in µs (raises on an empty container)."""
        if not len(self):
            raise EventsError("t_start of an empty Events")
        return int(self.t[0])

    @property
    def t_end(self) -> int:
        """Last timestamp in µs (raises on an empty container)."""
        if not len(self):
            raise EventsError("t_end of an empty Events")
        return int(self.t[-1])

    @property
    def duration_us(self) -> int:
        """``t_end - t_start`` in µs; 0 for fewer than two events."""
        return self.t_end - self.t_start if len(self) > 1 else 0

    # ------------------------------------------------------------------ indexing
    def __getitem__(self, index: int | slice | Tensor | np.ndarray) -> Events:
        """Select events by integer, slice, index tensor or boolean mask (order is kept)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        elif isinstance(index, np.ndarray):
            index = torch.as_tensor(index)
        if isinstance(index, Tensor):
            index = index.to(self.device)
            if self.device.type == "cpu" and index.ndim == 1 and index.dtype in (
                    torch.bool, torch.int64, torch.int32):  # (torch reads uint8 as a mask)
                # NumPy's gather: 5-6x faster than torch's boolean indexing of small CPU
                # tensors (the tracker masks every step group); the same values and errors
                idx = index.numpy()
                fields = [getattr(self, k).numpy() for k in ("x", "y", "t", "p")]
                if idx.dtype == np.bool_ and jit_available() and len(idx) == len(self):
                    # a mask: one compiled pass for the four fields, ~4x NumPy's four
                    # (the tracker's event mask of a 340k-event step group: 0.7 vs 3.2 ms)
                    selected = _compact(idx, *fields)
                else:
                    selected = [f[idx] for f in fields]
                return Events(*(torch.from_numpy(f) for f in selected), self.sensor_size)
        return Events(self.x[index], self.y[index], self.t[index], self.p[index], self.sensor_size)

    def between(self, t0_us: int, t1_us: int) -> Events:
        """Events with ``t0_us <= t < t1_us`` (binary search; timestamps must be sorted)."""
        lo, hi = self._search(t0_us, t1_us)
        return self[lo:hi]

    def _search(self, t0_us: int, t1_us: int) -> tuple[int, int]:
        bounds = torch.tensor([t0_us, t1_us], dtype=torch.int64, device=self.device)
        lo, hi = torch.searchsorted(self.t, bounds, right=False).tolist()
        return lo, max(lo, hi)

    def windows(
        self,
        duration_us: int | None = None,
        count: int | None = None,
        t_start_us: int | None = None,
        include_empty: bool = False,
    ) -> Iterator[Events]:
        """Iterate over consecutive windows of ``duration_us`` µs or of ``count`` events.

        Time windows are half-open ``[t_start + k·duration, t_start + (k+1)·duration)``
        starting at ``t_start_us`` (default: the first event). Empty time windows are skipped
        unless ``include_empty`` is set. Exactly one of ``duration_us`` and ``count`` is given.
        """
        if (duration_us is None) == (count is None):
            raise ValueError("give exactly one of duration_us and count")
        if count is not None:
            if count <= 0:
                raise ValueError(f"count must be positive, got {count}")
            for start in range(0, len(self), count):
                yield self[start : start + count]
            return
        if duration_us <= 0:
            raise ValueError(f"duration_us must be positive, got {duration_us}")
        if not len(self):
            return
        t0 = self.t_start if t_start_us is None else int(t_start_us)
        n_windows = (self.t_end - t0) // duration_us + 1
        edges = t0 + duration_us * torch.arange(n_windows + 1, dtype=torch.int64)
        idx = torch.searchsorted(self.t.cpu(), edges).tolist()
        for k in range(n_windows):
            if idx[k + 1] > idx[k] or include_empty:
                yield self[idx[k] : idx[k + 1]]

    # ------------------------------------------------------------------ conversion
    def to(self, device: str | torch.device) -> Events:
        """A copy on ``device`` (no copy if already there)."""
        return Events(
            self.x.to(device), self.y.to(device), self.t.to(device), self.p.to(device),
            self.sensor_size,
        )

    def numpy(self) -> dict[str, np.ndarray]:
        """The fields as numpy arrays (on CPU), keyed ``x, y, t, p``."""
        return {k: getattr(self, k).cpu().numpy() for k in ("x", "y", "t", "p")}

    def clone(self) -> Events:
        return Events(self.x.clone(), self.y.clone(), self.t.clone(), self.p.clone(),
                      self.sensor_size)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Events):
            return NotImplemented
        return (
            len(self) == len(other)
            and self.sensor_size == other.sensor_size
            and all(torch.equal(getattr(self, k).to(torch.int64).cpu(),
                                getattr(other, k).to(torch.int64).cpu())
                    for k in ("x", "y", "t", "p"))
        )

    __hash__ = None  # mutable tensors inside

    # ------------------------------------------------------------------ validation
    def validate(self, sensor_size: tuple[int, int] | None = None) -> EventsValidationReport:
        """Check timestamp order, coordinates against the sensor, and polarity.

        Args:
            sensor_size: ``(width, height)`` to check the coordinates against instead of the
                events' own ``sensor_size`` (a consumer's sensor).

        Returns a report with counts and first offending indices; never raises. Coordinates
        are checked only for negativity when the sensor size is unknown.
        """
        size = tuple(sensor_size) if sensor_size is not None else self.sensor_size
        n = len(self)
        problems: list[str] = []
        unsorted = outside = bad = 0
        first_unsorted = first_outside = first_bad = -1
        # numpy on CPU (zero-copy views, ~10x faster than torch's int16/int8 kernels there)
        fields = self.numpy() if self.device.type == "cpu" else None
        x, y, t, p = (fields[k] for k in "xytp") if fields is not None else (
            self.x, self.y, self.t, self.p)
        if n and self.device.type == "cpu" and jit_available():
            # the counts below in one compiled pass (a dozen NumPy passes otherwise)
            w, h = size if size is not None else (-1, -1)
            counts = _count_problems(x, y, t, p, w, h)
            if not any(counts[::2]):
                return EventsValidationReport(n, 0, -1, 0, -1, 0, -1, ())
        if n > 1:
            dec = t[1:] < t[:-1]
            unsorted = int(dec.sum())
            if unsorted:
                first_unsorted = _first_true(dec) + 1
                problems.append(
                    f"{unsorted} timestamps go backwards, first at index {first_unsorted} "
                    f"(t={int(t[first_unsorted])} µs after {int(t[first_unsorted - 1])})"
                )
        if n:
            out = (x < 0) | (y < 0)
            if size is not None:
                w, h = size
                out |= (x >= w) | (y >= h)
            outside = int(out.sum())
            if outside:
                first_outside = _first_true(out)
                problems.append(
                    f"{outside} events outside the sensor {size}, first at index "
                    f"{first_outside} (x={int(x[first_outside])}, y={int(y[first_outside])})"
                )
            badp = (p != 1) & (p != -1)
            bad = int(badp.sum())
            if bad:
                first_bad = _first_true(badp)
                problems.append(
                    f"{bad} events with polarity other than +1/-1, first at index {first_bad} "
                    f"(p={int(p[first_bad])})"
                )
        return EventsValidationReport(
            n, unsorted, first_unsorted, outside, first_outside, bad, first_bad, tuple(problems)
        )

    def check(self, source: str = "events") -> Events:
        """Raise :class:`EventsError` naming ``source`` if :meth:`validate` finds a problem."""
        report = self.validate()
        if not report.ok:
            raise EventsError(f"{source}: {report}")
        return self


@njit
def _compact(keep, x, y, t, p):
    """The events where ``keep`` (N,) bool is true: fields ``x, y, t, p`` (N,) -> four new
    arrays of ``keep.sum()`` in one pass (each slot written, then kept by advancing the output
    position when ``keep``: no branch per event)."""
    n = np.count_nonzero(keep)
    ox, oy = np.empty(n, x.dtype), np.empty(n, y.dtype)
    ot, op = np.empty(n, t.dtype), np.empty(n, p.dtype)
    j = 0
    if n:
        for i in range(keep.shape[0]):
            ox[j], oy[j], ot[j], op[j] = x[i], y[i], t[i], p[i]
            j += keep[i]
            if j == n:
                break
    return ox, oy, ot, op


@njit
def _count_problems(x, y, t, p, width, height):
    """``(unsorted, first, outside, first, bad polarity, first)`` of (N,) CPU event arrays in
    one pass, as :meth:`Events.validate` counts them (``width < 0``: sensor size unknown,
    coordinates checked for negativity only); a first index is -1 where the count is 0.

    The counting loop has no branch (it vectorises); the first indices are looked for only
    where a count is not 0."""
    n = x.shape[0]
    w_lim = width if width >= 0 else np.int64(1) << 62
    h_lim = height if width >= 0 else np.int64(1) << 62
    unsorted = outside = bad = 0
    for i in range(1, n):
        unsorted += t[i] < t[i - 1]
    for i in range(n):
        xi, yi, pi = x[i], y[i], p[i]
        outside += (xi < 0) | (yi < 0) | (xi >= w_lim) | (yi >= h_lim)
        bad += (pi != 1) & (pi != -1)
    first_unsorted = first_outside = first_bad = -1
    if unsorted:
        for i in range(1, n):
            if t[i] < t[i - 1]:
                first_unsorted = i
                break
    if outside:
        for i in range(n):
            if x[i] < 0 or y[i] < 0 or x[i] >= w_lim or y[i] >= h_lim:
                first_outside = i
                break
    if bad:
        for i in range(n):
            if p[i] != 1 and p[i] != -1:
                first_bad = i
                break
    return unsorted, first_unsorted, outside, first_outside, bad, first_bad


def concatenate(chunks: Sequence[Events]) -> Events:
    """Join event batches end to end (no re-sorting; the caller keeps time order).

    All chunks must share one sensor size (``None`` is compatible with anything) and device.
    """
    if not chunks:
        return Events.empty()
    sizes = {c.sensor_size for c in chunks if c.sensor_size is not None}
    if len(sizes) > 1:
        raise EventsError(f"cannot concatenate events of different sensor sizes {sorted(sizes)}")
    dtype = torch.int32 if any(c.x.dtype == torch.int32 for c in chunks) else chunks[0].x.dtype
    if all(c.device.type == "cpu" for c in chunks):  # numpy's concatenate is much faster on CPU
        np_dtype = torch.empty(0, dtype=dtype).numpy().dtype
        arrays = [c.numpy() for c in chunks]
        fields = {
            k: torch.from_numpy(np.concatenate(
                [a[k].astype(np_dtype, copy=False) if k in "xy" else a[k] for a in arrays]))
            for k in ("x", "y", "t", "p")
        }
    else:
        fields = {k: torch.cat([getattr(c, k).to(dtype) if k in "xy" else getattr(c, k)
                                for c in chunks]) for k in ("x", "y", "t", "p")}
    return Events(**fields, sensor_size=sizes.pop() if sizes else None)


Events.concatenate = staticmethod(concatenate)  # type: ignore[attr-defined]
