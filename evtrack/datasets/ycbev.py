"""YCB-Ev: real recordings of the 21 YCB-Video objects with an event camera and an RGB-D camera.

YCB-Ev (Rojtberg and Pöllabauer, ECCV 2024 Workshops; arXiv 2309.08482) records a Prophesee
event camera (1280 x 720) and a RealSense D435 on one rig, with ground-truth object poses in
the BOP format. This module turns one of its scenes into evtrack sequence folders, one per
object: ``evtrack import ycbev SCENE_DIR --out DIR`` or :func:`import_ycbev_scene`.

Layout read (as the dataset's published tools read it)::

    ROOT/calib_prophesee.json        event camera: camera_matrix, distortion_coefficients,
                                     img_size
    ROOT/calib_realsense.json        colour camera_matrix, depth_camera_matrix, Rt_d2col (m),
                                     img_size
    ROOT/calib_stereo_c2ev.json      R_c2ev, t_c2ev (millimetres): colour -> event camera
    ROOT/camera_d435.json            optional, BOP camera file (depth_scale)
    ROOT/NN_events.int32.zst         the scene's events (or SCENE_DIR/events.int32.zst)
    ROOT/NN/scene_gt.json            BOP ground truth in the colour camera
    ROOT/NN/rgb/000000.png|jpg       colour frames, 30 fps
    ROOT/NN/depth/000000.png         uint16 depth of the depth camera (not registered)
    ROOT/ycbv_models/models/         BOP ycbv models (obj_000001.ply ..., millimetres), or
                                     ROOT/models/, or --models

Conventions of the import:

* events are decoded by ``ycbev-toolkit`` (the dataset's own loader); their pixels stay as
  recorded (distorted) and the sequence's event camera carries the lens distortion;
* frame ``i`` of the colour camera is at ``i * 33333 µs + frame_offset_us`` on the event
  clock; the default offset of one frame period is how the dataset's published overlay tool
  lines poses up with the events;
* depth frames are registered to the colour camera (:func:`~evtrack.datasets.depth_registration.
  register_depth`) and stored in metres;
* ground truth moves from the colour camera to the event camera with ``R_c2ev``, ``t_c2ev``;
  the mesh is the BOP model in metres, in its own object frame, written as ``mesh.glb``.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError, EventFileError
from evtrack.events import Events

__all__ = [
    "YCBV_OBJECT_NAMES", "FRAME_PERIOD_US", "YcbevCalibration", "read_ycbev_calibration",
    "read_ycbev_events", "unpack_events", "ycbv_object_id", "find_events_file", "find_models_dir",
    "import_ycbev_scene", "register_import",
]

#: Names of the YCB-Video objects by BOP ``obj_id`` (1-based): ``YCBV_OBJECT_NAMES[obj_id - 1]``.
YCBV_OBJECT_NAMES = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can",
    "006_mustard_bottle", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
    "010_potted_meat_can", "011_banana", "019_pitcher_base", "021_bleach_cleanser", "024_bowl",
    "025_mug", "035_power_drill", "036_wood_block", "037_scissors", "040_large_marker",
    "051_large_clamp", "052_extra_large_clamp", "061_foam_brick",
)

#: Period of the colour frames (30 fps), µs, as the dataset's toolkit defines it.
FRAME_PERIOD_US = 1_000_000 // 30

CALIBRATION_FILES = ("calib_prophesee.json", "calib_realsense.json", "calib_stereo_c2ev.json")
EVENTS_SUFFIX = "_events.int32.zst"


# ---------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class YcbevCalibration:
    """The rig's calibration.

    Attributes:
        event_camera: the Prophesee camera, with its lens distortion (OpenCV, 5 coefficients).
        rgb_camera: the D435 colour camera (the depth frames are registered to it).
        K_depth: (3, 3) intrinsics of the D435 depth camera, pixels.
        T_rgb_depth: (4, 4) depth camera -> colour camera, metres.
        T_event_rgb: (4, 4) colour camera -> event camera, metres.
        depth_scale: a depth PNG value times this is millimetres.
    """

    event_camera: PinholeCamera
    rgb_camera: PinholeCamera
    K_depth: np.ndarray
    T_rgb_depth: np.ndarray
    T_event_rgb: np.ndarray
    depth_scale: float = 1.0


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise EventFileError(path, "calibration file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EventFileError(path, f"not valid JSON: {exc}") from exc


def _field(data: Any, key: str, path: Path, shape: tuple[int, ...] | None = None) -> Any:
    if not isinstance(data, dict) or key not in data:
        raise EventFileError(path, f"field '{key}' is missing")
    if shape is None:
        return data[key]
    try:
        value = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EventFileError(path, f"field '{key}' is not numeric: {exc}") from exc
    if value.size != int(np.prod(shape)) or not np.isfinite(value).all():
        raise EventFileError(path, f"field '{key}' must hold {int(np.prod(shape))} finite "
                                   f"numbers {shape}, got {value.size}")
    return value.reshape(shape)


def _camera(K: np.ndarray, size: Any, path: Path, size_key: str,
            dist: np.ndarray | None = None) -> PinholeCamera:
    try:
        width, height = (int(v) for v in size)
    except (TypeError, ValueError) as exc:
        raise EventFileError(path, f"field '{size_key}' must be [width, height], got "
                                   f"{size!r}") from exc
    try:
        return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, dist)
    except ConfigError as exc:
        raise EventFileError(path, str(exc)) from exc


def read_ycbev_calibration(folder: str | Path) -> YcbevCalibration:
    """Read the rig's calibration files from ``folder`` (the dataset's root).

    Raises:
        EventFileError: a missing file, invalid JSON, or a missing or malformed field (the
            message names the file and the field).
    """
    folder = Path(folder)
    ev_path, rs_path, rig_path = (folder / name for name in CALIBRATION_FILES)
    ev, rs, rig = _read_json(ev_path), _read_json(rs_path), _read_json(rig_path)
    dist = _field(ev, "distortion_coefficients", ev_path)
    dist = np.asarray(dist, np.float64).ravel()
    if dist.size not in (4, 5, 8) or not np.isfinite(dist).all():
        raise EventFileError(ev_path, f"field 'distortion_coefficients' must hold 4, 5 or 8 "
                                      f"finite numbers, got {dist.size}")
    event_camera = _camera(_field(ev, "camera_matrix", ev_path, (3, 3)),
                           _field(ev, "img_size", ev_path), ev_path, "img_size", dist)
    rgb_camera = _camera(_field(rs, "camera_matrix", rs_path, (3, 3)),
                         _field(rs, "img_size", rs_path), rs_path, "img_size")
    K_depth = _field(rs, "depth_camera_matrix", rs_path, (3, 3))
    T_rgb_depth = _field(rs, "Rt_d2col", rs_path, (4, 4))
    R = _field(rig, "R_c2ev", rig_path, (3, 3))
    t_mm = _field(rig, "t_c2ev", rig_path, (3,))
    if abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise EventFileError(rig_path, f"field 'R_c2ev' is not a rotation (determinant "
                                       f"{np.linalg.det(R):.4f})")
    T_event_rgb = np.eye(4)
    T_event_rgb[:3, :3] = R
    T_event_rgb[:3, 3] = t_mm / 1000.0
    depth_scale = 1.0
    bop_camera = folder / "camera_d435.json"
    if bop_camera.is_file():
        depth_scale = float(_field(_read_json(bop_camera), "depth_scale", bop_camera, (1,))[0])
    return YcbevCalibration(event_camera, rgb_camera, K_depth, T_rgb_depth, T_event_rgb,
                            depth_scale)


# ---------------------------------------------------------------------------- events
def find_events_file(scene_dir: str | Path) -> Path:
    """The scene's event stream: ``ROOT/NN_events.int32.zst`` or ``SCENE_DIR/events.int32.zst``.

    Raises:
        EventFileError: neither exists.
    """
    scene_dir = Path(scene_dir)
    candidates = [scene_dir.parent / f"{scene_dir.name}{EVENTS_SUFFIX}",
                  scene_dir / "events.int32.zst"]
    for path in candidates:
        if path.is_file():
            return path
    raise EventFileError(scene_dir, "no event stream found; looked for "
                                    + " and ".join(str(p) for p in candidates))


def unpack_events(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unpack YCB-Ev's decompressed event words, as ``ycbev-toolkit`` lays them out.

    Each event is two little-endian int32 words: ``t`` (µs), then x (bits 0-13), y (bits
    14-27) and polarity (bits 28-31).

    Returns:
        ``t, x, y, p`` as (N,) int32 arrays.

    Raises:
        ValueError: a byte count that is not a whole number of 8-byte events.
    """
    if len(data) % 8:
        raise ValueError(f"{len(data)} bytes is not a multiple of 8")
    words = np.frombuffer(data, np.dtype("<u4")).reshape(-1, 2)
    packed = words[:, 1]
    x = (packed & 0x3FFF).astype(np.int32)
    y = ((packed >> 14) & 0x3FFF).astype(np.int32)
    p = (packed >> 28).astype(np.int32)
    return words[:, 0].view(np.int32).copy(), x, y, p


def read_ycbev_events(path: str | Path, sensor_size: tuple[int, int]) -> Events:
    """Decode a YCB-Ev event stream with ``ycbev-toolkit``.

    Args:
        path: a ``*_events.int32.zst`` file (zstd-compressed int32 pairs: t µs, packed x/y/p).
        sensor_size: ``(width, height)`` of the event camera, pixels.

    Returns:
        the events, t in µs from the recording's start, polarity ±1.

    Raises:
        EventFileError: a truncated or corrupt zstd stream, a stream whose length is not a
            whole number of events, timestamps that go back, or events outside the sensor.
    """
    import ycbev
    import zstandard

    path = Path(path)
    if not path.is_file():
        raise EventFileError(path, "event stream not found")
    try:
        try:
            t, x, y, p = ycbev.load_event_data(path)
        except OverflowError:
            # ycbev-toolkit 1.1 masks int32 words with a Python int above the int32 range,
            # which NumPy 2 refuses; the same layout is unpacked here in that case
            t, x, y, p = unpack_events(zstandard.ZstdDecompressor().decompress(path.read_bytes()))
    except zstandard.ZstdError as exc:
        raise EventFileError(path, f"corrupt or truncated zstd stream: {exc}") from exc
    except ValueError as exc:  # a byte count that is not a whole number of int32 pairs
        raise EventFileError(path, f"the stream is not a whole number of 8-byte events: "
                                   f"{exc}") from exc
    if p.size and (p.min() < 0 or p.max() > 1):
        bad = int(np.flatnonzero((p < 0) | (p > 1))[0])
        raise EventFileError(path, f"event {bad}: polarity {int(p[bad])} is not 0 or 1")
    events = Events.from_unsigned_polarity(x.astype(np.int16), y.astype(np.int16),
                                           t.astype(np.int64), p, sensor_size)
    report = events.validate()
    if not report.ok:
        raise EventFileError(path, str(report))
    return events


# ---------------------------------------------------------------------------- objects
def ycbv_object_id(spec: str | int) -> int:
    """The BOP ``obj_id`` (1-21) of a YCB-Video object given by id or name.

    ``5``, ``"5"``, ``"006_mustard_bottle"`` and ``"mustard_bottle"`` all give 5.

    Raises:
        ConfigError: no such object (the message lists them).
    """
    text = str(spec).strip()
    if text.isdigit() and 1 <= int(text) <= len(YCBV_OBJECT_NAMES):
        return int(text)
    for index, name in enumerate(YCBV_OBJECT_NAMES, start=1):
        if text in (name, name[4:]):
            return index
    known = ", ".join(f"{i} {n}" for i, n in enumerate(YCBV_OBJECT_NAMES, start=1))
    raise ConfigError(f"--object {spec!r}: not a YCB-Video object; known: {known}")


def find_models_dir(root: str | Path) -> Path:
    """The BOP ``ycbv`` models folder under the dataset root.

    Looks at ``ROOT/ycbv_models/models``, ``ROOT/ycbv_models/models_eval``, ``ROOT/models``.

    Raises:
        EventFileError: none holds ``models_info.json``.
    """
    root = Path(root)
    candidates = [root / "ycbv_models" / "models", root / "ycbv_models" / "models_eval",
                  root / "models"]
    for folder in candidates:
        if (folder / "models_info.json").is_file():
            return folder
    raise EventFileError(root, "no BOP models folder (models_info.json) found in "
                               + ", ".join(str(c) for c in candidates) + "; pass --models")


# ---------------------------------------------------------------------------- frames
def _frame_file(folder: Path, im_id: int, suffixes: tuple[str, ...]) -> Path:
    for suffix in suffixes:
        path = folder / f"{im_id:06d}{suffix}"
        if path.is_file():
            return path
    raise EventFileError(folder / f"{im_id:06d}{suffixes[0]}",
                         f"frame {im_id} of scene_gt.json has no image file")


# ---------------------------------------------------------------------------- import
@dataclass(frozen=True)
class _Scene:
    """What the import reads once per scene and shares between its objects."""

    folder: Path
    root: Path
    calibration: YcbevCalibration
    events: Events
    gt: dict[int, list[Any]]
    models_dir: Path


def _scene_id(folder: Path) -> int:
    return int(folder.name) if folder.name.isdigit() else -1


def _read_scene(scene_dir: Path, calibration_dir: Path | None, models_dir: Path | None,
                events_file: Path | None) -> _Scene:
    from evtrack.datasets.bop import read_scene_gt

    if not scene_dir.is_dir():
        raise EventFileError(scene_dir, "scene folder not found")
    root = scene_dir.parent
    calibration = read_ycbev_calibration(calibration_dir or root)
    gt = read_scene_gt(scene_dir / "scene_gt.json")
    models = models_dir or find_models_dir(root)
    events = read_ycbev_events(events_file or find_events_file(scene_dir),
                               calibration.event_camera.size)
    return _Scene(scene_dir, root, calibration, events, gt, Path(models))


def _object_track(scene: _Scene, obj_id: int, frame_offset_us: int
                  ) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Image ids, times (µs) and event-camera poses (M, 4, 4) of one object."""
    im_ids, poses = [], []
    for im_id in sorted(scene.gt):
        found = [p for p in scene.gt[im_id] if p.obj_id == obj_id]
        if len(found) > 1:
            raise EventFileError(scene.folder / "scene_gt.json",
                                 f"image {im_id} holds obj_id {obj_id} {len(found)} times; "
                                 "one instance per object is supported")
        if found:
            im_ids.append(im_id)
            poses.append(scene.calibration.T_event_rgb @ np.asarray(found[0].T_m2c))
    times = np.asarray(im_ids, np.int64) * FRAME_PERIOD_US + int(frame_offset_us)
    return im_ids, times, np.asarray(poses, np.float64).reshape(-1, 4, 4)


def _object_sequence(scene: _Scene, obj_id: int, frame_offset_us: int) -> tuple[Any, Any, Any]:
    """``(meta, mesh, ground truth)`` of one object's sequence.

    Raises:
        ConfigError: the scene does not hold the object.
    """
    from evtrack.datasets.bop import load_bop_mesh
    from evtrack.datasets.groundtruth import ground_truth_from_poses
    from evtrack.sequence import SequenceMeta

    im_ids, times, poses = _object_track(scene, obj_id, frame_offset_us)
    if not im_ids:
        raise ConfigError(f"object {obj_id} ({YCBV_OBJECT_NAMES[obj_id - 1]}) is not in "
                          f"{scene.folder / 'scene_gt.json'}; it holds obj_id "
                          f"{sorted({p.obj_id for ps in scene.gt.values() for p in ps})}")
    cal = scene.calibration
    name = YCBV_OBJECT_NAMES[obj_id - 1]
    meta = SequenceMeta(
        event_camera=cal.event_camera, name=f"ycbev_{scene.folder.name}_{name}",
        object_name=name, mesh_path="mesh.glb", rgb_camera=cal.rgb_camera,
        T_event_rgb=torch.as_tensor(cal.T_event_rgb), depth_unit="mm_png16",
        rates={"rgb_hz": 1e6 / FRAME_PERIOD_US, "depth_hz": 1e6 / FRAME_PERIOD_US},
        source="recording",
        extra={"dataset": "YCB-Ev", "scene": str(scene.folder),
               "bop": {"scene_id": _scene_id(scene.folder), "obj_id": obj_id,
                       "im_ids": [int(i) for i in im_ids],
                       "im_times_us": [int(t) for t in times], "gt_frame": "rgb"},
               "frame_offset_us": int(frame_offset_us)})
    return meta, load_bop_mesh(scene.models_dir, obj_id), ground_truth_from_poses(times, poses)


def _write_sequences(scene: _Scene, objects: dict[int, Path], frame_offset_us: int,
                     overwrite: bool, progress: bool) -> None:
    """Write one sequence folder per object (``objects``: obj_id -> folder), reading and
    registering each frame once for all of them. Every object is checked before anything is
    written; a failure leaves no folder half-written."""
    from contextlib import ExitStack

    from tqdm.auto import tqdm

    from evtrack.datasets.bop import read_depth_image_m, read_rgb_image
    from evtrack.datasets.depth_registration import register_depth
    from evtrack.sequence import SequenceWriter

    parts = {obj_id: _object_sequence(scene, obj_id, frame_offset_us) for obj_id in objects}
    cal = scene.calibration
    all_ids = sorted(scene.gt)
    all_times = np.asarray(all_ids, np.int64) * FRAME_PERIOD_US + int(frame_offset_us)
    rgb_dir, depth_dir = scene.folder / "rgb", scene.folder / "depth"
    with ExitStack() as stack:
        writers = []
        for obj_id, (meta, mesh, gt) in parts.items():
            writer = stack.enter_context(SequenceWriter(objects[obj_id], meta,
                                                        overwrite=overwrite))
            writer.add_events(scene.events)
            mesh.export(writer.file_path("mesh.glb"))
            writer.set_ground_truth(gt)
            writers.append(writer)
        frames = tqdm(list(zip(all_ids, all_times, strict=True)), desc=scene.folder.name,
                      unit="frame", disable=not progress)
        for im_id, t_us in frames:
            rgb = read_rgb_image(_frame_file(rgb_dir, im_id, (".png", ".jpg")))
            depth_path = _frame_file(depth_dir, im_id, (".png",))
            depth = register_depth(read_depth_image_m(depth_path, cal.depth_scale), cal.K_depth,
                                   cal.rgb_camera.K().numpy(), cal.T_rgb_depth,
                                   cal.rgb_camera.size)
            for writer in writers:
                writer.add_rgb(int(t_us), rgb)
                writer.add_depth(int(t_us), depth)


def import_ycbev_scene(scene_dir: str | Path, out: str | Path,
                       objects: list[str | int] | None = None, *,
                       calibration_dir: str | Path | None = None,
                       models_dir: str | Path | None = None,
                       events_file: str | Path | None = None,
                       frame_offset_us: int = FRAME_PERIOD_US, overwrite: bool = False,
                       progress: bool = True) -> list[Path]:
    """Import one YCB-Ev scene as evtrack sequence folders, one per object.

    Args:
        scene_dir: the scene folder (``ROOT/NN`` holding ``scene_gt.json``, ``rgb/``,
            ``depth/``).
        out: folder that receives ``ycbev_NN_<object>/`` sequence folders.
        objects: YCB-Video objects by id or name (:func:`ycbv_object_id`); default: every
            object of ``scene_gt.json``.
        calibration_dir: folder of the calibration files (default: the scene's parent).
        models_dir: BOP ``ycbv`` models folder (default: :func:`find_models_dir`).
        events_file: the event stream (default: :func:`find_events_file`).
        frame_offset_us: time of colour frame 0 on the event clock, µs.
        overwrite: replace existing sequence folders.
        progress: show a progress bar over the frames.

    Returns:
        the sequence folders written.

    Raises:
        EventFileError: missing or malformed files (named in the message).
        ConfigError: an unknown object, or one the scene does not hold.
    """
    scene = _read_scene(Path(scene_dir), None if calibration_dir is None else Path(calibration_dir),
                        None if models_dir is None else Path(models_dir),
                        None if events_file is None else Path(events_file))
    if objects:
        ids = [ycbv_object_id(o) for o in objects]
    else:
        ids = sorted({p.obj_id for poses in scene.gt.values() for p in poses})
    unknown = [i for i in ids if not 1 <= i <= len(YCBV_OBJECT_NAMES)]
    if unknown:
        raise ConfigError(f"{Path(scene_dir) / 'scene_gt.json'}: obj_id {unknown} is not a "
                          f"YCB-Video object (1-{len(YCBV_OBJECT_NAMES)})")
    out = Path(out)
    folders = {obj_id: out / f"ycbev_{Path(scene_dir).name}_{YCBV_OBJECT_NAMES[obj_id - 1]}"
               for obj_id in ids}
    _write_sequences(scene, folders, frame_offset_us, overwrite, progress)
    return list(folders.values())


# ---------------------------------------------------------------------------- command
IMPORT_DESCRIPTION = """\
Import a YCB-Ev scene (Prophesee 1280x720 events, RealSense D435 RGB-D, BOP ground truth of
the YCB-Video objects) as evtrack sequence folders, one per object: OUT/ycbev_NN_<object>/.
Events are decoded with ycbev-toolkit and kept as recorded (the event camera carries the lens
distortion); depth is registered to the colour camera; ground truth moves from the colour
camera to the event camera; the mesh is the BOP ycbv model in metres.

SCENE_DIR is ROOT/NN, with the calibration files (calib_prophesee.json, calib_realsense.json,
calib_stereo_c2ev.json) and NN_events.int32.zst in ROOT, and the BOP models in
ROOT/ycbv_models/models or ROOT/models (or --models).
"""

IMPORT_EPILOG = """\
examples:
  evtrack import ycbev ycbev/06 --out ycbev-seqs
  evtrack import ycbev ycbev/06 --out ycbev-seqs --object 006_mustard_bottle
  evtrack evaluate --benchmark ycbev-seqs --methods full pose
"""


def register_import(subparsers: argparse._SubParsersAction) -> None:
    """Add ``evtrack import ycbev``."""
    p = subparsers.add_parser("ycbev", help="a YCB-Ev scene (events, RGB-D, BOP ground truth)",
                              description=IMPORT_DESCRIPTION, epilog=IMPORT_EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene_dir", type=Path, metavar="SCENE_DIR",
                   help="the scene folder (ROOT/NN, holding scene_gt.json, rgb/, depth/)")
    p.add_argument("--out", type=Path, required=True,
                   help="folder that receives one sequence folder per object")
    p.add_argument("--object", action="append", default=None, metavar="NAME|ID",
                   help="a YCB-Video object by BOP id (1-21) or name (006_mustard_bottle or "
                        "mustard_bottle); repeat for several; default: every object of the "
                        "scene")
    p.add_argument("--calibration", type=Path, default=None, metavar="DIR",
                   help="folder of the calibration files (default: SCENE_DIR's parent)")
    p.add_argument("--models", type=Path, default=None, metavar="DIR",
                   help="BOP ycbv models folder (default: ROOT/ycbv_models/models, "
                        "ROOT/ycbv_models/models_eval or ROOT/models)")
    p.add_argument("--events", type=Path, default=None, metavar="FILE",
                   help="the event stream (default: ROOT/NN_events.int32.zst or "
                        "SCENE_DIR/events.int32.zst)")
    p.add_argument("--frame-offset-us", type=int, default=FRAME_PERIOD_US, metavar="US",
                   help=f"time of colour frame 0 on the event clock, µs (default "
                        f"{FRAME_PERIOD_US}: one frame period, as the dataset's overlay tool "
                        "aligns them)")
    p.add_argument("--overwrite", action="store_true", help="replace existing sequence folders")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run_import)


def _run_import(args: argparse.Namespace) -> int:
    folders = import_ycbev_scene(args.scene_dir, args.out, args.object,
                                 calibration_dir=args.calibration, models_dir=args.models,
                                 events_file=args.events, frame_offset_us=args.frame_offset_us,
                                 overwrite=args.overwrite, progress=not args.quiet)
    for folder in folders:
        print(f"wrote {folder}")
    return 0
