"""Source kind ``bop``: the real (or rendered) images of BOP scenes with their annotated poses.

A user's BOP data (:mod:`evtrack.datasets.bop`: scene folders with ``scene_camera.json``,
``scene_gt.json`` and ``rgb/``, and a models folder) trains the pose network as the other
sources do::

    data:
      source: bop
      options:
        scenes: [ycbv/train_real/000000, "ycbv/train_real/00001*"]   # folders or glob patterns
        models: ycbv/models
        obj_id: 5
      val_source: bop
      val_options: {scenes: [ycbv/test/000048], models: ycbv/models, obj_id: 5}

The samples are the images that show ``obj_id`` (every annotated instance of it is a target),
in the order of the scenes and image ids, repeated when more samples are asked for than
there are images (the augmentation makes each repeat differ). Each image is scaled to fit
``data.image_size`` with its aspect ratio kept, centred, the borders filled with the input
normalisation's mean colour; the intrinsics follow.

Object frame: the config's cuboid (``object.mesh`` set to the BOP model file, or
``object.dimensions``) must be the model's bounding box, either in the model's own frame
(``object.recenter: false``; the BOP poses are used as they are) or centred on it
(``recenter: true``, the default; the poses are moved to the box's centre).
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evtrack.configs import Config, setting
from evtrack.errors import ConfigError
from evtrack.models.crop_refine import CropWindow, warp_crop
from evtrack.models.cuboid import Cuboid
from evtrack.models.weights import IMAGENET_MEAN
from evtrack.train.samples import PoseSample, SourceSpec, project_keypoints, register_source

__all__ = ["BopSourceOptions", "BopSource", "letterbox_window"]

_CUBOID_TOLERANCE_M = 1e-4  # the config's cuboid and the BOP model's box must agree this well
_FILL = tuple(255.0 * c for c in IMAGENET_MEAN)  # the normalised input's zero


@dataclass(frozen=True)
class BopSourceOptions(Config):
    """Options of the ``bop`` source (``data.options`` of a config).

    Attributes:
        scenes: BOP scene folders, or glob patterns of them (matches sorted); relative paths
            are from the working directory.
        models: the BOP models folder (``obj_<id:06d>.ply``, ``models_info.json``).
        obj_id: the object's BOP id.
    """

    scenes: tuple[str, ...]
    models: str
    obj_id: int = setting(ge=1)


def letterbox_window(size: tuple[int, int], image_size: tuple[int, int]) -> CropWindow:
    """The window that scales an image of ``size = (width, height)`` to fit ``image_size =
    (height, width)`` with its aspect ratio kept, centred (pixel centres at integers)."""
    w, h = (int(v) for v in size)
    out_h, out_w = (int(v) for v in image_size)
    scale = min(out_w / w, out_h / h)
    offset = ((out_w - 1) / 2 - scale * (w - 1) / 2, (out_h - 1) / 2 - scale * (h - 1) / 2)
    return CropWindow(scale, offset, (out_w, out_h))


def _scene_folders(patterns: tuple[str, ...], key: str) -> list[Path]:
    folders: list[Path] = []
    for pattern in patterns:
        if glob.has_magic(pattern):
            matches = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_dir())
            if not matches:
                raise ConfigError(f"{key}.scenes: no scene folder matches {pattern!r}")
            folders += matches
        else:
            folders.append(Path(pattern))
    if not folders:
        raise ConfigError(f"{key}.scenes: give at least one BOP scene folder")
    return folders


def _frame_offset(model_box: Cuboid, cuboid: Cuboid, key: str) -> np.ndarray:
    """``d`` (3,) metres: the network's object frame is the BOP model frame moved by ``d``
    (``P_bop = P_net + d``).

    Raises:
        ConfigError: the config's cuboid is not the model's box, kept or centred.
    """
    dims = np.asarray(cuboid.dimensions, np.float64)
    centre = np.asarray(cuboid.center, np.float64)
    box_centre = np.asarray(model_box.center, np.float64)
    if np.abs(dims - np.asarray(model_box.dimensions)).max() <= _CUBOID_TOLERANCE_M:
        for d in (np.zeros(3), box_centre):  # the model's frame kept, or centred on the box
            if np.abs(box_centre - d - centre).max() <= _CUBOID_TOLERANCE_M:
                return d
    raise ConfigError(
        f"{key}: the object's cuboid {cuboid.to_dict()} is not the BOP model's bounding box "
        f"{model_box.to_dict()} (metres, model frame): set object.mesh to the model file "
        "(recenter true or false), or object.dimensions to its size")


class BopSource:
    """Samples from BOP scenes (see the module docstring).

    Args:
        options: scenes, models folder and object id.
        cuboid: the object's cuboid in the network's object frame.
        num_samples: samples to provide (images repeat when there are fewer).
        image_size: ``(height, width)`` of the samples.
        object_name: name recorded with the samples.
        options_key: where the options are in the config, for errors.

    Raises:
        ConfigError: no image shows the object, or the cuboid is not the model's box.
        EventFileError: a malformed scene (naming the file and field).
    """

    def __init__(self, options: BopSourceOptions, cuboid: Cuboid, num_samples: int,
                 image_size: tuple[int, int], *, object_name: str = "",
                 options_key: str = "data.options") -> None:
        from evtrack.datasets.bop import BopScene, bop_model_file

        self.options = options
        self.cuboid = cuboid
        self.object_name = object_name or f"obj_{options.obj_id:06d}"
        self.num_samples = int(num_samples)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        model_box = Cuboid.from_mesh(bop_model_file(options.models, options.obj_id))
        self.offset = _frame_offset(model_box, cuboid, options_key)
        self.scenes = [BopScene(f) for f in _scene_folders(options.scenes, options_key)]
        self.items = [(k, im_id) for k, scene in enumerate(self.scenes)
                      for im_id in scene.image_ids if scene.poses(im_id, options.obj_id)]
        if not self.items:
            raise ConfigError(f"{options_key}: object {options.obj_id} is in no image of "
                              f"{[str(s.folder) for s in self.scenes]}")
        h, w = self.image_size
        self.description = (
            f"{self.num_samples} samples of {len(self.items)} BOP images of object "
            f"{options.obj_id} from {len(self.scenes)} scene(s) "
            f"({', '.join(s.folder.name for s in self.scenes[:4])}"
            f"{', ...' if len(self.scenes) > 4 else ''}), fitted into {w}x{h}")

    def __len__(self) -> int:
        return self.num_samples

    def __getitem__(self, index: int) -> PoseSample:
        if not 0 <= index < self.num_samples:
            raise IndexError(f"sample {index} out of range 0..{self.num_samples - 1}")
        k, im_id = self.items[index % len(self.items)]
        scene = self.scenes[k]
        image = scene.rgb(im_id)
        window = letterbox_window((image.shape[1], image.shape[0]), self.image_size)
        K = window.intrinsics(scene.camera(im_id).K)
        shift = np.eye(4)
        shift[:3, 3] = self.offset
        poses = np.array([p.T_m2c @ shift for p in scene.poses(im_id, self.options.obj_id)],
                         np.float64).reshape(-1, 4, 4)
        return PoseSample(image=warp_crop(image, window, _FILL), K=K, poses=poses,
                          keypoints=project_keypoints(self.cuboid, poses, K))


@register_source("bop")
def _bop_factory(spec: SourceSpec) -> BopSource:
    return BopSource(BopSourceOptions.from_dict(spec.options, spec.options_key), spec.cuboid,
                     spec.num_samples, spec.image_size, object_name=spec.object_name,
                     options_key=spec.options_key)
