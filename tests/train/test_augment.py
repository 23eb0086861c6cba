"""Domain-randomisation transforms: keypoints stay projections, inputs are never modified."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.errors import ConfigError
from evtrack.models import Cuboid
from evtrack.train import (
    AugmentConfig,
    ColorJitter,
    CuboidSourceOptions,
    GaussianNoise,
    MotionBlur,
    RandomCrop,
    RandomOcclusion,
    RandomScale,
    SyntheticCuboidSource,
    TrainConfig,
)

CUBOID = Cuboid((0.1, 0.16, 0.07))
ALWAYS = [RandomScale(p=1), ColorJitter(p=1), RandomOcclusion(p=1), MotionBlur(p=1),
          GaussianNoise(p=1)]


@pytest.fixture(scope="module")
def sample():
    src = SyntheticCuboidSource(CUBOID, 1, (96, 128), options=CuboidSourceOptions(
        empty_probability=0))
    return src[0]


def reprojection(sample):
    out = []
    for T in sample.poses:
        P = CUBOID.points() @ T[:3, :3].T + T[:3, 3]
        uvw = P @ sample.K.T
        out.append(uvw[:, :2] / uvw[:, 2:])
    return np.array(out)


@pytest.mark.parametrize("transform", ALWAYS, ids=lambda t: type(t).__name__)
def test_transforms_keep_keypoints_projections_and_do_not_mutate(sample, transform):
    before = sample.image.copy()
    out = transform(sample, np.random.default_rng(0))
    np.testing.assert_array_equal(sample.image, before)
    out.check()
    assert out.image.shape == sample.image.shape and out.image.dtype == np.uint8
    np.testing.assert_allclose(out.keypoints, reprojection(out), atol=1e-3)
    again = transform(sample, np.random.default_rng(0))
    np.testing.assert_array_equal(out.image, again.image)


def test_scale_moves_image_content_with_the_keypoints():
    from evtrack.train import PoseSample

    img = np.zeros((96, 128, 3), np.uint8)
    u, v = 40, 30
    img[v - 1:v + 2, u - 1:u + 2] = 255  # a bright dot at (40, 30)
    kp = np.full((1, 9, 2), (u, v), np.float32)
    s = PoseSample(img, np.eye(3), np.eye(4)[None], kp)
    out = RandomScale(scale_range=(1.5, 1.5), max_shift=0.1, p=1)(s, np.random.default_rng(3))
    nu, nv = out.keypoints[0, 0]
    patch = out.image[int(round(nv)) - 1:int(round(nv)) + 2, int(round(nu)) - 1:int(round(nu)) + 2]
    assert patch.mean() > 200
    np.testing.assert_allclose(out.K[:2, :2], 1.5 * np.eye(2))


def test_probability_zero_is_identity(sample):
    for t in [RandomScale(p=0), ColorJitter(p=0), RandomOcclusion(p=0), MotionBlur(p=0),
              GaussianNoise(p=0)]:
        assert t(sample, np.random.default_rng(0)) is sample


def test_config_from_dict():
    cfg = AugmentConfig.from_dict({"noise": None, "scale": {"scale_range": [0.9, 1.1]},
                                   "motion_blur": False})
    assert cfg.noise is None and cfg.motion_blur is None
    assert cfg.scale == RandomScale(scale_range=(0.9, 1.1))
    assert [type(t).__name__ for t in cfg.build().transforms] == [
        "RandomScale", "ColorJitter", "RandomOcclusion"]
    assert AugmentConfig.from_dict(cfg.to_dict()) == cfg
    assert AugmentConfig(enabled=False).build().transforms == ()
    assert AugmentConfig.from_dict({"crop": True, "color": None}) == AugmentConfig(
        crop=RandomCrop(), color=None)  # true: the transform's defaults
    with pytest.raises(ConfigError, match=r"^data\.augment: unknown field\(s\) \['blur'\]"):
        AugmentConfig.from_dict({"blur": {}}, "data.augment")
    with pytest.raises(ConfigError, match=r"^data\.augment: noise: unknown field\(s\) \['sigma'\] "
                       r"\('sigma': did you mean 'max_sigma'\?\)"):
        AugmentConfig.from_dict({"noise": {"sigma": 3}}, "data.augment")
    with pytest.raises(ConfigError, match=r"^data\.augment: enabled: expected true or false"):
        AugmentConfig.from_dict({"enabled": "yes"}, "data.augment")
    with pytest.raises(ConfigError, match=r"^data\.augment: color: expected a mapping, got int"):
        AugmentConfig.from_dict({"color": 3}, "data.augment")


def test_configs_round_trip_through_their_dicts():
    for cfg in [AugmentConfig(), AugmentConfig(enabled=False, crop=RandomCrop(size=(64, 96)),
                                               noise=None, scale=RandomScale((0.9, 1.1)))]:
        assert AugmentConfig.from_dict(cfg.to_dict()) == cfg
    for kind in (RandomCrop, RandomScale, ColorJitter, RandomOcclusion, MotionBlur,
                 GaussianNoise):
        assert kind.from_dict(kind().to_dict()) == kind()


def test_crop_keeps_keypoints_projections_and_content(sample):
    before = sample.image.copy()
    crop = RandomCrop(size=(48, 64), object_p=1.0, max_offset=0.0)
    out = crop(sample, np.random.default_rng(1))
    np.testing.assert_array_equal(sample.image, before)
    out.check()
    assert out.image.shape == (48, 64, 3)
    np.testing.assert_allclose(out.keypoints, reprojection(out), atol=1e-3)
    # with no offset the instance's centroid lands on the crop centre (to the rounding)
    np.testing.assert_allclose(out.keypoints[0, -1], (32, 24), atol=0.51)
    # pixels inside the source image are the source's own pixels, moved by the crop origin
    x0 = int(round(sample.keypoints[0, -1, 0] - 32))
    y0 = int(round(sample.keypoints[0, -1, 1] - 24))
    for v, u in [(10, 10), (30, 50), (47, 63)]:
        sv, su = v + y0, u + x0
        if 0 <= sv < 96 and 0 <= su < 128:
            np.testing.assert_array_equal(out.image[v, u], sample.image[sv, su])
    again = crop(sample, np.random.default_rng(1))
    np.testing.assert_array_equal(out.image, again.image)


def test_crop_outside_the_image_is_filled_and_uniform_crops_stay_inside():
    from evtrack.train import PoseSample

    img = np.full((40, 48, 3), 7, np.uint8)
    kp = np.full((1, 9, 2), (1.0, 1.0), np.float32)  # centroid at the top-left corner
    s = PoseSample(img, np.eye(3), np.eye(4)[None], kp)
    out = RandomCrop(size=(32, 32), object_p=1.0, max_offset=0.0)(s, np.random.default_rng(0))
    assert out.image.shape == (32, 32, 3)
    assert (out.image[-1, -1] == 7).all()  # bottom-right of the crop is inside the image
    fill = out.image[0, 0]
    assert (out.image[:10, :10] == fill).all()  # top-left is the flat fill colour
    np.testing.assert_allclose(out.keypoints[0, -1], (16, 16), atol=0.51)
    # no instance: a uniform crop, always entirely inside an image larger than the crop
    empty = PoseSample(img, np.eye(3), np.zeros((0, 4, 4)), np.zeros((0, 9, 2), np.float32))
    for seed in range(20):
        o = RandomCrop(size=(32, 32))(empty, np.random.default_rng(seed))
        assert (o.image == 7).all() and o.K[0, 2] <= 0 and o.K[0, 2] >= -16


def test_crop_config_is_validated_and_runs_first():
    cfg = AugmentConfig.from_dict({"crop": {"size": [160, 160]}, "noise": None})
    assert cfg.crop == RandomCrop(size=(160, 160))
    assert type(cfg.build().transforms[0]).__name__ == "RandomCrop"
    assert AugmentConfig().crop is None
    assert AugmentConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match=r"^RandomCrop\.size: must be positive multiples of 8"):
        RandomCrop(size=(100, 160))
    with pytest.raises(ConfigError, match=r"^RandomCrop\.object_p: must be in \[0, 1\]"):
        RandomCrop(object_p=1.5)
    with pytest.raises(ConfigError, match=r"^run\.yaml: data\.augment\.crop\.size: must be "
                       r"positive multiples of 8, got \(100, 160\)"):
        TrainConfig.from_dict({"object": {"name": "box", "dimensions": [0.1, 0.1, 0.1]},
                               "data": {"augment": {"crop": {"size": [100, 160]}}}}, "run.yaml")


def test_zoomed_crop_shows_the_instance_as_the_estimators_second_pass(sample):
    """``zoom_p=1``: the instance's corner box spans ``zoom_box`` of the crop width, centred
    within ``zoom_offset``; keypoints stay projections through the new ``K``; the content moves
    with them."""
    crop = RandomCrop(size=(64, 64), object_p=1.0, zoom_p=1.0, zoom_box=(0.7, 0.8),
                      zoom_offset=0.05)
    for seed in range(10):
        out = crop(sample, np.random.default_rng(seed))
        out.check()
        assert out.image.shape == (64, 64, 3)
        np.testing.assert_allclose(out.keypoints, reprojection(out), atol=1e-3)
        corners = out.keypoints[0, :8]
        side = (corners.max(0) - corners.min(0)).max()
        assert 0.7 * 64 - 1e-3 <= side <= 0.8 * 64 + 1e-3
        centre = (corners.max(0) + corners.min(0)) / 2
        assert np.abs(centre - 31.5).max() <= 0.05 * 64 + 1e-6
    # the zoomed window is an affine map of the image: a bright dot follows its keypoint
    from evtrack.train import PoseSample

    img = np.zeros((96, 128, 3), np.uint8)
    img[29:32, 59:62] = 255  # a dot at (60, 30)
    kp = np.array([[[50, 20], [70, 20], [50, 40], [70, 40], [50, 20], [70, 20], [50, 40],
                    [70, 40], [60, 30]]], np.float32)
    s = PoseSample(img, np.eye(3), np.eye(4)[None], kp)
    out = RandomCrop(size=(64, 64), object_p=1.0, zoom_p=1.0, zoom_box=(0.5, 0.5),
                     zoom_offset=0.0)(s, np.random.default_rng(0))
    np.testing.assert_allclose(out.keypoints[0, 8], (31.5, 31.5), atol=1e-4)
    np.testing.assert_allclose(out.K[0, 0], 32 / 20)  # the 20 px box spans half of 64 px
    assert out.image[31:33, 31:33].mean() > 200


def test_zoomed_crop_needs_two_known_corners_and_checks_its_settings(sample):
    from evtrack.train import PoseSample

    kp = np.full((1, 9, 2), np.nan, np.float32)
    kp[0, 8] = (40, 30)  # only the centroid is known: an ordinary crop around it
    s = PoseSample(np.zeros((96, 128, 3), np.uint8), np.eye(3), np.eye(4)[None], kp)
    out = RandomCrop(size=(32, 32), object_p=1.0, max_offset=0.0, zoom_p=1.0)(
        s, np.random.default_rng(0))
    np.testing.assert_allclose(out.keypoints[0, 8], (16, 16), atol=0.51)
    np.testing.assert_allclose(out.K[:2, :2], np.eye(2))  # not scaled
    with pytest.raises(ConfigError, match=r"^RandomCrop\.zoom_p: must be in \[0, 1\]"):
        RandomCrop(zoom_p=1.5)
    with pytest.raises(ConfigError, match=r"^RandomCrop\.zoom_box: must be \(low, high\) with "
                       r"0 < low <= high"):
        RandomCrop(zoom_box=(0.9, 0.5))
    with pytest.raises(ConfigError, match=r"^RandomCrop\.zoom_box: must be \(low, high\)"):
        RandomCrop(zoom_box=(0.5, 0.6, 0.7))
    with pytest.raises(ConfigError, match=r"^data\.augment: crop\.zoom_box: expected a list of 2 "
                       r"values"):
        AugmentConfig.from_dict({"crop": {"zoom_box": [0.5, 0.6, 0.7]}}, "data.augment")
    with pytest.raises(ConfigError, match=r"^RandomCrop\.zoom_offset: must be >= 0"):
        RandomCrop(zoom_offset=-0.1)
    cfg = AugmentConfig.from_dict({"crop": {"size": [320, 320], "zoom_p": 0.6,
                                            "zoom_box": [0.68, 0.86]}})
    assert cfg.crop.zoom_box == (0.68, 0.86) and AugmentConfig.from_dict(cfg.to_dict()) == cfg
