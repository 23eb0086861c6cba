"""BOP readers: scene cameras, ground truth, models info, model meshes and scenes."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_scene import DEPTH_SCALE, K_BOP, SIZE, pose, write_models, write_scene

from evtrack.datasets.bop import (
    BopScene,
    bop_model_file,
    is_bop_model_file,
    load_bop_mesh,
    read_models_info,
    read_scene_camera,
    read_scene_gt,
)
from evtrack.errors import ConfigError, EventFileError
from evtrack.sim.errors import MeshFileError

T1 = pose([0.3, -0.2, 0.1], [0.05, -0.02, 0.6])
T2 = pose([-1.0, 0.4, 2.0], [-0.1, 0.03, 0.9])


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    depth = np.full((SIZE[1], SIZE[0]), 0.75, np.float32)
    depth[10, 20] = 0.0
    return write_scene(tmp_path / "000048", {0: [(1, T1)], 2: [(1, T2), (3, T1)]},
                       depths_m={2: depth}, image_ids=[0, 2, 5])


# ---------------------------------------------------------------------------- scene_gt
@pytest.mark.parametrize("nested", [False, True])
def test_scene_gt_is_in_metres_for_flat_and_nested_rotations(tmp_path: Path, nested) -> None:
    folder = write_scene(tmp_path / "s", {0: [(1, T1)], 7: [(2, T2), (1, T1)]}, nested_R=nested)
    raw = json.loads((folder / "scene_gt.json").read_text())
    assert isinstance(raw["0"][0]["cam_R_m2c"][0], list) == nested
    assert raw["0"][0]["cam_t_m2c"][2] == pytest.approx(600.0)  # mm on disk
    gt = read_scene_gt(folder / "scene_gt.json")
    assert sorted(gt) == [0, 7]
    assert [p.obj_id for p in gt[7]] == [2, 1]
    np.testing.assert_allclose(gt[0][0].T_m2c, T1, atol=1e-12)
    np.testing.assert_allclose(gt[7][0].T_m2c, T2, atol=1e-12)
    assert gt[7][0].T_m2c.dtype == np.float64 and gt[7][0].T_m2c.shape == (4, 4)


def test_flat_rotation_is_row_major(tmp_path: Path) -> None:
    path = tmp_path / "scene_gt.json"
    path.write_text(json.dumps({"3": [{"obj_id": 1, "cam_R_m2c": [0, -1, 0, 1, 0, 0, 0, 0, 1],
                                       "cam_t_m2c": [[1.0], [2.0], [3.0]]}]}))
    T = read_scene_gt(path)[3][0].T_m2c
    np.testing.assert_array_equal(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(T[:3, 3], [0.001, 0.002, 0.003])


# ---------------------------------------------------------------------------- scene_camera
def test_scene_camera(scene: Path) -> None:
    cams = read_scene_camera(scene / "scene_camera.json")
    assert sorted(cams) == [0, 2, 5]
    np.testing.assert_array_equal(cams[2].K, K_BOP)
    assert cams[2].depth_scale == DEPTH_SCALE
    np.testing.assert_array_equal(cams[2].R_w2c, np.eye(3))
    np.testing.assert_allclose(cams[2].t_w2c_m, [0.01, -0.02, 0.5])


def test_scene_camera_optional_fields(tmp_path: Path) -> None:
    path = tmp_path / "scene_camera.json"
    path.write_text(json.dumps({"0": {"cam_K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]]}}))
    cam = read_scene_camera(path)[0]
    assert cam.depth_scale == 1.0 and cam.R_w2c is None and cam.t_w2c_m is None
    assert cam.K[0, 2] == 320.0


# ---------------------------------------------------------------------------- scenes
def test_scene_images_depth_and_poses(scene: Path) -> None:
    s = BopScene(scene)
    assert s.image_ids == [0, 2, 5]  # gaps allowed; image 5 has no ground truth
    assert s.object_ids == [1, 3]
    assert s.scene_id == 48
    rgb = s.rgb(2)
    assert rgb.shape == (SIZE[1], SIZE[0], 3) and rgb.dtype == np.uint8
    on_disk = cv2.imread(str(scene / "rgb" / "000002.png"))
    np.testing.assert_array_equal(rgb, on_disk[..., ::-1])  # RGB, not OpenCV's BGR
    raw = cv2.imread(str(scene / "depth" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert raw[0, 0] == 7500  # 0.75 m = 750 mm = 7500 x depth_scale 0.1
    depth = s.depth_m(2)
    assert depth.dtype == np.float32 and depth.shape == (SIZE[1], SIZE[0])
    assert depth[0, 0] == pytest.approx(0.75, abs=1e-6) and depth[10, 20] == 0.0
    assert [p.obj_id for p in s.poses(2)] == [1, 3]
    np.testing.assert_allclose(s.poses(2, obj_id=3)[0].T_m2c, T1, atol=1e-12)
    assert s.poses(5) == [] and s.poses(2, obj_id=9) == []
    np.testing.assert_array_equal(s.camera(5).K, K_BOP)


def test_scene_reads_jpg_images(scene: Path) -> None:
    rgb = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    rgb[..., 0] = 200  # red
    rgb[..., 1] = np.linspace(0, 100, SIZE[0]).astype(np.uint8)
    (scene / "rgb" / "000000.png").unlink()
    cv2.imwrite(str(scene / "rgb" / "000000.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert np.abs(BopScene(scene).rgb(0).astype(int) - rgb).max() <= 3


def _edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _drop(key: str, field: str):
    return lambda d: d[key].pop(field) if isinstance(d[key], dict) else d[key][0].pop(field)


@pytest.mark.parametrize(("name", "change", "message"), [
    ("scene_camera.json", _drop("2", "cam_K"), "image 2: missing field 'cam_K'"),
    ("scene_camera.json", lambda d: d["2"].update(cam_K=[1, 2, 3]),
     "image 2: field 'cam_K' must hold 9 numbers"),
    ("scene_camera.json", lambda d: d["2"].update(depth_scale="x"),
     "image 2: field 'depth_scale' must be a number"),
    ("scene_camera.json", lambda d: d.update(abc={}), "image id 'abc' is not an integer"),
    ("scene_gt.json", _drop("2", "cam_t_m2c"), "image 2, instance 0: missing field 'cam_t_m2c'"),
    ("scene_gt.json", _drop("0", "obj_id"), "image 0, instance 0: missing field 'obj_id'"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[1, 0, 0, 0, 2, 0, 0, 0, 1]),
     "image 0, instance 0: field 'cam_R_m2c' is not a rotation matrix"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[[1, 0], [0, 1]]),
     "field 'cam_R_m2c' must hold 9 numbers, got shape (2, 2)"),
    ("scene_gt.json", lambda d: d.update({"4": [{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0,
                                                                             0, 0, 1],
                                                 "cam_t_m2c": [0, 0, 1]}]}),
     "image 4 has ground truth but no camera in scene_camera.json"),
])
def test_bad_scene_json_names_file_and_field(scene: Path, name, change, message) -> None:
    _edit_json(scene / name, change)
    with pytest.raises(EventFileError) as info:
        BopScene(scene)
    text = str(info.value)
    assert message in text and str(scene / name) in text and "\n" not in text


@pytest.mark.parametrize("name", ["scene_camera.json", "scene_gt.json"])
def test_missing_or_malformed_json(scene: Path, name) -> None:
    (scene / name).write_text('{"0": [')
    with pytest.raises(EventFileError, match=f"{name}: invalid JSON"):
        BopScene(scene)
    (scene / name).unlink()
    with pytest.raises(EventFileError, match=f"{name}: file not found"):
        BopScene(scene)


def test_missing_and_malformed_images(scene: Path) -> None:
    s = BopScene(scene)
    (scene / "rgb" / "000002.png").unlink()
    with pytest.raises(EventFileError, match=r"rgb/000002\.png: RGB image of image 2 not found"):
        s.rgb(2)
    cv2.imwrite(str(scene / "rgb" / "000002.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(EventFileError, match=r"000002\.png: expected an 8-bit RGB image, got "
                                             r"shape \(4, 4\)"):
        s.rgb(2)
    cv2.imwrite(str(scene / "depth" / "000005.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(EventFileError, match=r"depth/000005\.png: expected a single-channel "
                                             "uint16 depth image"):
        s.depth_m(5)
    (scene / "depth" / "000000.png").unlink()
    with pytest.raises(EventFileError, match=r"depth/000000\.png: depth image of image 0 not"):
        s.depth_m(0)
    with pytest.raises(EventFileError, match="scene_camera.json: no image 3"):
        s.camera(3)


def test_missing_scene_folder(tmp_path: Path) -> None:
    with pytest.raises(EventFileError, match="BOP scene folder not found"):
        BopScene(tmp_path / "nope")


# ---------------------------------------------------------------------------- models
def test_models_info_in_metres(tmp_path: Path) -> None:
    folder = write_models(tmp_path / "models")
    write_models(folder, obj_id=3, size_mm=(10.0, 10.0, 10.0))
    info = read_models_info(folder / "models_info.json")
    assert sorted(info) == [1, 3]
    m = info[1]
    assert m.obj_id == 1
    assert m.diameter == pytest.approx(np.linalg.norm([0.04, 0.06, 0.02]))
    np.testing.assert_allclose(m.min, [-0.015, -0.033, -0.008])
    np.testing.assert_allclose(m.size, [0.04, 0.06, 0.02])
    assert m.symmetric
    np.testing.assert_allclose(m.symmetries_discrete[0][:3, 3], [0.01, -0.006, 0.0])
    np.testing.assert_allclose(m.symmetries_discrete[0][:3, :3], np.diag([-1.0, -1.0, 1.0]))
    np.testing.assert_allclose(m.symmetries_continuous[0].axis, [0, 0, 1])
    np.testing.assert_allclose(m.symmetries_continuous[0].offset, [0.005, -0.003, 0.0])


def test_models_info_without_symmetries_or_box(tmp_path: Path) -> None:
    path = tmp_path / "models_info.json"
    path.write_text(json.dumps({"2": {"diameter": 100.0}}))
    m = read_models_info(path)[2]
    assert not m.symmetric and m.min is None and m.size is None and m.diameter == 0.1


@pytest.mark.parametrize(("entry", "message"), [
    ({"min_x": 1.0}, "object 1: missing field 'diameter'"),
    ({"diameter": -4.0}, "object 1: field 'diameter' must be > 0"),
    ({"diameter": 4.0, "min_x": 1, "min_y": 1}, "object 1: missing field 'min_z'"),
    ({"diameter": 4.0, "symmetries_discrete": [[1, 0, 0]]},
     "object 1: field 'symmetries_discrete' entry 0 must hold 16 numbers"),
    ({"diameter": 4.0, "symmetries_continuous": [{"offset": [0, 0, 0]}]},
     "object 1, symmetries_continuous[0]: missing field 'axis'"),
])
def test_bad_models_info(tmp_path: Path, entry, message) -> None:
    path = tmp_path / "models_info.json"
    path.write_text(json.dumps({"1": entry}))
    with pytest.raises(EventFileError) as info:
        read_models_info(path)
    assert str(info.value).startswith(f"{path}: {message}")


def test_model_file_and_unknown_id(tmp_path: Path) -> None:
    folder = write_models(tmp_path / "models", obj_id=2)
    write_models(folder, obj_id=7)
    assert bop_model_file(folder, 7) == folder / "obj_000007.ply"
    with pytest.raises(ConfigError, match=r"models: no model of object 5 \(obj_000005.ply\); "
                                          r"the folder holds object ids \[2, 7\]"):
        bop_model_file(folder, 5)


def test_bop_mesh_in_metres_in_the_model_frame_with_its_texture(tmp_path: Path) -> None:
    folder = write_models(tmp_path / "models", texture=True)
    mesh = load_bop_mesh(folder, 1)
    assert mesh.name == "obj_000001"
    np.testing.assert_allclose(mesh.vertices.min(0), [-0.015, -0.033, -0.008], atol=1e-7)
    np.testing.assert_allclose(mesh.vertices.max(0), [0.025, 0.027, 0.012], atol=1e-7)
    np.testing.assert_array_equal(mesh.offset, 0.0)  # not recentred
    assert mesh.texture.shape == (8, 8, 3)
    np.testing.assert_array_equal(mesh.texture[0, 0], [255, 0, 0])  # the red TextureFile
    assert np.ptp(mesh.uv, axis=0).min() > 0.9


def test_bop_mesh_in_the_wrong_unit(tmp_path: Path) -> None:
    folder = write_models(tmp_path / "models", diameter_mm=0.072)  # diameter in metres
    with pytest.raises(EventFileError, match=r"obj_000001\.ply: the mesh read as millimetres "
                                             r"spans 0\.06 m .* 'diameter' 0\.072 mm for object 1"):
        load_bop_mesh(folder, 1)


def test_mesh_loaders_recognise_bop_models(tmp_path: Path) -> None:
    from evtrack.models.cuboid import Cuboid
    from evtrack.sim.objects import load_mesh, resolve_object

    folder = write_models(tmp_path / "models", obj_id=5)
    path = folder / "obj_000005.ply"
    assert is_bop_model_file(path)
    kept = load_mesh(path, recenter=False)  # the tracker's way: mm -> m, frame kept
    np.testing.assert_allclose(kept.vertices.min(0), [-0.015, -0.033, -0.008], atol=1e-7)
    centred = resolve_object(str(path))  # the simulator's way: recentred
    np.testing.assert_allclose(centred.extents, [0.04, 0.06, 0.02], atol=1e-7)
    np.testing.assert_allclose(centred.offset, [0.005, -0.003, 0.002], atol=1e-9)
    np.testing.assert_allclose(resolve_object(f"bop:{folder}:5").vertices, centred.vertices)
    box = Cuboid.from_mesh(path)
    np.testing.assert_allclose(box.dimensions, [0.04, 0.06, 0.02], atol=1e-9)
    np.testing.assert_allclose(box.center, [0.005, -0.003, 0.002], atol=1e-9)
    with pytest.raises(MeshFileError, match=r"object size 60 \(after scale=1.0\)"):
        load_mesh(path, scale=1.0)  # an explicit scale wins
    with pytest.raises(ConfigError, match="expected bop:MODELS_DIR:OBJ_ID"):
        resolve_object(f"bop:{folder}:five")
    with pytest.raises(ConfigError, match=r"object ids \[5\]"):
        resolve_object(f"bop:{folder}:6")


def test_a_model_outside_a_bop_folder_keeps_its_unit(tmp_path: Path) -> None:
    from evtrack.sim.objects import load_mesh

    folder = write_models(tmp_path / "models")
    (folder / "models_info.json").unlink()
    assert not is_bop_model_file(folder / "obj_000001.ply")
    with pytest.raises(MeshFileError, match="object size 60 "):
        load_mesh(folder / "obj_000001.ply")


def test_depth_refiner_reads_a_bop_model_in_metres(tmp_path: Path) -> None:
    from evtrack.models.depth_refine import DepthRefiner

    folder = write_models(tmp_path / "models", obj_id=2)
    refiner = DepthRefiner.from_mesh(folder / "obj_000002.ply")
    np.testing.assert_allclose(refiner.hull_points.max(0) - refiner.hull_points.min(0),
                               [0.04, 0.06, 0.02], atol=1e-9)
    np.testing.assert_allclose(refiner.centre, [0.005, -0.003, 0.002], atol=1e-9)
    wrong = write_models(tmp_path / "wrong", obj_id=2, diameter_mm=0.072)
    with pytest.raises(EventFileError, match=r"obj_000002\.ply: the mesh read as millimetres"):
        DepthRefiner.from_mesh(wrong / "obj_000002.ply")
