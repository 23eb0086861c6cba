"""The tracker's outputs: one sample per velocity step (pose, twist, status), the lookup of a
past or future pose, and the view check that declares the object lost."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from evtrack.filters.scalar_lie import normalized, rotation_matrix
from evtrack.geometry import tq_to_matrix
from evtrack.tracking.event_gate import moved_pose
from evtrack.tracking.silhouette import Silhouette
from evtrack.tracking.trajectory import STATUS_TRACKING, Trajectory

__all__ = ["TrackOutputs", "ViewCheck", "quat_to_matrix"]


def quat_to_matrix(t: Sequence[float], q: Sequence[float]) -> np.ndarray:
    """(3,), (4,) wxyz (arrays or sequences of numbers) -> (4, 4) float64. Python floats and
    one array: the tracker asks at every step, where NumPy's per-operation cost on scalars
    (~1 µs each) would be most of the time."""
    r0, r1, r2 = rotation_matrix(normalized(tuple(float(v) for v in q)))
    tx, ty, tz = (float(v) for v in t)
    return np.array([[*r0, tx], [*r1, ty], [*r2, tz], [0.0, 0.0, 0.0, 1.0]])


def _nan_pose() -> np.ndarray:
    return np.full((4, 4), np.nan)


class TrackOutputs:
    """The samples output so far: times (µs), ``[t, q]`` (7,) poses (NaN: none), twists (6,)
    and statuses."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.tq: list[np.ndarray] = []
        self.twist: list[np.ndarray] = []
        self.status: list[int] = []

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t_us: int, tq: np.ndarray, twist: np.ndarray, status: int) -> None:
        """One sample: ``tq`` (7,) float64, ``twist`` (6,)."""
        self.t.append(t_us)
        self.tq.append(tq)
        self.twist.append(twist)
        self.status.append(status)

    def extend_tracking(self, t_us: list[int], tq: np.ndarray, twists: np.ndarray) -> None:
        """Samples of steps tracked in one run: ``tq`` (N, 7) (rows kept as views: pass a new
        array), ``twists`` (N, 6)."""
        self.t.extend(t_us)
        self.tq.extend(tq)
        self.twist.extend(twists)
        self.status.extend([STATUS_TRACKING] * len(t_us))

    def sample_before(self, t_us: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The twist (6,), pose (4, 4) (NaN: none) and time of the last sample at or before
        ``t_us`` (no sample: zero twist, NaN pose, ``t_us``)."""
        i = int(np.searchsorted(np.asarray(self.t), int(t_us), side="right")) - 1
        if i < 0:
            return np.zeros(6), _nan_pose(), int(t_us)
        tq = self.tq[i]
        T = quat_to_matrix(tq[:3], tq[3:]) if np.isfinite(tq).all() else _nan_pose()
        return self.twist[i].copy(), T, self.t[i]

    def trajectory(self, method: str, meta: dict[str, Any]) -> Trajectory:
        """Every sample as a :class:`~evtrack.tracking.trajectory.Trajectory`."""
        n = len(self.t)
        tq = torch.from_numpy(np.asarray(self.tq, np.float64).reshape(n, 7))
        poses = torch.full((n, 4, 4), float("nan"), dtype=torch.float64)
        ok = torch.isfinite(tq).all(1)
        if ok.any():
            poses[ok] = tq_to_matrix(tq[ok, :3], tq[ok, 3:])
        return Trajectory(torch.tensor(self.t, dtype=torch.int64), poses,
                          torch.from_numpy(np.asarray(self.twist, np.float64).reshape(n, 6)),
                          torch.tensor(self.status, dtype=torch.int8), method, meta)


def extrapolated(twist: np.ndarray, T: np.ndarray, t_ref: int, t_us: int | None) -> np.ndarray:
    """The pose ``T`` (4, 4) of ``t_ref`` moved on by ``twist`` (6,) to ``t_us`` (``None``:
    ``T``); NaN poses stay NaN."""
    if not np.isfinite(T).all():
        return T
    dt = (t_us - t_ref) * 1e-6 if t_us is not None else 0.0
    if dt == 0:
        return T
    return moved_pose(T, twist, dt)


class ViewCheck:
    """Counts the steps whose predicted silhouette is (mostly) out of view; the object is lost
    after ``lost_after_ms`` of them in a row.

    Args:
        silhouette: the object's silhouette in the event camera.
        min_visible_fraction: a step with less of the silhouette in the image is out of view.
        lost_after_ms: out of view this long: lost.
        step_us: the velocity step (µs).
    """

    def __init__(self, silhouette: Silhouette, min_visible_fraction: float,
                 lost_after_ms: float, step_us: int) -> None:
        self.silhouette = silhouette
        self.min_visible_fraction = min_visible_fraction
        self.lost_after_us = lost_after_ms * 1e3
        self.step_us = step_us
        self.out_of_view_us = 0

    def in_view(self, t: Sequence[float], q: Sequence[float]) -> bool:
        """Count one step at the pose ``t`` (3,), ``q`` (4,) wxyz; whether the object is still
        not lost."""
        if self.silhouette.box_in_image(t, q):
            visible = 1.0  # the whole silhouette in view (the common case: no polygon)
        else:
            visible = self.silhouette.visible_fraction(quat_to_matrix(t, q))
        if visible >= self.min_visible_fraction:
            self.out_of_view_us = 0
            return True
        self.out_of_view_us += self.step_us
        return self.out_of_view_us < self.lost_after_us
