"""Ground truth of a recording from its poses alone (datasets give poses, not twists)."""

from __future__ import annotations

import numpy as np
import torch

from evtrack.geometry import twist_between
from evtrack.sequence import GroundTruth

__all__ = ["ground_truth_from_poses"]


def ground_truth_from_poses(t_us: np.ndarray, poses: np.ndarray) -> GroundTruth:
    """A :class:`~evtrack.sequence.GroundTruth` whose twists are those between poses.

    Between two consecutive poses the object moves with the constant twist that joins them
    (:func:`evtrack.geometry.twist_between`); that twist is stored at the midpoint of the two
    times. One pose gives one zero twist at its time.

    Args:
        t_us: (M,) int64 µs, strictly increasing.
        poses: (M, 4, 4) float64 object-to-camera poses, metres.

    Raises:
        ValueError: times not strictly increasing, or shapes that do not match.
    """
    t = np.asarray(t_us, np.int64)
    T = torch.as_tensor(np.asarray(poses, np.float64))
    if t.ndim != 1 or T.shape != (t.shape[0], 4, 4):
        raise ValueError(f"poses must be ({t.shape[0]}, 4, 4) to match (M,) times, got "
                         f"{tuple(T.shape)}")
    if t.size > 1 and bool((np.diff(t) <= 0).any()):
        raise ValueError("pose times must be strictly increasing")
    if t.size < 2:
        return GroundTruth(t, T, t.copy(), torch.zeros(t.size, 6, dtype=torch.float64))
    dt_s = torch.as_tensor(np.diff(t) * 1e-6)
    twists = twist_between(T[:-1], T[1:], 1.0) / dt_s.unsqueeze(-1)
    mid = t[:-1] + np.diff(t) // 2
    keep = np.concatenate([[True], np.diff(mid) > 0])  # two 1 µs steps share a midpoint
    return GroundTruth(t, T, mid[keep], twists[torch.as_tensor(keep)])
