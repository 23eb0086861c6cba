"""Regions of a depth frame that stand out of its dominant planes with an object's size
(:mod:`evtrack.models.depth_regions`), on analytic scenes: a tilted table and a wall, a ball
resting on the table, a block too large to be the object, a speck of noise."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.camera import PinholeCamera
from evtrack.models.depth_regions import RegionConfig, dominant_planes, object_regions

CAM = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)


def _rays() -> np.ndarray:
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    return np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones(u.shape)], -1)


def _plane_depth(normal, offset) -> np.ndarray:
    """Depth (z) of the plane ``n · X = d`` along each pixel's ray; inf where it is not hit
    in front of the camera."""
    denom = _rays() @ np.asarray(normal, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = offset / denom
    return np.where(z > 0, z, np.inf)


def _sphere_depth(centre, radius) -> np.ndarray:
    rays = _rays()
    c = np.asarray(centre, np.float64)
    a = np.einsum("hwi,hwi->hw", rays, rays)
    b = -2 * rays @ c
    disc = b * b - 4 * a * (c @ c - radius ** 2)
    with np.errstate(invalid="ignore"):
        s = (-b - np.sqrt(disc)) / (2 * a)
    return np.where(disc > 0, s, np.inf)


def _box_depth(lo, hi) -> np.ndarray:
    """The front face (z = lo[2]) of an axis-aligned block, seen head-on."""
    rays = _rays()
    X = rays * lo[2]
    inside = (X[..., 0] >= lo[0]) & (X[..., 0] <= hi[0]) & (X[..., 1] >= lo[1]) \
        & (X[..., 1] <= hi[1])
    return np.where(inside, lo[2], np.inf)


def _projected_box(centre, radius) -> tuple[float, float, float, float]:
    x, y, z = centre
    u, v = CAM.fx * x / z + CAM.cx, CAM.fy * y / z + CAM.cy
    r = CAM.fx * radius / z
    return u - r, v - r, u + r, v + r


# the table: y = 0.15 m below the camera's centre, tilted towards it; the wall at 1.6 m
TABLE = (np.array([0.0, -np.cos(0.5), -np.sin(0.5)]), -0.15 * np.cos(0.5) - 0.9 * np.sin(0.5))
WALL = (np.array([0.0, 0.0, -1.0]), -1.6)
BALL_R = 0.05


def _scene(rng: np.random.Generator, *, ball=True, block=True, speck=True) -> np.ndarray:
    parts = [_plane_depth(*TABLE), _plane_depth(*WALL)]
    if ball:
        parts.append(_sphere_depth((0.05, 0.02, 0.8), BALL_R))
    if block:  # 40 cm wide: far too large for a 5 cm ball
        parts.append(_box_depth((-0.5, -0.3, 1.2), (-0.1, 0.05)))
    depth = np.minimum.reduce(parts)
    depth = depth + rng.normal(0, 0.001, depth.shape)
    depth[~np.isfinite(depth)] = 0.0
    if speck:
        depth[30:32, 280:282] = 0.5  # 4 px: fewer than min_pixels
    depth[rng.random(depth.shape) < 0.02] = np.nan  # holes
    return depth.astype(np.float32)


def test_the_ball_on_the_table_is_found_and_nothing_else() -> None:
    rng = np.random.default_rng(0)
    depth = _scene(rng)
    regions = object_regions(depth, CAM, BALL_R)
    assert len(regions) == 1
    (region,) = regions
    u0, v0, u1, v1 = _projected_box((0.05, 0.02, 0.8), BALL_R)
    bu0, bv0, bu1, bv1 = region.box
    # the box holds the ball's projection and not much more
    assert bu0 <= u0 + 1 and bv0 <= v0 + 1 and bu1 >= u1 - 1 and bv1 >= v1 - 1
    assert (bu1 - bu0) < 1.4 * (u1 - u0) and (bv1 - bv0) < 1.4 * (v1 - v0)
    assert 0.8 - BALL_R < region.depth_m < 0.8  # the median of its front half
    assert 0.8 < region.fill <= 1.1


def test_the_planes_are_found() -> None:
    rng = np.random.default_rng(1)
    depth = _scene(rng, ball=False, block=False, speck=False)
    v, u = np.mgrid[0:CAM.height:2, 0:CAM.width:2]
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    pts = np.stack([(u[ok] - CAM.cx) / CAM.fx * z[ok], (v[ok] - CAM.cy) / CAM.fy * z[ok],
                    z[ok]], 1)
    planes = dominant_planes(pts)
    assert len(planes) == 2
    for truth in (TABLE, WALL):
        n = truth[0] / np.linalg.norm(truth[0])
        match = max(planes, key=lambda p: abs(float(p[0] @ n)))
        assert abs(float(match[0] @ n)) > 0.999
        assert match[1] == pytest.approx(truth[1], abs=0.005)
        assert match[1] < 0  # the camera on the positive side
    assert object_regions(depth, CAM, BALL_R) == []  # planes only: nothing stands out


def test_the_size_decides() -> None:
    """The block is found when the object is as large as it; then the ball is too small."""
    rng = np.random.default_rng(2)
    depth = _scene(rng)
    (region,) = object_regions(depth, CAM, 0.3)
    assert region.depth_m == pytest.approx(1.2, abs=0.01)
    assert object_regions(depth, CAM, BALL_R, RegionConfig(size_range=(1.2, 1.5))) == []


def test_bad_input() -> None:
    depth = np.zeros((CAM.height, CAM.width), np.float32)
    with pytest.raises(ValueError, match="no valid pixel"):
        object_regions(depth, CAM, BALL_R)
    with pytest.raises(ValueError, match="no valid pixel"):
        object_regions(np.full_like(depth, np.nan), CAM, BALL_R)
    with pytest.raises(ValueError, match=r"must be \(240, 320\)"):
        object_regions(depth[:10], CAM, BALL_R)
    with pytest.raises(ValueError, match="radius"):
        object_regions(depth + 1, CAM, 0.0)
    from evtrack.errors import ConfigError

    with pytest.raises(ConfigError, match="invalid settings"):
        RegionConfig(size_range=(1.0, 0.5))
