"""``PoseEstimator``: RGB image in, object poses out, for any backend (torch or onnxruntime).

``estimator(rgb_uint8_hwc) -> list[PoseDetection]``. The base class does what every backend
shares: input checks, resizing by ``input_scale``, normalisation with the weights record's
mean/std, padding to a multiple of the output stride, decoding and PnP, then a second pass
on a crop around each detection (``DecodeConfig.crop_refine``, :mod:`evtrack.models.crop_refine`;
one more network call per image, on all its crops at once). A backend only implements
:meth:`PoseEstimator.run_network` on a normalised float32 batch (any image size).
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models.crop_refine import CropWindow, crop_window, halfway_rotation, warp_crop
from evtrack.models.cuboid import CENTROID_INDEX, Cuboid
from evtrack.models.decode import DecodeConfig, PoseDetection, decode_poses, with_alternatives
from evtrack.models.fold_batchnorm import fold_batchnorm as fold_bn
from evtrack.models.weights import IMAGENET_MEAN, IMAGENET_STD, WeightsRecord

__all__ = ["PoseEstimator", "TorchPoseEstimator", "preprocess", "training_input_scale"]


def preprocess(
    rgb: np.ndarray,
    mean: Sequence[float],
    std: Sequence[float],
    input_scale: float = 1.0,
    size_divisor: int = 8,
) -> tuple[np.ndarray, tuple[float, float]]:
    """uint8 RGB (H, W, 3) -> normalised float32 (3, H', W') padded to ``size_divisor``.

    The image is resized by ``input_scale`` (area interpolation when shrinking), scaled to
    [0, 1], normalised per channel, and zero-padded at the bottom and right (zero = the mean
    colour) so both sides are multiples of ``size_divisor``; padding moves no keypoint.

    Returns:
        The network input and the actual ``(sx, sy)`` resize factors (after rounding).
    """
    h, w = rgb.shape[:2]
    if input_scale != 1.0:
        nw, nh = max(1, round(w * input_scale)), max(1, round(h * input_scale))
        interp = cv2.INTER_AREA if input_scale < 1 else cv2.INTER_LINEAR
        rgb = cv2.resize(rgb, (nw, nh), interpolation=interp)
    else:
        nw, nh = w, h
    # (x / 255 - mean) / std as one scale and offset per channel, written channel by channel
    # into the padded planar array: ~10x faster than numpy's chain of temporaries at 640x480
    scale = 1.0 / (255.0 * np.asarray(std, np.float64))
    offset = -np.asarray(mean, np.float64) / np.asarray(std, np.float64)
    ph, pw = -nh % size_divisor, -nw % size_divisor
    x = (np.zeros if ph or pw else np.empty)((3, nh + ph, nw + pw), np.float32)
    for c, plane in enumerate(cv2.split(np.ascontiguousarray(rgb))):
        view = x[c, :nh, :nw]
        view[...] = plane
        view *= np.float32(scale[c])
        view += np.float32(offset[c])
    return x, (nw / w, nh / h)


def _batch(inputs: Sequence[np.ndarray]) -> np.ndarray:
    """(B, 3, H, W) from B network inputs; one input without a copy (a 640x480 input is
    3.7 MB)."""
    return inputs[0][None] if len(inputs) == 1 else np.stack(inputs)


def check_rgb(rgb: object) -> np.ndarray:
    """``rgb`` if it is a uint8 (H, W, 3) RGB image of at least one output cell.

    Raises:
        ValueError: saying what it got.
    """
    if not isinstance(rgb, np.ndarray):
        raise ValueError(f"expected an RGB image as a numpy array, got {type(rgb).__name__}")
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected a uint8 (H, W, 3) RGB image, got {rgb.dtype} {rgb.shape}")
    if rgb.shape[0] < 8 or rgb.shape[1] < 8:
        raise ValueError(f"image {rgb.shape[1]}x{rgb.shape[0]} is smaller than one output cell")
    return rgb


class PoseEstimator(abc.ABC):
    """Base class: image -> list of :class:`PoseDetection`, most confident first.

    Args:
        camera: the camera of the images (intrinsics and distortion; its size must match
            the images), or a (3, 3) intrinsic matrix for undistorted images of any size.
        cuboid: the object's cuboid.
        object_name: name reported in detections.
        mean, std: input normalisation (RGB in [0, 1]).
        output_stride: the network's output stride.
        decode: decoding and PnP settings.
        input_scale: resize images by this factor before the network (e.g. 0.5 runs a
            640x480 camera at 320x240); poses stay in the camera's pixel frame.
    """

    def __init__(
        self,
        camera: PinholeCamera | np.ndarray,
        cuboid: Cuboid,
        *,
        object_name: str = "",
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        output_stride: int = 8,
        decode: DecodeConfig | None = None,
        input_scale: float = 1.0,
    ) -> None:
        if not input_scale > 0:
            raise ConfigError(f"input_scale must be positive, got {input_scale}")
        self.camera = camera
        self.cuboid = cuboid
        self.object_name = object_name
        self.mean = tuple(mean)
        self.std = tuple(std)
        self.output_stride = int(output_stride)
        self.decode = decode or DecodeConfig()
        self.input_scale = float(input_scale)

    # ------------------------------------------------------------------ backend
    @abc.abstractmethod
    def run_network(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, 3, H, W) float32 -> belief (B, 9, H/8, W/8), affinity (B, 16, H/8, W/8)."""

    # ------------------------------------------------------------------ shared pipeline
    def _intrinsics(
        self, camera: PinholeCamera | np.ndarray | None, shape: tuple[int, ...]
    ) -> tuple[np.ndarray, np.ndarray | None]:
        cam = self.camera if camera is None else camera
        if isinstance(cam, PinholeCamera):
            if (cam.width, cam.height) != (shape[1], shape[0]):
                raise ValueError(
                    f"image is {shape[1]}x{shape[0]} but the camera is {cam.width}x{cam.height}"
                )
            dist = None if cam.dist is None else cam.dist.numpy()
            return cam.K().numpy(), dist
        K = np.asarray(cam, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera must be a PinholeCamera or a (3, 3) K, got shape {K.shape}")
        return K, None

    def predict_maps(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, tuple]:
        """Network maps for a list of same-size uint8 RGB images.

        Returns:
            ``belief (B, 9, h, w)``, ``affinity (B, 16, h, w)`` (float32) and the ``(sx, sy)``
            resize factors applied before the network.
        """
        images = [check_rgb(im) for im in images]
        if len({im.shape for im in images}) > 1:
            raise ValueError("all images of a batch must have the same size")
        inputs, scales = zip(
            *(preprocess(im, self.mean, self.std, self.input_scale, self.output_stride)
              for im in images),
            strict=True,
        )
        belief, affinity = self.run_network(_batch(inputs))
        return np.asarray(belief, np.float32), np.asarray(affinity, np.float32), scales[0]

    def estimate_batch(
        self, images: Sequence[np.ndarray], camera: PinholeCamera | np.ndarray | None = None
    ) -> list[list[PoseDetection]]:
        """Poses for a list of same-size images (one network call)."""
        if len(images) == 0:
            return []
        images = [check_rgb(im) for im in images]  # before the size check: clearer errors
        K, dist = self._intrinsics(camera, images[0].shape)
        belief, affinity, scale = self.predict_maps(images)
        detections = [
            decode_poses(
                belief[i], affinity[i], self.cuboid, K, dist, stride=self.output_stride,
                config=self.decode, pixel_scale=scale, object_name=self.object_name,
            )
            for i in range(len(images))
        ]
        if self.decode.crop_refine > 0:
            detections = self._refine_in_crops(images, detections, K, dist, scale[0])
        return detections

    def crop_size(self, image_width: int, input_scale: float | None = None) -> int:
        """Side (pixels) of the second pass's crops for images ``image_width`` pixels wide:
        ``decode.crop_refine`` of the network's input width, a multiple of the output stride
        (at least two cells)."""
        scale = self.input_scale if input_scale is None else input_scale
        cells = round(self.decode.crop_refine * image_width * scale / self.output_stride)
        return max(2, int(cells)) * self.output_stride

    def _refine_in_crops(
        self, images: Sequence[np.ndarray], detections: list[list[PoseDetection]],
        K: np.ndarray, dist: np.ndarray | None, input_scale: float,
    ) -> list[list[PoseDetection]]:
        """The second pass (see ``DecodeConfig.crop_refine``): one network call on a crop
        around every detection of every image; a detection whose crop finds the object takes
        the crop's pose (the crop's instance nearest its centre), keypoints mapped back to
        the image and its reprojection error in image pixels; its confidence is the crop's
        (the reprojection term measured in the crop's pixels, where every object has about
        one size), and the first pass's detection joins its alternatives
        (:attr:`PoseDetection.alternatives`). Where the two rotations agree within
        ``decode.crop_blend_max_deg`` the detection's turns halfway to the first pass's, and
        the crop's own pose joins the alternatives too. The refined detection's confidence is
        the better of the two passes' (its alternatives keep their own), so that instances are
        ranked by the best look each had. A crop reading less confident than
        ``decode.search_below`` (the decoder's mark of a failed fit) does not replace a first
        pass's reading that is not: that detection keeps the first pass's pose and confidence,
        the crop's readings join its alternatives. The others stay as they were. Most
        confident first again."""
        size = self.crop_size(images[0].shape[1], input_scale)
        jobs, windows = [], []
        for i, dets in enumerate(detections):
            for j, det in enumerate(dets):
                window = crop_window(det.pose.numpy(), self.cuboid, K, dist, size,
                                     self.decode.crop_margin)
                if window is not None:
                    jobs.append((i, j))
                    windows.append((images[i], window))
        refined = [list(dets) for dets in detections]
        for (i, j), found in zip(jobs, self._detect_in_crops(windows, K, dist), strict=True):
            if found is None:
                continue
            first, (kept, *others) = detections[i][j], found
            failed = self.decode.search_below
            if kept.confidence < failed <= first.confidence:
                # a failed second look (its fit below the decoder's mark of a failed one)
                # is no evidence against a confident first one: a network that mixes the
                # corners of a near or symmetric object up in the crop would otherwise sink
                # its object below a distractor's detection
                refined[i][j] = with_alternatives(first, [kept, *others])
                continue
            blend = self.decode.crop_blend_max_deg
            turned = (halfway_rotation(kept.pose.numpy(), first.pose.numpy(), blend)
                      if blend > 0 else None)
            if turned is not None:
                others.append(kept)
                kept = replace(kept, pose=torch.from_numpy(turned))
            refined[i][j] = with_alternatives(kept, [*others, first])
            if first.confidence > kept.confidence:
                # ranked by its better look: the crop enlarges a motion-blurred object and
                # fits its corners worse than it fits a sharp distractor's, which would
                # otherwise rank the distractor first
                refined[i][j] = replace(refined[i][j], confidence=first.confidence)
        for dets in refined:
            dets.sort(key=lambda d: -d.confidence)
        return refined

    def _detect_in_crops(
        self, windows: Sequence[tuple[np.ndarray, CropWindow]], K: np.ndarray,
        dist: np.ndarray | None,
    ) -> list[list[PoseDetection] | None]:
        """One network call on the crops ``(image, window)`` (all of one size); per crop, its
        instance nearest the crop's centre and that one's alternatives, in image pixels
        (the instance first), or ``None`` where the crop finds nothing."""
        if not windows:
            return []
        fill = tuple(255.0 * m for m in self.mean)
        crops = [preprocess(warp_crop(image, window, fill), self.mean, self.std, 1.0,
                            self.output_stride)[0] for image, window in windows]
        belief, affinity = self.run_network(_batch(crops))
        belief, affinity = np.asarray(belief, np.float32), np.asarray(affinity, np.float32)
        out: list[list[PoseDetection] | None] = []
        for (_, window), b, a in zip(windows, belief, affinity, strict=True):
            K_crop = window.intrinsics(K)
            found = decode_poses(b, a, self.cuboid, K_crop, dist, stride=self.output_stride,
                                 config=self.decode, object_name=self.object_name)
            if not found:
                out.append(None)
                continue
            best = min(found, key=lambda d: float(np.linalg.norm(
                self.cuboid.project(d.pose.numpy(), K_crop, dist)[CENTROID_INDEX]
                - window.centre)))
            out.append([self._crop_to_image(d, window) for d in (best, *best.alternatives)])
        return out

    def estimate_near(
        self, rgb: np.ndarray, prior: np.ndarray | torch.Tensor,
        camera: PinholeCamera | np.ndarray | None = None,
    ) -> list[PoseDetection]:
        """The object's pose in one image, looked for where a tracker expects it first.

        Instead of the first pass over the whole image, the crop pass
        (``decode.crop_refine``) runs on a crop placed on ``prior``'s projected cuboid. Its
        detection (the instance nearest the crop's centre) then stands for the first pass's:

        * within ``decode.prior_recrop`` of where the prior put the object (crop centre and
          zoom), it is the answer: one network call on a quarter to a third of a 640x480
          image's pixels instead of the whole image and a crop;
        * otherwise, up to a quarter of the crop's side off its centre, the crop pass runs
          again on a crop placed on that detection, as after a first pass (its alternatives,
          ``decode.crop_blend_max_deg``): two crop calls;
        * farther off, or with nothing found, a prior that projects to no usable crop, or an
          estimator of one pass (``crop_refine = 0``): the whole two-pass estimate
          (:meth:`__call__`).

        Args:
            rgb: uint8 (H, W, 3) image.
            prior: (4, 4) object-to-camera pose expected in this image (e.g. the tracker's
                prediction at its time), in the camera of ``camera``/the estimator.
            camera: as in :meth:`__call__`.

        Returns:
            At most one detection, with its other readings as its alternatives, or what
            :meth:`__call__` returns.

        Raises:
            ValueError: ``prior`` is not (4, 4) (a non-finite one falls back as above).
        """
        rgb = check_rgb(rgb)
        prior = np.asarray(prior, np.float64)
        if prior.shape != (4, 4):
            raise ValueError(f"estimate_near: prior must be a (4, 4) pose, got shape "
                             f"{prior.shape}")
        if self.decode.crop_refine <= 0 or not np.isfinite(prior).all():
            return self(rgb, camera)
        K, dist = self._intrinsics(camera, rgb.shape)
        width = rgb.shape[1]
        scale = max(1, round(width * self.input_scale)) / width  # as preprocess rounds it
        size = self.crop_size(width, scale)
        margin = self.decode.crop_margin
        window = crop_window(prior, self.cuboid, K, dist, size, margin)
        if window is None:
            return self(rgb, camera)
        (found,) = self._detect_in_crops([(rgb, window)], K, dist)
        if found is None:
            return self(rgb, camera)
        first = with_alternatives(found[0], found[1:])
        placed = crop_window(first.pose.numpy(), self.cuboid, K, dist, size, margin)
        if placed is None:
            return self(rgb, camera)
        # where the detection's own crop lies in the prior's crop: its centre and its zoom
        centre = window.centre
        offset = np.linalg.norm(window.to_crop(placed.to_image(placed.centre)) - centre) / size
        zoom = placed.scale / window.scale
        tol = self.decode.prior_recrop
        if offset <= tol and abs(zoom - 1.0) <= 2 * tol:
            return [first]
        if offset > 0.25:
            return self(rgb, camera)
        return self._refine_in_crops([rgb], [[first]], K, dist, scale)[0]

    @staticmethod
    def _crop_to_image(det: PoseDetection, window) -> PoseDetection:
        """A crop's detection with its keypoints and reprojection error in image pixels
        (its pose is already in the image's camera; its alternatives are left out)."""
        return PoseDetection(
            pose=det.pose,
            confidence=det.confidence,
            keypoints=torch.from_numpy(window.to_image(det.keypoints.numpy())),
            keypoint_scores=det.keypoint_scores,
            reprojection_error_px=det.reprojection_error_px / window.scale,
            num_points=det.num_points,
            object_name=det.object_name,
        )

    def __call__(
        self, rgb: np.ndarray, camera: PinholeCamera | np.ndarray | None = None
    ) -> list[PoseDetection]:
        """Poses of the object's instances in one uint8 (H, W, 3) RGB image."""
        return self.estimate_batch([rgb], camera)[0]


def training_input_scale(record: WeightsRecord | None, camera: PinholeCamera | np.ndarray
                         ) -> float:
    """The resize factor that shows the network images at its training resolution.

    ``record.input_size`` width / camera width for a :class:`PinholeCamera` (e.g. 0.5 for a
    network trained at 320x240 on a 640x480 camera: the training renders keep the camera's
    field of view, so objects then appear at the size the network learned); 1.0 without a
    record or for a bare intrinsic matrix (image size unknown).
    """
    if record is None or not isinstance(camera, PinholeCamera):
        return 1.0
    return record.input_size[1] / camera.width


def _record_kwargs(record: WeightsRecord | None, cuboid: Cuboid | None, object_name: str | None,
                   camera: PinholeCamera | np.ndarray, input_scale: float | None = None,
                   decode: DecodeConfig | None = None):
    """The :class:`PoseEstimator` arguments a weights record supplies where not given: cuboid,
    object name, normalisation, stride, input scale and the record's decoding
    (``WeightsRecord.decode``; an explicit ``decode`` wins)."""
    if record is None and cuboid is None:
        raise ConfigError("the network has no weights record: pass cuboid=... (and object_name)")
    if input_scale is None:
        input_scale = training_input_scale(record, camera)
    return {
        "input_scale": input_scale,
        "cuboid": cuboid if cuboid is not None else record.cuboid,
        "object_name": object_name if object_name is not None else (
            record.object_name if record else ""),
        "mean": record.mean if record else IMAGENET_MEAN,
        "std": record.std if record else IMAGENET_STD,
        "output_stride": record.output_stride if record else 8,
        "decode": decode if decode is not None else (
            DecodeConfig.from_dict(record.decode, "record.decode") if record else None),
    }


class TorchPoseEstimator(PoseEstimator):
    """:class:`PoseEstimator` running a torch network (eager).

    Args:
        net: a network from :func:`evtrack.models.create`; its ``weights_record`` supplies
            cuboid, object name and normalisation unless given here.
        camera: see :class:`PoseEstimator`.
        device: torch device to run on.
        cuboid, object_name: override (or supply, for a network without a record).
        input_scale: resize factor before the network; ``None`` (default): the network's
            training resolution (:func:`training_input_scale`).
        fold_batchnorm: run a copy of ``net`` with its batch norms folded into the
            convolutions (:func:`~evtrack.models.fold_batchnorm.fold_batchnorm`; the same maps
            up to float round-off, ~35 % faster on a CPU); ``False``: run ``net`` itself.
            ``net`` is never changed.
        **kwargs: ``decode`` as in :class:`PoseEstimator`; default: the record's
            (``WeightsRecord.decode``, else the library's defaults).
    """

    def __init__(
        self,
        net: nn.Module,
        camera: PinholeCamera | np.ndarray,
        *,
        device: str | torch.device = "cpu",
        cuboid: Cuboid | None = None,
        object_name: str | None = None,
        input_scale: float | None = None,
        fold_batchnorm: bool = True,
        **kwargs,
    ) -> None:
        record = getattr(net, "weights_record", None)
        decode = kwargs.pop("decode", None)
        super().__init__(camera, **_record_kwargs(record, cuboid, object_name, camera,
                                                  input_scale, decode), **kwargs)
        self.device = torch.device(device)
        if fold_batchnorm:
            net, _ = fold_bn(net)
        self.net = net.to(self.device).eval()
        """The module that runs: ``net``, or its copy with folded batch norms."""

    @classmethod
    def from_weights(
        cls, path: str | Path, camera: PinholeCamera | np.ndarray, *,
        object_name: str | None = None, **kwargs
    ) -> TorchPoseEstimator:
        """Load a weights file (or training checkpoint) and wrap it."""
        from evtrack.models.factory import load_model

        net, _ = load_model(path, object_name=object_name)
        return cls(net, camera, **kwargs)

    def run_network(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.inference_mode():
            x = torch.from_numpy(batch).to(self.device)
            belief, affinity = self.net(x)
        return belief.float().cpu().numpy(), affinity.float().cpu().numpy()
