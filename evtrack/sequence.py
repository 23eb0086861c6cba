"""The sequence folder: one recording or simulation with events, RGB-D frames and ground truth.

Layout of a sequence folder::

    meta.yaml             cameras, extrinsic, object, rates (see :class:`SequenceMeta`)
    events.h5             events in the native HDF5 layout (:mod:`evtrack.io`)
    rgb/timestamps.txt    one int64 µs timestamp per line; rgb/000000.png, ... (8-bit RGB)
    depth/timestamps.txt  depth/000000.png (uint16 millimetres, 0 = missing) or
                          depth/000000.tiff (float32 metres, 0 or NaN = missing)
    groundtruth.h5        optional: poses, twists, per-event flow (see :class:`GroundTruth`)

Loading is lazy: :meth:`Sequence.load` reads ``meta.yaml`` only; events, frames and ground
truth are read when first used. Writing goes through :class:`SequenceWriter`, which fills a
temporary folder and renames it onto the target only when everything was written.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import h5py
import numpy as np
import torch
import yaml
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError, EventFileError
from evtrack.events import Events
from evtrack.sequence_objects import SequenceObject, parse_objects
from evtrack.utils import make_public

__all__ = ["SequenceMeta", "SequenceObject", "GroundTruth", "Sequence", "SequenceWriter",
           "FORMAT_VERSION"]

FORMAT_VERSION = 1
META_FILE = "meta.yaml"
EVENTS_FILE = "events.h5"
GT_FILE = "groundtruth.h5"
DEPTH_UNITS = ("mm_png16", "m_float32")


# ---------------------------------------------------------------------------- metadata
@dataclass
class SequenceMeta:
    """What ``meta.yaml`` holds.

    Attributes:
        event_camera: intrinsics of the event camera (required).
        name: a short name of the sequence.
        object_name: name of the tracked object (e.g. ``"003_cracker_box"``).
        mesh_path: path of the object's mesh, relative to the sequence folder or absolute;
            ``None`` if unknown.
        rgb_camera: intrinsics of the RGB-D camera (depth registered to RGB); ``None`` if the
            sequence has no frames.
        T_event_rgb: (4, 4) float64, maps points of the RGB camera frame into the event camera
            frame. Identity when both are the same (simulation).
        rates: nominal rates in Hz, e.g. ``{"render_hz": 500, "rgb_hz": 60, "depth_hz": 60}``.
        depth_unit: ``"mm_png16"`` (uint16 PNG in mm) or ``"m_float32"`` (float32 TIFF in m).
        source: ``"simulation"`` or ``"recording"``.
        extra: free-form information (simulation settings, seeds, ...).
        objects: with several objects, all of them (the first is ``object_name`` with
            ``mesh_path`` and ``groundtruth.h5``); empty for one object.
    """

    event_camera: PinholeCamera
    name: str = ""
    object_name: str = ""
    mesh_path: str | None = None
    rgb_camera: PinholeCamera | None = None
    T_event_rgb: Tensor = field(default_factory=lambda: torch.eye(4, dtype=torch.float64))
    rates: dict[str, float] = field(default_factory=dict)
    depth_unit: str = "mm_png16"
    source: str = "recording"
    extra: dict[str, Any] = field(default_factory=dict)
    objects: list[SequenceObject] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.T_event_rgb = torch.as_tensor(self.T_event_rgb, dtype=torch.float64)
        if self.T_event_rgb.shape != (4, 4):
            raise ConfigError(f"T_event_rgb must be 4x4, got shape {tuple(self.T_event_rgb.shape)}")
        if self.depth_unit not in DEPTH_UNITS:
            raise ConfigError(f"depth_unit must be one of {DEPTH_UNITS}, got {self.depth_unit!r}")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ConfigError(f"the sequence's object names must be unique, got {names}")
        if self.objects and self.objects[0].name != self.object_name:
            raise ConfigError(f"objects[0] ({self.objects[0].name!r}) must be the sequence's "
                              f"object ({self.object_name!r})")

    def to_dict(self) -> dict[str, Any]:
        out = {
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "source": self.source,
            "object": {"name": self.object_name, "mesh": self.mesh_path},
            "event_camera": self.event_camera.to_dict(),
            "rgb_camera": None if self.rgb_camera is None else self.rgb_camera.to_dict(),
            "T_event_rgb": self.T_event_rgb.tolist(),
            "rates": {k: float(v) for k, v in self.rates.items()},
            "depth_unit": self.depth_unit,
            "extra": _plain(self.extra),
        }
        if self.objects:
            out["objects"] = [o.to_dict() for o in self.objects]
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str = META_FILE) -> SequenceMeta:
        """Parse ``meta.yaml`` content; errors name ``source`` and the field."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: expected a YAML mapping at the top level")
        version = data.get("format_version")
        if version is None:
            raise ConfigError(f"{source}: missing field 'format_version'")
        if version != FORMAT_VERSION:
            raise ConfigError(
                f"{source}: format_version {version} is not supported (this evtrack reads "
                f"{FORMAT_VERSION})"
            )
        if "event_camera" not in data or data["event_camera"] is None:
            raise ConfigError(f"{source}: missing field 'event_camera'")
        known = {"format_version", "name", "source", "object", "event_camera", "rgb_camera",
                 "T_event_rgb", "rates", "depth_unit", "extra", "objects"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"{source}: unknown field(s) {unknown}")
        obj = data.get("object") or {}
        if not isinstance(obj, Mapping):
            raise ConfigError(f"{source}: field 'object' must be a mapping with 'name' and 'mesh'")
        rgb = data.get("rgb_camera")
        try:
            T = torch.as_tensor(data.get("T_event_rgb", np.eye(4).tolist()), dtype=torch.float64)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: field 'T_event_rgb' is not a 4x4 matrix: {exc}") from exc
        if T.shape != (4, 4):
            raise ConfigError(f"{source}: field 'T_event_rgb' must be 4x4, got {tuple(T.shape)}")
        rates = data.get("rates") or {}
        if not isinstance(rates, Mapping):
            raise ConfigError(f"{source}: field 'rates' must be a mapping of name to Hz")
        for k, v in rates.items():
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ConfigError(f"{source}: field 'rates.{k}' must be a number (Hz), got {v!r}")
        mesh = obj.get("mesh")
        if mesh is not None and not isinstance(mesh, str):
            raise ConfigError(f"{source}: field 'object.mesh' must be a file path, got {mesh!r}")
        objects = parse_objects(data.get("objects"), source)
        try:
            return cls(
                objects=objects,
                event_camera=PinholeCamera.from_dict(
                    data["event_camera"], f"{source}: event_camera"),
                name=str(data.get("name") or ""),
                object_name=str(obj.get("name") or ""),
                mesh_path=mesh,
                rgb_camera=None if rgb is None else PinholeCamera.from_dict(
                    rgb, f"{source}: rgb_camera"),
                T_event_rgb=T,
                rates={str(k): float(v) for k, v in rates.items()},
                depth_unit=str(data.get("depth_unit", "mm_png16")),
                source=str(data.get("source") or "recording"),
                extra=dict(data.get("extra") or {}),
            )
        except ConfigError as exc:
            if str(exc).startswith(source):
                raise
            raise ConfigError(f"{source}: {exc}") from exc


def _plain(value: Any) -> Any:
    """Make a value YAML-safe: tensors and numpy values become lists and Python scalars."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (Tensor, np.ndarray)):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


# ---------------------------------------------------------------------------- ground truth
@dataclass
class GroundTruth:
    """Ground truth of a sequence, all in the event camera frame.

    Attributes:
        pose_t_us: (M,) int64 µs, increasing.
        poses: (M, 4, 4) float64 object-to-camera poses.
        twist_t_us: (K,) int64 µs, increasing.
        twists: (K, 6) float64 ``[v_o (m/s), ω (rad/s)]`` (the package's convention).
        event_flow: (N, 2) float32 px/s at each event of ``events.h5`` (same order), NaN where
            the event is not on the object, or ``None``.
        event_object: (N,) int16, the index in :attr:`SequenceMeta.objects` of the object each
            event is on (-1: none), or ``None``; simulations of several objects store it.
    """

    pose_t_us: Tensor
    poses: Tensor
    twist_t_us: Tensor
    twists: Tensor
    event_flow: Tensor | None = None
    event_object: Tensor | None = None

    def __post_init__(self) -> None:
        self.pose_t_us = torch.as_tensor(self.pose_t_us, dtype=torch.int64)
        self.poses = torch.as_tensor(self.poses, dtype=torch.float64)
        self.twist_t_us = torch.as_tensor(self.twist_t_us, dtype=torch.int64)
        self.twists = torch.as_tensor(self.twists, dtype=torch.float64)
        if self.event_flow is not None:
            self.event_flow = torch.as_tensor(self.event_flow, dtype=torch.float32)
        if self.event_object is not None:
            self.event_object = torch.as_tensor(self.event_object, dtype=torch.int16)
        m = self.pose_t_us.shape[0]
        if self.poses.shape != (m, 4, 4):
            raise ValueError(f"poses must be ({m}, 4, 4) to match pose_t_us, got "
                             f"{tuple(self.poses.shape)}")
        k = self.twist_t_us.shape[0]
        if self.twists.shape != (k, 6):
            raise ValueError(f"twists must be ({k}, 6) to match twist_t_us, got "
                             f"{tuple(self.twists.shape)}")
        for name, t in (("pose_t_us", self.pose_t_us), ("twist_t_us", self.twist_t_us)):
            if t.numel() > 1 and bool((t[1:] <= t[:-1]).any()):
                raise ValueError(f"ground truth {name} must be strictly increasing")

    def pose_at(self, t_us: int | Tensor) -> Tensor:
        """Ground-truth pose at ``t_us`` (scalar or (T,)), interpolated on SE(3).

        Between two stored poses the constant twist joining them is applied (geodesic
        interpolation); outside the stored range the end pose is held.

        Returns:
            (4, 4) or (T, 4, 4) float64.
        """
        from evtrack.geometry import integrate_twist, twist_between

        t = torch.as_tensor(t_us, dtype=torch.int64)
        scalar = t.ndim == 0
        t = t.reshape(-1)
        ts = self.pose_t_us
        if ts.numel() == 0:
            raise ValueError("ground truth has no poses")
        hi = torch.searchsorted(ts, t, right=True).clamp(1, max(ts.numel() - 1, 1))
        lo = hi - 1
        if ts.numel() == 1:
            out = self.poses[0].expand(t.numel(), 4, 4).clone()
        else:
            dt = (ts[hi] - ts[lo]).to(torch.float64) * 1e-6
            frac_t = ((t - ts[lo]).to(torch.float64) * 1e-6).clamp(min=0)
            frac_t = torch.minimum(frac_t, dt)
            V = twist_between(self.poses[lo], self.poses[hi], 1.0) / dt.unsqueeze(-1)
            out = integrate_twist(self.poses[lo], V, frac_t)
        return out[0] if scalar else out

    def twist_at(self, t_us: int | Tensor) -> Tensor:
        """Ground-truth twist at ``t_us``, linearly interpolated; (6,) or (T, 6)."""
        t = torch.as_tensor(t_us, dtype=torch.int64)
        scalar = t.ndim == 0
        x = t.reshape(-1).to(torch.float64).numpy()
        xp = self.twist_t_us.to(torch.float64).numpy()
        out = np.stack([np.interp(x, xp, self.twists[:, i].numpy()) for i in range(6)], -1)
        out = torch.from_numpy(out)
        return out[0] if scalar else out

    def save(self, path: str | Path) -> None:
        from evtrack.utils import atomic_path

        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            f.create_dataset("poses/t_us", data=self.pose_t_us.numpy())
            f.create_dataset("poses/T", data=self.poses.numpy())
            f.create_dataset("twists/t_us", data=self.twist_t_us.numpy())
            f.create_dataset("twists/V", data=self.twists.numpy())
            if self.event_flow is not None:
                f.create_dataset("event_flow", data=self.event_flow.numpy(), chunks=True,
                                 compression="lzf")
            if self.event_object is not None:
                f.create_dataset("event_object", data=self.event_object.numpy(), chunks=True,
                                 compression="lzf")

    @classmethod
    def load(cls, path: str | Path) -> GroundTruth:
        try:
            with h5py.File(path, "r") as f:
                missing = [k for k in ("poses/t_us", "poses/T", "twists/t_us", "twists/V")
                           if k not in f]
                if missing:
                    raise EventFileError(path, f"ground-truth datasets missing: {missing}")
                flow = f["event_flow"][()] if "event_flow" in f else None
                owner = f["event_object"][()] if "event_object" in f else None
                return cls(f["poses/t_us"][()], f["poses/T"][()], f["twists/t_us"][()],
                           f["twists/V"][()], flow, owner)
        except (OSError, KeyError, ValueError) as exc:
            if isinstance(exc, EventFileError):
                raise
            raise EventFileError(path, f"cannot read ground truth: {exc}") from exc


# ---------------------------------------------------------------------------- frames
def _read_timestamps(path: Path) -> Tensor:
    if not path.is_file():
        return torch.zeros(0, dtype=torch.int64)
    values = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values.append(int(line))
        except ValueError:
            raise EventFileError(
                path, f"line {lineno}: expected an integer timestamp in µs, got {line!r}"
            ) from None
    t = torch.tensor(values, dtype=torch.int64)
    if t.numel() > 1 and bool((t[1:] < t[:-1]).any()):
        first = int(torch.nonzero(t[1:] < t[:-1])[0, 0]) + 1
        raise EventFileError(path, f"timestamps go backwards at frame {first}")
    return t


def _check_events_sensor(events_path: Path, meta: SequenceMeta, meta_path: Path) -> None:
    """The events file's sensor size (from its header) is the event camera's of ``meta.yaml``.

    Raises:
        EventFileError: naming both files and both sizes.
    """
    from evtrack.io import open_events

    reader = open_events(events_path)
    try:
        size = reader.sensor_size
    finally:
        reader.close()
    cam = meta.event_camera
    if size is not None and tuple(size) != (cam.width, cam.height):
        raise EventFileError(events_path, f"its sensor is {size[0]}x{size[1]}, but {meta_path.name}"
                                          f" gives the event camera as {cam.width}x{cam.height}")


def _check_frame_files(folder: Path, count: int, suffixes: tuple[str, ...]) -> None:
    """One frame file (``000000.png``, ...) per line of ``folder/timestamps.txt``.

    Raises:
        EventFileError: a frame missing, or frames the timestamps do not cover (they would
            be left out without a word).
    """
    if not folder.is_dir():
        if count:
            raise EventFileError(folder, f"timestamps.txt lists {count} frames but the folder "
                                         "is missing")
        return
    found = {int(f.stem) for f in folder.iterdir()
             if f.suffix.lower() in suffixes and len(f.stem) == 6 and f.stem.isdigit()}
    if found == set(range(count)):
        return
    missing = sorted(set(range(count)) - found)
    if missing:
        raise EventFileError(folder, f"timestamps.txt lists {count} frames but frame "
                                     f"{missing[0]:06d} is missing ({len(missing)} missing)")
    extra = sorted(found - set(range(count)))
    raise EventFileError(folder, f"timestamps.txt lists {count} frames but the folder has "
                                 f"{len(found)} (from {extra[0]:06d} on none has a timestamp)")


def _frame_path(folder: Path, index: int, ext: str) -> Path:
    return folder / f"{index:06d}{ext}"


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise EventFileError(path, "missing or unreadable RGB frame")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_uint16_depth_png(path: str | Path) -> np.ndarray:
    """A single-channel 16-bit depth PNG as it is stored: (H, W) uint16.

    Raises:
        EventFileError: naming ``path``: unreadable (missing, truncated, corrupt), or not a
            single-channel uint16 image.
    """
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise EventFileError(path, "unreadable depth PNG (truncated or corrupt)")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise EventFileError(path, f"expected a single-channel uint16 depth image, got "
                                   f"shape {raw.shape} {raw.dtype}")
    return raw


def _read_depth(path_png: Path, path_tiff: Path) -> np.ndarray:
    if path_png.is_file():
        depth = read_uint16_depth_png(path_png).astype(np.float32) * 1e-3  # mm -> m
    elif path_tiff.is_file():
        depth = cv2.imread(str(path_tiff), cv2.IMREAD_UNCHANGED)
        if depth is None:
            raise EventFileError(path_tiff, "unreadable depth TIFF (truncated or corrupt)")
        if depth.dtype != np.float32 or depth.ndim != 2:
            raise EventFileError(path_tiff, f"depth TIFF must be single-channel float32 (m), "
                                            f"got {depth.dtype} {depth.shape}")
    else:
        raise EventFileError(path_png.with_suffix(""), "missing depth frame (.png or .tiff)")
    depth = depth.copy()
    depth[~(depth > 0)] = np.nan  # 0 and NaN both mean "no depth"
    return depth


# ---------------------------------------------------------------------------- sequence
class Sequence:
    """A recording or simulation stored as a folder (see the module docstring).

    Build one with :meth:`load`, or in memory with the constructor and then :meth:`save`.

    Args:
        meta: cameras, extrinsic, object and rates.
        events: the events, or ``None`` to read them lazily from ``root``.
        rgb_frames: in-memory RGB frames (F, H, W, 3) uint8 with ``rgb_times_us`` (F,).
        depth_frames: in-memory depth frames (F, H, W) float32 metres with ``depth_times_us``.
        ground_truth: optional ground truth.
        root: the folder it was loaded from.
    """

    def __init__(
        self,
        meta: SequenceMeta,
        events: Events | None = None,
        rgb_times_us: Tensor | None = None,
        rgb_frames: np.ndarray | None = None,
        depth_times_us: Tensor | None = None,
        depth_frames: np.ndarray | None = None,
        ground_truth: GroundTruth | None = None,
        root: str | Path | None = None,
    ) -> None:
        self.meta = meta
        self.root = None if root is None else Path(root)
        self._events = events
        self._rgb_frames = rgb_frames
        self._depth_frames = depth_frames
        self._gt = ground_truth
        self._gt_loaded = ground_truth is not None or root is None
        self.rgb_times_us = (torch.zeros(0, dtype=torch.int64) if rgb_times_us is None
                             else torch.as_tensor(rgb_times_us, dtype=torch.int64))
        self.depth_times_us = (torch.zeros(0, dtype=torch.int64) if depth_times_us is None
                               else torch.as_tensor(depth_times_us, dtype=torch.int64))
        if rgb_frames is not None and len(rgb_frames) != len(self.rgb_times_us):
            raise ValueError(f"{len(rgb_frames)} RGB frames but {len(self.rgb_times_us)} "
                             "timestamps")
        if depth_frames is not None and len(depth_frames) != len(self.depth_times_us):
            raise ValueError(f"{len(depth_frames)} depth frames but "
                             f"{len(self.depth_times_us)} timestamps")

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, folder: str | Path) -> Sequence:
        """Open a sequence folder lazily (reads and checks ``meta.yaml`` and timestamps)."""
        root = Path(folder)
        meta_path = root / META_FILE
        if not root.is_dir():
            raise EventFileError(root, "not a sequence folder (no such directory)")
        if not meta_path.is_file():
            raise EventFileError(root, f"not a sequence folder: {META_FILE} is missing")
        try:
            data = yaml.safe_load(meta_path.read_text())
        except yaml.YAMLError as exc:
            raise ConfigError(f"{meta_path}: invalid YAML: {exc}") from exc
        meta = SequenceMeta.from_dict(data, source=str(meta_path))
        if not (root / EVENTS_FILE).is_file():
            raise EventFileError(root / EVENTS_FILE, "events file of the sequence is missing")
        seq = cls(meta, root=root,
                  rgb_times_us=_read_timestamps(root / "rgb" / "timestamps.txt"),
                  depth_times_us=_read_timestamps(root / "depth" / "timestamps.txt"))
        _check_frame_files(root / "rgb", seq.num_rgb, (".png",))
        _check_frame_files(root / "depth", seq.num_depth, (".png", ".tiff"))
        _check_events_sensor(root / EVENTS_FILE, meta, meta_path)
        return seq

    @property
    def events_path(self) -> Path | None:
        return None if self.root is None else self.root / EVENTS_FILE

    @property
    def events(self) -> Events:
        """All events (read from ``events.h5`` on first access, then cached)."""
        if self._events is None:
            from evtrack.io import read_events

            self._events = read_events(self.events_path)
        return self._events

    def iter_events(self, window_us: int | None = None, count: int | None = None
                    ) -> Iterator[Events]:
        """Stream the events in windows without loading them all (see ``evtrack.io``)."""
        if self._events is not None or self.root is None:
            yield from self.events.windows(duration_us=window_us, count=count)
            return
        from evtrack.io import iter_events

        yield from iter_events(self.events_path, window_us=window_us, count=count)

    @property
    def num_rgb(self) -> int:
        return int(self.rgb_times_us.numel())

    @property
    def num_depth(self) -> int:
        return int(self.depth_times_us.numel())

    def rgb(self, index: int) -> np.ndarray:
        """RGB frame ``index`` as (H, W, 3) uint8."""
        index = self._check_index(index, self.num_rgb, "RGB")
        if self._rgb_frames is not None:
            return np.asarray(self._rgb_frames[index])
        return _read_rgb(_frame_path(self.root / "rgb", index, ".png"))

    def depth(self, index: int) -> np.ndarray:
        """Depth frame ``index`` as (H, W) float32 metres; NaN where depth is missing."""
        index = self._check_index(index, self.num_depth, "depth")
        if self._depth_frames is not None:
            d = np.array(self._depth_frames[index], dtype=np.float32)
            d[~(d > 0)] = np.nan
            return d
        folder = self.root / "depth"
        return _read_depth(_frame_path(folder, index, ".png"), _frame_path(folder, index, ".tiff"))

    @staticmethod
    def _check_index(index: int, n: int, what: str) -> int:
        if not -n <= index < n:
            raise IndexError(f"{what} frame {index} out of range (sequence has {n})")
        return index % n

    @property
    def ground_truth(self) -> GroundTruth | None:
        """Ground truth if the sequence has it (read lazily), else ``None``."""
        if not self._gt_loaded:
            path = self.root / GT_FILE
            self._gt = GroundTruth.load(path) if path.is_file() else None
            self._gt_loaded = True
        return self._gt

    @property
    def objects(self) -> list[SequenceObject]:
        """The sequence's objects: ``meta.objects``, or for a one-object sequence its object
        (with ``groundtruth.h5`` when the folder has one)."""
        if self.meta.objects:
            return list(self.meta.objects)
        return [SequenceObject(self.meta.object_name, self.meta.mesh_path, GT_FILE)]

    def _resolve(self, path: str | None) -> Path | None:
        if not path:
            return None
        p = Path(path)
        return p if p.is_absolute() or self.root is None else self.root / p

    def object_mesh_file(self, index: int) -> Path | None:
        """Object ``index``'s mesh path resolved against the folder, or ``None``."""
        return self._resolve(self.objects[index].mesh_path)

    def object_ground_truth(self, index: int) -> GroundTruth | None:
        """Object ``index``'s ground truth (object 0's is :attr:`ground_truth`), or ``None``."""
        if index == 0 or (index < 0 and index + len(self.objects) == 0):
            return self.ground_truth
        path = self._resolve(self.objects[index].ground_truth_path)
        if path is None or not path.is_file():
            return None
        return GroundTruth.load(path)

    def object_view(self, index: int) -> Sequence:
        """The same recording seen as a one-object sequence of object ``index``: its name,
        mesh and ground truth, the whole event stream and every frame (e.g. to track that
        object alone with a :class:`~evtrack.Tracker`)."""
        import dataclasses

        obj = self.objects[index]
        # the view keeps this folder as its root: the object's path as meta.yaml gives it
        # (relative to the root, or absolute), not the path already resolved against it
        meta = dataclasses.replace(self.meta, object_name=obj.name, objects=[],
                                   mesh_path=obj.mesh_path)
        view = Sequence(meta, self._events, self.rgb_times_us, self._rgb_frames,
                        self.depth_times_us, self._depth_frames,
                        self.object_ground_truth(index), self.root)
        view._gt_loaded = True
        return view

    @property
    def mesh_file(self) -> Path | None:
        """The object's mesh path resolved against the folder, or ``None``."""
        if not self.meta.mesh_path:
            return None
        p = Path(self.meta.mesh_path)
        return p if p.is_absolute() or self.root is None else self.root / p

    # ------------------------------------------------------------------ saving
    def save(self, folder: str | Path, overwrite: bool = False) -> None:
        """Write the sequence to ``folder`` atomically (see :class:`SequenceWriter`)."""
        with SequenceWriter(folder, self.meta, overwrite=overwrite) as writer:
            for chunk in self.iter_events(count=1_000_000):
                writer.add_events(chunk)
            for i in range(self.num_rgb):
                writer.add_rgb(int(self.rgb_times_us[i]), self.rgb(i))
            for i in range(self.num_depth):
                writer.add_depth(int(self.depth_times_us[i]), self.depth(i))
            if self.ground_truth is not None:
                writer.set_ground_truth(self.ground_truth)
            for k, obj in enumerate(self.meta.objects[1:], start=1):
                gt = self.object_ground_truth(k)
                if gt is not None and obj.ground_truth_path and not Path(
                        obj.ground_truth_path).is_absolute():
                    gt.save(writer.file_path(obj.ground_truth_path))
                mesh = self.object_mesh_file(k)
                if (mesh is not None and mesh.is_file() and obj.mesh_path
                        and not Path(obj.mesh_path).is_absolute()):
                    shutil.copyfile(mesh, writer.file_path(obj.mesh_path))

    def summary(self) -> dict[str, Any]:
        """A dictionary describing the sequence (used by ``evtrack info``)."""
        if self._events is not None or self.root is None:
            ev = self.events
            n = len(ev)
            span = (ev.t_start, ev.t_end) if n else (0, 0)
        else:
            from evtrack.io import open_events

            reader = open_events(self.events_path)
            try:
                n = reader.num_events
                span = (reader.t_start, reader.t_end) if n else (0, 0)
            finally:
                reader.close()
        gt = self.ground_truth
        return {
            "name": self.meta.name,
            "source": self.meta.source,
            "object": self.meta.object_name,
            "mesh": self.meta.mesh_path,
            "event camera": repr(self.meta.event_camera),
            "rgb camera": repr(self.meta.rgb_camera),
            "events": n,
            "event span (s)": (span[1] - span[0]) * 1e-6,
            "rgb frames": self.num_rgb,
            "depth frames": self.num_depth,
            "rates (Hz)": self.meta.rates,
            "ground truth": "none" if gt is None else (
                f"{gt.pose_t_us.numel()} poses, {gt.twist_t_us.numel()} twists, "
                f"event flow {'yes' if gt.event_flow is not None else 'no'}"),
        }

    def __repr__(self) -> str:
        where = f"root={str(self.root)!r}, " if self.root else ""
        return (f"Sequence({where}name={self.meta.name!r}, object={self.meta.object_name!r}, "
                f"rgb={self.num_rgb}, depth={self.num_depth})")


class SequenceWriter:
    """Write a sequence folder incrementally; the folder appears only when writing succeeds.

    Use as a context manager. Data goes into a hidden temporary folder beside ``folder``; on a
    clean exit it is renamed onto ``folder`` (replacing an existing one only with
    ``overwrite=True``); on an exception it is deleted.

    Example:
        >>> with SequenceWriter(out, meta) as w:            # doctest: +SKIP
        ...     w.add_events(ev); w.add_rgb(t_us, rgb); w.add_depth(t_us, depth_m)
    """

    def __init__(self, folder: str | Path, meta: SequenceMeta, overwrite: bool = False) -> None:
        self.folder = Path(folder)
        self.meta = meta
        self.overwrite = overwrite
        if self.folder.exists() and not overwrite:
            raise FileExistsError(f"{self.folder} exists; pass overwrite=True to replace it")
        self._tmp: Path | None = None
        self._event_writer = None
        self._rgb_t: list[int] = []
        self._depth_t: list[int] = []
        self._gt: GroundTruth | None = None

    def __enter__(self) -> SequenceWriter:
        from evtrack.io import EventWriter

        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.folder.name}.tmp-",
                                          dir=self.folder.parent))
        (self._tmp / "rgb").mkdir()
        (self._tmp / "depth").mkdir()
        self._event_writer = EventWriter(self._tmp / EVENTS_FILE, self.meta.event_camera.size)
        self._event_writer.__enter__()
        return self

    def add_events(self, events: Events) -> None:
        """Append a chunk of events (chunks in time order)."""
        self._event_writer.write(events)

    def add_rgb(self, t_us: int, rgb: np.ndarray) -> None:
        """Append an RGB frame (H, W, 3) uint8 taken at ``t_us``."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"RGB frame must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        self._check_time(self._rgb_t, t_us, "RGB")
        path = _frame_path(self._tmp / "rgb", len(self._rgb_t), ".png")
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{path}: cannot write RGB frame")
        self._rgb_t.append(int(t_us))

    def add_depth(self, t_us: int, depth_m: np.ndarray) -> None:
        """Append a depth frame (H, W) in metres; NaN or <= 0 means missing.

        Stored per ``meta.depth_unit``: uint16 PNG in mm (rounded; depths beyond 65.535 m
        raise), or float32 TIFF in metres.
        """
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.ndim != 2:
            raise ValueError(f"depth frame must be (H, W), got shape {depth.shape}")
        self._check_time(self._depth_t, t_us, "depth")
        valid = depth > 0
        index = len(self._depth_t)
        if self.meta.depth_unit == "mm_png16":
            mm = np.where(valid, np.round(depth * 1000.0), 0.0)
            if mm.max(initial=0) > np.iinfo(np.uint16).max:
                raise ValueError("depth beyond 65.535 m cannot be stored as 16-bit mm PNG; "
                                 "use depth_unit='m_float32'")
            path = _frame_path(self._tmp / "depth", index, ".png")
            ok = cv2.imwrite(str(path), mm.astype(np.uint16))
        else:
            path = _frame_path(self._tmp / "depth", index, ".tiff")
            ok = cv2.imwrite(str(path), np.where(valid, depth, 0.0).astype(np.float32))
        if not ok:
            raise OSError(f"{path}: cannot write depth frame")
        self._depth_t.append(int(t_us))

    @staticmethod
    def _check_time(times: list[int], t_us: int, what: str) -> None:
        if times and int(t_us) < times[-1]:
            raise ValueError(f"{what} frame at {t_us} µs comes before the previous one "
                             f"({times[-1]} µs)")

    def file_path(self, relpath: str | Path) -> Path:
        """Where to write an extra file (e.g. the object's mesh) so it lands with the folder.

        ``relpath`` is relative to the sequence folder; the returned path lies inside the
        temporary folder, which becomes the sequence only when every write succeeded.
        """
        if self._tmp is None:
            raise RuntimeError("file_path() is only available inside the writer's with-block")
        rel = Path(relpath)
        if rel.is_absolute() or ".." in rel.parts or not rel.parts:
            raise ValueError(f"extra file path must be relative inside the folder, got {relpath}")
        if rel.parts[0] in (META_FILE, EVENTS_FILE, GT_FILE, "rgb", "depth"):
            raise ValueError(f"{relpath} is reserved by the sequence format")
        target = self._tmp / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def set_ground_truth(self, gt: GroundTruth) -> None:
        """Attach ground truth (written on close)."""
        self._gt = gt

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._tmp is not None
        try:
            self._event_writer.__exit__(exc_type, exc, tb)
            if exc_type is not None:
                return
            for name, times in (("rgb", self._rgb_t), ("depth", self._depth_t)):
                (self._tmp / name / "timestamps.txt").write_text(
                    "".join(f"{t}\n" for t in times))
            if self._gt is not None:
                self._gt.save(self._tmp / GT_FILE)
            meta = dataclasses.replace(self.meta)
            (self._tmp / META_FILE).write_text(yaml.safe_dump(meta.to_dict(), sort_keys=False))
            make_public(self._tmp)  # mkdtemp's folders are private (0700)
            if self.folder.exists():
                if not self.overwrite:
                    raise FileExistsError(f"{self.folder} appeared while writing")
                old = self.folder.with_name(f".{self.folder.name}.old-{self._tmp.name[-8:]}")
                self.folder.rename(old)
                self._tmp.rename(self.folder)
                shutil.rmtree(old)
            else:
                self._tmp.rename(self.folder)
            self._tmp = None
        finally:
            if self._tmp is not None and self._tmp.exists():
                shutil.rmtree(self._tmp, ignore_errors=True)
