"""Objects: procedural meshes (sizes, outward normals, seeds), mesh files, name resolution."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from evtrack.errors import ConfigError
from evtrack.sim.errors import MeshFileError
from evtrack.sim.objects import (
    PROCEDURAL_OBJECTS,
    load_mesh,
    procedural_object,
    resolve_object,
)

# YCB extents (sorted, metres) the procedural stand-ins should resemble
YCB_LIKE = {"box": (0.072, 0.164, 0.213), "coded_box": (0.072, 0.164, 0.213),
            "can": (0.068, 0.068, 0.102), "bottle": (0.067, 0.097, 0.191)}


@pytest.mark.parametrize("kind", PROCEDURAL_OBJECTS)
def test_procedural_objects(kind: str) -> None:
    a = procedural_object(kind, seed=1)
    np.testing.assert_allclose(np.sort(a.extents), YCB_LIKE[kind], rtol=0.05)
    np.testing.assert_allclose(a.vertices.min(0) + a.vertices.max(0), 0.0, atol=1e-6)
    assert a.uv.min() >= 0 and a.uv.max() <= 1
    assert np.allclose(np.linalg.norm(a.normals, axis=1), 1.0, atol=1e-5)
    # closed surface with normals pointing outwards: positive volume, faces agree with normals
    tm = a.to_trimesh()
    assert tm.volume > 0.5 * np.prod(a.extents) * (1.0 if "box" in kind else 0.5)
    ok = np.linalg.norm(tm.face_normals, axis=1) > 0
    centroid_dir = tm.triangles_center[ok]
    assert ((tm.face_normals[ok] * centroid_dir).sum(1) > 0).mean() > 0.95
    # texture has edges everywhere on the object (for events): strong gradients in most of
    # the 32x32 tiles that the mesh's UV triangles cover
    th, tw = a.texture.shape[:2]
    used = np.zeros((th, tw), np.uint8)
    px = np.stack([a.uv[:, 0] * (tw - 1), (1 - a.uv[:, 1]) * (th - 1)], -1)
    for f in a.faces:
        cv2.fillConvexPoly(used, np.round(px[f]).astype(np.int32), 1)
    gray = a.texture.astype(float).mean(2)
    g = np.maximum(np.abs(np.diff(gray, axis=1))[:-1], np.abs(np.diff(gray, axis=0))[:, :-1])
    n = 32
    crop = (slice(0, (th - 1) // n * n), slice(0, (tw - 1) // n * n))
    tiles = g[crop].reshape((th - 1) // n, n, -1, n).max(axis=(1, 3))
    covered = used[crop].reshape((th - 1) // n, n, -1, n).mean(axis=(1, 3)) > 0.9
    assert covered.sum() > 50
    assert (tiles[covered] > 30).mean() > 0.8
    b = procedural_object(kind, seed=1)
    c = procedural_object(kind, seed=2)
    assert np.array_equal(a.texture, b.texture) and not np.array_equal(a.texture, c.texture)


def test_export_and_reload_keeps_the_frame(tmp_path) -> None:
    can = procedural_object("can", seed=0)
    can.export(tmp_path / "can.glb")
    back = load_mesh(tmp_path / "can.glb", recenter=False)
    np.testing.assert_allclose(back.vertices, can.vertices, atol=1e-7)
    np.testing.assert_allclose(back.uv, can.uv, atol=1e-6)
    np.testing.assert_array_equal(back.faces, can.faces)
    assert np.abs(back.texture.astype(int) - can.texture.astype(int)).max() <= 1


def test_load_ycb_recentred(ycb_dir) -> None:
    path = ycb_dir / "003_cracker_box" / "003_cracker_box_textured.gltf"
    raw = trimesh.load(path, process=False).to_geometry()
    mesh = load_mesh(path)
    assert mesh.name == "003_cracker_box"
    np.testing.assert_allclose(mesh.offset, raw.bounds.mean(0), atol=1e-9)
    np.testing.assert_allclose(mesh.vertices, raw.vertices - raw.bounds.mean(0), atol=1e-6)
    assert mesh.texture.shape[2] == 3 and mesh.texture.shape[0] >= 1024
    assert len(mesh.faces) == 16384
    same = resolve_object("cracker_box", ycb_dir=ycb_dir)
    np.testing.assert_array_equal(same.vertices, mesh.vertices)


def test_vertex_coloured_mesh(tmp_path) -> None:
    tm = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    tm.visual.vertex_colors = np.tile([255, 0, 0, 255], (len(tm.vertices), 1))
    tm.export(tmp_path / "sphere.ply")
    mesh = load_mesh(tmp_path / "sphere.ply")
    np.testing.assert_allclose(mesh.colors[0], [1.0, 0.0, 0.0], atol=1e-6)
    assert mesh.texture.shape == (1, 1, 3)


def test_mesh_errors(tmp_path) -> None:
    with pytest.raises(MeshFileError, match="not found"):
        load_mesh(tmp_path / "nope.glb")
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(MeshFileError, match="bad.glb"):
        load_mesh(bad)
    big = trimesh.creation.box(extents=(150.0, 200.0, 70.0))  # millimetres
    big.export(tmp_path / "mm.ply")
    with pytest.raises(MeshFileError, match="wrong units"):
        load_mesh(tmp_path / "mm.ply")
    assert load_mesh(tmp_path / "mm.ply", scale=1e-3).extents.max() == pytest.approx(0.2)
    with pytest.raises(ConfigError, match="unknown object"):
        resolve_object("teapot")
    with pytest.raises(ConfigError, match="needs the YCB meshes"):
        resolve_object("003_cracker_box", ycb_dir=tmp_path / "missing")


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_box_faces_have_distinct_base_colours(seed):
    """Every face of the procedural box is printed on its own hue (corners can be told apart)."""
    from evtrack.sim.objects import make_box

    atlas = make_box(seed=seed).texture
    cell = atlas.shape[0] // 2
    hues = []
    for row in range(2):
        for col in range(3):
            panel = atlas[row * cell:(row + 1) * cell, col * cell:(col + 1) * cell]
            hsv = cv2.cvtColor(np.ascontiguousarray(panel), cv2.COLOR_RGB2HSV)
            hist = np.bincount(hsv[..., 0].ravel(), minlength=180)
            hues.append(int(np.argmax(hist)))  # the dominant hue: the panel's base colour
    gaps = [min(abs(a - b), 180 - abs(a - b)) for i, a in enumerate(hues) for b in hues[i + 1:]]
    assert min(gaps) >= 20, hues  # evenly spread hues are 30 apart (OpenCV hue: 0..180)
