"""Planes: the textured rectangle's frame, facing and texture, the plane that fills a view."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim import facing_pose, plane_facing_camera, plane_mesh, view_plane_size
from evtrack.sim.objects import load_mesh

DAVIS = PinholeCamera(199.092366542, 198.82882047, 132.192071378, 110.712660011, 240, 180,
                      [-0.368436311798, 0.150947243557, -0.000296130534385,
                       -0.000759431726241, 0.0])


def test_plane_mesh_frame_and_facing() -> None:
    m = plane_mesh(0.6, 0.4, segments=(3, 2))
    assert len(m.vertices) == 12 and len(m.faces) == 12
    np.testing.assert_allclose(m.extents, [0.6, 0.4, 0.0], atol=1e-6)
    np.testing.assert_allclose(m.vertices.min(0) + m.vertices.max(0), 0.0, atol=1e-6)
    np.testing.assert_allclose(m.normals, np.tile([0.0, 0.0, -1.0], (12, 1)))
    # every face's winding agrees: its normal looks towards -z (at a camera at the facing pose)
    tm = m.to_trimesh()
    np.testing.assert_allclose(tm.face_normals, np.tile([0.0, 0.0, -1.0], (12, 1)), atol=1e-6)
    # upright texture: row 0 (v = 1) at y = -h/2, the camera's up; column 0 (u = 0) at x = -w/2
    top = m.vertices[:, 1] < -0.19
    left = m.vertices[:, 0] < -0.29
    assert (m.uv[top, 1] == 1.0).all() and (m.uv[~top, 1] < 1.0).all()
    assert (m.uv[left, 0] == 0.0).all() and (m.uv[~left, 0] > 0.0).all()


def test_plane_mesh_texture_and_errors() -> None:
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    m = plane_mesh(1.0, 1.0, grey)
    assert m.texture.shape == (3, 4, 3) and (m.texture[..., 0] == grey).all()
    assert plane_mesh(2.0, 1.0, seed=1).texture.shape == (512, 1024, 3)
    assert np.array_equal(plane_mesh(2.0, 1.0, seed=1).texture,
                          plane_mesh(2.0, 1.0, seed=1).texture)
    for bad in ((0.0, 1.0), (1.0, -1.0), (float("nan"), 1.0)):
        with pytest.raises(ConfigError, match="plane size"):
            plane_mesh(*bad)
    with pytest.raises(ConfigError, match="segments"):
        plane_mesh(1.0, 1.0, segments=(0, 1))
    with pytest.raises(ConfigError, match="uint8"):
        plane_mesh(1.0, 1.0, np.zeros((4, 4), np.float32))


def test_view_plane_size_of_a_pinhole() -> None:
    cam = PinholeCamera(500.0, 400.0, 300.0, 200.0, 640, 480)
    w, h = view_plane_size(cam, 2.0, margin=1.5)
    # the farther pixel edge from the principal point, either side
    assert w == pytest.approx(2 * (640 - 300 - 0.5) / 500.0 * 2.0 * 1.5)
    assert h == pytest.approx(2 * (480 - 200 - 0.5) / 400.0 * 2.0 * 1.5)
    with pytest.raises(ConfigError, match="depth"):
        view_plane_size(cam, 0.0)


def test_plane_covers_a_distorted_view() -> None:
    """Every pixel's ray, lens distortion undone, meets the plane at its facing pose."""
    depth = 1.3
    w, h = view_plane_size(DAVIS, depth)
    ys, xs = np.mgrid[-0.5:180:4.0, -0.5:240:4.0]
    uv = torch.tensor(np.stack([xs.ravel(), ys.ravel()], 1))
    P = DAVIS.unproject(uv, torch.full((len(uv),), depth, dtype=torch.float64)).numpy()
    assert (np.abs(P[:, 0]) <= w / 2 + 1e-9).all() and (np.abs(P[:, 1]) <= h / 2 + 1e-9).all()
    # and it is tight: some ray meets it near its edge
    assert np.abs(P[:, 0]).max() > 0.98 * w / 2 and np.abs(P[:, 1]).max() > 0.98 * h / 2


def test_plane_textured_with_the_camera_image() -> None:
    """A texel shows the image's colour where its plane point projects (distortion applied)."""
    rng = np.random.default_rng(0)
    image = (rng.random((180 // 10, 240 // 10)) * 255).astype(np.uint8)
    image = np.kron(image, np.ones((10, 10), np.uint8))  # 10-px blocks: colours checkable
    depth = 0.9
    m = plane_facing_camera(DAVIS, depth, margin=1.25, image=image, texture_px=800)
    th, tw = m.texture.shape[:2]
    w, h = m.extents[:2]
    checked = 0
    for _ in range(400):
        i, j = rng.integers(0, th), rng.integers(0, tw)
        P = np.array([(j + 0.5) / tw * w - w / 2, (i + 0.5) / th * h - h / 2, depth])
        u, v = DAVIS.project(torch.from_numpy(P)).numpy()
        iu, iv = int(round(u)), int(round(v))
        if not (2 <= iu < 238 and 2 <= iv < 178) or (iu % 10 in (0, 9)) or (iv % 10 in (0, 9)):
            continue  # outside the image, or next to a block edge
        assert m.texture[i, j, 0] == image[iv, iu], (i, j, u, v)
        checked += 1
    assert checked > 50
    # outside the image: the image's mean
    assert abs(int(m.texture[0, 0, 0]) - image.mean()) <= 1


def test_plane_file_round_trip_keeps_the_frame(tmp_path) -> None:
    m = plane_facing_camera(DAVIS, 1.0, segments=(4, 3))
    m.export(tmp_path / "plane.glb")
    back = load_mesh(tmp_path / "plane.glb", recenter=False)
    np.testing.assert_allclose(np.sort(back.vertices, 0), np.sort(m.vertices, 0), atol=1e-6)
    np.testing.assert_allclose(facing_pose(1.0)[:3, 3], [0.0, 0.0, 1.0])
