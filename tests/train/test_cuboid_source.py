"""The OpenCV-drawn cuboid source: geometry against an independent projection and hull."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from evtrack.errors import ConfigError
from evtrack.models import Cuboid
from evtrack.train import (
    CuboidSourceOptions,
    PoseSample,
    SourceSpec,
    SyntheticCuboidSource,
    build_source,
    draw_textured_cuboid,
)

CUBOID = Cuboid((0.1, 0.16, 0.07), (0.01, 0.0, -0.02))


def corners_camera(pose: np.ndarray, cuboid: Cuboid) -> np.ndarray:
    c, d = np.asarray(cuboid.center), np.asarray(cuboid.dimensions)
    pts = np.array([c + d / 2 * np.array(s) for s in itertools.product((-1, 1), repeat=3)]
                   + [c])
    return pts @ pose[:3, :3].T + pose[:3, 3]


def pinhole(P: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2],
                     K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]], axis=1)


def test_samples_are_deterministic_and_consistent():
    src = SyntheticCuboidSource(CUBOID, 6, (96, 128), seed=4,
                                options=CuboidSourceOptions(max_instances=2))
    again = SyntheticCuboidSource(CUBOID, 6, (96, 128), seed=4,
                                  options=CuboidSourceOptions(max_instances=2))
    counts = []
    for i in range(len(src)):
        s = src[i]
        assert isinstance(s, PoseSample)
        s.check()
        np.testing.assert_array_equal(s.image, again[i].image)
        for T, kp in zip(s.poses, s.keypoints, strict=True):
            np.testing.assert_allclose(kp, pinhole(corners_camera(T, CUBOID), s.K), atol=1e-3)
            assert np.all(corners_camera(T, CUBOID)[:, 2] > 0)
        counts.append(s.num_instances)
    assert max(counts) <= 2
    other = SyntheticCuboidSource(CUBOID, 6, (96, 128), seed=5)
    assert not np.array_equal(other[0].image, src[0].image)
    with pytest.raises(IndexError):
        src[6]


def test_drawn_box_covers_exactly_its_projected_hull():
    K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.array([0.5, -0.7, 0.2]))[0]
    pose[:3, 3] = (0.0, 0.0, 0.6)
    white = [np.full((32, 32, 3), 255, np.uint8)] * 6
    image = draw_textured_cuboid(np.zeros((120, 160, 3), np.uint8), K, pose, CUBOID, white,
                                 ambient=1.0)
    hull = cv2.convexHull(pinhole(corners_camera(pose, CUBOID)[:8], K).astype(np.float32))
    inside = outside = 0
    for y in range(0, 120, 3):
        for x in range(0, 160, 3):
            d = cv2.pointPolygonTest(hull, (float(x), float(y)), True)
            if d > 1.5:
                assert image[y, x].min() >= 250, (x, y)
                inside += 1
            elif d < -1.5:
                assert image[y, x].max() == 0, (x, y)
                outside += 1
    assert inside > 50 and outside > 50


def test_faces_have_distinct_textures_so_orientation_is_visible():
    src = SyntheticCuboidSource(CUBOID, 1, (96, 128))
    means = [t.reshape(-1, 3).mean(0) for t in src.textures]
    assert min(np.linalg.norm(a - b) for a, b in itertools.combinations(means, 2)) > 5


def test_behind_camera_is_refused_and_options_are_checked():
    pose = np.eye(4)
    pose[2, 3] = 0.01
    with pytest.raises(ValueError, match="in front of the camera"):
        draw_textured_cuboid(np.zeros((10, 10, 3), np.uint8), np.eye(3), pose, CUBOID,
                             [np.zeros((4, 4, 3), np.uint8)] * 6)
    with pytest.raises(ConfigError, match=r"^data\.options: unknown field\(s\) \['fov'\]"):
        CuboidSourceOptions.from_dict({"fov": 3}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: distance_range: must be 0 < low <= "
                       r"high, got \(3\.0, 1\.0\)"):
        CuboidSourceOptions.from_dict({"distance_range": [3, 1]}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: hfov_deg: must be in \(0, 170\) deg"):
        CuboidSourceOptions.from_dict({"hfov_deg": 170}, "data.options")
    with pytest.raises(ConfigError, match=r"^CuboidSourceOptions\.max_instances: must be >= 1"):
        CuboidSourceOptions(max_instances=0)


def test_options_round_trip_and_errors_name_the_options_key():
    opts = CuboidSourceOptions.from_dict({"distance_range": [3, 4], "max_instances": 2.0})
    assert opts.distance_range == (3.0, 4.0) and opts.max_instances == 2
    for cfg in (CuboidSourceOptions(), opts):
        assert CuboidSourceOptions.from_dict(cfg.to_dict()) == cfg
    spec = SourceSpec(options={"fov": 3}, object_name="box", cuboid=CUBOID, mesh=None,
                      num_samples=1, image_size=(48, 64), seed=0, options_key="data.val_options")
    with pytest.raises(ConfigError, match=r"^data\.val_options: unknown field\(s\) \['fov'\]"):
        build_source("cuboid", spec)
