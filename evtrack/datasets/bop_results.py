"""Pose estimates in the BOP challenge's results format, and a tracked trajectory as such.

A BOP results file is a CSV with the header ``scene_id,im_id,obj_id,score,R,t,time`` and one
line per estimate::

    48,1,5,1.0,0.1 0.2 ... (9 numbers),10.5 -3.25 812.0,0.012

``R`` is the model-to-camera rotation, 9 numbers row-major separated by spaces; ``t`` the
translation in millimetres, 3 numbers separated by spaces; ``score`` the estimate's confidence;
``time`` the seconds spent on the image, ``-1`` if unknown. Numbers are written with Python's
shortest round-trip form (``t`` rounded to 1e-9 mm first), so reading a file back gives the
same rotation and the translation to 1e-12 m.

:func:`trajectory_bop_rows` samples an :class:`evtrack.Tracker` trajectory at the times of a
sequence's images and moves the poses into the camera frame of the BOP ground truth;
:func:`sequence_bop_rows` does so for a sequence imported from BOP (``meta.extra["bop"]``, see
:mod:`evtrack.datasets.bop_import`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from evtrack.errors import ConfigError, EventFileError
from evtrack.utils import atomic_write_text

if TYPE_CHECKING:
    from evtrack.sequence import SequenceMeta
    from evtrack.tracking.trajectory import Trajectory

__all__ = [
    "BopResult",
    "BOP_RESULTS_HEADER",
    "write_bop_results",
    "read_bop_results",
    "trajectory_bop_rows",
    "bop_record",
    "sequence_bop_rows",
]

BOP_RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
_COLUMNS = tuple(BOP_RESULTS_HEADER.split(","))
_MM = 1000.0  # millimetres per metre
_T_DECIMALS = 9  # t is written to 1e-9 mm: 0.0125 m is "12.5", not "12.500000000000002"


@dataclass(frozen=True)
class BopResult:
    """One pose estimate of one object in one image.

    Attributes:
        scene_id, im_id, obj_id: what the estimate is of.
        score: its confidence (higher is better).
        T_m2c: (4, 4) float64 model-to-camera pose, translation in metres.
        time_s: seconds spent on the image, ``-1`` if unknown.
    """

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_m2c: np.ndarray
    time_s: float = -1.0

    @property
    def R(self) -> np.ndarray:
        """(3, 3) float64 rotation."""
        return np.asarray(self.T_m2c, np.float64)[:3, :3]

    @property
    def t_mm(self) -> np.ndarray:
        """(3,) float64 translation, millimetres."""
        return np.asarray(self.T_m2c, np.float64)[:3, 3] * _MM


def _num(value: float) -> str:
    """The shortest text that reads back as the same float."""
    return repr(float(value))


def _line(row: BopResult) -> str:
    T = np.asarray(row.T_m2c, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"BOP result of scene {row.scene_id}, image {row.im_id}, object "
                         f"{row.obj_id}: T_m2c must be a finite (4, 4) pose")
    R = " ".join(_num(v) for v in T[:3, :3].reshape(-1))
    t = " ".join(_num(round(v, _T_DECIMALS)) for v in T[:3, 3] * _MM)
    return (f"{int(row.scene_id)},{int(row.im_id)},{int(row.obj_id)},{_num(row.score)},"
            f"{R},{t},{'-1' if row.time_s == -1 else _num(row.time_s)}")


def write_bop_results(path: str | Path, rows: Iterable[BopResult]) -> None:
    """Write pose estimates as a BOP results CSV, atomically (nothing half-written).

    Args:
        path: the ``.csv`` file (BOP names it ``METHOD_DATASET-SPLIT.csv``).
        rows: the estimates.

    Raises:
        ValueError: a row with a non-finite or malformed pose.
    """
    lines = [BOP_RESULTS_HEADER] + [_line(row) for row in rows]
    atomic_write_text(path, "\n".join(lines) + "\n")


def _parse_line(path: Path, lineno: int, line: str) -> BopResult:
    parts = line.split(",")
    if len(parts) != len(_COLUMNS):
        raise EventFileError(path, f"line {lineno}: expected {len(_COLUMNS)} comma-separated "
                                   f"fields ({BOP_RESULTS_HEADER}), got {len(parts)}")
    fields = dict(zip(_COLUMNS, parts, strict=True))
    try:
        ids = [int(fields[k]) for k in ("scene_id", "im_id", "obj_id")]
    except ValueError:
        raise EventFileError(path, f"line {lineno}: scene_id, im_id and obj_id must be "
                                   "integers") from None
    values = {}
    for name, count in (("score", 1), ("R", 9), ("t", 3), ("time", 1)):
        try:
            numbers = [float(v) for v in fields[name].split()]
        except ValueError:
            raise EventFileError(path, f"line {lineno}: field '{name}' must hold numbers, got "
                                       f"{fields[name]!r}") from None
        if len(numbers) != count:
            raise EventFileError(path, f"line {lineno}: field '{name}' must hold {count} "
                                       f"number(s), got {len(numbers)}")
        values[name] = numbers
    T = np.eye(4)
    T[:3, :3] = np.reshape(values["R"], (3, 3))
    T[:3, 3] = np.asarray(values["t"]) / _MM
    return BopResult(*ids, score=values["score"][0], T_m2c=T, time_s=values["time"][0])


def read_bop_results(path: str | Path) -> list[BopResult]:
    """Read a BOP results CSV.

    Args:
        path: the file; its first non-empty line must be the header
            ``scene_id,im_id,obj_id,score,R,t,time``.

    Returns:
        The estimates in file order, translations in metres.

    Raises:
        EventFileError: a missing file, a wrong header or a malformed line (naming the file,
            the line and the field).
    """
    path = Path(path)
    if not path.is_file():
        raise EventFileError(path, "BOP results file not found")
    rows, header_seen = [], False
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        if not header_seen:
            if tuple(c.strip() for c in line.split(",")) != _COLUMNS:
                raise EventFileError(path, f"line {lineno}: expected the header "
                                           f"{BOP_RESULTS_HEADER}")
            header_seen = True
            continue
        rows.append(_parse_line(path, lineno, line))
    if not header_seen:
        raise EventFileError(path, f"no header line {BOP_RESULTS_HEADER}: not a BOP results file")
    return rows


def trajectory_bop_rows(
    trajectory: Trajectory,
    image_times_us: Sequence[int] | np.ndarray,
    im_ids: Sequence[int] | np.ndarray,
    scene_id: int,
    obj_id: int,
    T_frame_event: np.ndarray | None = None,
    score: float = 1.0,
) -> list[BopResult]:
    """A tracked trajectory's poses at the times of images, as BOP results.

    The pose at an image's time is the last trajectory sample at or before it, moved on to
    the image's time by the sample's twist (samples are about 1 ms apart). Images before the
    first sample, after the last one, or whose sample is not tracking (waiting for the first
    pose, or lost) get no row: BOP counts a missing estimate as a miss.

    Args:
        trajectory: an :class:`~evtrack.tracking.trajectory.Trajectory` (poses of the object
            in the event camera frame).
        image_times_us: (N,) int µs, the images' times on the trajectory's clock.
        im_ids: (N,) the images' BOP ids.
        scene_id, obj_id: the BOP scene and object.
        T_frame_event: (4, 4) maps event-camera points into the frame of the BOP ground
            truth (for ground truth in the RGB camera: the inverse of the sequence's
            ``meta.T_event_rgb``); ``None``: identity.
        score: the score of every row.

    Returns:
        One :class:`BopResult` per tracked image, in image order (``time_s`` -1).

    Raises:
        ValueError: times and ids of different lengths, or a malformed ``T_frame_event``.
    """
    from evtrack.geometry import integrate_twist

    times = np.asarray(image_times_us, np.int64).reshape(-1)
    ids = np.asarray(im_ids).reshape(-1)
    if times.shape != ids.shape:
        raise ValueError(f"{times.size} image times but {ids.size} image ids")
    F = np.eye(4) if T_frame_event is None else np.asarray(T_frame_event, np.float64)
    if F.shape != (4, 4) or not np.isfinite(F).all():
        raise ValueError(f"T_frame_event must be a finite (4, 4) matrix, got shape {F.shape}")
    t_traj = trajectory.t_us.numpy()
    if not len(t_traj):
        return []
    index = np.searchsorted(t_traj, times, side="right") - 1
    usable = (index >= 0) & (times <= t_traj[-1])
    index = np.clip(index, 0, None)
    tracked = trajectory.tracked.numpy()[index]
    finite = torch.isfinite(trajectory.poses).flatten(1).all(1).numpy()[index]
    keep = np.flatnonzero(usable & tracked & finite)
    if not keep.size:
        return []
    pick = torch.from_numpy(index[keep])
    dt = torch.from_numpy((times[keep] - t_traj[index[keep]]) * 1e-6)
    poses = integrate_twist(trajectory.poses[pick], trajectory.twists[pick], dt).numpy()
    return [BopResult(int(scene_id), int(ids[k]), int(obj_id), float(score), F @ T)
            for k, T in zip(keep, poses, strict=True)]


def bop_record(meta: SequenceMeta) -> dict[str, Any]:
    """The BOP record of a sequence imported from a BOP-layout dataset, checked.

    ``meta.extra["bop"]`` holds ``scene_id``, ``obj_id``, ``im_ids`` (the images where the
    object is annotated), ``im_times_us`` (their times on the sequence's clock) and
    ``gt_frame`` (``"rgb"`` or ``"event"``: the camera of the BOP ground truth); ``evtrack import
    bop`` and the other BOP-layout importers record it.

    Args:
        meta: the sequence's :class:`~evtrack.sequence.SequenceMeta`.

    Raises:
        ConfigError: the sequence has no such record, or a malformed one (naming the field).
    """
    record = meta.extra.get("bop") if isinstance(meta.extra, dict) else None
    where = f"sequence {meta.name or '(unnamed)'}: meta.yaml extra.bop"
    if not isinstance(record, dict):
        raise ConfigError(f"{where} is missing: BOP results need a sequence imported from a "
                          "BOP-layout dataset (evtrack import bop / ycbev), which records the "
                          "scene, object and image ids")
    missing = [k for k in ("scene_id", "obj_id", "im_ids", "im_times_us", "gt_frame")
               if k not in record]
    if missing:
        raise ConfigError(f"{where}: missing field '{missing[0]}'")
    if record["gt_frame"] not in ("rgb", "event"):
        raise ConfigError(f"{where}.gt_frame must be 'rgb' or 'event', got "
                          f"{record['gt_frame']!r}")
    if not (isinstance(record["im_ids"], list) and isinstance(record["im_times_us"], list)
            and len(record["im_ids"]) == len(record["im_times_us"])):
        raise ConfigError(f"{where}: im_ids and im_times_us must be lists of one length")
    return record


def sequence_bop_rows(trajectory: Trajectory, meta: SequenceMeta, score: float = 1.0
                      ) -> list[BopResult]:
    """:func:`trajectory_bop_rows` for a sequence imported from a BOP-layout dataset.

    Reads :func:`bop_record`; for ground truth in the RGB camera (``gt_frame: rgb``) the poses
    are moved there with the inverse of ``meta.T_event_rgb``.

    Args:
        trajectory: the tracker's output for the sequence.
        meta: the sequence's :class:`~evtrack.sequence.SequenceMeta`.
        score: the score of every row.

    Raises:
        ConfigError: the sequence has no (or a malformed) BOP record.
    """
    record = bop_record(meta)
    F = (np.linalg.inv(np.asarray(meta.T_event_rgb, np.float64))
         if record["gt_frame"] == "rgb" else np.eye(4))
    return trajectory_bop_rows(trajectory, record["im_times_us"], record["im_ids"],
                               int(record["scene_id"]), int(record["obj_id"]), F, score)
