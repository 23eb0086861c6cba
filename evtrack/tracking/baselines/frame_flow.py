"""Dense optical flow between consecutive RGB frames (OpenCV), for the ``frame-flow`` baseline.

The ROFT-like baseline measures the object's motion from the RGB camera instead of the event
camera: OpenCV's DIS (or Farnebäck) flow between two consecutive frames, sampled on a grid
inside the object's predicted silhouette, divided by the frame interval to give px/s, with the
depth at each sample. :func:`twist_adjoint` carries the resulting twist from the RGB camera
into the event camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from evtrack.tracking.config import FrameFlowConfig

__all__ = ["DenseFlow", "FramePairFlow", "grid_in_polygon", "twist_adjoint"]

_DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
# Farnebäck parameters (OpenCV's documented example values, wider window for blur).
_FARNEBACK = {"pyr_scale": 0.5, "levels": 4, "winsize": 21, "iterations": 3, "poly_n": 7,
              "poly_sigma": 1.5, "flags": 0}


@dataclass
class FramePairFlow:
    """Dense flow of one frame pair.

    Attributes:
        t0_us, t1_us: the two frames' times.
        flow: (H, W, 2) float32 displacement in pixels from frame 0 to frame 1, at frame 0's
            pixels.
    """

    t0_us: int
    t1_us: int
    flow: np.ndarray

    @property
    def t_mid_us(self) -> int:
        return (self.t0_us + self.t1_us) // 2

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flow at integer pixels (N, 2) of frame 0 -> ``(uv_mid (N,2) px, flow (N,2) px/s)``.

        ``uv_mid`` is the pixel half-way along the displacement (the point's position at the
        middle of the interval, when the flow is the mean velocity).
        """
        pts = np.asarray(points, np.int64).reshape(-1, 2)
        d = self.flow[pts[:, 1], pts[:, 0]].astype(np.float64)
        dt = (self.t1_us - self.t0_us) * 1e-6
        return pts + 0.5 * d, d / dt


class DenseFlow:
    """Keep the previous frame and give the dense flow to each new one.

    Args:
        config: algorithm and limits (:class:`~evtrack.tracking.config.FrameFlowConfig`).
    """

    def __init__(self, config: FrameFlowConfig | None = None) -> None:
        self.config = config or FrameFlowConfig()
        self._prev: tuple[int, np.ndarray] | None = None
        self._dis = None
        if self.config.algorithm == "dis":
            self._dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[self.config.dis_preset])

    def reset(self) -> None:
        self._prev = None

    def push(self, t_us: int, rgb: np.ndarray) -> FramePairFlow | None:
        """Add a uint8 RGB frame; returns the flow from the previous one (``None`` for the first
        frame or after a gap longer than ``max_gap_ms``)."""
        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        prev, self._prev = self._prev, (int(t_us), gray)
        if prev is None or prev[1].shape != gray.shape:
            return None
        t0, g0 = prev
        if not 0 < t_us - t0 <= self.config.max_gap_ms * 1e3:
            return None
        if self._dis is not None:
            flow = self._dis.calc(g0, gray, None)
        else:
            flow = cv2.calcOpticalFlowFarneback(g0, gray, None, **_FARNEBACK)
        return FramePairFlow(t0, int(t_us), flow)


def grid_in_polygon(polygon, shape: tuple[int, int], pitch: int, max_points: int) -> np.ndarray:
    """Grid pixels (pitch ``pitch``) inside a silhouette polygon and the image.

    Args:
        polygon: a :class:`~evtrack.tracking.silhouette.SilhouettePolygon`.
        shape: ``(height, width)``.
        pitch: grid spacing in pixels.
        max_points: evenly thinned to at most this many.

    Returns:
        (N, 2) int64 ``(u, v)``.
    """
    h, w = shape
    lo = np.floor(polygon.vertices.min(0)).astype(np.int64)
    hi = np.ceil(polygon.vertices.max(0)).astype(np.int64)
    us = np.arange(max(lo[0], 0), min(hi[0], w - 1) + 1, pitch)
    vs = np.arange(max(lo[1], 0), min(hi[1], h - 1) + 1, pitch)
    if len(us) == 0 or len(vs) == 0:
        return np.zeros((0, 2), np.int64)
    gu, gv = np.meshgrid(us, vs)
    pts = np.stack([gu.ravel(), gv.ravel()], 1)
    pts = pts[polygon.contains(pts)]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(np.int64)]
    return pts


def twist_adjoint(T_ab: Tensor) -> Tensor:
    """The 6x6 map of twists ``[v_o, ω]`` from frame b to frame a, for ``P_a = R P_b + p``.

    With ``Ṗ_b = v + ω × P_b``: ``Ṗ_a = (R v + p × R ω) + (R ω) × P_a``, hence
    ``[v_a; ω_a] = [[R, [p]× R], [0, R]] [v; ω]``.
    """
    from evtrack.geometry import skew

    T = torch.as_tensor(T_ab, dtype=torch.float64)
    R, p = T[:3, :3], T[:3, 3]
    A = torch.zeros(6, 6, dtype=torch.float64)
    A[:3, :3] = R
    A[:3, 3:] = skew(p) @ R
    A[3:, 3:] = R
    return A
