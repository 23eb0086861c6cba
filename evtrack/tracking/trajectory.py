"""``Trajectory``: the output of :class:`evtrack.Tracker` (poses and twists over time).

Saved as CSV (one row per sample) or HDF5, atomically (temporary file, then rename).

CSV layout: ``#`` comment lines first (``# evtrack trajectory v1``, then ``# method: ...`` and
``# meta: {json}``), a header, then one row per sample::

    t_us,tx,ty,tz,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,status

Pose: object-to-event-camera, translation in metres and quaternion wxyz. Twist: ``[v_o (m/s),
ω (rad/s)]`` in the event camera frame (the convention ``Ṗ = v_o + ω × P``). Status: 0 =
waiting for the first pose, 1 = tracking, 2 = lost (the last pose is held until a pose
re-initialises the filter).

HDF5 layout: datasets ``t_us`` (N,) int64, ``poses`` (N,4,4) float64, ``twists`` (N,6) float64,
``status`` (N,) int8; attributes ``format`` = ``"evtrack trajectory"``, ``version``, ``method``
and ``meta`` (JSON).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.errors import EventFileError
from evtrack.geometry import matrix_to_tq, tq_to_matrix
from evtrack.utils import atomic_path

__all__ = ["Trajectory", "STATUS_WAITING", "STATUS_TRACKING", "STATUS_LOST"]

STATUS_WAITING = 0
STATUS_TRACKING = 1
STATUS_LOST = 2

_VERSION = 1
_MAGIC = "evtrack trajectory"
_COLUMNS = ("t_us", "tx", "ty", "tz", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz",
            "status")


@dataclass(repr=False)
class Trajectory:
    """Poses and twists of one tracked object over time.

    Attributes:
        t_us: (N,) int64 µs, increasing.
        poses: (N, 4, 4) float64 object-to-camera poses (event camera frame).
        twists: (N, 6) float64 ``[v_o, ω]``.
        status: (N,) int8, :data:`STATUS_WAITING`, :data:`STATUS_TRACKING` or :data:`STATUS_LOST`.
        method: the tracking method that made it.
        meta: free-form information (configuration, counters), JSON-serialisable.
    """

    t_us: Tensor
    poses: Tensor
    twists: Tensor
    status: Tensor
    method: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t_us = torch.as_tensor(self.t_us, dtype=torch.int64).reshape(-1)
        n = self.t_us.shape[0]
        for name, shape in (("poses", (n, 4, 4)), ("twists", (n, 6)), ("status", (n,))):
            value = torch.as_tensor(getattr(self, name),
                                    dtype=torch.int8 if name == "status" else torch.float64)
            if value.numel() != math.prod(shape):
                raise ValueError(f"trajectory {name} must be {shape} for {n} timestamps, got "
                                 f"shape {tuple(value.shape)}")
            setattr(self, name, value.reshape(shape))
        if n > 1 and bool((self.t_us[1:] <= self.t_us[:-1]).any()):
            raise ValueError("trajectory timestamps must be strictly increasing")
        if not isinstance(self.method, str) or any(c in self.method for c in "\r\n"):
            raise ValueError(f"trajectory method must be a one-line string, got {self.method!r}")

    def __len__(self) -> int:
        return int(self.t_us.shape[0])

    def __repr__(self) -> str:
        n = len(self)
        span = f", t=[{int(self.t_us[0])}, {int(self.t_us[-1])}] µs" if n else ""
        tracked = int((self.status == STATUS_TRACKING).sum()) if n else 0
        return f"Trajectory(method={self.method!r}, n={n}{span}, tracked={tracked})"

    @property
    def tracked(self) -> Tensor:
        """(N,) bool, True where the tracker was tracking (status 1)."""
        return self.status == STATUS_TRACKING

    @property
    def translations(self) -> Tensor:
        """(N, 3) metres."""
        return self.poses[:, :3, 3]

    def __getitem__(self, index: slice | Tensor) -> Trajectory:
        return Trajectory(self.t_us[index], self.poses[index], self.twists[index],
                          self.status[index], self.method, dict(self.meta))

    # ------------------------------------------------------------------ saving
    def save(self, path: str | Path) -> None:
        """Write to ``.csv`` or ``.h5``/``.hdf5`` atomically."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in (".csv", ".h5", ".hdf5"):
            raise ValueError(f"{path}: unknown trajectory format {suffix!r} "
                             "(use .csv, .h5 or .hdf5)")
        meta_json = json.dumps(self.meta, default=_json_default)
        with atomic_path(path) as tmp:
            if suffix == ".csv":
                self._write_csv(tmp, meta_json)
            else:
                import h5py

                with h5py.File(tmp, "w") as f:
                    f.create_dataset("t_us", data=self.t_us.numpy())
                    f.create_dataset("poses", data=self.poses.numpy())
                    f.create_dataset("twists", data=self.twists.numpy())
                    f.create_dataset("status", data=self.status.numpy())
                    f.attrs["format"] = _MAGIC
                    f.attrs["version"] = _VERSION
                    f.attrs["method"] = self.method
                    f.attrs["meta"] = meta_json

    def _write_csv(self, path: Path, meta_json: str) -> None:
        t, q = matrix_to_tq(self.poses) if len(self) else (torch.zeros(0, 3), torch.zeros(0, 4))
        table = np.concatenate([t.numpy(), q.numpy(), self.twists.numpy()], axis=1)
        lines = [f"# {_MAGIC} v{_VERSION}", f"# method: {self.method}", f"# meta: {meta_json}",
                 ",".join(_COLUMNS)]
        for ti, row, s in zip(self.t_us.tolist(), table, self.status.tolist(), strict=True):
            lines.append(f"{ti}," + ",".join(f"{v:.10g}" for v in row) + f",{s}")
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | Path) -> Trajectory:
        """Read a trajectory written by :meth:`save`.

        Raises:
            EventFileError: missing, truncated or malformed file (naming the file and line).
        """
        path = Path(path)
        if not path.is_file():
            raise EventFileError(path, "trajectory file not found")
        suffix = path.suffix.lower()
        if suffix == ".csv":
            return cls._read_csv(path)
        if suffix in (".h5", ".hdf5"):
            return cls._read_h5(path)
        raise EventFileError(path, f"unknown trajectory format {suffix!r} (use .csv or .h5)")

    @classmethod
    def _read_csv(cls, path: Path) -> Trajectory:
        method, meta, header_seen = "", {}, False
        rows: list[list[float]] = []
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if not line.strip():
                continue
            if line.startswith("#"):
                body = line[1:].strip()
                if body.startswith("method:"):
                    method = body[len("method:"):].strip()
                elif body.startswith("meta:"):
                    try:
                        meta = json.loads(body[len("meta:"):].strip())
                    except json.JSONDecodeError as exc:
                        raise EventFileError(path, f"line {lineno}: bad meta JSON: {exc}") from exc
                continue
            if not header_seen:
                if tuple(c.strip() for c in line.split(",")) != _COLUMNS:
                    raise EventFileError(path, f"line {lineno}: expected the header "
                                               f"{','.join(_COLUMNS)}")
                header_seen = True
                continue
            parts = line.split(",")
            if len(parts) != len(_COLUMNS):
                raise EventFileError(path, f"line {lineno}: expected {len(_COLUMNS)} values, "
                                           f"got {len(parts)} (truncated?)")
            try:
                rows.append([float(v) for v in parts])
            except ValueError as exc:
                raise EventFileError(path, f"line {lineno}: {exc}") from exc
        if not header_seen:
            raise EventFileError(path, "no header line: not a trajectory CSV")
        table = np.asarray(rows, np.float64).reshape(-1, len(_COLUMNS))
        t_us = torch.from_numpy(table[:, 0].astype(np.int64))
        poses = tq_to_matrix(torch.from_numpy(table[:, 1:4]), torch.from_numpy(table[:, 4:8]))
        poses[~np.isfinite(table[:, 1:8]).all(1)] = float("nan")  # no estimate: NaN throughout
        try:
            return cls(t_us, poses, torch.from_numpy(table[:, 8:14]),
                       torch.from_numpy(table[:, 14].astype(np.int8)), method, meta)
        except ValueError as exc:
            raise EventFileError(path, str(exc)) from exc

    @classmethod
    def _read_h5(cls, path: Path) -> Trajectory:
        import h5py

        try:
            with h5py.File(path, "r") as f:
                if f.attrs.get("format") != _MAGIC:
                    raise EventFileError(path, "not an evtrack trajectory (format attribute)")
                missing = [k for k in ("t_us", "poses", "twists", "status") if k not in f]
                if missing:
                    raise EventFileError(path, f"datasets missing: {missing}")
                meta = json.loads(f.attrs.get("meta", "{}"))
                return cls(f["t_us"][()], f["poses"][()], f["twists"][()], f["status"][()],
                           str(f.attrs.get("method", "")), meta)
        except (OSError, KeyError, ValueError) as exc:
            if isinstance(exc, EventFileError):
                raise
            raise EventFileError(path, f"cannot read trajectory: {exc}") from exc


def _json_default(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.tolist()
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__} in trajectory meta")
