"""Independent ray casting with trimesh's pure-python triangle intersector, for the sim tests.

trimesh's broad phase wants ``rtree``; a brute-force box query stands in for it here (same
narrow phase: ray/plane intersection and barycentric inside test).
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.ray.ray_triangle import ray_triangle_id

from evtrack.camera import PinholeCamera


class _BruteForceBoxes:
    """The two methods of an ``rtree.Index`` that trimesh's ray caster uses."""

    def __init__(self, triangles: np.ndarray) -> None:
        self.lo, self.hi = triangles.min(axis=1), triangles.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(0), self.hi.max(0)])

    def intersection(self, box) -> np.ndarray:
        lo, hi = np.asarray(box[:3]), np.asarray(box[3:])
        return np.nonzero(((self.hi >= lo) & (self.lo <= hi)).all(axis=1))[0]


def pixel_rays(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """(N, 2) pixel centres -> (N, 3) camera-frame ray directions with z = 1."""
    return np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy,
                     np.ones(len(uv))], -1)


def raycast(mesh: trimesh.Trimesh, pose: np.ndarray, camera: PinholeCamera, uv: np.ndarray):
    """First hits of the rays through pixels ``uv`` with ``mesh`` at object->camera ``pose``.

    Returns:
        depth (N,) camera z in metres (NaN where the ray misses), points (N, 3) object frame,
        triangle index (N,) (-1 where it misses).
    """
    d_cam = pixel_rays(camera, uv)
    R, t = pose[:3, :3], pose[:3, 3]
    origins = np.tile(-R.T @ t, (len(uv), 1))
    dirs = d_cam @ R  # R^T d for each row
    triangles = np.asarray(mesh.triangles, np.float64)
    tri_idx, ray_idx, hits = ray_triangle_id(
        triangles, origins, dirs, triangles_normal=np.asarray(mesh.face_normals),
        tree=_BruteForceBoxes(triangles), multiple_hits=False)
    depth = np.full(len(uv), np.nan)
    points = np.full((len(uv), 3), np.nan)
    tris = np.full(len(uv), -1)
    if len(ray_idx) == 0:
        return depth, points, tris
    hits = np.asarray(hits).reshape(-1, 3)
    cam_pts = hits @ R.T + t
    depth[ray_idx] = cam_pts[:, 2]
    points[ray_idx] = hits
    tris[ray_idx] = tri_idx
    return depth, points, tris


def hit_uv(mesh: trimesh.Trimesh, uv_attr: np.ndarray, points: np.ndarray,
           tris: np.ndarray) -> np.ndarray:
    """Texture coordinates at hit points by barycentric interpolation of the face's UVs."""
    tri_pts = mesh.triangles[tris]
    bary = trimesh.triangles.points_to_barycentric(tri_pts, points)
    return np.einsum("nk,nkj->nj", bary, uv_attr[mesh.faces[tris]])
