"""Domain randomisation applied to samples: colour jitter, motion blur, noise, scale, occlusion.

Backgrounds, lighting and distractor objects belong to the image source (the renderer);
these transforms perturb a finished image. Each is a frozen dataclass whose ``__call__(sample,
rng)`` returns a new :class:`~evtrack.train.samples.PoseSample` (the input is never modified)
and applies itself with probability ``p``. Geometric transforms move the keypoints and update
the intrinsics ``K`` so that keypoints stay the projections of the poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import cv2
import numpy as np

from evtrack.errors import ConfigError
from evtrack.train.samples import PoseSample

__all__ = [
    "ColorJitter",
    "MotionBlur",
    "GaussianNoise",
    "RandomScale",
    "RandomOcclusion",
    "Compose",
    "AugmentConfig",
]


@dataclass(frozen=True)
class ColorJitter:
    """Random brightness, contrast, saturation (factors ``1 ± x``) and hue shift (degrees)."""

    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    hue_deg: float = 8.0
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
class MotionBlur:
    """Linear motion blur of random length (pixels) and direction, centred on each pixel."""

    max_length_px: int = 11
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
class GaussianNoise:
    """Additive Gaussian noise with a standard deviation drawn from [0, max_sigma] (grey levels)."""

    max_sigma: float = 8.0
    p: float = 0.5

    def __call__(self, sample: PoseSample, rng: np.random.Generator) -> PoseSample:
        if rng.random() >= self.p:
            return sample
        sigma = rng.uniform(0, self.max_sigma)
        noisy = sample.image.astype(np.float32) + rng.normal(0, sigma, sample.image.shape)
        return sample.replace(image=np.clip(noisy + 0.5, 0, 255).astype(np.uint8))


@dataclass(frozen=True)
class RandomScale:
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
class RandomOcclusion:
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
    "scale": RandomScale,
    "color": ColorJitter,
    "occlusion": RandomOcclusion,
    "motion_blur": MotionBlur,
    "noise": GaussianNoise,
}


@dataclass(frozen=True)
class AugmentConfig:
    """Which transforms run (in this order: scale, colour, occlusion, motion blur, noise).

    Each section is ``None`` (off) or the transform's parameters; ``enabled: false`` turns
    everything off (validation data is never augmented).
    """

    enabled: bool = True
    scale: RandomScale | None = field(default_factory=RandomScale)
    color: ColorJitter | None = field(default_factory=ColorJitter)
    occlusion: RandomOcclusion | None = field(default_factory=RandomOcclusion)
    motion_blur: MotionBlur | None = field(default_factory=MotionBlur)
    noise: GaussianNoise | None = field(default_factory=GaussianNoise)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, source: str = "data.augment") -> AugmentConfig:
        data = dict(data or {})
        unknown = sorted(set(data) - {"enabled", *_SECTIONS})
        if unknown:
            raise ConfigError(f"{source}: unknown section(s) {unknown}; known: "
                              f"{['enabled', *_SECTIONS]}")
        kwargs: dict[str, Any] = {"enabled": bool(data.get("enabled", True))}
        for name, kind in _SECTIONS.items():
            if name not in data:
                continue
            value = data[name]
            if value is None or value is False:
                kwargs[name] = None
                continue
            value = {} if value is True else dict(value)
            known = {f.name for f in fields(kind)}
            bad = sorted(set(value) - known)
            if bad:
                raise ConfigError(f"{source}.{name}: unknown field(s) {bad}; known: "
                                  f"{sorted(known)}")
            value = {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()}
            kwargs[name] = kind(**value)
        return cls(**kwargs)

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        out: dict[str, Any] = {"enabled": self.enabled}
        for name in _SECTIONS:
            t = getattr(self, name)
            out[name] = None if t is None else {
                k: list(v) if isinstance(v, tuple) else v for k, v in asdict(t).items()
            }
        return out

    def build(self) -> Compose:
        if not self.enabled:
            return Compose(())
        return Compose(tuple(t for n in _SECTIONS if (t := getattr(self, n)) is not None))
