"""``evtrack import bop``: one object of a BOP scene as an evtrack sequence folder.

A BOP scene (:mod:`evtrack.datasets.bop`) has RGB-D images and poses but no times and no
events. The import gives image ``im_id`` the time ``frame_offset_us + im_id / fps``, writes
every image of the scene as the sequence's RGB and depth frames, the object's annotated poses
as ground truth (twists between consecutive poses), its model in metres (``object.glb``, the
model's own frame) and ``meta.extra["bop"]`` (``scene_id``, ``obj_id``, the ``im_ids`` where the
object is annotated with their ``im_times_us``, ``gt_frame: rgb``), with which ``evtrack track
--bop-results`` writes the tracked poses as a BOP results file.

Events are optional: a file recorded (or simulated) in the RGB camera's pixels, on the clock
of the image times above; the event camera is then the RGB camera (``T_event_rgb`` identity).
Without events the sequence has an empty event stream, which serves the pose-network and
depth parts of the tracker and ``evtrack evaluate``'s single-frame metrics.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.datasets.bop import SCENE_CAMERA, SCENE_GT, BopScene, load_bop_mesh
from evtrack.errors import ConfigError, EventFileError
from evtrack.events import Events

__all__ = ["import_bop_scene", "register_import", "MESH_FILE"]

MESH_FILE = "object.glb"
_K_TOLERANCE_PX = 1e-6

IMPORT_DESCRIPTION = """\
Write one object of a BOP scene (scene_camera.json, scene_gt.json, rgb/, depth/) as an evtrack
sequence folder: the scene's images as RGB-D frames (image ID at FRAME_OFFSET + ID / FPS), the
object's BOP poses as ground truth, its model from MODELS_DIR in metres (object.glb), and the
BOP ids that 'evtrack track --bop-results' needs. Events are optional (--events): a file in the
RGB camera's pixels and on the images' clock.
"""

IMPORT_EPILOG = """\
examples:
  evtrack import bop ycbv/test/000048 --models ycbv/models --object 5 --out seq/ycbv_48_5
  evtrack import bop scene/ --models models/ --object 1 --events ev.h5 --fps 30 --out seq/s1
"""


def _rgb_camera(scene: BopScene, im_ids: list[int], size: tuple[int, int]) -> PinholeCamera:
    """The one camera of the scene's images (width, height = ``size``).

    Raises:
        EventFileError: an image whose intrinsics differ from the first image's.
    """
    K0 = scene.camera(im_ids[0]).K
    for im_id in im_ids[1:]:
        if np.abs(scene.camera(im_id).K - K0).max() > _K_TOLERANCE_PX:
            raise EventFileError(scene.folder / SCENE_CAMERA,
                                 f"image {im_id}: field 'cam_K' differs from image {im_ids[0]}'s;"
                                 " a sequence has one RGB camera")
    return PinholeCamera(K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], *size)


def _object_track(scene: BopScene, obj_id: int) -> tuple[list[int], np.ndarray]:
    """The ids of the images that show ``obj_id`` and its (M, 4, 4) poses there.

    Raises:
        ConfigError: the object is in no image.
        EventFileError: an image with several instances of it.
    """
    ids, poses = [], []
    for im_id in scene.image_ids:
        found = scene.poses(im_id, obj_id)
        if len(found) > 1:
            raise EventFileError(scene.folder / SCENE_GT,
                                 f"image {im_id} holds obj_id {obj_id} {len(found)} times; the "
                                 "import follows one instance")
        if found:
            ids.append(im_id)
            poses.append(found[0].T_m2c)
    if not ids:
        raise ConfigError(f"{scene.folder / SCENE_GT}: object {obj_id} is in no image; the scene "
                          f"holds obj_id {scene.object_ids}")
    return ids, np.asarray(poses, np.float64).reshape(-1, 4, 4)


def _events(path: Path | None, sensor_size: tuple[int, int] | None,
            camera: PinholeCamera) -> Events:
    """The events of ``path`` (none: an empty stream), checked to be in the RGB camera's
    pixels."""
    if path is None:
        if sensor_size is not None:
            raise ConfigError("--sensor-size describes the --events file; give that too")
        return Events(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros(0, np.int8), sensor_size=camera.size)
    from evtrack.io import read_events

    events = read_events(path, sensor_size=None if sensor_size is None else tuple(sensor_size))
    if events.sensor_size is None:
        raise ConfigError(f"{path}: the file does not record its sensor size; pass "
                          "--sensor-size W H")
    if tuple(events.sensor_size) != tuple(camera.size):
        w, h = events.sensor_size
        raise ConfigError(f"{path}: the events' sensor is {w}x{h} but the BOP images are "
                          f"{camera.width}x{camera.height}; the import takes events in the RGB "
                          "camera's pixels")
    return events


def _frame_times(im_ids: list[int], fps: float, frame_offset_us: int) -> np.ndarray:
    return np.round(np.asarray(im_ids, np.float64) * 1e6 / fps).astype(np.int64) + int(
        frame_offset_us)


def import_bop_scene(
    scene_dir: str | Path,
    models_dir: str | Path,
    obj_id: int,
    out: str | Path,
    *,
    events: str | Path | None = None,
    sensor_size: tuple[int, int] | None = None,
    fps: float = 30.0,
    frame_offset_us: int = 0,
    scene_id: int | None = None,
    name: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Write one object of a BOP scene as a sequence folder (see the module docstring).

    Args:
        scene_dir: the BOP scene folder.
        models_dir: the BOP models folder (``obj_<id:06d>.ply``, ``models_info.json``).
        obj_id: the object to follow (one instance per image).
        out: the sequence folder to write (appears only once complete).
        events: an event file in the RGB camera's pixels, on the images' clock; ``None``: an
            empty event stream.
        sensor_size: ``(width, height)`` for an event file that does not record it.
        fps: image rate: image ``im_id`` is at ``frame_offset_us + im_id / fps``.
        frame_offset_us: time of image 0, µs.
        scene_id: the BOP scene id (default: the folder's name, e.g. ``000048``).
        name: the sequence's name (default ``bop_<scene_id>_obj_<obj_id>``).
        overwrite: replace an existing ``out``.
        progress: show a progress bar over the frames.

    Returns:
        The sequence folder.

    Raises:
        ConfigError: bad arguments, an object in no image, events of another sensor size.
        EventFileError: a missing or malformed BOP file (naming the file and field).
        FileExistsError: ``out`` exists and ``overwrite`` is false.
    """
    from tqdm.auto import tqdm

    from evtrack.datasets.groundtruth import ground_truth_from_poses
    from evtrack.sequence import SequenceMeta, SequenceWriter

    if not (np.isfinite(fps) and fps > 0):
        raise ConfigError(f"fps must be a positive number, got {fps}")
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=True (--overwrite) to replace it")
    scene = BopScene(scene_dir)
    sid = scene.scene_id if scene_id is None else int(scene_id)
    if sid is None:
        raise ConfigError(f"{scene.folder}: the folder's name is not a BOP scene id; pass "
                          "scene_id (--scene-id)")
    obj_ids, poses = _object_track(scene, int(obj_id))
    all_ids = scene.image_ids
    first = scene.rgb(all_ids[0])
    camera = _rgb_camera(scene, all_ids, (first.shape[1], first.shape[0]))
    stream = _events(None if events is None else Path(events), sensor_size, camera)
    mesh = load_bop_mesh(models_dir, int(obj_id))
    times = _frame_times(all_ids, fps, frame_offset_us)
    gt_times = _frame_times(obj_ids, fps, frame_offset_us)
    has_depth = (scene.folder / "depth").is_dir()
    meta = SequenceMeta(
        event_camera=camera, name=name or f"bop_{sid}_obj_{int(obj_id)}",
        object_name=mesh.name, mesh_path=MESH_FILE, rgb_camera=camera,
        rates={"rgb_hz": float(fps), **({"depth_hz": float(fps)} if has_depth else {})},
        source="recording",
        extra={"dataset": "BOP", "scene": str(scene.folder.resolve()),
               "models": str(Path(models_dir).resolve()), "fps": float(fps),
               "frame_offset_us": int(frame_offset_us),
               "events": None if events is None else str(Path(events).resolve()),
               "bop": {"scene_id": sid, "obj_id": int(obj_id), "im_ids": obj_ids,
                       "im_times_us": gt_times.tolist(), "gt_frame": "rgb"}})
    with SequenceWriter(out, meta, overwrite=overwrite) as writer:
        writer.add_events(stream)
        mesh.export(writer.file_path(MESH_FILE))
        for im_id, t_us in tqdm(list(zip(all_ids, times.tolist(), strict=True)), unit="frame",
                                desc=meta.name, disable=not progress):
            rgb = first if im_id == all_ids[0] else scene.rgb(im_id)
            if rgb.shape[:2] != first.shape[:2]:
                raise EventFileError(scene.rgb_path(im_id), f"image size {rgb.shape[1]}x"
                                     f"{rgb.shape[0]} differs from image {all_ids[0]}'s "
                                     f"{first.shape[1]}x{first.shape[0]}")
            writer.add_rgb(t_us, rgb)
            if has_depth:
                writer.add_depth(t_us, _checked_depth(scene, im_id, first.shape[:2]))
        writer.set_ground_truth(ground_truth_from_poses(gt_times, poses))
    return out


def _checked_depth(scene: BopScene, im_id: int, shape: tuple[int, int]) -> np.ndarray:
    depth = scene.depth_m(im_id)
    if depth.shape != tuple(shape):
        raise EventFileError(scene.folder / "depth" / f"{im_id:06d}.png",
                             f"depth size {depth.shape[1]}x{depth.shape[0]} differs from the RGB "
                             f"images' {shape[1]}x{shape[0]}")
    return depth


# ---------------------------------------------------------------------------- command line
def register_import(subparsers: argparse._SubParsersAction) -> None:
    """Add ``evtrack import bop``."""
    p = subparsers.add_parser("bop", help="one object of a BOP scene (RGB-D, poses, models)",
                              description=IMPORT_DESCRIPTION, epilog=IMPORT_EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene_dir", type=Path, metavar="SCENE_DIR",
                   help="the BOP scene folder (scene_camera.json, scene_gt.json, rgb/, depth/)")
    p.add_argument("--models", type=Path, required=True, metavar="MODELS_DIR",
                   help="the BOP models folder (obj_000001.ply, ..., models_info.json; mm)")
    p.add_argument("--object", type=int, required=True, metavar="ID",
                   help="the BOP obj_id of the object to follow")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the sequence folder to write")
    p.add_argument("--events", type=Path, default=None, metavar="FILE",
                   help="an event file (any readable format) in the RGB camera's pixels, on the "
                        "images' clock (default: none, an empty event stream)")
    p.add_argument("--sensor-size", type=int, nargs=2, default=None, metavar=("W", "H"),
                   help="the event sensor's size, for an event file that does not record it")
    p.add_argument("--fps", type=float, default=30.0,
                   help="image rate: image ID is at ID / FPS seconds after image 0 "
                        "(default: 30)")
    p.add_argument("--frame-offset-us", type=int, default=0, metavar="US",
                   help="time of image 0, µs (default: 0)")
    p.add_argument("--scene-id", type=int, default=None,
                   help="the BOP scene id (default: SCENE_DIR's name, e.g. 000048 -> 48)")
    p.add_argument("--name", default=None, help="the sequence's name "
                                                "(default: bop_<scene id>_obj_<ID>)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_import)


def _run_import(args: argparse.Namespace) -> int:
    out = import_bop_scene(args.scene_dir, args.models, args.object, args.out,
                           events=args.events, sensor_size=args.sensor_size, fps=args.fps,
                           frame_offset_us=args.frame_offset_us, scene_id=args.scene_id,
                           name=args.name, overwrite=args.overwrite, progress=not args.quiet)
    print(f"wrote {out}")
    return 0
