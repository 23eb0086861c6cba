"""The frame-flow baseline's parts (evtrack.tracking.baselines.frame_flow): the twist adjoint
against moving points, dense flow of a shifted image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from tracker_helpers import rigid_pose

from evtrack.geometry import integrate_twist
from evtrack.tracking.baselines.frame_flow import DenseFlow, twist_adjoint


def test_twist_adjoint_against_moving_points() -> None:
    """A twist mapped by the adjoint moves points of the other frame identically."""
    T_ab = torch.from_numpy(rigid_pose([0.3, -0.2, 0.5], [0.1, 0.2, -0.3]))
    V_b = torch.tensor([0.2, -0.4, 0.1, 1.0, 0.5, -0.7], dtype=torch.float64)
    V_a = twist_adjoint(T_ab) @ V_b
    P_obj = torch.eye(4, dtype=torch.float64)
    P_obj[:3, 3] = torch.tensor([0.05, -0.02, 0.6])
    dt = 0.01
    moved_b = integrate_twist(P_obj, V_b, dt)
    moved_a = integrate_twist(T_ab @ P_obj, V_a, dt)
    torch.testing.assert_close(moved_a, T_ab @ moved_b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("algorithm", ["dis", "farneback"])
def test_dense_flow_measures_a_shift(algorithm) -> None:
    from evtrack.tracking.config import FrameFlowConfig

    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (140, 180)).astype(np.float32), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    a = np.repeat(tex[10:130, 10:170, None], 3, 2)
    b = np.repeat(tex[8:128, 13:173, None], 3, 2)  # content moves by (-3, +2) px
    flow = DenseFlow(FrameFlowConfig(algorithm=algorithm))
    assert flow.push(0, a) is None
    pair = flow.push(20_000, b)
    uv, f = pair.sample(np.array([[80, 60], [60, 50], [100, 70]]))
    np.testing.assert_allclose(f, np.tile([-150.0, 100.0], (3, 1)), atol=25.0)  # px/s
    assert flow.push(200_000, a) is None  # gap longer than max_gap_ms
