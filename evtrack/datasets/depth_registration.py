"""Depth frames of a separate depth sensor registered to the colour camera.

An RGB-D camera such as the RealSense D435 records depth with its own lens: each depth pixel
is a point seen by the depth camera. The tracker wants depth registered to the colour camera
(``depth[v, u]`` is the depth of the colour pixel ``(u, v)``). Registration unprojects every
valid depth pixel, moves the point into the colour camera and splats its depth onto the colour
pixels it covers, keeping the nearest surface where several land on one pixel.
"""

from __future__ import annotations

import numpy as np

__all__ = ["register_depth"]


def register_depth(depth_m: np.ndarray, K_depth: np.ndarray, K_colour: np.ndarray,
                   T_colour_depth: np.ndarray, colour_size: tuple[int, int],
                   splat: int = 2) -> np.ndarray:
    """Depth of the colour camera's pixels from a depth camera's frame.

    Both cameras are pinhole cameras without distortion (the D435's depth and colour streams
    as calibrated). A depth point lands on the colour pixel ``floor(u), floor(v)`` and, with
    ``splat=2``, also on the three pixels to its right and below, which closes the holes a
    depth camera with a lower focal length than the colour camera leaves (each depth pixel
    covers more than one colour pixel). Where several points land on a pixel the nearest wins.

    Args:
        depth_m: (Hd, Wd) float depth of the depth camera, metres along its optical axis;
            0 or NaN = missing.
        K_depth, K_colour: (3, 3) intrinsics, pixels.
        T_colour_depth: (4, 4) maps points of the depth camera frame into the colour camera
            frame, metres.
        colour_size: ``(width, height)`` of the colour image, pixels.
        splat: 1 (nearest pixel only) or 2 (a 2x2 footprint).

    Returns:
        (H, W) float32 depth along the colour camera's optical axis, metres, 0 where no depth
        point landed.

    Raises:
        ValueError: a depth frame that is not 2-D, or ``splat`` not 1 or 2.
    """
    depth = np.asarray(depth_m, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth frame must be (H, W), got shape {depth.shape}")
    if splat not in (1, 2):
        raise ValueError(f"splat must be 1 or 2, got {splat}")
    width, height = int(colour_size[0]), int(colour_size[1])
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u]
    K_d = np.asarray(K_depth, np.float64)
    points = np.stack([(u - K_d[0, 2]) * z / K_d[0, 0], (v - K_d[1, 2]) * z / K_d[1, 1], z], -1)
    T = np.asarray(T_colour_depth, np.float64)
    points = points @ T[:3, :3].T + T[:3, 3]
    front = points[:, 2] > 0
    points = points[front]
    K_c = np.asarray(K_colour, np.float64)
    zc = points[:, 2]
    uc = K_c[0, 0] * points[:, 0] / zc + K_c[0, 2]
    vc = K_c[1, 1] * points[:, 1] / zc + K_c[1, 2]
    if splat == 1:
        offsets = ((0, 0),)
        uc, vc = np.floor(uc + 0.5), np.floor(vc + 0.5)
    else:
        offsets = ((0, 0), (1, 0), (0, 1), (1, 1))
        uc, vc = np.floor(uc), np.floor(vc)
    out = np.full(height * width, np.inf)
    for du, dv in offsets:
        col, row = uc + du, vc + dv
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        index = row[inside].astype(np.int64) * width + col[inside].astype(np.int64)
        np.minimum.at(out, index, zc[inside])
    out[np.isinf(out)] = 0.0
    return out.reshape(height, width).astype(np.float32)
