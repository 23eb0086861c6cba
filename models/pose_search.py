"""Pose search over corner identities: the pose whose projected cuboid the belief maps support best.

DOPE-style decoding takes, for each corner, the strongest peak of that corner's belief map.
A network that has learnt *where* the cuboid's corners are but not yet *which* corner is which
(every corner map fires on every corner; typical early in training, and for objects whose
faces look alike) then gives all eight corners the same image point, and PnP collapses.

The search instead treats the corner peaks of an instance as an unlabelled point set:

1. **Points.** The corner peaks of every corner map that joined the instance (through the
   affinity fields) are pooled; points closer than ``merge_px`` are merged (the stronger
   stays). At most ``max_points`` of the strongest are kept.
2. **Hypotheses.** For every unordered pair of pooled points ``(q_a, q_b)`` and every
   directed cuboid edge ``(c_i, c_j)`` (24), P3P on ``{c_i -> q_a, c_j -> q_b, centre ->
   centroid peak}`` gives up to four poses (all problems at once: :mod:`evtrack.models.p3p`;
   the edge ``(c_j, c_i)`` covers the pair's other order).
3. **Score.** Each pose projects the 8 corners and the centre; the score is the sum over
   corners of ``(1 - w) * max_k B_k(p_c) + w * B_c(p_c)`` (``B_k``: corner map ``k`` sampled
   bilinearly at the projection ``p_c``; ``w = identity_weight``) plus ``B_centroid(p_centre)``.
   The first term rewards the geometry whatever the identities; the second picks, among
   poses equal up to the cuboid's symmetries, the one whose corners land on their own maps.
4. The best pose is returned for refinement; the caller matches each projected corner to the
   nearest pooled point (within ``gate_px``) and refines on those.

With maps whose identities are clear, the search and the strongest-peak decoding give the
same pose. Cost: ``P (P - 1) / 2 * 24`` P3P problems for ``P`` pooled points (``P <=
max_points``): ~10 ms for eight points on one CPU thread.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from evtrack.models.cuboid import CENTROID_INDEX, Cuboid
from evtrack.models.p3p import bearings, solve_p3p

__all__ = ["SearchResult", "cuboid_edges", "merge_points", "search_pose", "sample_maps"]


@dataclass
class SearchResult:
    """The best pose of :func:`search_pose`.

    Attributes:
        rvec, tvec: (3, 1) float64 OpenCV rotation vector and translation (metres).
        score: its evidence (see the module docstring), in ``[0, 9]`` for maps in ``[0, 1]``.
        hypotheses: how many poses were scored.
    """

    rvec: np.ndarray
    tvec: np.ndarray
    score: float
    hypotheses: int


def cuboid_edges(cuboid: Cuboid) -> np.ndarray:
    """(24, 2) int: the directed edges of the cuboid (corner pairs differing in one axis)."""
    pts = cuboid.points()[:CENTROID_INDEX]
    diff = np.abs(pts[:, None, :] - pts[None, :, :]) > 1e-12
    i, j = np.nonzero(diff.sum(axis=2) == 1)
    return np.stack([i, j], axis=1)


def merge_points(points: np.ndarray, merge_px: float) -> np.ndarray:
    """Greedy merge of (N, 3) ``(x, y, score)`` points, strongest first; returns (M, 3)."""
    order = np.argsort(-points[:, 2], kind="stable")
    kept: list[np.ndarray] = []
    for p in points[order]:
        if all(np.hypot(*(p[:2] - q[:2])) >= merge_px for q in kept):
            kept.append(p)
    return np.array(kept).reshape(-1, 3)


def sample_maps(maps: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Bilinear samples of (C, h, w) maps at grid points; outside the maps the value is 0.

    Args:
        maps: (C, h, w).
        gx, gy: (...,) grid coordinates (cells), same shape.

    Returns:
        (..., C) float64.
    """
    _, h, w = maps.shape
    inside = (gx >= 0) & (gx <= w - 1) & (gy >= 0) & (gy <= h - 1)
    x = np.clip(np.nan_to_num(gx, nan=-1.0), 0, w - 1)
    y = np.clip(np.nan_to_num(gy, nan=-1.0), 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 1)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay = (x - x0)[..., None], (y - y0)[..., None]
    f = np.moveaxis(maps.astype(np.float64), 0, -1)  # (h, w, C)
    top = f[y0, x0] * (1 - ax) + f[y0, x1] * ax
    bottom = f[y1, x0] * (1 - ax) + f[y1, x1] * ax
    return np.where(inside[..., None], top * (1 - ay) + bottom * ay, 0.0)


def _project(obj: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
             dist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations, (N, 3) translations -> (N, P, 2) pixels and (N, P) depths."""
    P = np.einsum("nij,pj->npi", R, obj) + t[:, None, :]
    z = P[..., 2]
    if dist is None or not np.any(dist):
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([K[0, 0] * P[..., 0] / z + K[0, 1] * P[..., 1] / z + K[0, 2],
                           K[1, 1] * P[..., 1] / z + K[1, 2]], axis=-1)
        return uv, z
    # every pose's points are already in the camera frame: one call projects them all
    zero = np.zeros(3)
    uv, _ = cv2.projectPoints(P.reshape(-1, 3), zero, zero, K, np.asarray(dist, np.float64))
    return uv.reshape(P.shape[:2] + (2,)), z


def search_pose(
    points: np.ndarray,
    centroid: np.ndarray,
    belief: np.ndarray,
    cuboid: Cuboid,
    K: np.ndarray,
    dist: np.ndarray | None,
    to_grid,
    *,
    identity_weight: float = 0.5,
    max_points: int = 8,
) -> SearchResult | None:
    """The pose best supported by the belief maps (see the module docstring).

    Args:
        points: (N, 3) pooled corner points ``(x, y, score)`` in pixels of the image ``K``
            describes (already merged).
        centroid: (2,) the instance's centroid peak, same pixels.
        belief: (9, h, w) the network's belief maps.
        cuboid: the object's cuboid; K: (3, 3); dist: distortion coefficients or ``None``.
        to_grid: maps (..., 2) pixels of ``K``'s image to (..., 2) belief-grid coordinates.
        identity_weight: ``w`` of the score.
        max_points: at most this many of the strongest points make hypotheses.

    Returns:
        The best hypothesis in front of the camera, or ``None`` (fewer than two points, or no
        P3P solution).
    """
    pts = points[np.argsort(-points[:, 2], kind="stable")][:max_points]
    if len(pts) < 2:
        return None
    obj = cuboid.points()
    K = np.asarray(K, dtype=np.float64)
    edges = cuboid_edges(cuboid)
    # every unordered pair of points with every directed edge: the ordered pair (b, a) with
    # the edge (j, i) is the same problem as (a, b) with (i, j)
    a, b = np.triu_indices(len(pts), k=1)
    pair = np.repeat(np.arange(len(a)), len(edges))
    edge = np.tile(np.arange(len(edges)), len(a))
    rays = bearings(np.concatenate([pts[:, :2], np.asarray(centroid, np.float64)[None]]), K, dist)
    problem_rays = np.stack([rays[a[pair]], rays[b[pair]],
                             np.broadcast_to(rays[-1], (len(pair), 3))], axis=1)
    problem_points = np.stack([obj[edges[edge, 0]], obj[edges[edge, 1]],
                               np.broadcast_to(obj[CENTROID_INDEX], (len(edge), 3))], axis=1)
    R, t, _ = solve_p3p(problem_points, problem_rays)
    if len(R) == 0:
        return None
    uv, z = _project(obj, R, t, K, dist)
    grid = to_grid(uv)  # (N, 9, 2)
    samples = sample_maps(belief, grid[..., 0], grid[..., 1])  # (N, 9, 9)
    corners = samples[:, :CENTROID_INDEX, :CENTROID_INDEX]  # (N, corner c, map k)
    own = np.diagonal(corners, axis1=1, axis2=2)  # (N, 8): B_c(p_c)
    geometry = corners.max(axis=2)
    score = ((1 - identity_weight) * geometry + identity_weight * own).sum(axis=1)
    score = score + samples[:, CENTROID_INDEX, CENTROID_INDEX]
    valid = (z > 0).all(axis=1) & np.isfinite(score)
    if not valid.any():
        return None
    score = np.where(valid, score, -np.inf)
    best = int(np.argmax(score))
    rvec, _ = cv2.Rodrigues(R[best])
    return SearchResult(rvec=rvec.reshape(3, 1), tvec=t[best].reshape(3, 1).copy(),
                        score=float(score[best]), hypotheses=len(R))

