"""How far a depth frame lies from an object's mesh at a pose, without a renderer.

Two parts of the tracker ask the same question of a sensor depth frame: by how much does the
object's visible surface at a given pose sit in front of or behind what the sensor measured?
:class:`~evtrack.tracking.pose_alignment.PoseRayAligner` moves the pose network's poses by that
offset,
:class:`~evtrack.tracking.depth_range.DepthRange` turns it into a range measurement for the pose
filter.

:class:`SurfaceDepthSampler` answers it with a point z-buffer: area-sampled surface points of
the mesh, back faces culled, are projected through the camera (with its distortion) into
square image cells; each cell keeps its nearest point, and that point's depth is compared
with the sensor's at the point's own pixel (not the cell's centre, which biases tilted faces).
:func:`robust_offset` reduces the per-cell offsets to one: the median of the cells within
``inlier_m`` of the median, or the reason there is none. Projecting 3000 points costs ~1-2 ms
per frame on one CPU core at 640x480, about a tenth of a render at half resolution, and needs
no OpenGL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from evtrack.camera import PinholeCamera

__all__ = ["RobustOffset", "SurfaceDepthSampler", "robust_offset", "sample_surface"]


def sample_surface(mesh, n_points: int = 3000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n_points`` surface points of ``mesh`` (anything with ``vertices`` (V, 3) and
    ``faces`` (F, 3), e.g. :class:`evtrack.sim.objects.ObjectMesh`), area-weighted, with a
    fixed ``seed`` (trimesh's sampler): ``(points (N, 3), outward unit normals (N, 3))``,
    object frame."""
    import trimesh

    tm = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64),
                         np.asarray(mesh.faces, np.int64), process=False)
    points, faces = trimesh.sample.sample_surface(tm, n_points, seed=seed)
    return points, tm.face_normals[faces]


class SurfaceDepthSampler:
    """Per-cell offsets between a depth frame and the object's surface at a pose.

    Args:
        points: (N, 3) surface samples of the object, object frame, metres.
        normals: (N, 3) their outward unit normals (back-facing points are skipped).
        camera: the camera of the depth maps given to :meth:`offsets` (with distortion,
            points are projected through it).
        cell_px: side of the square image cells, pixels (each keeps its nearest point).

    Raises:
        ValueError: points and normals of different or wrong shapes, or ``cell_px < 1``.
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, camera: PinholeCamera,
                 cell_px: int = 4) -> None:
        points = np.asarray(points, np.float64)
        normals = np.asarray(normals, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
            raise ValueError(f"points and normals must be (N, 3) each, got {points.shape} and "
                             f"{normals.shape}")
        if cell_px < 1:
            raise ValueError(f"cell_px must be >= 1, got {cell_px}")
        self.points, self.normals = points, normals
        self.camera = camera
        self.cell_px = int(cell_px)

    @classmethod
    def from_mesh(cls, mesh, camera: PinholeCamera, n_points: int = 3000, seed: int = 0,
                  cell_px: int = 4) -> SurfaceDepthSampler:
        """A sampler on :func:`sample_surface` of ``mesh``."""
        return cls(*sample_surface(mesh, n_points, seed), camera, cell_px)

    def offsets(self, depth: np.ndarray, pose: np.ndarray) -> np.ndarray | None:
        """Sensor-minus-model depth offsets (m) of the cells with a visible surface point and
        a valid sensor depth.

        Args:
            depth: (H, W) metres in ``camera`` (NaN or <= 0: missing).
            pose: (4, 4) float64 object-to-camera transform.

        Returns:
            (K,) float64 offsets, cells in no particular order; ``None`` when a visible point
            lies behind the camera (or none is visible).
        """
        R, t = pose[:3, :3], pose[:3, 3]
        P = self.points @ R.T + t
        facing = np.einsum("ij,ij->i", self.normals @ R.T, P) < 0
        P = P[facing]
        z = P[:, 2]
        if not len(z) or z.min() <= 1e-3:
            return None
        u, v = self.camera.project(torch.from_numpy(P)).numpy().T
        h, w = depth.shape
        px, py = np.floor(u + 0.5).astype(np.int64), np.floor(v + 0.5).astype(np.int64)
        inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        px, py, z = px[inside], py[inside], z[inside]
        cols = -(-w // self.cell_px)
        key = (py // self.cell_px) * cols + px // self.cell_px
        order = np.lexsort((z, key))  # by cell, nearest first
        first = order[np.r_[True, key[order][1:] != key[order][:-1]]] if len(key) else order
        # each cell's nearest point, compared with the sensor at that point's own pixel
        px, py, z = px[first], py[first], z[first]
        sensor = depth[py, px].astype(np.float64)
        valid = np.isfinite(sensor) & (sensor > 0)
        return sensor[valid] - z[valid]


@dataclass
class RobustOffset:
    """The robust offset of a set of per-cell offsets, or the reason there is none.

    Attributes:
        offset: median of the inliers (m); NaN without one.
        median: median of all cells (m); NaN without cells.
        cells: cells given.
        inliers: (I,) the offsets within ``inlier_m`` of the median (empty when too few cells).
        reason: ``""``, ``"too few cells"`` or ``"too few agreeing"``.
    """

    offset: float
    median: float
    cells: int
    inliers: np.ndarray
    reason: str = ""

    @property
    def ok(self) -> bool:
        return not self.reason


def robust_offset(diff: np.ndarray, inlier_m: float, min_cells: int,
                  min_inlier_fraction: float) -> RobustOffset:
    """The median of the offsets within ``inlier_m`` of their median.

    Args:
        diff: (K,) per-cell offsets (m), e.g. :meth:`SurfaceDepthSampler.offsets`.
        inlier_m: cells this close to the median are inliers.
        min_cells: fewest cells, and fewest inliers, for an offset.
        min_inlier_fraction: fewest inliers as a share of the cells. Below it the cells
            disagree: the pose is off across the viewing ray or turned, so part of the
            surface falls on the background.
    """
    cells = len(diff)
    if cells < min_cells:
        return RobustOffset(float("nan"), float("nan"), cells, diff[:0], "too few cells")
    median = float(np.median(diff))
    agreeing = diff[np.abs(diff - median) <= inlier_m]
    if len(agreeing) < min_cells or len(agreeing) < min_inlier_fraction * cells:
        return RobustOffset(float("nan"), median, cells, agreeing, "too few agreeing")
    return RobustOffset(float(np.median(agreeing)), median, cells, agreeing)
