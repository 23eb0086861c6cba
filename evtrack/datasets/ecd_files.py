"""The files of the Event Camera Dataset (ECD; Mueggler et al., IJRR 2017).

Layout of one ECD recording folder (all times in seconds on the recording's clock)::

    events.txt       t x y p      one event per line; x, y raw (distorted) pixels; p 1 ON, 0 OFF
    calib.txt        fx fy cx cy k1 k2 p1 p2 k3    OpenCV radial-tangential, pixels
    groundtruth.txt  t px py pz qx qy qz qw        camera-to-world poses, quaternion scalar-last
    images.txt       t images/frame_XXXXXXXX.png   the DAVIS's APS frames (8-bit grey)
    imu.txt, ...     (not read)

Some cuts of the dataset also carry ``motion.txt``: the camera's angular velocity over the cut,
``wx wy wz`` in rad/s (:func:`read_ecd_motion`).

The readers here turn each file into the package's types and conventions (µs int64 times,
4x4 float64 poses, :class:`~evtrack.camera.PinholeCamera`); every malformed input raises
:class:`~evtrack.errors.EventFileError` naming the file, the line and the field. The import
into a sequence folder is :mod:`evtrack.datasets.ecd` (``evtrack import ecd``).

Quaternion convention: ECD writes ``qx qy qz qw`` (scalar last, as ROS and
``scipy.spatial.transform.Rotation.from_quat(..., scalar_first=False)``); evtrack's are
``(w, x, y, z)``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError, EventFileError
from evtrack.geometry import tq_to_matrix
from evtrack.io import parse_seconds_to_us

__all__ = [
    "CALIB_FIELDS",
    "DAVIS240C_SIZE",
    "GROUNDTRUTH_FIELDS",
    "QUATERNION_TOLERANCE",
    "ecd_sensor_size",
    "find_ecd_events",
    "read_aps_frame",
    "read_ecd_calib",
    "read_ecd_groundtruth",
    "read_ecd_images",
    "read_ecd_motion",
]

#: The fields of ``calib.txt``, in order (a file of the first four only: no distortion).
CALIB_FIELDS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: The fields of a ``groundtruth.txt`` line, in order.
GROUNDTRUTH_FIELDS = ("t", "px", "py", "pz", "qx", "qy", "qz", "qw")
#: The sensor of every ECD recording (width, height), pixels.
DAVIS240C_SIZE = (240, 180)
#: A ``groundtruth.txt`` quaternion whose norm differs from 1 by more than this is an error
#: (the file's digits give unit norms to ~1e-9); within it, the quaternion is normalised.
QUATERNION_TOLERANCE = 1e-3

_SIZE_HINT = ("pass the sensor size as --sensor-size W H (Python: sensor_size=(W, H)); the "
              "ECD's DAVIS240C is 240x180")


# ---------------------------------------------------------------------------- lines
def _data_lines(path: Path, what: str) -> Iterator[tuple[int, list[str]]]:
    """``(line number, tokens)`` of the non-blank, non-``#`` lines of a text file.

    Raises:
        EventFileError: a missing or unreadable file, non-UTF-8 bytes.
    """
    if not path.is_file():
        raise EventFileError(path, f"{what} not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise EventFileError(path, f"cannot read {what}: {exc}") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield lineno, line.split()


def _number(path: Path, lineno: int, field: str, token: str) -> float:
    """A finite float from ``token`` or an error naming the line and the field."""
    try:
        value = float(token)
    except ValueError:
        raise EventFileError(path, f"line {lineno}: field {field!r} is not a number: "
                                   f"{token[:40]!r}") from None
    if not math.isfinite(value):
        raise EventFileError(path, f"line {lineno}: field {field!r} is not finite: {token!r}")
    return value


def _seconds_us(path: Path, lineno: int, token: str) -> int:
    """A timestamp in seconds (decimal text) as exact int64 µs, or an error naming the line."""
    try:
        value = parse_seconds_to_us(token)
    except ValueError:
        raise EventFileError(path, f"line {lineno}: field 't' is not a time in seconds: "
                                   f"{token[:40]!r}") from None
    if not -(2**63) <= value < 2**63:
        raise EventFileError(path, f"line {lineno}: field 't' = {token} s overflows int64 µs")
    return value


def _fields(path: Path, lineno: int, tokens: list[str], names: tuple[str, ...]) -> None:
    if len(tokens) != len(names):
        raise EventFileError(path, f"line {lineno}: expected {len(names)} values "
                                   f"'{' '.join(names)}', got {len(tokens)}")


def _check_order(path: Path, t_us: list[int], lines: list[int], strict: bool) -> None:
    for i in range(1, len(t_us)):
        if t_us[i] < t_us[i - 1] or (strict and t_us[i] == t_us[i - 1]):
            word = "repeats" if t_us[i] == t_us[i - 1] else "goes back"
            raise EventFileError(path, f"line {lines[i]}: field 't' {word} in time "
                                       f"({t_us[i]} µs after {t_us[i - 1]} µs on line "
                                       f"{lines[i - 1]}); times must increase")


# ---------------------------------------------------------------------------- calib.txt
def read_ecd_calib(path: str | Path, sensor_size: tuple[int, int] | None = None
                   ) -> PinholeCamera:
    """The event camera of an ECD ``calib.txt``.

    Args:
        path: the ``calib.txt`` file: one line ``fx fy cx cy k1 k2 p1 p2 k3`` (pixels; OpenCV
            radial-tangential coefficients, the order OpenCV's ``distCoeffs`` takes), or
            ``fx fy cx cy`` for an ideal pinhole.
        sensor_size: ``(width, height)`` pixels; ``None``: from the APS frames listed in the
            ``images.txt`` beside it (:func:`ecd_sensor_size`).

    Returns:
        A :class:`~evtrack.camera.PinholeCamera` with ``dist = (k1, k2, p1, p2, k3)`` (``None``
        when all are zero).

    Raises:
        EventFileError: a missing file, not one line of 9 (or 4) numbers, a focal length that
            is not positive, or no sensor size to be found.
    """
    path = Path(path)
    lines = list(_data_lines(path, "calibration file (calib.txt)"))
    if len(lines) != 1:
        raise EventFileError(path, f"expected one line '{' '.join(CALIB_FIELDS)}', got "
                                   f"{len(lines)} lines")
    lineno, tokens = lines[0]
    if len(tokens) not in (4, len(CALIB_FIELDS)):
        raise EventFileError(path, f"line {lineno}: expected 9 values "
                                   f"'{' '.join(CALIB_FIELDS)}' (or the first 4 without "
                                   f"distortion), got {len(tokens)}")
    values = {name: _number(path, lineno, name, tok)
              for name, tok in zip(CALIB_FIELDS, tokens, strict=False)}
    for name in ("fx", "fy"):
        if values[name] <= 0:
            raise EventFileError(path, f"line {lineno}: field {name!r} must be positive, got "
                                       f"{values[name]}")
    size = ecd_sensor_size(path.parent, sensor_size)
    dist = [values[k] for k in CALIB_FIELDS[4:]] if len(tokens) > 4 else None
    try:
        return PinholeCamera(values["fx"], values["fy"], values["cx"], values["cy"], *size,
                             dist=dist)
    except ConfigError as exc:
        raise EventFileError(path, str(exc)) from None


# ---------------------------------------------------------------------------- groundtruth.txt
def read_ecd_groundtruth(path: str | Path) -> tuple[Tensor, Tensor]:
    """The camera poses of an ECD ``groundtruth.txt``.

    Each line is ``t px py pz qx qy qz qw``: time (s), the camera's position in the world
    (m), and its orientation as a unit quaternion **scalar last**. Together they are the
    camera-to-world transform ``T_w_c``: a point ``P_c`` of the camera frame is at
    ``R(q) P_c + p`` in the world.

    Returns:
        ``(t_us, T_w_c)``: (M,) int64 µs, strictly increasing, and (M, 4, 4) float64
        camera-to-world transforms (the quaternions normalised).

    Raises:
        EventFileError: a missing or empty file, a line without 8 numbers, times that do not
            increase, a quaternion whose norm is off 1 by more than
            :data:`QUATERNION_TOLERANCE`; each names the line and field.
    """
    path = Path(path)
    times: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, tokens in _data_lines(path, "ground-truth file (groundtruth.txt)"):
        _fields(path, lineno, tokens, GROUNDTRUTH_FIELDS)
        times.append(_seconds_us(path, lineno, tokens[0]))
        row = [_number(path, lineno, name, tok)
               for name, tok in zip(GROUNDTRUTH_FIELDS[1:], tokens[1:], strict=True)]
        norm = math.sqrt(sum(v * v for v in row[3:]))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise EventFileError(path, f"line {lineno}: quaternion 'qx qy qz qw' has norm "
                                       f"{norm:.6g}, not 1 (±{QUATERNION_TOLERANCE})")
        rows.append(row)
        lines.append(lineno)
    if not rows:
        raise EventFileError(path, "no poses: the file has no data lines")
    _check_order(path, times, lines, strict=True)
    data = torch.tensor(rows, dtype=torch.float64)
    q_wxyz = data[:, [6, 3, 4, 5]]  # (qx, qy, qz, qw) -> (w, x, y, z)
    return torch.tensor(times, dtype=torch.int64), tq_to_matrix(data[:, :3], q_wxyz)


# ---------------------------------------------------------------------------- images.txt
def read_ecd_images(path: str | Path) -> tuple[Tensor, list[Path]]:
    """The APS frames listed in an ECD ``images.txt``.

    Each line is ``t relative/path.png``; paths are relative to the file's folder. The files
    themselves are not opened (cuts of the dataset list frames they leave out).

    Returns:
        ``(t_us, paths)``: (F,) int64 µs, non-decreasing, and the F frame paths.

    Raises:
        EventFileError: a missing file, a line without 2 fields, a bad time or times going back.
    """
    path = Path(path)
    times: list[int] = []
    paths: list[Path] = []
    lines: list[int] = []
    for lineno, tokens in _data_lines(path, "image list (images.txt)"):
        _fields(path, lineno, tokens, ("t", "path"))
        times.append(_seconds_us(path, lineno, tokens[0]))
        paths.append(path.parent / tokens[1])
        lines.append(lineno)
    _check_order(path, times, lines, strict=False)
    return torch.tensor(times, dtype=torch.int64), paths


def read_aps_frame(path: Path) -> np.ndarray:
    """An APS frame as (H, W) uint8 grey (a colour file is converted).

    Raises:
        EventFileError: a missing or unreadable file, or not 8 bits.
    """
    if not path.is_file():
        raise EventFileError(path, "APS frame listed in images.txt is missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise EventFileError(path, "cannot decode the APS frame")
    if img.dtype != np.uint8:
        raise EventFileError(path, f"APS frame must be 8-bit, got {img.dtype}")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return img


# ---------------------------------------------------------------------------- motion.txt
def read_ecd_motion(path: str | Path) -> np.ndarray:
    """The camera's angular velocity of a ``motion.txt``: one line ``wx wy wz`` (rad/s).

    It is the IMU gyroscope's reading over a short cut, in the DAVIS's IMU axes (those of the
    camera to within a small rotation): the camera's own angular velocity in its frame. The
    static scene then turns by ``-w`` relative to the camera.

    Returns:
        (3,) float64 rad/s.

    Raises:
        EventFileError: a missing file, not one line of 3 numbers.
    """
    path = Path(path)
    lines = list(_data_lines(path, "angular velocity file (motion.txt)"))
    if len(lines) != 1:
        raise EventFileError(path, f"expected one line 'wx wy wz', got {len(lines)} lines")
    lineno, tokens = lines[0]
    _fields(path, lineno, tokens, ("wx", "wy", "wz"))
    return np.array([_number(path, lineno, n, t) for n, t in zip(("wx", "wy", "wz"), tokens,
                                                                   strict=True)])


# ---------------------------------------------------------------------------- folder
def ecd_sensor_size(folder: str | Path, sensor_size: tuple[int, int] | None = None
                    ) -> tuple[int, int]:
    """The sensor size ``(width, height)`` of an ECD folder: ``sensor_size`` when given,
    else the size of the first APS frame of ``images.txt`` that exists.

    Raises:
        EventFileError: a size that is not two positive integers, or none given and no APS
            frame to read it from (the message says to pass ``--sensor-size W H``).
    """
    folder = Path(folder)
    if sensor_size is not None:
        size = tuple(sensor_size)
        if (len(size) != 2 or not all(isinstance(v, int | np.integer) and v > 0 for v in size)):
            raise EventFileError(folder, f"sensor size must be two positive integers (W, H), "
                                         f"got {sensor_size!r}")
        return int(size[0]), int(size[1])
    images = folder / "images.txt"
    if not images.is_file():
        raise EventFileError(folder, f"no images.txt to read the sensor size from: {_SIZE_HINT}")
    _, paths = read_ecd_images(images)
    first = next((p for p in paths if p.is_file()), None)
    if first is None:
        raise EventFileError(images, f"none of its {len(paths)} APS frames exists to read the "
                                     f"sensor size from: {_SIZE_HINT}")
    h, w = read_aps_frame(first).shape[:2]
    return w, h


def find_ecd_events(folder: str | Path) -> Path:
    """The events file of an ECD folder: ``events.txt``, else the one ``events*.txt``.

    Raises:
        EventFileError: none, or several candidates.
    """
    folder = Path(folder)
    if (folder / "events.txt").is_file():
        return folder / "events.txt"
    found = sorted(folder.glob("events*.txt"))
    if len(found) == 1:
        return found[0]
    if not found:
        raise EventFileError(folder / "events.txt", "events file not found (nor any "
                                                    "events*.txt)")
    raise EventFileError(folder, f"several events files and no events.txt: "
                                 f"{[p.name for p in found]}")
