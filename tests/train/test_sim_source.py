"""The ``sim`` source: renders of the engine's objects, with keypoints in the engine's frame."""

from __future__ import annotations

import itertools
import pickle

import cv2
import numpy as np
import pytest

from evtrack.errors import ConfigError
from evtrack.models import Cuboid
from evtrack.train import SourceSpec, build_source
from evtrack.train.config import ObjectConfig
from evtrack.train.sim_source import SimSource, SimSourceOptions, sim_object_cuboid

SIZE = (96, 128)


def hull_of(cuboid: Cuboid, pose: np.ndarray, K: np.ndarray) -> np.ndarray:
    c, d = np.asarray(cuboid.center), np.asarray(cuboid.dimensions)
    P = np.array([c + d / 2 * np.array(s) for s in itertools.product((-1, 1), repeat=3)])
    P = P @ pose[:3, :3].T + pose[:3, 3]
    uv = np.stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]], 1)
    return cv2.convexHull(uv.astype(np.float32))


def check_object_fills_its_cuboid(source: SimSource, index: int) -> None:
    """Render the sample's pose alone: the object's mask lies inside the projected cuboid and
    touches it (so the cuboid, the keypoints and the engine's object frame agree)."""
    from evtrack.sim.renderer import Renderer

    sample = source[index]
    with Renderer(source.camera) as r:
        r.set_object(source._mesh)
        mask = r.render(sample.poses[0]).mask
    hull = hull_of(source.cuboid, sample.poses[0], sample.K)
    ys, xs = np.nonzero(mask)
    assert len(xs) > 30
    inside = [cv2.pointPolygonTest(hull, (float(x), float(y)), True)
              for x, y in zip(xs, ys, strict=True)]
    assert min(inside) > -1.0  # no object pixel outside the cuboid's outline
    x0, y0, w, h = cv2.boundingRect(hull)
    assert xs.min() - x0 < 0.2 * w and (x0 + w) - xs.max() < 0.2 * w + 1  # and it fills it
    assert ys.min() - y0 < 0.2 * h and (y0 + h) - ys.max() < 0.2 * h + 1


def test_procedural_box_renders_inside_its_keypoints(gl):
    cuboid = sim_object_cuboid("box")
    assert cuboid.dimensions == pytest.approx((0.16, 0.21, 0.07), abs=1e-6)
    src = SimSource("box", cuboid, 40, SIZE, object_name="box", seed=3, options=SimSourceOptions(
        samples_per_scene=20, blur_probability=0.0, max_distractors=1, z_range=(0.6, 0.9)))
    first = src[0].image.copy()
    assert first.shape == (*SIZE, 3) and first.dtype == np.uint8
    assert src[25].image.shape == first.shape  # another scene
    np.testing.assert_array_equal(src[0].image, first)  # back again: the same bytes
    for i in (0, 1):
        s = src[i]
        s.check()
        np.testing.assert_allclose(s.keypoints[0, 8], (s.K @ s.poses[0][:3, 3] /
                                                         s.poses[0][2, 3])[:2], atol=1e-3)
        check_object_fills_its_cuboid(src, i)
    clone = pickle.loads(pickle.dumps(src))
    np.testing.assert_array_equal(clone[1].image, src[1].image)
    src.close()


def test_blurred_samples_differ_from_sharp_ones(gl):
    cuboid = sim_object_cuboid("can")
    opts = dict(samples_per_scene=4, max_distractors=0, z_range=(0.4, 0.5))
    sharp = SimSource("can", cuboid, 1, SIZE, object_name="can",
                      options=SimSourceOptions(blur_probability=0.0, **opts))[0]
    blurred = SimSource("can", cuboid, 1, SIZE, object_name="can", options=SimSourceOptions(
        blur_probability=1.0, blur_renders=6, max_linear_speed=3.0, **opts))[0]
    assert np.abs(sharp.image.astype(int) - blurred.image.astype(int)).mean() > 0.5


def test_ycb_mesh_frame_matches_the_config_cuboid(gl, ycb_dir):
    mesh = str(ycb_dir / "003_cracker_box" / "003_cracker_box_textured.gltf")
    cuboid = ObjectConfig(name="003_cracker_box", mesh=mesh).cuboid()
    assert cuboid.center == (0.0, 0.0, 0.0)
    spec = SourceSpec({"samples_per_scene": 8, "blur_probability": 0.0, "max_distractors": 0,
                       "z_range": [0.5, 0.7]}, "003_cracker_box", cuboid, mesh, 2, SIZE, 0)
    src = build_source("sim", spec)
    check_object_fills_its_cuboid(src, 0)
    src.close()
    off_centre = ObjectConfig(name="003_cracker_box", mesh=mesh, recenter=False).cuboid()
    with pytest.raises(ConfigError, match="differs from the engine's mesh"):
        build_source("sim", SourceSpec({}, "x", off_centre, mesh, 2, SIZE, 0))


def test_engine_names_give_the_cuboid_and_options_are_checked():
    pytest.importorskip("moderngl")
    assert ObjectConfig(name="bottle").cuboid() == sim_object_cuboid("bottle")
    with pytest.raises(ConfigError, match=r"^data\.options: unknown field\(s\) \['fov'\]"):
        SimSourceOptions.from_dict({"fov": 1}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: z_range: must be 0 < low <= high, "
                       r"got \(1\.0, 0\.5\)"):
        SimSourceOptions.from_dict({"z_range": [1.0, 0.5]}, "data.options")


def test_demo_config_trains_end_to_end_on_renders(gl, tmp_path, monkeypatch, capsys):
    from pathlib import Path

    from evtrack.cli import main

    repo = Path(__file__).resolve().parents[2]
    monkeypatch.chdir(tmp_path)
    args = ["train", "--config", str(repo / "configs" / "pose_demo_box.yaml"), "--quiet",
            "--set", "model.name=dope_lite_tiny", "--set", "data.train_samples=4",
            "--set", "data.val_samples=2", "--set", "data.image_size=[48, 64]",
            "--set", "data.batch_size=2", "--set", "data.num_workers=0",
            "--set", "data.options.samples_per_scene=8", "--set", "trainer.max_epochs=1",
            "--set", "optim.warmup_steps=0"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "weights:" in out and "val/loss" in out
    assert len(list((tmp_path / "runs" / "cache").iterdir())) == 2  # train and val shards
    from evtrack.models import load_model

    _, record = load_model(tmp_path / "runs/pose/box_dope_lite_tiny/box_dope_lite_tiny.pt")
    assert record.object_name == "box" and "evtrack.sim renders" in record.training_data


def _distractor_sources(kinds, seeds=range(12)):
    from evtrack.camera import PinholeCamera
    from evtrack.sim.config import SceneConfig
    from evtrack.sim.scene import build_scene

    cam = PinholeCamera(150.0, 150.0, 79.5, 59.5, 160, 120)
    found = set()
    for seed in seeds:
        scene = build_scene(SceneConfig(randomize=True, max_distractors=4,
                                        distractor_kinds=kinds), cam,
                            np.random.default_rng(seed))
        found |= {p.mesh.source.split(":")[1] for p in scene.parts
                  if p.mesh.name.startswith("distractor")}
    return found


def test_training_scenes_of_a_procedural_object_have_no_look_alike_distractors():
    assert _distractor_sources(("box", "can", "bottle")) == {"box", "can", "bottle"}
    assert _distractor_sources(("can", "bottle")) == {"can", "bottle"}
    assert _distractor_sources(()) == set()
    with pytest.raises(ConfigError, match="distractor_kinds"):
        _distractor_sources(("cube",), seeds=[0, 1, 2])
    spec = SourceSpec(options={}, object_name="box", cuboid=sim_object_cuboid("box"),
                      mesh=None, num_samples=4, image_size=(64, 96), seed=0)
    box_source = build_source("sim", spec)
    assert box_source._distractor_kinds() == ("can", "bottle")
    spec = SourceSpec(options={"distractor_kinds": ["box"]}, object_name="box",
                      cuboid=sim_object_cuboid("box"), mesh=None, num_samples=4,
                      image_size=(64, 96), seed=0)
    assert build_source("sim", spec)._distractor_kinds() == ("box",)


def test_view_bias_draws_rotations_around_the_given_views():
    """``view_probability`` of the samples look at the object from around one of
    ``view_directions`` (object frame, towards the camera): with 10 deg of noise per axis the
    angle to the chosen direction has a median near 12 deg; the rotations are proper; the
    other samples keep the uniform draw, and without the option the poses are those of the
    plain source, draw for draw."""
    pytest.importorskip("moderngl")
    views = np.array([[0.7, 0.65, 0.28], [0.1, -0.98, 0.1]])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    cuboid = sim_object_cuboid("bottle")

    def poses(**options):
        src = SimSource("bottle", cuboid, 8, SIZE, object_name="bottle", seed=3,
                        options=SimSourceOptions(**options))
        rng = np.random.default_rng(0)
        return [src._random_pose(rng) for _ in range(400)]

    def nearest_view_deg(T: np.ndarray) -> float:
        centre = T[:3, 3] + T[:3, :3] @ np.asarray(cuboid.center)
        towards_camera = T[:3, :3].T @ (-centre / np.linalg.norm(centre))
        return float(np.degrees(np.arccos(np.clip(views @ towards_camera, -1, 1))).min())

    biased = poses(view_directions=[list(v * 3) for v in views], view_probability=1.0,
                   view_spread_deg=10.0)
    angles = np.array([nearest_view_deg(T) for T in biased])
    assert 9.0 < np.median(angles) < 15.0 and np.percentile(angles, 99) < 40.0
    assert all(abs(np.linalg.det(T[:3, :3]) - 1) < 1e-9 for T in biased)
    uniform = np.array([nearest_view_deg(T) for T in poses()])
    assert np.median(uniform) > 40.0  # two directions cover little of the sphere
    half = np.array([nearest_view_deg(T) for T in poses(view_directions=views.tolist(),
                                                        view_probability=0.5)])
    assert 0.35 < np.mean(half < 30.0) < 0.7
    plain = poses()
    off = poses(view_directions=views.tolist(), view_probability=0.0)
    assert all(np.array_equal(a, b) for a, b in zip(plain, off, strict=True))
    with pytest.raises(ConfigError, match=r"^data\.options: view_probability: is 0\.5, which "
                       r"needs view_directions"):
        SimSourceOptions.from_dict({"view_probability": 0.5}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: view_directions: must be non-zero "
                       r"finite \[x, y, z\] directions"):
        SimSourceOptions.from_dict({"view_directions": [[0, 0, 0]], "view_probability": 0.5},
                                   "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: view_probability: must be in "
                       r"\[0, 1\], got 2\.0"):
        SimSourceOptions.from_dict({"view_directions": [[0, 0, 1]], "view_probability": 2},
                                   "data.options")


def test_options_are_read_by_the_config_loader_and_round_trip():
    """Typed fields, ranges and choices without rendering anything."""
    opts = SimSourceOptions.from_dict({
        "z_range": ["1e-1", 2], "distractor_kinds": ["can"], "view_directions": [[0, 2, 0]],
        "view_probability": 0.25, "samples_per_scene": 8.0}, "data.options")
    assert opts.z_range == (0.1, 2.0) and opts.samples_per_scene == 8
    assert opts.distractor_kinds == ("can",) and opts.view_directions == ((0.0, 2.0, 0.0),)
    for cfg in (SimSourceOptions(), opts):
        assert SimSourceOptions.from_dict(cfg.to_dict()) == cfg
    assert SimSourceOptions.from_dict(None) == SimSourceOptions()
    with pytest.raises(ConfigError, match=r"^data\.options: distractor_kinds\[0\]: must be one "
                       r"of \['box', 'can', 'bottle'\], got 'cube'"):
        SimSourceOptions.from_dict({"distractor_kinds": ["cube"]}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: samples_per_scene: must be >= 1, "
                       r"got 0"):
        SimSourceOptions.from_dict({"samples_per_scene": 0}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: margin: must be in \[0, 0\.5\)"):
        SimSourceOptions.from_dict({"margin": 0.5}, "data.options")
    with pytest.raises(ConfigError, match=r"^data\.options: view_directions\[0\]: expected a "
                       r"list of 3 values"):
        SimSourceOptions.from_dict({"view_directions": [[0, 1]]}, "data.options")
    with pytest.raises(ConfigError, match=r"^SimSourceOptions\.z_range: must be > 0 m"):
        SimSourceOptions(z_range=(0.0, 1.0))
    # directions given in code are normalised to float triples
    assert SimSourceOptions(view_directions=[[1, 0, 0]]).view_directions == ((1.0, 0.0, 0.0),)
