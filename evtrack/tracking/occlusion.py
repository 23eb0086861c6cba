"""Where other tracked objects hide an object: the pixels its frame alignments leave out.

With several objects in one stream (:class:`~evtrack.tracking.multi.MultiTracker`), a frame
shows an object partly behind nearer ones. Its depth alignment (ICP) and appearance alignment
compare the whole object with the frame; the pixels the nearer objects cover hold the
occluders' depth and texture, not the object's. :class:`Occluders` holds the nearer objects'
predicted poses over one assignment window, and :func:`occluder_mask` rasterises their convex
silhouettes in the camera of a frame, for the alignments to leave those pixels out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.tracking.event_gate import moved_pose
from evtrack.tracking.silhouette import MIN_DEPTH_M

__all__ = ["Occluder", "Occluders", "occluder_mask"]


@dataclass(frozen=True)
class Occluder:
    """A nearer object over a window: its pose at ``t0_us`` (event camera), its twist, and
    its silhouette's vertices (the convex hull's, object frame)."""

    pose: np.ndarray
    twist: np.ndarray
    t0_us: int
    vertices: np.ndarray

    def pose_at(self, t_us: int) -> np.ndarray:
        """(4, 4) its pose at ``t_us``, moved from ``t0_us`` by its twist."""
        if t_us == self.t0_us or not np.isfinite(self.twist).all():
            return self.pose
        return moved_pose(self.pose, self.twist, (t_us - self.t0_us) * 1e-6)


@dataclass(frozen=True)
class Occluders:
    """The objects nearer than the tracked one, as predicted over one window."""

    objects: tuple[Occluder, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.objects)

    def mask(self, t_us: int, camera: PinholeCamera, T_camera_event: np.ndarray) -> np.ndarray:
        """(H, W) bool, the pixels of ``camera`` (its frame reached from the event camera's by
        ``T_camera_event``) that the occluders cover at ``t_us``."""
        poses = [T_camera_event @ o.pose_at(t_us) for o in self.objects]
        return occluder_mask(camera, poses, [o.vertices for o in self.objects])


def occluder_mask(camera: PinholeCamera, poses: list[np.ndarray],
                  vertices: list[np.ndarray]) -> np.ndarray:
    """The union of the convex silhouettes of objects at ``poses`` (object -> ``camera``),
    as an (H, W) bool mask of ``camera``'s pixels. An object with a vertex closer to the
    camera plane than :data:`~evtrack.tracking.silhouette.MIN_DEPTH_M` covers nothing (its
    projection is not meaningful)."""
    mask = np.zeros((camera.height, camera.width), np.uint8)
    for T, V in zip(poses, vertices, strict=True):
        T = np.asarray(T, np.float64)
        if not np.isfinite(T).all():
            continue
        P = np.asarray(V, np.float64) @ T[:3, :3].T + T[:3, 3]
        if (P[:, 2] < MIN_DEPTH_M).any():
            continue
        uv = camera.project(torch.from_numpy(P)).numpy()  # the lens's distortion included
        hull = cv2.convexHull(uv.astype(np.float32))
        cv2.fillConvexPoly(mask, np.round(hull.reshape(-1, 2)).astype(np.int32), 1)
    return mask.astype(bool)
