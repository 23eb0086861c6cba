"""Training targets from keypoints: belief Gaussians and affinity fields at the output stride.

For every object instance with projected keypoints ``u_k`` (8 corners, then the centroid, in
input pixels) and output cell centres ``p`` (see :mod:`evtrack.models.keypoints`):

* belief map ``k``: ``max`` over instances of ``exp(-|p - u_k|^2 / (2 sigma^2))``;
* affinity field ``k`` (channels ``2k, 2k+1``): inside the disc ``|p - u_k| <= radius``, the unit
  vector from corner ``k`` to its instance's centroid, averaged where discs of several
  instances overlap (as DOPE does); zero elsewhere.

Keypoints that are NaN (unknown) produce nothing; keypoints outside the image still produce the
part of their Gaussian that falls inside, so a corner just off-image is still located.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evtrack.errors import ConfigError
from evtrack.models.cuboid import CENTROID_INDEX, NUM_KEYPOINTS
from evtrack.models.keypoints import grid_to_pixel

__all__ = ["TargetConfig", "make_targets"]


@dataclass(frozen=True)
class TargetConfig:
    """Shape of the training targets.

    Attributes:
        stride: output stride of the network (pixels per cell).
        sigma_px: standard deviation of the belief Gaussians, input pixels. The default, two
            output cells (as DOPE: sigma 2 on its stride-8 maps), gives every keypoint a blob
            of about 5x5 cells; one cell (8 px) gave blobs too sparse to learn from.
        affinity_radius_px: radius of the disc around each corner where the affinity field is
            set, input pixels.
    """

    stride: int = 8
    sigma_px: float = 16.0
    affinity_radius_px: float = 12.0

    def __post_init__(self) -> None:
        if self.stride < 1 or self.sigma_px <= 0 or self.affinity_radius_px <= 0:
            raise ConfigError(f"targets: stride, sigma_px and affinity_radius_px must be "
                              f"positive, got {self}")


def make_targets(
    keypoints: np.ndarray, image_size: tuple[int, int], config: TargetConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Belief maps and affinity fields of one image.

    Args:
        keypoints: (N, 9, 2) pixels of N instances (NaN = unknown); N may be 0.
        image_size: ``(height, width)`` of the input image, multiples of the stride.
        config: target shape.

    Returns:
        ``belief (9, h, w)`` and ``affinity (16, h, w)`` float32, ``h = height / stride``.
    """
    cfg = config or TargetConfig()
    height, width = image_size
    if height % cfg.stride or width % cfg.stride:
        raise ValueError(f"image size {width}x{height} is not a multiple of stride {cfg.stride}")
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, NUM_KEYPOINTS, 2)
    h, w = height // cfg.stride, width // cfg.stride
    px = grid_to_pixel(np.arange(w, dtype=np.float64), cfg.stride)[None, :]
    py = grid_to_pixel(np.arange(h, dtype=np.float64), cfg.stride)[:, None]
    belief = np.zeros((NUM_KEYPOINTS, h, w), np.float64)
    affinity = np.zeros((NUM_KEYPOINTS - 1, 2, h, w), np.float64)
    count = np.zeros((NUM_KEYPOINTS - 1, h, w), np.float64)
    two_s2 = 2.0 * cfg.sigma_px**2
    r2 = cfg.affinity_radius_px**2
    for inst in keypoints:
        valid = np.all(np.isfinite(inst), axis=1)
        for k in np.nonzero(valid)[0]:
            d2 = (px - inst[k, 0]) ** 2 + (py - inst[k, 1]) ** 2
            np.maximum(belief[k], np.exp(-d2 / two_s2), out=belief[k])
            if k == CENTROID_INDEX or not valid[CENTROID_INDEX]:
                continue
            v = inst[CENTROID_INDEX] - inst[k]
            n = np.hypot(*v)
            disc = d2 <= r2
            if n > 0:
                affinity[k, 0][disc] += v[0] / n
                affinity[k, 1][disc] += v[1] / n
            count[k][disc] += 1
    affinity = np.divide(affinity, count[:, None], out=np.zeros_like(affinity),
                         where=count[:, None] > 0)
    return belief.astype(np.float32), affinity.reshape(-1, h, w).astype(np.float32)
