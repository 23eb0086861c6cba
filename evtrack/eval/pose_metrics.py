"""Single-frame pose accuracy: ADD, ADD-S and their pass rates (Hinterstoisser et al. 2012).

* ADD: mean distance between the model points moved by the estimated and by the true pose.
* ADD-S: for symmetric objects, the mean distance from each truly-posed point to the *nearest*
  estimated-posed point.
A pose passes when the distance is below ``fraction`` (default 10%) of the object's diameter.

:func:`add_distance` and :func:`adds_distance` score one pose; :func:`add_distances` and
:func:`adds_distances` score many at once (the same numbers, vectorised over the poses).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["add_distance", "adds_distance", "add_distances", "adds_distances", "object_diameter",
           "GROSS_MISS_M", "PoseAccuracy", "pose_accuracy", "pooled_rate_interval"]


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def add_distance(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    """ADD in metres: mean ``|T_est p - T_true p|`` over the model points (M, 3)."""
    return float(np.linalg.norm(_apply(T_est, points) - _apply(T_true, points), axis=1).mean())


def adds_distance(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    """ADD-S in metres: mean distance from each true point to its nearest estimated point."""
    tree = cKDTree(_apply(T_est, points))
    dist, _ = tree.query(_apply(T_true, points), k=1)
    return float(dist.mean())


_CHUNK = 256
"""Poses (or hull points) handled at once by the vectorised functions: bounds their memory to
``_CHUNK x M x 3`` float64 values."""


def add_distances(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> np.ndarray:
    """ADD of many poses: (N, 4, 4), (N, 4, 4), (M, 3) model points -> (N,) metres.

    ``ADD_i = mean_p |(R_est,i - R_true,i) p + (t_est,i - t_true,i)|``, as :func:`add_distance`
    per pose, in chunks of poses.
    """
    T_est, T_true = np.asarray(T_est, np.float64), np.asarray(T_true, np.float64)
    points = np.asarray(points, np.float64)
    out = np.empty(len(T_est))
    for i in range(0, len(T_est), _CHUNK):
        dR = T_est[i:i + _CHUNK, :3, :3] - T_true[i:i + _CHUNK, :3, :3]
        dt = T_est[i:i + _CHUNK, :3, 3] - T_true[i:i + _CHUNK, :3, 3]
        diff = np.einsum("nij,mj->nmi", dR, points) + dt[:, None, :]
        out[i:i + _CHUNK] = np.linalg.norm(diff, axis=-1).mean(axis=1)
    return out


def adds_distances(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray,
                   workers: int = 1, targets: np.ndarray | None = None) -> np.ndarray:
    """ADD-S of many poses: (N, 4, 4), (N, 4, 4), (M, 3) model points -> (N,) metres.

    The mean over the points ``p`` of ``min_q |T_true p - T_est q|``, ``q`` over ``targets``.
    A rigid motion keeps distances, so that is ``min_q |T_est⁻¹ T_true p - q|``: one k-d tree
    of the targets serves every pose, queried with the points moved by ``T_est⁻¹ T_true``.
    With ``targets`` left out, the same numbers as :func:`adds_distance` per pose.

    Args:
        workers: threads of the k-d tree queries (``-1``: all cores).
        targets: (V, 3) the model points searched for the nearest (default: ``points``); e.g.
            all the vertices of a mesh while ``points`` are some of them, which estimates the
            ADD-S of all the vertices at the cost of ``M`` queries per pose.
    """
    T_est, T_true = np.asarray(T_est, np.float64), np.asarray(T_true, np.float64)
    points = np.asarray(points, np.float64)
    tree = cKDTree(points if targets is None else np.asarray(targets, np.float64))
    out = np.empty(len(T_est))
    for i in range(0, len(T_est), _CHUNK):
        R_e, t_e = T_est[i:i + _CHUNK, :3, :3], T_est[i:i + _CHUNK, :3, 3]
        R_t, t_t = T_true[i:i + _CHUNK, :3, :3], T_true[i:i + _CHUNK, :3, 3]
        # T_est⁻¹ T_true = [R_eᵀ R_t | R_eᵀ (t_t - t_e)]
        R = np.einsum("nji,njk->nik", R_e, R_t)
        t = np.einsum("nji,nj->ni", R_e, t_t - t_e)
        moved = np.einsum("nij,mj->nmi", R, points) + t[:, None, :]
        dist, _ = tree.query(moved.reshape(-1, 3), k=1, workers=workers)
        out[i:i + _CHUNK] = dist.reshape(len(R), len(points)).mean(axis=1)
    return out


def object_diameter(points: np.ndarray) -> float:
    """Largest distance between two model points (M, 3), metres (exact, O(H²) on the hull of
    H points, in chunks of rows so that a large hull stays within memory)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import cdist

    points = np.asarray(points, np.float64)
    hull = points[ConvexHull(points).vertices] if len(points) > 4 else points
    return float(max(cdist(hull[i:i + _CHUNK], hull).max() for i in range(0, len(hull), _CHUNK)))


GROSS_MISS_M = 0.10
"""Position error (m) above which a detection counts as a gross miss."""


@dataclass
class PoseAccuracy:
    """Accuracy of single-frame pose estimates against ground truth.

    Attributes:
        frames: frames evaluated; detected: frames with at least one detection.
        detection_rate: detected / frames.
        median_translation_cm, median_rotation_deg: over detected frames (NaN if none).
        add_pass, adds_pass: fraction of *all* frames whose ADD / ADD-S is below the
            threshold (a missed detection fails).
        threshold_m: ``fraction`` x diameter.
        gross_miss_rate: fraction of *detected* frames whose position is more than
            ``gross_miss_m`` off: the network found something else (a distractor), or the
            object at a badly wrong range. The medians hide these; a tracker must reject them.
        gross_miss_m: that threshold, metres (:data:`GROSS_MISS_M` by default).
    """

    frames: int
    detected: int
    detection_rate: float
    median_translation_cm: float
    median_rotation_deg: float
    add_pass: float
    adds_pass: float
    threshold_m: float
    gross_miss_rate: float
    gross_miss_m: float

    def as_dict(self) -> dict:
        return asdict(self)


def pose_accuracy(
    estimates: list[np.ndarray | None],
    truths: list[np.ndarray],
    points: np.ndarray,
    fraction: float = 0.1,
    gross_miss_m: float = GROSS_MISS_M,
) -> PoseAccuracy:
    """Summarise estimates (4x4 or ``None`` for no detection) against true poses (4x4).

    Args:
        estimates: one (4, 4) pose (metres) or ``None`` (no detection) per frame.
        truths: the true (4, 4) poses, one per frame.
        points: (N, 3) points of the object's model (metres), for ADD / ADD-S.
        fraction: ADD / ADD-S threshold as a fraction of the object's diameter.
        gross_miss_m: position error (metres) above which a detection is a gross miss.
    """
    if len(estimates) != len(truths):
        raise ValueError(f"{len(estimates)} estimates for {len(truths)} ground-truth poses")
    threshold = fraction * object_diameter(points)
    t_err, r_err, add_ok, adds_ok = [], [], 0, 0
    for T_est, T_true in zip(estimates, truths, strict=True):
        if T_est is None:
            continue
        T_est, T_true = np.asarray(T_est, np.float64), np.asarray(T_true, np.float64)
        t_err.append(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
        R = T_true[:3, :3].T @ T_est[:3, :3]
        r_err.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
        add_ok += add_distance(T_est, T_true, points) < threshold
        adds_ok += adds_distance(T_est, T_true, points) < threshold
    n = len(truths)
    return PoseAccuracy(
        frames=n,
        detected=len(t_err),
        detection_rate=len(t_err) / n if n else float("nan"),
        median_translation_cm=float(np.median(t_err) * 100) if t_err else float("nan"),
        median_rotation_deg=float(np.median(r_err)) if r_err else float("nan"),
        add_pass=add_ok / n if n else float("nan"),
        adds_pass=adds_ok / n if n else float("nan"),
        threshold_m=threshold,
        gross_miss_rate=(float(np.mean(np.asarray(t_err) > gross_miss_m)) if t_err
                         else float("nan")),
        gross_miss_m=gross_miss_m,
    )


def pooled_rate_interval(passed: np.ndarray, frames: np.ndarray, level: float = 0.9,
                         resamples: int = 4000, seed: int = 0) -> tuple[float, float]:
    """Bootstrap interval of a pass rate pooled over sequences, resampling whole sequences.

    Frames of one sequence are far from independent (a pose the network finds hard can fill a
    whole second), so the interval resamples sequences with replacement and pools each
    resample's frames: ``sum(passed) / sum(frames)`` over the drawn sequences.

    Args:
        passed: (S,) frames that passed, per sequence.
        frames: (S,) frames, per sequence (each >= 1).
        level: central probability of the interval, in (0, 1).
        resamples: bootstrap resamples.
        seed: random seed (the interval is reproducible).

    Returns:
        ``(low, high)``: the ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles of the pooled
        rate over the resamples.
    """
    passed = np.asarray(passed, dtype=np.float64).reshape(-1)
    frames = np.asarray(frames, dtype=np.float64).reshape(-1)
    if passed.shape != frames.shape or len(frames) == 0:
        raise ValueError(f"need one (passed, frames) pair per sequence, got {passed.shape} and "
                         f"{frames.shape}")
    if np.any(frames < 1) or np.any(passed < 0) or np.any(passed > frames):
        raise ValueError("each sequence needs frames >= 1 and 0 <= passed <= frames")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    draw = np.random.default_rng(seed).integers(0, len(frames), size=(resamples, len(frames)))
    rates = passed[draw].sum(axis=1) / frames[draw].sum(axis=1)
    low, high = np.quantile(rates, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(low), float(high)
