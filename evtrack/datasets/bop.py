"""Readers of the BOP layout of pose datasets: scenes, their cameras and ground truth, models.

A BOP dataset (https://bop.felk.cvut.cz) holds one folder per scene and one folder of object
models::

    <split>/<scene_id:06d>/scene_camera.json   per image: cam_K (3x3, row-major list of 9),
                                               depth_scale (depth png value x scale = mm),
                                               optionally cam_R_w2c, cam_t_w2c (mm)
    <split>/<scene_id:06d>/scene_gt.json       per image: a list of {obj_id, cam_R_m2c (9
                                               numbers, row-major), cam_t_m2c (3 numbers, mm)}
    <split>/<scene_id:06d>/rgb/<im_id:06d>.png (or .jpg)   8-bit RGB
    <split>/<scene_id:06d>/depth/<im_id:06d>.png           uint16 depth
    models/models_info.json                    per object: diameter, min_x.., size_x.. (mm),
                                               symmetries_discrete, symmetries_continuous
    models/obj_<obj_id:06d>.ply                the mesh in millimetres (optionally textured:
                                               ``comment TextureFile obj_<obj_id:06d>.png``)

Everything these readers return is in the project's units: metres, and poses as (4, 4)
float64 object-to-camera matrices (a point ``P_o`` of the model maps to ``R P_o + t``).
Every malformed file raises :class:`~evtrack.errors.EventFileError` naming the file, the image
or object and the field.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from evtrack.errors import ConfigError, EventFileError
from evtrack.sequence import read_uint16_depth_png

if TYPE_CHECKING:
    from evtrack.sim.objects import ObjectMesh

__all__ = [
    "BopCamera",
    "BopPose",
    "ContinuousSymmetry",
    "ModelInfo",
    "BopScene",
    "read_scene_camera",
    "read_scene_gt",
    "read_models_info",
    "read_rgb_image",
    "read_depth_image_m",
    "bop_model_file",
    "is_bop_model_file",
    "load_bop_mesh",
    "check_bop_model_size",
    "MODELS_INFO",
    "SCENE_CAMERA",
    "SCENE_GT",
]

SCENE_CAMERA = "scene_camera.json"
SCENE_GT = "scene_gt.json"
MODELS_INFO = "models_info.json"
MM = 0.001  # metres per millimetre
_MODEL_NAME = re.compile(r"obj_(\d{6})\.ply", re.IGNORECASE)
_RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
_ROTATION_TOLERANCE = 1e-3  # |RᵀR - I| and |det R - 1| of a stored rotation (6-digit values)
_SIZE_TOLERANCE = 0.1  # relative slack of the diameter check (BOP diameters are exact)


# ---------------------------------------------------------------------------- records
@dataclass(frozen=True)
class BopCamera:
    """The camera of one BOP image.

    Attributes:
        K: (3, 3) float64 intrinsics, pixels (OpenCV convention).
        depth_scale: a depth png value times ``depth_scale`` is millimetres.
        R_w2c: (3, 3) float64 world-to-camera rotation, or ``None`` when not given.
        t_w2c_m: (3,) float64 world-to-camera translation, metres, or ``None``.
    """

    K: np.ndarray
    depth_scale: float
    R_w2c: np.ndarray | None = None
    t_w2c_m: np.ndarray | None = None


@dataclass(frozen=True)
class BopPose:
    """One annotated object instance of a BOP image.

    Attributes:
        obj_id: the object's id (``obj_<obj_id:06d>.ply``).
        T_m2c: (4, 4) float64 model-to-camera pose, translation in metres.
    """

    obj_id: int
    T_m2c: np.ndarray


@dataclass(frozen=True)
class ContinuousSymmetry:
    """A continuous rotational symmetry: any rotation about ``axis`` through ``offset``.

    Attributes:
        axis: (3,) float64 unit axis, model frame.
        offset: (3,) float64 a point of the axis, metres.
    """

    axis: np.ndarray
    offset: np.ndarray


@dataclass(frozen=True)
class ModelInfo:
    """One object's entry of ``models_info.json``, in metres.

    Attributes:
        obj_id: the object's id.
        diameter: largest distance between two points of the model, metres.
        min: (3,) float64 the bounding box's minimum corner, metres, or ``None``.
        size: (3,) float64 the bounding box's extents, metres, or ``None``.
        symmetries_discrete: (4, 4) float64 transforms mapping the model onto itself,
            translation in metres.
        symmetries_continuous: the continuous rotational symmetries.
    """

    obj_id: int
    diameter: float
    min: np.ndarray | None = None
    size: np.ndarray | None = None
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)
    symmetries_continuous: list[ContinuousSymmetry] = field(default_factory=list)

    @property
    def symmetric(self) -> bool:
        """Whether the object has any discrete or continuous symmetry."""
        return bool(self.symmetries_discrete or self.symmetries_continuous)


# ---------------------------------------------------------------------------- JSON helpers
def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise EventFileError(path, "file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EventFileError(path, f"invalid JSON: {exc}") from None


def _id_table(path: Path, data: Any, what: str) -> dict[int, Any]:
    """``{"0": ..., "1": ...}`` -> ``{0: ..., 1: ...}``; ``what`` names the keys."""
    if not isinstance(data, Mapping):
        raise EventFileError(path, f"expected a JSON object of {what} ids at the top level, got "
                                   f"{type(data).__name__}")
    out = {}
    for key, value in data.items():
        try:
            number = int(key)
        except ValueError:
            raise EventFileError(path, f"{what} id {key!r} is not an integer") from None
        if number < 0:
            raise EventFileError(path, f"{what} id {key!r} is negative")
        out[number] = value
    return out


def _numbers(path: Path, where: str, entry: Mapping, name: str, shapes: tuple[tuple, ...],
             required: bool = True) -> np.ndarray | None:
    """The field ``name`` of ``entry`` as a float64 array of the first of ``shapes`` it fits
    (a list of 9 or a nested 3x3 list both give (3, 3) when ``shapes[0]`` is (3, 3))."""
    if name not in entry or entry[name] is None:
        if required:
            raise EventFileError(path, f"{where}: missing field '{name}'")
        return None
    return _array(path, f"{where}: field '{name}'", entry[name], shapes)


def _array(path: Path, what: str, raw: Any, shapes: tuple[tuple, ...]) -> np.ndarray:
    """``raw`` as a finite float64 array reshaped to ``shapes[0]``; its shape must be one of
    ``shapes``. ``what`` starts the error message."""
    try:
        value = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise EventFileError(path, f"{what} must hold numbers, got {raw!r}") from None
    target = shapes[0]
    if value.shape not in shapes:
        raise EventFileError(path, f"{what} must hold {int(np.prod(target))} numbers, got "
                                   f"shape {value.shape}")
    if not np.isfinite(value).all():
        raise EventFileError(path, f"{what} holds NaN or infinity")
    return value.reshape(target)


def _rotation(path: Path, where: str, entry: Mapping, name: str,
              required: bool = True) -> np.ndarray | None:
    R = _numbers(path, where, entry, name, ((3, 3), (9,)), required)
    if R is None:
        return None
    if (np.abs(R.T @ R - np.eye(3)).max() > _ROTATION_TOLERANCE
            or abs(np.linalg.det(R) - 1.0) > _ROTATION_TOLERANCE):
        raise EventFileError(path, f"{where}: field '{name}' is not a rotation matrix "
                                   "(expected 9 numbers, row-major)")
    return R


def _entry(path: Path, where: str, value: Any) -> Mapping:
    if not isinstance(value, Mapping):
        raise EventFileError(path, f"{where}: expected a JSON object, got {type(value).__name__}")
    return value


def _number(path: Path, where: str, entry: Mapping, name: str, positive: bool = True) -> float:
    if name not in entry or entry[name] is None:
        raise EventFileError(path, f"{where}: missing field '{name}'")
    value = entry[name]
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise EventFileError(path, f"{where}: field '{name}' must be a number, got {value!r}")
    if positive and not value > 0:
        raise EventFileError(path, f"{where}: field '{name}' must be > 0, got {value!r}")
    return float(value)


# ---------------------------------------------------------------------------- readers
def read_scene_camera(path: str | Path) -> dict[int, BopCamera]:
    """Read a scene's ``scene_camera.json``.

    Args:
        path: the file.

    Returns:
        ``{im_id: BopCamera}``; ``cam_t_w2c`` (mm) becomes ``t_w2c_m`` (metres). A missing
        ``depth_scale`` is 1 (depth in mm).

    Raises:
        EventFileError: missing file, invalid JSON, a missing or malformed field (naming the
            file, the image id and the field).
    """
    path = Path(path)
    cameras = {}
    for im_id, raw in sorted(_id_table(path, _read_json(path), "image").items()):
        where = f"image {im_id}"
        entry = _entry(path, where, raw)
        K = _numbers(path, where, entry, "cam_K", ((3, 3), (9,)))
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], (0, 0, 1))):
            raise EventFileError(path, f"{where}: field 'cam_K' is not an intrinsic matrix "
                                       "(fx, fy > 0 and last row 0 0 1)")
        scale = _number(path, where, entry, "depth_scale") if "depth_scale" in entry else 1.0
        R = _rotation(path, where, entry, "cam_R_w2c", required=False)
        t = _numbers(path, where, entry, "cam_t_w2c", ((3,), (3, 1)), required=False)
        cameras[im_id] = BopCamera(K=K, depth_scale=scale, R_w2c=R,
                                   t_w2c_m=None if t is None else t * MM)
    return cameras


def read_scene_gt(path: str | Path) -> dict[int, list[BopPose]]:
    """Read a scene's ``scene_gt.json``.

    ``cam_R_m2c`` may be a flat list of 9 numbers (row-major, the BOP standard) or a nested
    3x3 list; ``cam_t_m2c`` is millimetres and becomes metres.

    Args:
        path: the file.

    Returns:
        ``{im_id: [BopPose, ...]}`` in the file's instance order.

    Raises:
        EventFileError: missing file, invalid JSON, a missing or malformed field (naming the
            file, the image id, the instance index and the field).
    """
    path = Path(path)
    out: dict[int, list[BopPose]] = {}
    for im_id, raw in sorted(_id_table(path, _read_json(path), "image").items()):
        if not isinstance(raw, list):
            raise EventFileError(path, f"image {im_id}: expected a list of object instances, "
                                       f"got {type(raw).__name__}")
        poses = []
        for k, item in enumerate(raw):
            where = f"image {im_id}, instance {k}"
            entry = _entry(path, where, item)
            obj_id = entry.get("obj_id")
            if obj_id is None:
                raise EventFileError(path, f"{where}: missing field 'obj_id'")
            if isinstance(obj_id, bool) or not isinstance(obj_id, int):
                raise EventFileError(path, f"{where}: field 'obj_id' must be an integer, got "
                                           f"{obj_id!r}")
            T = np.eye(4)
            T[:3, :3] = _rotation(path, where, entry, "cam_R_m2c")
            T[:3, 3] = _numbers(path, where, entry, "cam_t_m2c", ((3,), (3, 1))) * MM
            poses.append(BopPose(obj_id=int(obj_id), T_m2c=T))
        out[im_id] = poses
    return out


def _model_info(path: Path, obj_id: int, entry: Mapping) -> ModelInfo:
    where = f"object {obj_id}"
    diameter = _number(path, where, entry, "diameter") * MM
    box = {}
    for part in ("min", "size"):
        names = [f"{part}_{axis}" for axis in "xyz"]
        given = [n for n in names if n in entry]
        if given and len(given) < 3:
            missing = sorted(set(names) - set(given))
            raise EventFileError(path, f"{where}: missing field '{missing[0]}'")
        box[part] = (np.array([_number(path, where, entry, n, positive=part == "size")
                               for n in names]) * MM if given else None)
    discrete = []
    for k, sym in enumerate(entry.get("symmetries_discrete") or []):
        S = _array(path, f"{where}: field 'symmetries_discrete' entry {k}", sym,
                   ((4, 4), (16,))).copy()
        S[:3, 3] *= MM
        discrete.append(S)
    continuous = []
    for k, sym in enumerate(entry.get("symmetries_continuous") or []):
        w = f"{where}, symmetries_continuous[{k}]"
        sym = _entry(path, w, sym)
        axis = _numbers(path, w, sym, "axis", ((3,),))
        if not np.linalg.norm(axis) > 0:
            raise EventFileError(path, f"{w}: field 'axis' is zero")
        offset = _numbers(path, w, sym, "offset", ((3,),), required=False)
        continuous.append(ContinuousSymmetry(
            axis=axis / np.linalg.norm(axis),
            offset=np.zeros(3) if offset is None else offset * MM))
    return ModelInfo(obj_id=obj_id, diameter=diameter, min=box["min"], size=box["size"],
                     symmetries_discrete=discrete, symmetries_continuous=continuous)


def read_models_info(path: str | Path) -> dict[int, ModelInfo]:
    """Read ``models_info.json`` (lengths in mm) into metres.

    Args:
        path: the file.

    Returns:
        ``{obj_id: ModelInfo}``.

    Raises:
        EventFileError: missing file, invalid JSON, a missing or malformed field (naming the
            file, the object id and the field).
    """
    path = Path(path)
    return {obj_id: _model_info(path, obj_id, _entry(path, f"object {obj_id}", raw))
            for obj_id, raw in sorted(_id_table(path, _read_json(path), "object").items())}


# ---------------------------------------------------------------------------- models
def bop_model_file(models_dir: str | Path, obj_id: int) -> Path:
    """The mesh file ``models_dir/obj_<obj_id:06d>.ply``.

    Raises:
        ConfigError: no such file; the message names the folder and the object ids it holds.
    """
    folder = Path(models_dir)
    path = folder / f"obj_{int(obj_id):06d}.ply"
    if path.is_file():
        return path
    if not folder.is_dir():
        raise ConfigError(f"{folder}: BOP models folder not found")
    known = sorted(int(m.group(1)) for p in folder.iterdir()
                   if (m := _MODEL_NAME.fullmatch(p.name)))
    raise ConfigError(f"{folder}: no model of object {obj_id} (obj_{int(obj_id):06d}.ply); the "
                      f"folder holds object ids {known or 'none'}")


def is_bop_model_file(path: str | Path) -> bool:
    """Whether ``path`` is a BOP model: named ``obj_<6 digits>.ply`` in a folder that holds
    ``models_info.json``. Its coordinates are then millimetres."""
    path = Path(path)
    return bool(_MODEL_NAME.fullmatch(path.name)) and (path.parent / MODELS_INFO).is_file()


def check_bop_model_size(path: str | Path, vertices_m: np.ndarray) -> None:
    """Check a loaded BOP model against its ``models_info.json`` diameter.

    The mesh's diameter lies between its largest bounding-box extent and the box's diagonal;
    the recorded diameter must fall there (within 10 %). A model in another unit than the
    millimetres BOP prescribes misses by a factor of 1000. Nothing is checked when the folder
    has no ``models_info.json`` or it has no entry for the object.

    Args:
        path: the model file ``obj_<id>.ply``.
        vertices_m: (V, 3) its vertices as loaded, metres.

    Raises:
        EventFileError: naming the model file, ``diameter`` and both sizes.
    """
    path = Path(path)
    match = _MODEL_NAME.fullmatch(path.name)
    info_path = path.parent / MODELS_INFO
    if match is None or not info_path.is_file():
        return
    info = read_models_info(info_path).get(int(match.group(1)))
    if info is None:
        return
    v = np.asarray(vertices_m, np.float64)
    extents = v.max(0) - v.min(0)
    lo, hi = float(extents.max()), float(np.linalg.norm(extents))
    if not (1 - _SIZE_TOLERANCE) * lo <= info.diameter <= (1 + _SIZE_TOLERANCE) * hi:
        raise EventFileError(
            path, f"the mesh read as millimetres spans {lo:.4g} m (diagonal {hi:.4g} m), but "
                  f"{MODELS_INFO} gives 'diameter' {info.diameter * 1000:.6g} mm for object "
                  f"{info.obj_id}: is the mesh in another unit than millimetres?")


def load_bop_mesh(models_dir: str | Path, obj_id: int) -> ObjectMesh:
    """Load the BOP model of ``obj_id`` in metres, in the model's own frame.

    The vertices are scaled from millimetres to metres and not recentred, so BOP poses apply
    to them directly. The texture of a textured model (``comment TextureFile ...`` in the PLY
    header, with per-vertex texture coordinates) comes with it.

    Args:
        models_dir: the models folder (``models``, ``models_eval``, ...).
        obj_id: the object's id.

    Returns:
        An :class:`~evtrack.sim.objects.ObjectMesh` named ``obj_<obj_id:06d>``.

    Raises:
        ConfigError: no model file for ``obj_id`` (naming the ids the folder holds).
        EventFileError: the mesh disagrees with the ``diameter`` of ``models_info.json``.
        MeshFileError: an unreadable mesh file.
    """
    from evtrack.sim.objects import load_mesh

    path = bop_model_file(models_dir, obj_id)
    mesh = load_mesh(path, scale=MM, recenter=False, name=f"obj_{int(obj_id):06d}")
    check_bop_model_size(path, mesh.vertices)
    return mesh


# ---------------------------------------------------------------------------- scenes
def read_rgb_image(path: str | Path) -> np.ndarray:
    """A BOP colour image (8-bit PNG or JPEG, 3 or 4 channels) as (H, W, 3) uint8 RGB.

    Raises:
        EventFileError: an unreadable file, or not an 8-bit colour image.
    """
    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise EventFileError(path, "cannot read the image")
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise EventFileError(path, f"expected an 8-bit RGB image, got shape {image.shape} "
                                   f"{image.dtype}")
    return np.ascontiguousarray(cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB))


def read_depth_image_m(path: str | Path, depth_scale: float) -> np.ndarray:
    """A BOP depth image (single-channel uint16 PNG; value x ``depth_scale`` = millimetres) as
    (H, W) float32 metres, 0 where missing.

    Raises:
        EventFileError: an unreadable file, or not a single-channel 16-bit image.
    """
    depth = read_uint16_depth_png(Path(path))
    return (depth.astype(np.float32) * np.float32(depth_scale * MM)).astype(np.float32)


class BopScene:
    """One BOP scene folder: its images, cameras and ground-truth poses.

    Reads ``scene_camera.json`` and ``scene_gt.json`` on construction (both required); images
    are read when asked for.

    Args:
        folder: the scene folder (``.../<split>/<scene_id:06d>``).

    Raises:
        EventFileError: no such folder, a missing or malformed JSON file, or an image id of
            ``scene_gt.json`` without a camera.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise EventFileError(self.folder, "BOP scene folder not found")
        self.cameras = read_scene_camera(self.folder / SCENE_CAMERA)
        self.gt = read_scene_gt(self.folder / SCENE_GT)
        orphans = sorted(set(self.gt) - set(self.cameras))
        if orphans:
            raise EventFileError(self.folder / SCENE_GT,
                                 f"image {orphans[0]} has ground truth but no camera in "
                                 f"{SCENE_CAMERA}" + (f" ({len(orphans)} such images)"
                                                      if len(orphans) > 1 else ""))

    @property
    def scene_id(self) -> int | None:
        """The scene id from the folder's name (``000048`` -> 48), or ``None``."""
        return int(self.folder.name) if self.folder.name.isdigit() else None

    @property
    def image_ids(self) -> list[int]:
        """The image ids, sorted (gaps allowed): those of ``scene_camera.json``."""
        return sorted(self.cameras)

    @property
    def object_ids(self) -> list[int]:
        """The ids of the objects annotated in any image, sorted."""
        return sorted({p.obj_id for poses in self.gt.values() for p in poses})

    def camera(self, im_id: int) -> BopCamera:
        """The camera of image ``im_id``.

        Raises:
            EventFileError: the image has no camera.
        """
        if im_id not in self.cameras:
            raise EventFileError(self.folder / SCENE_CAMERA, f"no image {im_id}")
        return self.cameras[im_id]

    def poses(self, im_id: int, obj_id: int | None = None) -> list[BopPose]:
        """The annotated instances of image ``im_id`` (only those of ``obj_id`` if given);
        an empty list for an image without ground truth."""
        return [p for p in self.gt.get(im_id, []) if obj_id is None or p.obj_id == obj_id]

    def rgb_path(self, im_id: int) -> Path:
        """The RGB file of image ``im_id`` (``rgb/<im_id:06d>.png`` or ``.jpg``).

        Raises:
            EventFileError: no such file.
        """
        folder = self.folder / "rgb"
        for suffix in _RGB_SUFFIXES:
            path = folder / f"{im_id:06d}{suffix}"
            if path.is_file():
                return path
        raise EventFileError(folder / f"{im_id:06d}.png", f"RGB image of image {im_id} not "
                                                          "found (.png or .jpg)")

    def rgb(self, im_id: int) -> np.ndarray:
        """Image ``im_id`` as (H, W, 3) uint8 RGB.

        Raises:
            EventFileError: a missing or unreadable file, or not an 8-bit colour image.
        """
        return read_rgb_image(self.rgb_path(im_id))

    def depth_m(self, im_id: int) -> np.ndarray:
        """The depth of image ``im_id``: (H, W) float32 metres, 0 where missing.

        The uint16 png value times the camera's ``depth_scale`` is millimetres.

        Raises:
            EventFileError: a missing or unreadable file, or not a single-channel 16-bit image.
        """
        scale = self.camera(im_id).depth_scale
        path = self.folder / "depth" / f"{im_id:06d}.png"
        if not path.is_file():
            raise EventFileError(path, f"depth image of image {im_id} not found")
        return read_depth_image_m(path, scale)

    def __repr__(self) -> str:
        return (f"BopScene({str(self.folder)!r}, images={len(self.cameras)}, "
                f"objects={self.object_ids})")
