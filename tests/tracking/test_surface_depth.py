"""The shared depth-offset pieces of the pose alignment and the range
(evtrack.tracking.surface_depth),
against hand-made offsets and a ray-cast plane."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.camera import PinholeCamera
from evtrack.tracking.surface_depth import SurfaceDepthSampler, robust_offset


def test_robust_offset_takes_the_agreeing_majority() -> None:
    rng = np.random.default_rng(0)
    agreeing = 0.012 + rng.uniform(-0.005, 0.005, 60)
    outliers = rng.uniform(0.2, 1.0, 25)  # background behind the object
    res = robust_offset(np.r_[agreeing, outliers], inlier_m=0.03, min_cells=20,
                        min_inlier_fraction=0.5)
    assert res.ok and res.cells == 85 and len(res.inliers) == 60
    assert res.offset == pytest.approx(float(np.median(agreeing)))


def test_robust_offset_says_why_there_is_none() -> None:
    few = robust_offset(np.full(5, 0.01), 0.03, 20, 0.5)
    assert few.reason == "too few cells" and np.isnan(few.offset) and few.cells == 5
    scattered = np.linspace(-0.5, 0.5, 101)  # a third within 3 cm of the median at most
    split = robust_offset(scattered, 0.03, 5, 0.5)
    assert split.reason == "too few agreeing" and np.isnan(split.offset)
    assert split.median == pytest.approx(0.0, abs=1e-12) and len(split.inliers) < 50


def test_sampler_offsets_of_a_plane_seen_head_on() -> None:
    """A 20 cm square facing the camera at 0.9 m (44 px wide: 12 x 12 cells of 4 px), the
    sensor plane 3 cm behind it: every cell's offset is 3 cm; cells on missing depth give
    none; points whose normals face away are never used."""
    cam = PinholeCamera(200.0, 200.0, 99.5, 99.5, 200, 200)
    g = np.linspace(-0.1, 0.1, 81)
    face = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    points = np.c_[face, np.zeros(len(face))]
    towards = np.tile([0.0, 0.0, -1.0], (len(face), 1))
    sampler = SurfaceDepthSampler(points, towards, cam, cell_px=4)
    depth = np.full((200, 200), 0.93, np.float32)
    T = np.eye(4)
    T[2, 3] = 0.9
    diff = sampler.offsets(depth, T)
    assert 121 <= len(diff) <= 169
    np.testing.assert_allclose(diff, 0.03, atol=1e-6)
    depth[:, :100] = np.nan  # the left half missing: about half the cells
    assert abs(len(sampler.offsets(depth, T)) - len(diff) / 2) <= 13
    away = SurfaceDepthSampler(points, -towards, cam, cell_px=4)
    assert away.offsets(depth, T) is None  # nothing faces the camera
    T[2, 3] = -0.9  # behind the camera, where normals along +z face the camera's centre
    assert away.offsets(depth, T) is None


def test_sampler_rejects_bad_shapes() -> None:
    cam = PinholeCamera(100.0, 100.0, 49.5, 49.5, 100, 100)
    with pytest.raises(ValueError, match="points and normals"):
        SurfaceDepthSampler(np.zeros((4, 3)), np.zeros((3, 3)), cam)
    with pytest.raises(ValueError, match="cell_px"):
        SurfaceDepthSampler(np.zeros((4, 3)), np.zeros((4, 3)), cam, cell_px=0)
