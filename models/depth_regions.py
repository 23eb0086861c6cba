"""Where in a depth frame an object of a known size may be: regions that stand out of the
scene's dominant planes, each with a box for
:func:`~evtrack.models.mesh_registration.register_mesh`.

A table, a wall, a floor: most of a tabletop or lab scene's depth pixels lie on a few planes,
and an object stands in front of them. :func:`object_regions`

1. back-projects the valid depth pixels through the camera (its lens distortion included,
   :meth:`~evtrack.camera.PinholeCamera.unproject`) and, on a subsample, finds up to ``max_planes``
   dominant planes by RANSAC (each holding at least ``min_plane_share`` of the valid pixels;
   the fit refined by least squares on its inliers);
2. leaves out every pixel within ``plane_tolerance_m`` of such a plane or behind it (seen from
   the camera), and every pixel without depth;
3. splits what is left into connected regions (after a morphological opening that cuts thin
   bridges and specks), and keeps those whose size fits the object: seen at the region's
   median depth ``z``, an object of radius ``r`` spans at most ``2 r f / z`` pixels, so a
   region's longer side must lie within ``size_range`` times that, and it must hold
   ``min_pixels`` pixels;
4. returns them best first: the nearer the region's longer side to ``expected_fill`` of the
   object's span (a whole object seen from one side fills about that share of its bounding
   sphere's), the better.

It finds where something of the object's size stands out of the planes; which of the regions
is the object is for the registration to say (its colour image fit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError

__all__ = ["DepthRegion", "RegionConfig", "dominant_planes", "object_regions"]


@dataclass(frozen=True)
class RegionConfig:
    """Settings of :func:`object_regions`.

    Attributes:
        max_planes: dominant planes removed at most.
        min_plane_share: a plane is removed only when it holds at least this share of the
            valid depth pixels.
        plane_tolerance_m: pixels within this of a removed plane count as on it (m).
        ransac_iterations: plane hypotheses per plane.
        stride: every ``stride``-th pixel in each direction feeds the plane search.
        size_range: a region's longer side in pixels, over the object's largest projected
            span at the region's depth, must lie in this range.
        expected_fill: the share of that span a whole object seen from one side fills (the
            regions are ranked by how near they are to it).
        min_pixels: the fewest pixels of a region.
        margin: the boxes are grown by this share of their size on every side.
        seed: seed of the plane search.
    """

    max_planes: int = 3
    min_plane_share: float = 0.2
    plane_tolerance_m: float = 0.015
    ransac_iterations: int = 200
    stride: int = 4
    size_range: tuple[float, float] = (0.3, 1.5)
    expected_fill: float = 0.8
    min_pixels: int = 30
    margin: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        lo, hi = self.size_range
        if not (0 < lo < hi and self.plane_tolerance_m > 0 and self.stride >= 1
                and self.ransac_iterations >= 1 and 0 < self.min_plane_share <= 1
                and self.max_planes >= 0 and self.min_pixels >= 1 and self.margin >= 0):
            raise ConfigError(f"depth regions: invalid settings {self}")


@dataclass(frozen=True)
class DepthRegion:
    """One region that stands out of the planes.

    Attributes:
        box: ``(u0, v0, u1, v1)`` pixels (``u1``, ``v1`` exclusive), grown by the margin and
            clipped to the image.
        pixels: the region's pixels.
        depth_m: its median depth (m).
        fill: its longer side over the object's largest projected span at that depth.
    """

    box: tuple[int, int, int, int]
    pixels: int
    depth_m: float
    fill: float


def dominant_planes(points: np.ndarray, config: RegionConfig | None = None
                    ) -> list[tuple[np.ndarray, float]]:
    """Up to ``max_planes`` planes ``n · X = d`` (unit ``n``, oriented so that the camera's
    origin lies on the positive side: ``d < 0``) each holding ``min_plane_share`` of
    ``points`` (N, 3), by RANSAC, the largest first; a plane's inliers are left out of the
    search for the next."""
    cfg = config or RegionConfig()
    rng = np.random.default_rng(cfg.seed)
    pts = np.asarray(points, np.float64)
    total = len(pts)
    planes: list[tuple[np.ndarray, float]] = []
    rest = pts
    while len(planes) < cfg.max_planes and len(rest) >= 3:
        idx = rng.integers(0, len(rest), size=(cfg.ransac_iterations, 3))
        a, b, c = rest[idx[:, 0]], rest[idx[:, 1]], rest[idx[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        if not good.any():
            break
        n = n[good] / norm[good, None]
        d = np.einsum("ij,ij->i", n, a[good])
        counts = (np.abs(rest @ n.T - d) < cfg.plane_tolerance_m).sum(0)
        k = int(np.argmax(counts))
        if counts[k] < cfg.min_plane_share * total:
            break
        inliers = np.abs(rest @ n[k] - d[k]) < cfg.plane_tolerance_m
        sel = rest[inliers]  # least squares on the inliers: the smallest principal direction
        centre = sel.mean(0)
        normal = np.linalg.svd(sel - centre, full_matrices=False)[2][-1]
        offset = float(normal @ centre)
        if offset > 0:
            normal, offset = -normal, -offset
        planes.append((normal, offset))
        rest = rest[np.abs(rest @ normal - offset) >= cfg.plane_tolerance_m]
    return planes


def object_regions(depth: np.ndarray, camera: PinholeCamera, radius_m: float,
                   config: RegionConfig | None = None) -> list[DepthRegion]:
    """The regions of ``depth`` where an object of radius ``radius_m`` may stand, best first
    (see the module docstring).

    Args:
        depth: (H, W) metres registered to ``camera`` (NaN or <= 0: missing).
        camera: the depth's camera.
        radius_m: the object's radius (its farthest surface point from its bounding box's
            centre, m).
        config: settings.

    Raises:
        ValueError: a depth of the wrong shape, a radius that is not positive, or no valid
            depth pixel.
    """
    cfg = config or RegionConfig()
    depth = np.asarray(depth, np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth regions: depth must be ({camera.height}, {camera.width}), got "
                         f"{depth.shape}")
    if not radius_m > 0:
        raise ValueError(f"depth regions: the object's radius must be > 0 m, got {radius_m}")
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise ValueError("depth regions: the depth frame has no valid pixel (all zero or NaN)")
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    uv = torch.from_numpy(np.stack([u, v], -1).astype(np.float64))
    z = torch.from_numpy(np.where(valid, depth, np.nan))
    X = camera.unproject(uv, z).numpy()  # (H, W, 3) m; NaN where no depth
    stride = cfg.stride
    points = X[::stride, ::stride][valid[::stride, ::stride]]
    keep = valid.copy()
    for normal, offset in dominant_planes(points, cfg):
        with np.errstate(invalid="ignore"):
            keep &= (X @ normal - offset) >= cfg.plane_tolerance_m  # in front of the plane
    mask = cv2.morphologyEx(keep.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    f = 0.5 * (camera.fx + camera.fy)
    regions = []
    for k in range(1, count):
        x0, y0, w, h, area = (int(s) for s in stats[k])
        if area < cfg.min_pixels:
            continue
        zk = float(np.median(depth[labels == k]))
        span = 2.0 * radius_m * f / zk
        fill = max(w, h) / span
        if not cfg.size_range[0] <= fill <= cfg.size_range[1]:
            continue
        gu, gv = int(math.ceil(cfg.margin * w)), int(math.ceil(cfg.margin * h))
        box = (max(0, x0 - gu), max(0, y0 - gv), min(W, x0 + w + gu), min(H, y0 + h + gv))
        regions.append(DepthRegion(box, area, zk, fill))
    regions.sort(key=lambda r: abs(math.log(r.fill / cfg.expected_fill)))
    return regions
