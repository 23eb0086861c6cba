"""The Event Camera Dataset (ECD) as evtrack sequences: a moving camera before a static scene.

ECD (Mueggler, Rebecq, Gallego, Delbruck, Scaramuzza, "The event-camera dataset and
simulator", IJRR 2017) records a hand-held or slider-mounted DAVIS240C before static scenes.
evtrack tracks a known object relative to a camera; here the object is the **scene**, and its
pose is the scene's pose relative to the moving camera:

    T_c_o(t) = inv(T_w_c(t)) @ T_w_o

for the camera-to-world poses ``T_w_c`` of ``groundtruth.txt`` and a fixed ``T_w_o``. The
ground-truth twist ``[v_o, ω]`` is then the scene's motion seen from the camera: a camera
turning with angular velocity ``w`` (its own frame) gives ``ω = -w``; a camera moving along
its ``+x`` gives ``v_o`` along ``-x``.

The scene's mesh is either a plane facing the camera's first pose at ``plane_depth`` metres,
sized to fill the view (:func:`evtrack.sim.plane.plane_facing_camera`; ``T_w_o`` is the first
camera pose moved ``plane_depth`` along its optical axis), or a mesh of the scene given in the
world frame of ``groundtruth.txt`` (``T_w_o`` identity; without ground truth, in the frame of
the camera at the first event).

What the sequence folder gets (``evtrack import ecd DIR --out SEQ`` or :func:`import_ecd`):

* ``events.h5``: the events as recorded (raw, distorted pixels): the event camera carries the
  lens distortion of ``calib.txt``;
* ``rgb/``: the APS frames of ``images.txt`` within the window (grey copied to 3 channels);
  the RGB camera is the event camera itself (``T_event_rgb`` identity); no depth frames;
* ``groundtruth.h5``: with ``groundtruth.txt``, the scene's poses ``T_c_o`` at its times and
  the twists between consecutive ones (:func:`~evtrack.datasets.groundtruth.
  ground_truth_from_poses`); without it, no ground truth;
* ``scene.glb``: the scene's mesh; ``meta.yaml`` names it, so ``Tracker.for_sequence`` finds it;
* ``meta.yaml`` ``extra``: ``start_t_us`` and ``start_pose`` (the scene's pose at the first
  event, the pose to start a ``velocity`` tracker from), the scene's placement, and
  ``motion.txt``'s angular velocity if the folder has one (``imu_angular_velocity``).

The file readers are in :mod:`evtrack.datasets.ecd_files` (re-exported here).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.datasets.ecd_files import (
    CALIB_FIELDS,
    DAVIS240C_SIZE,
    GROUNDTRUTH_FIELDS,
    QUATERNION_TOLERANCE,
    ecd_sensor_size,
    find_ecd_events,
    read_aps_frame,
    read_ecd_calib,
    read_ecd_groundtruth,
    read_ecd_images,
    read_ecd_motion,
)
from evtrack.errors import ConfigError, EventFileError

__all__ = [
    "CALIB_FIELDS",
    "DAVIS240C_SIZE",
    "GROUNDTRUTH_FIELDS",
    "QUATERNION_TOLERANCE",
    "EcdRecording",
    "MESH_FILE",
    "ecd_sensor_size",
    "find_ecd_events",
    "import_ecd",
    "open_ecd",
    "read_aps_frame",
    "read_ecd_calib",
    "read_ecd_groundtruth",
    "read_ecd_images",
    "read_ecd_motion",
    "register_import",
]

#: The scene mesh's file in the sequence folder.
MESH_FILE = "scene.glb"
#: Default distance of the scene plane from the first camera pose, metres.
DEFAULT_PLANE_DEPTH_M = 1.0
#: Default size of the scene plane over the camera's view (it stays in view as the camera
#: turns by up to ~10° or shifts by ~10 % of the depth).
DEFAULT_PLANE_MARGIN = 1.25
#: The largest mesh evtrack's mesh reader accepts (:func:`evtrack.sim.objects.load_mesh`).
MAX_MESH_SIZE_M = 3.0
_EVENTS_CHUNK = 1_000_000  # events read per chunk while copying
_UNTEXTURED = np.full((1, 1, 3), 128, np.uint8)


# ---------------------------------------------------------------------------- a recording
@dataclass(frozen=True)
class EcdRecording:
    """The small files of one ECD folder, read and checked (the events are not read).

    Attributes:
        folder: the recording's folder.
        camera: the event camera (:func:`read_ecd_calib`), with the sensor size.
        events_path: the events file (:func:`find_ecd_events`).
        image_t_us: (F,) int64 µs of the APS frames listed in ``images.txt`` (F = 0 without).
        image_paths: their F files (not all need exist).
        gt_t_us: (M,) int64 µs of ``groundtruth.txt``, or ``None`` without the file.
        T_w_c: (M, 4, 4) float64 camera-to-world poses, or ``None``.
        angular_velocity: (3,) rad/s of ``motion.txt`` (the camera's own, in its frame), or
            ``None``.
    """

    folder: Path
    camera: PinholeCamera
    events_path: Path
    image_t_us: Tensor
    image_paths: list[Path]
    gt_t_us: Tensor | None
    T_w_c: Tensor | None
    angular_velocity: np.ndarray | None

    def camera_pose_at(self, t_us: int) -> Tensor:
        """(4, 4) camera-to-world pose at ``t_us``, interpolated on SE(3) between the two
        nearest samples (the end pose held outside them).

        Raises:
            ValueError: the recording has no ground truth.
        """
        if self.T_w_c is None or self.gt_t_us is None:
            raise ValueError(f"{self.folder}: no groundtruth.txt, so no camera poses")
        from evtrack.sequence import GroundTruth

        empty = torch.zeros(0, dtype=torch.int64)
        gt = GroundTruth(self.gt_t_us, self.T_w_c, empty, torch.zeros(0, 6))
        return gt.pose_at(int(t_us))


def open_ecd(folder: str | Path, sensor_size: tuple[int, int] | None = None) -> EcdRecording:
    """Read the calibration, frame list, ground truth and IMU rate of an ECD folder.

    Args:
        folder: holds ``calib.txt`` and ``events.txt``; ``images.txt``, ``groundtruth.txt``
            and ``motion.txt`` are read when present.
        sensor_size: ``(width, height)``; default from the APS frames (:func:`ecd_sensor_size`).

    Raises:
        EventFileError: a missing folder, ``calib.txt`` or events file, or any malformed file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise EventFileError(folder, "ECD folder not found")
    calib = folder / "calib.txt"
    if not calib.is_file():
        raise EventFileError(calib, "calibration file missing: an ECD folder holds calib.txt "
                                    f"('{' '.join(CALIB_FIELDS)}')")
    events = find_ecd_events(folder)
    camera = read_ecd_calib(calib, sensor_size)
    image_t, image_paths = (read_ecd_images(folder / "images.txt")
                            if (folder / "images.txt").is_file()
                            else (torch.zeros(0, dtype=torch.int64), []))
    gt_t, T_w_c = (read_ecd_groundtruth(folder / "groundtruth.txt")
                   if (folder / "groundtruth.txt").is_file() else (None, None))
    motion = read_ecd_motion(folder / "motion.txt") if (folder / "motion.txt").is_file() else None
    return EcdRecording(folder, camera, events, image_t, image_paths, gt_t, T_w_c, motion)


# ---------------------------------------------------------------------------- the import
def import_ecd(folder: str | Path, out: str | Path, *, sensor_size: tuple[int, int] | None = None,
               plane_depth: float | None = None, scene_mesh: str | Path | None = None,
               plane_margin: float = DEFAULT_PLANE_MARGIN, plane_texture: bool = True,
               start_s: float | None = None, duration_s: float | None = None,
               name: str | None = None, overwrite: bool = False) -> Path:
    """Write an ECD recording as an evtrack sequence folder (see the module docstring).

    Args:
        folder: the ECD recording's folder.
        out: the sequence folder to write (atomically: it appears only when complete).
        sensor_size: ``(width, height)`` px; default from the APS frames. Needed for folders
            without ``images.txt`` (the ECD's DAVIS240C is 240 x 180).
        plane_depth: the scene is a plane this many metres in front of the camera's pose at
            the first event (default :data:`DEFAULT_PLANE_DEPTH_M` unless ``scene_mesh``).
        scene_mesh: instead of the plane, the scene's mesh (metres) in the world frame of
            ``groundtruth.txt`` (without ground truth: in the frame of the camera at the first
            event). Written into the folder as GLB.
        plane_margin: the plane's size over the view's (:func:`~evtrack.sim.plane.
            view_plane_size`).
        plane_texture: texture the plane with the APS frame nearest the first event (seen
            at that frame's ground-truth pose where there is one); else, or without frames,
            plain grey.
        start_s, duration_s: the window of the recording to import, seconds on its own clock
            (default: from the first event to the last).
        name: the sequence's name (default: the folder's name).
        overwrite: replace an existing ``out``.

    Returns:
        ``out`` as a :class:`~pathlib.Path` (open it with :meth:`evtrack.Sequence.load`).

    Raises:
        EventFileError: a missing or malformed file, events outside the sensor, APS frames
            of another size than the sensor's, no events in the window.
        ConfigError: both ``plane_depth`` and ``scene_mesh``, a bad window or plane
            settings, a plane too large for the mesh reader.
        FileExistsError: ``out`` exists and not ``overwrite``.
    """
    from evtrack.sequence import SequenceMeta, SequenceWriter

    if plane_depth is not None and scene_mesh is not None:
        raise ConfigError("give either plane_depth (--plane-depth) or scene_mesh "
                          "(--scene-mesh), not both")
    rec = open_ecd(folder, sensor_size)
    window = _window_us(start_s, duration_s)
    depth = None if scene_mesh is not None else float(
        DEFAULT_PLANE_DEPTH_M if plane_depth is None else plane_depth)
    if depth is not None:
        _check_plane(rec.camera, depth, plane_margin)
    mesh_obj = None
    if scene_mesh is not None:
        from evtrack.sim.objects import load_mesh

        mesh_obj = load_mesh(scene_mesh, recenter=False)
    out = Path(out)
    meta = SequenceMeta(
        event_camera=rec.camera, name=name or rec.folder.name,
        object_name="scene_plane" if mesh_obj is None else mesh_obj.name, mesh_path=MESH_FILE,
        rgb_camera=rec.camera, source="recording",
        extra={"dataset": "Event Camera Dataset (ECD)", "ecd_folder": str(rec.folder.resolve()),
               "events_file": rec.events_path.name})
    with SequenceWriter(out, meta, overwrite=overwrite) as writer:
        t_first, t_last, count = _copy_events(rec, writer, window)
        span = (window[0] if window[0] is not None else t_first,
                window[1] - 1 if window[1] is not None else t_last)
        frames = _copy_frames(rec, writer, span)
        start_pose, T_w_o = _start_pose(rec, t_first, depth)
        if rec.T_w_c is not None:
            writer.set_ground_truth(_scene_ground_truth(rec, span, T_w_o))
        if mesh_obj is None:
            mesh_obj, texture_note = _plane(rec, depth, plane_margin, plane_texture, frames,
                                            t_first, start_pose, T_w_o)
        else:
            texture_note = "the mesh's own"
        mesh_obj.export(writer.file_path(MESH_FILE))
        # the writer writes meta.yaml from this same object when the block closes
        meta.rates.update(_frame_rate(frames))
        meta.extra.update(_extra(rec, t_first, t_last, count, window, start_pose, T_w_o, depth,
                                 plane_margin, mesh_obj, scene_mesh, texture_note))
    return out


def _window_us(start_s: float | None, duration_s: float | None) -> tuple[int | None, int | None]:
    """``[start, end)`` µs of the import window (``None``: open)."""
    for what, value in (("start", start_s), ("duration", duration_s)):
        if value is not None and not math.isfinite(float(value)):
            raise ConfigError(f"window {what} must be a finite number of seconds, got {value}")
    if duration_s is not None and float(duration_s) <= 0:
        raise ConfigError(f"window duration must be positive, got {duration_s} s")
    start = None if start_s is None else round(float(start_s) * 1e6)
    if duration_s is None:
        return start, None
    if start is None:
        raise ConfigError("a window duration (--duration) needs its start (--start), seconds "
                          "on the recording's clock")
    return start, start + round(float(duration_s) * 1e6)


def _check_plane(camera: PinholeCamera, depth: float, margin: float) -> None:
    from evtrack.sim.plane import view_plane_size

    w, h = view_plane_size(camera, depth, margin)
    if max(w, h) > MAX_MESH_SIZE_M:
        raise ConfigError(
            f"a plane filling this camera's view at {depth} m (margin {margin}) is "
            f"{w:.2f} x {h:.2f} m, over the {MAX_MESH_SIZE_M} m evtrack's mesh reader accepts: "
            "lower --plane-depth or --plane-margin (for a turning camera the depth hardly "
            "matters: the flow of a rotation does not depend on it)")


def _copy_events(rec: EcdRecording, writer: Any, window: tuple[int | None, int | None]
                 ) -> tuple[int, int, int]:
    """Stream the window's events into the writer; ``(first t, last t, count)``."""
    from evtrack.io import iter_events

    start, end = window
    first = last = None
    count = 0
    stream = iter_events(rec.events_path, count=_EVENTS_CHUNK, sensor_size=rec.camera.size)
    with contextlib.closing(stream) as chunks:
        for chunk in chunks:
            if end is not None and chunk.t_start >= end:
                break
            lo = 0 if start is None else int(torch.searchsorted(chunk.t, start))
            hi = len(chunk) if end is None else int(torch.searchsorted(chunk.t, end))
            if hi <= lo:
                continue
            part = chunk[lo:hi]
            writer.add_events(part)
            first = part.t_start if first is None else first
            last = part.t_end
            count += len(part)
    if first is None:
        where = "" if start is None else f" in the window [{start}, {end}) µs"
        raise EventFileError(rec.events_path, f"no events{where}")
    return int(first), int(last), count


def _copy_frames(rec: EcdRecording, writer: Any, span: tuple[int, int]
                 ) -> list[tuple[int, np.ndarray]]:
    """The APS frames within ``span`` (µs, inclusive) into the writer, as RGB; returns them."""
    keep = [(int(t), p) for t, p in zip(rec.image_t_us.tolist(), rec.image_paths, strict=True)
            if span[0] <= t <= span[1]]
    frames = []
    for t, path in keep:
        grey = read_aps_frame(path)
        if grey.shape != (rec.camera.height, rec.camera.width):
            raise EventFileError(path, f"APS frame is {grey.shape[1]}x{grey.shape[0]}, the "
                                       f"sensor {rec.camera.width}x{rec.camera.height}")
        writer.add_rgb(t, np.repeat(grey[..., None], 3, axis=2))
        frames.append((t, grey))
    return frames


def _start_pose(rec: EcdRecording, t_first: int, depth: float | None) -> tuple[Tensor,
                                                                               Tensor | None]:
    """The scene's object-to-camera pose at the first event, and ``T_w_o`` (with ground
    truth; else ``None``)."""
    from evtrack.geometry import inverse
    from evtrack.sim.plane import facing_pose

    facing = torch.from_numpy(facing_pose(depth)) if depth is not None else torch.eye(
        4, dtype=torch.float64)
    if rec.T_w_c is None:
        return facing, None
    T_w_c0 = rec.camera_pose_at(t_first)
    if depth is None:  # a scene mesh in the world frame
        T_w_o = torch.eye(4, dtype=torch.float64)
        return inverse(T_w_c0), T_w_o
    return facing, T_w_c0 @ facing


def _scene_ground_truth(rec: EcdRecording, span: tuple[int, int], T_w_o: Tensor) -> Any:
    """The scene's poses ``inv(T_w_c) @ T_w_o`` at the ground-truth times covering ``span``
    (one sample beyond each end), and the twists between them."""
    from evtrack.datasets.groundtruth import ground_truth_from_poses
    from evtrack.geometry import inverse

    t = rec.gt_t_us
    lo = max(int(torch.searchsorted(t, span[0], right=True)) - 1, 0)
    hi = min(int(torch.searchsorted(t, span[1])) + 1, t.numel())
    if t[0] > span[0] or t[-1] < span[1]:
        warnings.warn(f"{rec.folder / 'groundtruth.txt'}: the poses span "
                      f"[{int(t[0])}, {int(t[-1])}] µs, not all of the imported "
                      f"[{span[0]}, {span[1]}] µs; outside them the end pose is held",
                      UserWarning, stacklevel=3)
    T_c_o = inverse(rec.T_w_c[lo:hi]) @ T_w_o
    return ground_truth_from_poses(t[lo:hi].numpy(), T_c_o.numpy())


def _plane(rec: EcdRecording, depth: float, margin: float, textured: bool,
           frames: list[tuple[int, np.ndarray]], t_first: int, start_pose: Tensor,
           T_w_o: Tensor | None) -> tuple[Any, str]:
    """The scene plane's mesh and a note on its texture."""
    from evtrack.geometry import inverse
    from evtrack.sim.plane import plane_facing_camera, plane_mesh, view_plane_size

    if textured and frames:
        t_img, image = min(frames, key=lambda f: abs(f[0] - t_first))
        pose = start_pose if T_w_o is None else inverse(rec.camera_pose_at(t_img)) @ T_w_o
        mesh = plane_facing_camera(rec.camera, depth, margin=margin, image=image,
                                   image_pose=pose.numpy(), name="scene_plane")
        seen = "its ground-truth pose" if T_w_o is not None else "the start pose"
        return mesh, f"the APS frame at {t_img} µs, seen from {seen}"
    w, h = view_plane_size(rec.camera, depth, margin)
    return plane_mesh(w, h, _UNTEXTURED, segments=(8, 6), name="scene_plane"), "none (grey)"


def _frame_rate(frames: list[tuple[int, np.ndarray]]) -> dict[str, float]:
    if len(frames) < 2:
        return {}
    dt = np.median(np.diff([t for t, _ in frames]))
    return {"rgb_hz": float(1e6 / dt)} if dt > 0 else {}


def _extra(rec: EcdRecording, t_first: int, t_last: int, count: int,
           window: tuple[int | None, int | None], start_pose: Tensor, T_w_o: Tensor | None,
           depth: float | None, margin: float, mesh: Any, scene_mesh: Any,
           texture_note: str) -> dict[str, Any]:
    """``meta.yaml`` ``extra`` entries of an imported ECD recording."""
    scene: dict[str, Any]
    if depth is not None:
        scene = {"kind": "plane", "depth_m": depth, "margin": margin,
                 "size_m": [float(v) for v in mesh.extents[:2]], "texture": texture_note,
                 "frame": "object x, y along the first camera pose's x, y; the face looks "
                          "at the camera (-z)"}
    else:
        scene = {"kind": "mesh", "file": str(Path(scene_mesh).resolve()),
                 "frame": "world of groundtruth.txt" if rec.T_w_c is not None
                 else "camera at the first event"}
    if T_w_o is not None:
        scene["T_world_object"] = T_w_o.tolist()
    extra: dict[str, Any] = {
        "window_us": [window[0], window[1]], "event_span_us": [t_first, t_last],
        "events": count, "scene": scene, "start_t_us": t_first,
        "start_pose": start_pose.tolist(),
        "twist": "the scene's motion relative to the camera (camera frame): the opposite of "
                 "the camera's own (a camera turning with w gives omega = -w)",
    }
    if rec.angular_velocity is not None:
        extra["imu_angular_velocity"] = {
            "w_rad_s": [float(v) for v in rec.angular_velocity],
            "frame": "the DAVIS IMU's axes (the camera's to within a small rotation)",
            "meaning": "the camera's own angular velocity over the recording (motion.txt); "
                       "the scene's twist relative to the camera has omega = -w",
        }
    return extra


# ---------------------------------------------------------------------------- CLI
IMPORT_DESCRIPTION = """\
Write an Event Camera Dataset (ECD) recording as an evtrack sequence folder. The tracked
"object" is the static scene: its pose is the scene relative to the moving camera
(T_c_o = inv(T_w_c) @ T_w_o), its twist the scene's motion seen from the camera (the opposite
of the camera's own). The scene is a plane facing the camera at the first event (--plane-depth,
default 1 m) or a mesh of it (--scene-mesh, in groundtruth.txt's world frame).
"""

IMPORT_EPILOG = """\
The folder holds calib.txt and events.txt (else one events*.txt); images.txt,
groundtruth.txt and motion.txt are read when present. Without images.txt the sensor size must
be given: --sensor-size 240 180 for the ECD's DAVIS240C.

examples:
  evtrack import ecd shapes_rotation --out seq/shapes
  evtrack import ecd poster_6dof --out seq/poster --start 10 --duration 2 --plane-depth 0.8

Tracking: with ground truth, 'evtrack track SEQ --method velocity --oracle' starts from the
ground-truth pose; without, start a Python Tracker from meta.yaml's extra.start_pose
(docs/datasets.md, "Event Camera Dataset").
"""


def register_import(subparsers: argparse._SubParsersAction) -> None:
    """Add ``evtrack import ecd``."""
    p = subparsers.add_parser("ecd", help="an Event Camera Dataset recording (moving camera, "
                                          "static scene)",
                              description=IMPORT_DESCRIPTION, epilog=IMPORT_EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", type=Path, metavar="DIR", help="the ECD recording's folder")
    p.add_argument("--out", type=Path, required=True, metavar="SEQ",
                   help="the sequence folder to write")
    p.add_argument("--sensor-size", type=int, nargs=2, default=None, metavar=("W", "H"),
                   help="sensor size in pixels (default: the APS frames'; DAVIS240C: 240 180)")
    scene = p.add_mutually_exclusive_group()
    scene.add_argument("--plane-depth", type=float, default=None, metavar="M",
                       help=f"the scene is a plane this far (metres) in front of the first "
                            f"camera pose (default {DEFAULT_PLANE_DEPTH_M})")
    scene.add_argument("--scene-mesh", type=Path, default=None, metavar="FILE",
                       help="the scene's mesh (metres, groundtruth.txt's world frame) instead "
                            "of a plane")
    p.add_argument("--plane-margin", type=float, default=DEFAULT_PLANE_MARGIN, metavar="F",
                   help=f"the plane's size over the camera's view (default "
                        f"{DEFAULT_PLANE_MARGIN})")
    p.add_argument("--no-plane-texture", dest="plane_texture", action="store_false",
                   help="leave the plane grey instead of texturing it with the first APS frame")
    p.add_argument("--start", type=float, default=None, metavar="S",
                   help="first second to import, on the recording's clock (default: the "
                        "first event)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="seconds to import from --start (default: to the end)")
    p.add_argument("--name", default=None, help="the sequence's name (default: DIR's name)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing SEQ")
    p.set_defaults(func=_run_import)


def _run_import(args: argparse.Namespace) -> int:
    out = import_ecd(args.folder, args.out, sensor_size=args.sensor_size,
                     plane_depth=args.plane_depth, scene_mesh=args.scene_mesh,
                     plane_margin=args.plane_margin, plane_texture=args.plane_texture,
                     start_s=args.start, duration_s=args.duration, name=args.name,
                     overwrite=args.overwrite)
    print(f"wrote {out}")
    return 0
