"""The second, zoomed-in pass of the pose estimator: a crop around each first-pass detection.

The network finds corners to a few of its input pixels whatever the object's size, so the
pose of a small object (far away) is poor in depth, and one that fills the view (close)
sits outside the sizes the network learned. A second pass on a square crop centred on the
first pose's projected cuboid, resized so that the cuboid spans a fixed share of the
network's input, sees every object at about one size: the corners' pixel errors shrink by
the zoom factor for a far object, and a close one is shrunk back to a size the network
knows (the part of the crop outside the image is the mean colour, the network's zero).

The crop is an affine map of the image's pixels, ``u' = s u + t`` (pixel centres at integer
coordinates, as OpenCV warps), so a camera ``u = K d(x)`` (``d``: the lens distortion of the
normalised point ``x``) sees the crop through ``K' = A K`` with ``A = [[s, 0, tx], [0, s,
ty], [0, 0, 1]]`` and the same distortion: PnP on the crop's keypoints with ``K'`` gives
the pose in the camera frame directly, and keypoints map back with ``u = (u' - t) / s``.

Measured with the shipped coded-box weights on six held-out regular sequences
(``benchmarks/bench_pose_accuracy.py``, see ``DecodeConfig.crop_refine``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from evtrack.models.cuboid import Cuboid

__all__ = ["CropWindow", "box_window", "crop_window", "halfway_rotation", "warp_crop"]


@dataclass(frozen=True)
class CropWindow:
    """A crop of an image, resized: crop pixel ``u' = scale * u + offset``.

    Attributes:
        scale: crop pixels per image pixel.
        offset: (2,) ``(tx, ty)`` crop pixels.
        size: ``(width, height)`` of the crop, pixels.
    """

    scale: float
    offset: tuple[float, float]
    size: tuple[int, int]

    @property
    def centre(self) -> np.ndarray:
        """(2,) float64 the crop's centre, crop pixels (pixel centres at integers)."""
        return (np.asarray(self.size, np.float64) - 1) / 2

    @property
    def affine(self) -> np.ndarray:
        """(2, 3) float64: image pixel -> crop pixel (``cv2.warpAffine``'s matrix)."""
        s = self.scale
        return np.array([[s, 0.0, self.offset[0]], [0.0, s, self.offset[1]]])

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """(3, 3) intrinsics of the crop for a camera of intrinsics ``K`` (``A K``)."""
        return np.vstack([self.affine, [0.0, 0.0, 1.0]]) @ np.asarray(K, np.float64)

    def to_image(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) crop pixels -> image pixels (NaN stays NaN)."""
        return (np.asarray(points, np.float64) - np.asarray(self.offset)) / self.scale

    def to_crop(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) image pixels -> crop pixels (NaN stays NaN)."""
        return np.asarray(points, np.float64) * self.scale + np.asarray(self.offset)


def box_window(lo: np.ndarray, hi: np.ndarray, size: tuple[int, int], box_side: float,
               shift: tuple[float, float] = (0.0, 0.0)) -> CropWindow:
    """The crop of ``size = (width, height)`` pixels in which the box ``[lo, hi]`` (image
    pixels) has its longer side ``box_side`` crop pixels and its centre at the crop's centre
    plus ``shift`` (pixel centres at integer coordinates: the centre is ``((w - 1) / 2, (h -
    1) / 2)``). The estimator's second pass and the training crops that imitate it
    (``RandomCrop.zoom_p``) both place their crops with it. The box must be wider than 0."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    scale = float(box_side) / float((hi - lo).max())
    centre = (lo + hi) / 2
    w, h = (int(v) for v in size)
    tx = (w - 1) / 2 + shift[0] - scale * centre[0]
    ty = (h - 1) / 2 + shift[1] - scale * centre[1]
    return CropWindow(scale, (float(tx), float(ty)), (w, h))


def crop_window(pose: np.ndarray, cuboid: Cuboid, K: np.ndarray, dist: np.ndarray | None,
                size: int, margin: float) -> CropWindow | None:
    """The crop of side ``size`` pixels centred on the projected cuboid of ``pose``, whose
    bounding box's longer side times ``margin`` fills the crop.

    Args:
        pose: (4, 4) object-to-camera. cuboid: the object's cuboid. K: (3, 3) intrinsics;
            dist: OpenCV distortion coefficients or ``None``.
        size: crop side, pixels (> 0). margin: crop side / projected box side (>= 1).

    Returns:
        The window, or ``None`` when the cuboid does not project to a usable box (a corner
        behind the camera, non-finite values, a box under one pixel).
    """
    pose = np.asarray(pose, np.float64)
    corners = cuboid.points()[:8]
    depth = corners @ pose[:3, :3].T + pose[:3, 3]
    if not np.isfinite(pose).all() or (depth[:, 2] <= 1e-6).any():
        return None
    uv = cuboid.project(pose, K, dist)[:8]
    if not np.isfinite(uv).all():
        return None
    # on a 1/8 px grid: the crop and its intrinsics A K (PnP's input) are then the same for
    # poses a hair apart (the first pass on torch and on onnxruntime; see PNP_GRID_PX)
    lo, hi = np.round(uv.min(axis=0) * 8.0) / 8.0, np.round(uv.max(axis=0) * 8.0) / 8.0
    if not margin * float((hi - lo).max()) >= 1.0:
        return None
    return box_window(lo, hi, (size, size), size / margin)


def warp_crop(image: np.ndarray, window: CropWindow, fill: tuple[float, float, float]
              ) -> np.ndarray:
    """The (height, width, 3) crop of an (H, W, 3) uint8 image (bilinear; ``fill`` outside
    it)."""
    return cv2.warpAffine(np.ascontiguousarray(image), window.affine, window.size,
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=tuple(float(v) for v in fill))


def halfway_rotation(pose_a: np.ndarray, pose_b: np.ndarray, max_deg: float) -> np.ndarray | None:
    """``pose_a`` (4, 4) with its rotation moved halfway along the geodesic to ``pose_b``'s,
    its translation kept; ``None`` when the two rotations differ by more than ``max_deg``
    degrees (the two disagree; a mean of them would be neither)."""
    a, b = np.asarray(pose_a, np.float64), np.asarray(pose_b, np.float64)
    rel, _ = cv2.Rodrigues(a[:3, :3].T @ b[:3, :3])
    if np.degrees(float(np.linalg.norm(rel))) > max_deg:
        return None
    out = a.copy()
    out[:3, :3] = a[:3, :3] @ cv2.Rodrigues(0.5 * rel)[0]
    return out
