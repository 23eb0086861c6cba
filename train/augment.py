"""Domain randomisation of samples: crop, colour jitter, motion blur, noise, scale, occlusion.

Backgrounds, lighting and distractor objects belong to the image source (the renderer);
these transforms perturb a finished image. Each is a frozen dataclass whose ``__call__(sample,
rng)`` returns a new :class:`~evtrack.train.samples.PoseSample` (the input is never modified)
and applies itself with probability ``p``. Geometric transforms move the keypoints and update
the intrinsics ``K`` so that keypoints stay the projections of the poses.
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from evtrack.configs import Config, FieldError, converter, setting
from evtrack.models.crop_refine import box_window, warp_crop
from evtrack.train.samples import PoseSample

__all__ = [
    "ColorJitter",
    "MotionBlur",
    "GaussianNoise",
    "RandomCrop",
    "RandomScale",
    "RandomOcclusion",
    "Compose",
    "AugmentConfig",
]


@dataclass(frozen=True)
class ColorJitter(Config):
    """Random brightness, contrast, saturation (factors ``1 ± x``) and hue shift (degrees)."""

    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    hue_deg: float = setting(8.0, unit="deg")
    p: float = 0.8

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p:
            return sample
        img = sample.image.astype(np.float32)
        img *= rng.uniform(1 - self.brightness, 1 + self.brightness)
        mean = img.mean()
        img = (img - mean) * rng.uniform(1 - self.contrast, 1 + self.contrast) + mean
        img = np.clip(img, 0, 255).astype(np.uint8)
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV).astype(np.float32)
        hsv[..., 0] = (hsv[..., 0] + rng.uniform(-self.hue_deg, self.hue_deg) / 2) % 180
        hsv[..., 1] *= rng.uniform(1 - self.saturation, 1 + self.saturation)
        hsv = np.clip(hsv, 0, [179, 255, 255]).astype(np.uint8)
        return sample.replace(image=cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB))


@dataclass(frozen=True)
class MotionBlur(Config):
    """Linear motion blur of random length (pixels) and direction, centred on each pixel."""

    max_length_px: int = setting(11, unit="px")
    p: float = 0.3

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p or self.max_length_px < 2:
            return sample
        length = int(rng.integers(2, self.max_length_px + 1))
        size = length | 1  # odd kernel, centred
        kernel = np.zeros((size, size), np.float32)
        c = size // 2
        angle = rng.uniform(0, np.pi)
        dx, dy = np.cos(angle) * (length - 1) / 2, np.sin(angle) * (length - 1) / 2
        cv2.line(kernel, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, 1)
        kernel /= kernel.sum()
        return sample.replace(image=cv2.filter2D(sample.image, -1, kernel,
                                                 borderType=cv2.BORDER_REFLECT_101))


@dataclass(frozen=True)
class GaussianNoise(Config):
    """Additive Gaussian noise with a standard deviation drawn from [0, max_sigma] (grey levels)."""

    max_sigma: float = setting(8.0, unit="grey levels")
    p: float = 0.5

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p:
            return sample
        sigma = rng.uniform(0, self.max_sigma)
        noisy = sample.image.astype(np.float32) + rng.normal(0, sigma, sample.image.shape)
        return sample.replace(image=np.clip(noisy + 0.5, 0, 255).astype(np.uint8))


@dataclass(frozen=True)
class RandomCrop(Config):
    """Cut a fixed-size window, usually around an object instance; keypoints and ``K`` follow.

    Training on crops spends the compute on the pixels that carry the object: a 160x160 crop of
    a 320x240 render costs a third of the full frame, and the fully convolutional network still
    runs on whole frames at inference. The crop always happens (every training image gets the
    crop size, so batches stack); validation images are never augmented and stay whole.

    With probability ``object_p`` the window is placed so that the centroid of a random instance
    lands within ``max_offset`` (a fraction of the crop side) of the window's centre; otherwise
    (or when no instance has a known centroid) the window is placed uniformly. Parts of the
    window outside the image are filled with a random flat colour.

    With probability ``zoom_p`` an instance-centred window is instead the view of the pose
    estimator's second pass (``DecodeConfig.crop_refine``): the image is scaled so that the
    instance's projected cuboid (the bounding box of its corner keypoints) spans a uniform
    ``zoom_box`` fraction of the crop width, and centred on that box up to ``zoom_offset``
    of the crop side (the first pass's errors). The estimator's default crop is half the
    network's input width with the box at 1 / 1.3 = 0.77 of it, so a stage trained at 640x480
    for it uses 320x320 crops and a ``zoom_box`` around 0.77.

    Attributes:
        size: ``(height, width)`` of the crop in pixels, multiples of 8.
        object_p: probability of centring on an instance.
        max_offset: largest offset of the instance centroid from the crop centre, fraction of the
            crop side.
        zoom_p: probability that an instance-centred crop is a zoomed one (0: never).
        zoom_box: ``(low, high)``: the zoomed instance's box side, fraction of the crop width.
        zoom_offset: largest offset of the zoomed box's centre from the crop centre, fraction
            of the crop side.
    """

    size: tuple[int, int] = setting((160, 160), gt=0, unit="px")
    object_p: float = setting(0.85, ge=0, le=1)
    max_offset: float = setting(0.3, ge=0)
    zoom_p: float = setting(0.0, ge=0, le=1, note="0: never")
    zoom_box: tuple[float, float] = setting((0.65, 0.9), gt=0)
    zoom_offset: float = setting(0.05, ge=0)

    def __post_init__(self) -> None:
        super().__post_init__()
        if len(self.size) != 2 or any(int(v) % 8 for v in self.size):
            raise FieldError(self, "size", f"must be positive multiples of 8, got {self.size}")
        box = tuple(self.zoom_box)
        if len(box) != 2 or not float(box[0]) <= float(box[1]):
            raise FieldError(self, "zoom_box", f"must be (low, high) with 0 < low <= high, got "
                             f"{self.zoom_box}")

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        ch, cw = (int(v) for v in self.size)
        h, w = sample.image.shape[:2]
        centroids = sample.keypoints[:, -1, :] if sample.num_instances else np.zeros((0, 2))
        known = np.flatnonzero(np.isfinite(centroids).all(axis=1))
        if known.size and rng.random() < self.object_p:
            index = int(rng.choice(known))
            if self.zoom_p > 0 and rng.random() < self.zoom_p:
                zoomed = self._zoomed(sample, index, rng)
                if zoomed is not None:
                    return zoomed
            c = centroids[index].astype(np.float64)
            off = rng.uniform(-self.max_offset, self.max_offset, 2) * (cw, ch)
            x0 = int(round(c[0] + off[0] - cw / 2))
            y0 = int(round(c[1] + off[1] - ch / 2))
        else:
            x0 = int(rng.integers(min(0, w - cw), max(0, w - cw) + 1))
            y0 = int(rng.integers(min(0, h - ch), max(0, h - ch) + 1))
        fill = rng.integers(0, 256, 3).astype(np.uint8)
        out = np.empty((ch, cw, 3), np.uint8)
        out[:] = fill
        sx0, sy0 = max(x0, 0), max(y0, 0)
        sx1, sy1 = min(x0 + cw, w), min(y0 + ch, h)
        if sx1 > sx0 and sy1 > sy0:
            out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = sample.image[sy0:sy1, sx0:sx1]
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        K = shift @ np.asarray(sample.K, dtype=np.float64)
        kps = (sample.keypoints.astype(np.float64) - (x0, y0)).astype(np.float32)
        return sample.replace(image=out, K=K, keypoints=kps)

    def _zoomed(self, sample: PoseSample, index: int, rng: np.random.Generator
                ) -> PoseSample | None:
        """The zoomed crop around instance ``index`` (``None``: fewer than two of its corners
        are known, or they coincide)."""
        ch, cw = (int(v) for v in self.size)
        corners = sample.keypoints[index, :8].astype(np.float64)
        corners = corners[np.isfinite(corners).all(axis=1)]
        if len(corners) < 2:
            return None
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        if not float((hi - lo).max()) > 1.0:
            return None
        side = rng.uniform(*self.zoom_box) * cw
        off = rng.uniform(-self.zoom_offset, self.zoom_offset, 2) * (cw, ch)
        window = box_window(lo, hi, (cw, ch), side, (float(off[0]), float(off[1])))
        fill = tuple(float(v) for v in rng.integers(0, 256, 3))
        image = warp_crop(sample.image, window, fill)
        K = window.intrinsics(sample.K)
        kps = window.to_crop(sample.keypoints).astype(np.float32)
        return sample.replace(image=image, K=K, keypoints=kps)


@dataclass(frozen=True)
class RandomScale(Config):
    """Zoom about the image centre and shift; keypoints and ``K`` follow, the size is kept.

    The new pixel of an old pixel ``p`` is ``s * (p - c) + c + d`` with ``c`` the image centre,
    ``s`` in ``scale_range`` and ``d`` up to ``max_shift`` of the image size. Uncovered borders
    are filled with a random flat colour (never a mirrored copy of the object).
    """

    scale_range: tuple[float, float] = (0.75, 1.3)
    max_shift: float = 0.1
    p: float = 0.5

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p:
            return sample
        h, w = sample.image.shape[:2]
        s = rng.uniform(*self.scale_range)
        c = np.array([(w - 1) / 2, (h - 1) / 2])
        d = rng.uniform(-self.max_shift, self.max_shift, 2) * (w, h)
        b = c - s * c + d
        A = np.array([[s, 0, b[0]], [0, s, b[1]]])
        fill = tuple(float(v) for v in rng.integers(0, 256, 3))
        image = cv2.warpAffine(sample.image, A, (w, h), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
        K = np.vstack([A, [0, 0, 1]]) @ sample.K
        kps = (sample.keypoints.astype(np.float64) * s + b).astype(np.float32)
        return sample.replace(image=image, K=K, keypoints=kps)


@dataclass(frozen=True)
class RandomOcclusion(Config):
    """Up to ``max_boxes`` rectangles of noise or flat colour, each up to ``max_size`` of the
    image side, pasted anywhere (keypoints keep their targets: the network learns to
    predict hidden corners, as DOPE does)."""

    max_boxes: int = 3
    max_size: float = 0.25
    p: float = 0.4

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p or self.max_boxes < 1:
            return sample
        img = sample.image.copy()
        h, w = img.shape[:2]
        for _ in range(int(rng.integers(1, self.max_boxes + 1))):
            bw = max(1, int(rng.uniform(0.05, self.max_size) * w))
            bh = max(1, int(rng.uniform(0.05, self.max_size) * h))
            x0, y0 = int(rng.integers(0, max(1, w - bw))), int(rng.integers(0, max(1, h - bh)))
            if rng.random() < 0.5:
                img[y0:y0 + bh, x0:x0 + bw] = rng.integers(0, 256, 3, dtype=np.uint8)
            else:
                img[y0:y0 + bh, x0:x0 + bw] = rng.integers(0, 256, (bh, bw, 3), dtype=np.uint8)
        return sample.replace(image=img)


@dataclass(frozen=True)
class Compose:
    """Apply transforms in order."""

    transforms: tuple = ()

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        for t in self.transforms:
            sample = t(sample, rng)
        return sample


_SECTIONS: dict[str, type] = {
    "crop": RandomCrop,
    "scale": RandomScale,
    "color": ColorJitter,
    "occlusion": RandomOcclusion,
    "motion_blur": MotionBlur,
    "noise": GaussianNoise,
}


def _is_section(tp: Any) -> bool:
    """Whether ``tp`` is the type of an :class:`AugmentConfig` section (``Transform | None``)."""
    return (typing.get_origin(tp) in (typing.Union, types.UnionType)
            and any(arg in _SECTIONS.values() for arg in typing.get_args(tp)))


def _structure_section(value: Any, tp: Any) -> Any:
    """An :class:`AugmentConfig` section: ``null`` or ``false`` (off), ``true`` (the
    transform's defaults) or a mapping of the transform's fields."""
    if value is None or value is False:
        return None
    kind = next(arg for arg in typing.get_args(tp) if arg in _SECTIONS.values())
    return converter.structure({} if value is True else value, kind)


converter.register_structure_hook_func(_is_section, _structure_section)


@dataclass(frozen=True)
class AugmentConfig(Config):
    """Which transforms run (in this order: crop, scale, colour, occlusion, motion blur, noise).

    Each section is ``None`` or ``false`` (off), ``true`` (the transform's defaults) or the
    transform's parameters; ``enabled: false`` turns everything off (validation data is never
    augmented). ``crop`` is off by default.
    """

    enabled: bool = True
    crop: RandomCrop | None = None
    scale: RandomScale | None = field(default_factory=RandomScale)
    color: ColorJitter | None = field(default_factory=ColorJitter)
    occlusion: RandomOcclusion | None = field(default_factory=RandomOcclusion)
    motion_blur: MotionBlur | None = field(default_factory=MotionBlur)
    noise: GaussianNoise | None = field(default_factory=GaussianNoise)

    def build(self) -> Compose:
        """The transforms that are on, in the order of the class docstring."""
        if not self.enabled:
            return Compose(())
        return Compose(tuple(t for n in _SECTIONS if (t := getattr(self, n)) is not None))
