"""Depth registration to the colour camera, against a per-point reference."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.datasets.depth_registration import register_depth

K_DEPTH = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
K_COLOUR = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])


def _pose(rx: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(rx), np.sin(rx)
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    T[:3, 3] = t
    return T


def _reference(depth: np.ndarray, T: np.ndarray, size: tuple[int, int], splat: int) -> np.ndarray:
    """One point at a time, the nearest kept by comparison."""
    width, height = size
    out = np.zeros((height, width))
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            z = depth[v, u]
            if not z > 0:
                continue
            p = np.array([(u - K_DEPTH[0, 2]) * z / K_DEPTH[0, 0],
                          (v - K_DEPTH[1, 2]) * z / K_DEPTH[1, 1], z])
            q = T[:3, :3] @ p + T[:3, 3]
            if q[2] <= 0:
                continue
            uc = K_COLOUR[0, 0] * q[0] / q[2] + K_COLOUR[0, 2]
            vc = K_COLOUR[1, 1] * q[1] / q[2] + K_COLOUR[1, 2]
            base = ((int(np.floor(uc + 0.5)), int(np.floor(vc + 0.5))),) if splat == 1 else \
                tuple((int(np.floor(uc)) + du, int(np.floor(vc)) + dv)
                      for du in (0, 1) for dv in (0, 1))
            for col, row in base:
                if 0 <= col < width and 0 <= row < height and (
                        out[row, col] == 0 or q[2] < out[row, col]):
                    out[row, col] = q[2]
    return out


@pytest.mark.parametrize("splat", [1, 2])
def test_matches_a_per_point_reference(splat: int) -> None:
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.4, 2.0, size=(48, 64))
    depth[rng.random(depth.shape) < 0.1] = 0.0  # missing
    depth[5, 7] = np.nan
    T = _pose(0.05, (0.015, -0.002, 0.004))
    got = register_depth(depth, K_DEPTH, K_COLOUR, T, (80, 60), splat=splat)
    want = _reference(depth, T, (80, 60), splat)
    assert got.shape == (60, 80) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


def test_plane_keeps_its_depth_in_the_colour_camera() -> None:
    """A fronto-parallel plane seen by both cameras, one shifted sideways: depth unchanged."""
    depth = np.full((48, 64), 1.25)
    got = register_depth(depth, K_DEPTH, K_COLOUR, _pose(0.0, (0.02, 0.0, 0.0)), (80, 60))
    covered = got > 0
    assert covered.mean() > 0.5
    np.testing.assert_allclose(got[covered], 1.25, rtol=1e-6)


def test_nearest_surface_wins() -> None:
    depth = np.full((48, 64), 2.0)
    depth[20:28, 28:36] = 0.5  # a near box in front of a far wall
    got = register_depth(depth, K_DEPTH, K_COLOUR, np.eye(4), (80, 60), splat=2)
    centre = got[28:32, 38:42]
    np.testing.assert_allclose(centre, 0.5)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        register_depth(np.zeros((4, 4, 1)), K_DEPTH, K_COLOUR, np.eye(4), (8, 8))
    with pytest.raises(ValueError, match="splat"):
        register_depth(np.zeros((4, 4)), K_DEPTH, K_COLOUR, np.eye(4), (8, 8), splat=3)
