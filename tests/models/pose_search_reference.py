"""Brute-force reference of the pose search (:func:`evtrack.models.pose_search.search_pose`):
one ``cv2.solveP3P`` per ordered pair of points and directed cuboid edge, every solution
scored as ``search_pose`` describes. ``tests/models/test_p3p.py`` pins the search against it
and ``benchmarks/bench_pose_speed.py`` times the two side by side."""

from __future__ import annotations

import cv2
import numpy as np

from evtrack.models.cuboid import CENTROID_INDEX
from evtrack.models.pose_search import cuboid_edges, sample_maps


def opencv_search(points, centroid, belief, cuboid, K, to_grid, identity_weight=0.5):
    """``(R (3, 3), t (3,), score, solutions)``: the best-scoring pose over every P3P solution
    of the points ``(P, 3)`` (pixels, confidence) and the ``centroid`` pixel; ``-inf`` scores
    for poses with a cuboid point behind the camera; ties to the first solution."""
    obj = cuboid.points()
    rotations, translations = [], []
    for a in range(len(points)):
        for b in range(len(points)):
            if a == b:
                continue
            img = np.array([points[a, :2], points[b, :2], centroid])
            for i, j in cuboid_edges(cuboid):
                o = np.ascontiguousarray(obj[[i, j, CENTROID_INDEX]])
                n, rvecs, tvecs = cv2.solveP3P(o, img, K, None, flags=cv2.SOLVEPNP_P3P)
                for k in range(n):
                    rotations.append(cv2.Rodrigues(rvecs[k])[0])
                    translations.append(tvecs[k].reshape(3))
    R, t = np.array(rotations), np.array(translations)
    cam = np.einsum("nij,pj->npi", R, obj) + t[:, None]
    uv = cam[..., :2] / cam[..., 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    g = to_grid(uv)
    s = sample_maps(belief, g[..., 0], g[..., 1])
    corners = s[:, :CENTROID_INDEX, :CENTROID_INDEX]
    score = ((1 - identity_weight) * corners.max(axis=2)
             + identity_weight * np.diagonal(corners, axis1=1, axis2=2)).sum(1)
    score = np.where((cam[..., 2] > 0).all(axis=1),
                     score + s[:, CENTROID_INDEX, CENTROID_INDEX], -np.inf)
    best = int(np.argmax(score))
    return R[best], t[best], float(score[best]), len(R)
