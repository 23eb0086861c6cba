"""Half-turn ambiguities of a cuboid-keypoint pose network, resolved against the filter's pose.

A DOPE-style network finds the eight corners of the object's bounding cuboid and PnP turns
them into a pose. A half turn about one of the cuboid's axes (through its centre) maps the
cuboid onto itself, so if the network swaps the corners' identities that way, PnP returns the
pose turned half a turn about that axis *at the right position and range*. Where the camera
looks at the object along that axis the two poses also show nearly the same silhouette, so
neither the image cues nor a depth check can tell them apart: the mustard bottle seen from
below, along its long axis, is the benchmark's case (networks trained on more of those views
answered some of them with such half turns, and a track that took one was 180° off).

The tracker has a third source: its own pose. :class:`HalfTurnResolver` offers, for a pose
seen within ``max_view_deg`` of the line of sight along one of the chosen axes, the pose
turned half a turn about that axis as an alternative, and keeps whichever of the two lies
nearer the filter's pose in rotation. A right pose is kept as long as the filter is within
90° of the truth; a half-turned one is turned back. A filter that is itself half a turn off
(started on such a pose: nothing can resolve the first pose) disagrees with every right pose;
the tracker re-initialises it when several in a row need the turn
(``TrackerConfig.pose_gate.half_turn_reinit_after``), and away from those views nothing is turned,
so the filter's gate and re-initialisation correct it as without the resolver.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

from evtrack.eval.metrics import rotation_errors

__all__ = ["HalfTurnResolver", "half_turn"]

_AXES = {"x": 0, "y": 1, "z": 2}


def half_turn(axis: int, center: np.ndarray) -> np.ndarray:
    """(4, 4) float64: the half turn about the object-frame axis ``axis`` (0, 1, 2 for x, y, z)
    through ``center`` (3,), metres, as a map of object points ``X -> R (X - c) + c``."""
    R = -np.eye(3)
    R[axis, axis] = 1.0
    S = np.eye(4)
    S[:3, :3] = R
    S[:3, 3] = np.asarray(center, np.float64) - R @ np.asarray(center, np.float64)
    return S


class HalfTurnResolver:
    """Choose between a pose and its half turns about chosen cuboid axes, by a reference pose.

    Args:
        axes: the object-frame axes whose half turns the pose network may confuse, a string of
            ``"x"``, ``"y"``, ``"z"`` (e.g. ``"y"``: the long axis of a bottle; ``""``: none).
        center: (3,) the cuboid's centre in the object frame, metres (the half turns go through
            it, so the object's centre keeps its place).
        max_view_deg: a half turn is offered only where the line of sight from the camera to
            the cuboid's centre lies within this angle of its axis (either end), degrees.

    Raises:
        ValueError: an unknown axis letter, a repeated one, or ``max_view_deg`` outside
            ``[0, 90]``.

    Example:
        >>> import numpy as np
        >>> r = HalfTurnResolver("y", np.zeros(3), max_view_deg=30.0)
        >>> P = np.eye(4); P[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]; P[2, 3] = 1.0
        >>> flipped = P @ half_turn(1, np.zeros(3))
        >>> chosen, axis = r.resolve(flipped, reference=P)
        >>> bool(np.allclose(chosen, P)), axis
        (True, 'y')
    """

    def __init__(self, axes: str | Iterable[str], center: np.ndarray,
                 max_view_deg: float = 30.0) -> None:
        letters = list(axes)
        unknown = [a for a in letters if a not in _AXES]
        if unknown or len(set(letters)) != len(letters):
            raise ValueError(f"half-turn axes must be distinct letters of 'xyz', got {axes!r}")
        if not 0.0 <= float(max_view_deg) <= 90.0:
            raise ValueError(f"max_view_deg must be in [0, 90], got {max_view_deg}")
        self.axes = "".join(letters)
        self.center = np.asarray(center, np.float64).reshape(3)
        self.max_view_deg = float(max_view_deg)
        self._cos_max = math.cos(math.radians(self.max_view_deg))
        self._turns = {a: half_turn(_AXES[a], self.center) for a in self.axes}

    def offered(self, pose: np.ndarray) -> list[str]:
        """The axes whose half turn is offered for ``pose`` (4, 4), object to camera: those
        within ``max_view_deg`` of the line of sight to the cuboid's centre."""
        R, t = pose[:3, :3], pose[:3, 3]
        centre_cam = R @ self.center + t
        dist = float(np.linalg.norm(centre_cam))
        if dist <= 0.0 or not math.isfinite(dist):
            return []
        sight = R.T @ (centre_cam / dist)  # the line of sight in the object frame
        return [a for a in self.axes if abs(float(sight[_AXES[a]])) >= self._cos_max]

    def resolve(self, pose: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, str | None]:
        """``pose`` (4, 4) or its offered half turn, whichever is nearer ``reference`` (4, 4)
        in rotation (ties keep ``pose``).

        Returns:
            the chosen (4, 4) pose and the axis it was turned about (``None``: unchanged).
        """
        axes = self.offered(pose)
        if not axes:
            return pose, None
        candidates = np.stack([pose] + [pose @ self._turns[a] for a in axes])
        angles = rotation_errors(torch.from_numpy(candidates),
                                 torch.from_numpy(np.asarray(reference, np.float64)))
        best = int(torch.argmin(angles))  # the first of equal minima: pose itself on a tie
        return (pose, None) if best == 0 else (candidates[best], axes[best - 1])
