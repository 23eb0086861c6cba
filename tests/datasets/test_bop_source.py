"""The ``bop`` training source: BOP images with their poses, fitted into the training size."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_scene import K_BOP, SIZE, pose, write_models, write_scene

from evtrack.errors import ConfigError
from evtrack.models.cuboid import Cuboid
from evtrack.train.samples import SourceSpec, build_source, list_sources, project_keypoints

BOX_MM = (40.0, 60.0, 20.0)
CENTRE_MM = (5.0, -3.0, 2.0)
KEPT = Cuboid(tuple(np.array(BOX_MM) / 1000), tuple(np.array(CENTRE_MM) / 1000))  # model frame
CENTRED = Cuboid(tuple(np.array(BOX_MM) / 1000))  # recentred on the box
T_A = pose([0.4, -0.3, 0.2], [0.01, -0.005, 0.35])
T_B = pose([-0.5, 0.6, 1.2], [-0.02, 0.015, 0.4])
IMAGE_SIZE = (96, 96)  # (height, width): the 160x120 images become 96x72, centred


def _marked_image(poses: list[np.ndarray]) -> np.ndarray:
    """A dark image with a bright dot on each projected cuboid keypoint of ``poses``."""
    image = np.full((SIZE[1], SIZE[0], 3), 20, np.uint8)
    for uv in project_keypoints(KEPT, np.array(poses), K_BOP).reshape(-1, 2):
        cv2.circle(image, (int(round(uv[0])), int(round(uv[1]))), 3, (255, 255, 255), -1)
    return image


@pytest.fixture
def bop(tmp_path: Path) -> tuple[Path, Path]:
    models = write_models(tmp_path / "models", obj_id=1, size_mm=BOX_MM, centre_mm=CENTRE_MM)
    gt = {0: [(1, T_A)], 3: [(2, T_B)], 4: [(1, T_A), (2, T_A), (1, T_B)]}
    images = {0: _marked_image([T_A]), 4: _marked_image([T_A, T_B])}
    scene = write_scene(tmp_path / "train" / "000001", gt, images)
    return scene, models


def _spec(scene, models, cuboid=KEPT, num_samples=5, **options) -> SourceSpec:
    return SourceSpec(options={"scenes": [str(scene)], "models": str(models), "obj_id": 1,
                               **options},
                      object_name="obj_000001", cuboid=cuboid, mesh=None,
                      num_samples=num_samples, image_size=IMAGE_SIZE, seed=0)


def test_samples_are_the_images_with_the_object_and_its_projected_cuboid(bop) -> None:
    assert "bop" in list_sources()
    source = build_source("bop", _spec(*bop))
    assert len(source) == 5 and source.object_name == "obj_000001"
    assert "2 BOP images of object 1" in source.description
    a, b = source[0].check(), source[1].check()  # images 0 and 4; 3 lacks the object
    assert a.image.shape == (96, 96, 3) and a.num_instances == 1 and b.num_instances == 2
    np.testing.assert_allclose(a.poses[0], T_A)
    np.testing.assert_allclose(b.poses, [T_A, T_B])
    # K of the 0.6 x letterbox: f x 0.6; the 96x72 image's pixel edges at 0..96 and 12..84
    np.testing.assert_allclose(a.K, [[180.0, 0, 0.6 * 80 - 0.5], [0, 186.0, 0.6 * 60 + 12 - 0.5],
                                     [0, 0, 1]], atol=1e-9)
    for sample in (a, b):
        kps = sample.keypoints.reshape(-1, 2)
        np.testing.assert_allclose(kps, project_keypoints(KEPT, sample.poses, sample.K)
                                   .reshape(-1, 2), atol=1e-4)
        inside = (kps > 2).all(1) & (kps < 93).all(1)
        assert inside.sum() >= 9
        grey = sample.image.mean(axis=2)
        at = grey[np.round(kps[inside, 1]).astype(int), np.round(kps[inside, 0]).astype(int)]
        assert at.min() > 120, at  # each keypoint lands on its dot
    assert grey[:10].std() < 1 and grey[:10].mean() > 100  # the band: the mean colour
    np.testing.assert_array_equal(source[2].image, a.image)  # repeats after the images


def test_a_recentred_cuboid_moves_the_poses_not_the_keypoints(bop) -> None:
    kept = build_source("bop", _spec(*bop))[1]
    centred = build_source("bop", _spec(*bop, cuboid=CENTRED))[1]
    np.testing.assert_allclose(centred.keypoints, kept.keypoints, atol=1e-4)
    d = np.array(CENTRE_MM) / 1000
    for T_c, T_k in zip(centred.poses, kept.poses, strict=True):
        np.testing.assert_allclose(T_c[:3, 3], T_k[:3, 3] + T_k[:3, :3] @ d, atol=1e-12)


def test_scene_patterns_and_bad_options(bop, tmp_path: Path) -> None:
    scene, models = bop
    source = build_source("bop", _spec(str(scene.parent / "0000*"), models, num_samples=2))
    assert [s.folder for s in source.scenes] == [scene]
    with pytest.raises(ConfigError, match="data.options.scenes: no scene folder matches"):
        build_source("bop", _spec(str(tmp_path / "none*"), models))
    with pytest.raises(ConfigError, match=r"object ids \[1\]"):
        build_source("bop", _spec(scene, models, obj_id=3, cuboid=Cuboid((0.03,) * 3)))
    write_models(models, obj_id=3, size_mm=(30.0, 30.0, 30.0), centre_mm=(0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="data.options: object 3 is in no image"):
        build_source("bop", _spec(scene, models, obj_id=3, cuboid=Cuboid((0.03,) * 3)))


def test_cuboid_and_model_must_agree(bop) -> None:
    with pytest.raises(ConfigError, match="is not the BOP model's bounding box"):
        build_source("bop", _spec(*bop, cuboid=Cuboid((0.04, 0.06, 0.03))))
    with pytest.raises(ConfigError, match="is not the BOP model's bounding box"):
        build_source("bop", _spec(*bop, cuboid=Cuboid(KEPT.dimensions, (0.01, 0.0, 0.0))))
    with pytest.raises(ConfigError, match="obj_id"):
        build_source("bop", SourceSpec(options={"scenes": ["x"], "models": "m"},
                                       object_name="o", cuboid=KEPT, mesh=None, num_samples=1,
                                       image_size=IMAGE_SIZE, seed=0))


def test_training_config_with_a_bop_source(bop) -> None:
    from evtrack.train.config import TrainConfig
    from evtrack.train.data import PoseDataModule

    scene, models = bop
    cfg = TrainConfig.from_dict({
        "object": {"name": "obj_000001", "mesh": str(models / "obj_000001.ply")},
        "data": {"source": "bop", "options": {"scenes": [str(scene)], "models": str(models),
                                              "obj_id": 1},
                 "train_samples": 4, "val_samples": 0, "image_size": [96, 128]},
    })
    data = PoseDataModule(cfg.data, cfg.object.name, cfg.object.cuboid(), cfg.object.mesh)
    data.setup()
    item = data.train_dataloader().dataset[(0, 1)]
    assert item["image"].shape == (3, 96, 128) and item["belief"].shape == (9, 12, 16)
    assert float(item["belief"].max()) > 0.5  # the targets have the object's corners
