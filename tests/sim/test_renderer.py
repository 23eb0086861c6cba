"""The renderer: projection and pixel centres, exact depth (vs. ray casting), texture lookup."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sim_raycast import hit_uv, raycast

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim.errors import RendererUnavailableError
from evtrack.sim.frames import srgb_to_linear
from evtrack.sim.objects import ObjectMesh, load_mesh, make_box, make_can
from evtrack.sim.renderer import Renderer, gl_projection
from evtrack.sim.textures import checker_texture
from evtrack.sim.trajectory import rotvec_to_matrix

# small, off-centre, non-square pixels: a swapped axis or a half-pixel shift would show
CAM = PinholeCamera(150.0, 140.0, 61.3, 44.8, 128, 96)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(np.asarray(rotvec, float))
    T[:3, 3] = t
    return T


def _quad(corners: np.ndarray) -> ObjectMesh:
    return ObjectMesh("quad", corners.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]],
                      np.int32), np.tile(np.float32([0, 0, -1]), (4, 1)),
                      np.zeros((4, 2), np.float32), np.full((1, 1, 3), 255, np.uint8),
                      np.ones((4, 3), np.float32), "test")


def test_projection_matrix_maps_vertices_to_project() -> None:
    P = gl_projection(CAM, 0.05, 20.0)
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.3, 0.3, 50),
                    rng.uniform(0.3, 3.0, 50)], -1)
    clip = np.hstack([pts, np.ones((50, 1))]) @ P.T
    ndc = clip[:, :3] / clip[:, 3:]
    # viewport transform: window x = (ndc + 1) W / 2 has pixel centres at k + 0.5
    win = np.stack([(ndc[:, 0] + 1) * CAM.width / 2, (ndc[:, 1] + 1) * CAM.height / 2], -1)
    expected = CAM.project(torch.from_numpy(pts)).numpy()
    np.testing.assert_allclose(win - 0.5, expected, atol=1e-9)
    assert (np.abs(ndc[:, 2]) < 1).all()
    with pytest.raises(ConfigError, match="distortion"):
        gl_projection(PinholeCamera(100, 100, 50, 50, 100, 100, dist=[0.1, 0, 0, 0]), 0.1, 10)


def test_rasterised_quad_covers_the_pixel_centres_inside_its_projection() -> None:
    """Mask pixel (u, v) is set iff its centre lies inside the projected quad (image order)."""
    # a tilted planar quad: origin + s e1 + t e2 for a convex (s, t) quadrilateral
    e1, e2 = np.array([1.0, 0.05, 0.4]), np.array([-0.1, 1.0, 0.3])
    st = np.array([[-0.11, -0.08], [0.09, -0.1], [0.12, 0.09], [-0.1, 0.07]])
    corners = np.array([0.0, 0.0, 0.65]) + st[:, :1] * e1 + st[:, 1:] * e2
    with Renderer(CAM) as r:
        r.set_object(_quad(corners))
        out = r.render(np.eye(4))
    poly = CAM.project(torch.from_numpy(corners)).numpy()
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    pts = np.stack([u.ravel(), v.ravel()], -1).astype(float)
    signed = []
    for k in range(4):
        a, b = poly[k], poly[(k + 1) % 4]
        e = b - a
        signed.append((e[0] * (pts[:, 1] - a[1]) - e[1] * (pts[:, 0] - a[0])) / np.hypot(*e))
    signed = np.stack(signed, -1)
    inside = ((signed > 0).all(1) | (signed < 0).all(1)).reshape(u.shape)
    near_edge = (np.abs(signed).min(1) < 1e-3).reshape(u.shape)
    assert inside.sum() > 500
    assert np.array_equal(out.mask[~near_edge], inside[~near_edge])
    # depth at pixel centres: the plane through the (planar) quad hit by the pixel ray
    n = np.cross(corners[1] - corners[0], corners[3] - corners[0])
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], -1)
    z = (n @ corners[0]) / (rays @ n)
    np.testing.assert_allclose(out.depth[out.mask], z[out.mask], rtol=2e-6)
    assert (out.depth[~out.mask] == 0).all()


def _depth_vs_raycast(mesh: ObjectMesh, pose: np.ndarray, samples: int = 300) -> int:
    with Renderer(CAM) as r:
        r.set_object(mesh)
        out = r.render(pose)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(out.mask)
    pick = rng.choice(len(xs), min(samples, len(xs)), replace=False)
    uv = np.stack([xs[pick], ys[pick]], -1).astype(float)
    depth, _, _ = raycast(mesh.to_trimesh(), pose, CAM, uv)
    hit = np.isfinite(depth)
    assert hit.mean() > 0.97  # misses only at silhouette pixels
    rendered = out.depth[ys[pick], xs[pick]]
    err = np.abs(rendered[hit] - depth[hit])
    assert np.median(err) < 1e-4
    assert err.max() < 1e-3, err.max()  # 1 mm
    return int(hit.sum())


def test_depth_matches_raycast_procedural() -> None:
    assert _depth_vs_raycast(make_can(seed=0), _pose([0.5, -0.3, 0.2], [0.01, -0.02, 0.35])) > 200
    assert _depth_vs_raycast(make_box(seed=0), _pose([2.5, 0.4, 0.7], [0.0, 0.01, 0.6])) > 200


def test_depth_matches_raycast_ycb(ycb_dir) -> None:
    mesh = load_mesh(ycb_dir / "006_mustard_bottle" / "006_mustard_bottle_textured.gltf")
    assert _depth_vs_raycast(mesh, _pose([1.9, 0.8, -0.4], [0.0, 0.0, 0.45]), samples=150) > 120


def test_texture_lookup_orientation() -> None:
    """Unshaded render colour equals the texture at the ray-cast UV (checker cells)."""
    # 7 colours on 8x8 cells: every row and every column is shifted, so flips show
    colors = ((230, 30, 30), (30, 200, 40), (40, 60, 220), (240, 220, 30), (20, 20, 20),
              (250, 250, 250), (200, 40, 200))
    tex = checker_texture(512, 8, colors)
    box = make_box(seed=0)
    mesh = ObjectMesh("checker", box.vertices, box.faces, box.normals, box.uv, tex,
                      box.colors, "test")
    pose = _pose([0.4, -0.6, 0.1], [0.0, 0.0, 0.45])
    with Renderer(CAM, ambient=1.0, diffuse=0.0) as r:
        r.set_object(mesh)
        out = r.render(pose)
    ys, xs = np.nonzero(out.mask)
    pick = np.random.default_rng(1).choice(len(xs), 400, replace=False)
    uv_pix = np.stack([xs[pick], ys[pick]], -1).astype(float)
    tm = mesh.to_trimesh()
    _, pts, tris = raycast(tm, pose, CAM, uv_pix)
    ok = tris >= 0
    uv = hit_uv(tm, mesh.uv.astype(np.float64), pts[ok], tris[ok])
    # texel (row 0 = top of the image; v grows upwards)
    col = uv[:, 0] * 512
    row = (1.0 - uv[:, 1]) * 512
    cell = 512 / 8
    away = (np.abs(col / cell - np.round(col / cell)) > 0.15) & (
        np.abs(row / cell - np.round(row / cell)) > 0.15)
    # faces seen at grazing angles sample coarse mip levels: keep faces turned to the camera
    normals_cam = tm.face_normals[tris[ok]] @ pose[:3, :3].T
    view = pts[ok] @ pose[:3, :3].T + pose[:3, 3]
    facing = -(normals_cam * view).sum(1) / np.linalg.norm(view, axis=1) > 0.5
    away &= facing
    expected = srgb_to_linear(tex[row.astype(int).clip(0, 511), col.astype(int).clip(0, 511)])
    got = out.rgb[ys[pick][ok], xs[pick][ok]]
    err = np.abs(got - expected).max(axis=1)[away]
    assert away.sum() > 150
    assert (err < 0.02).mean() > 0.97


def test_static_scene_only_and_object_sign() -> None:
    back = _quad(np.array([[-2, -2, 3.0], [2, -2, 3.0], [2, 2, 3.0], [-2, 2, 3.0]]))
    with Renderer(CAM) as r:
        r.add_static(back, np.eye(4), lit=False)
        r.set_object(make_can(seed=0))
        empty = r.render(None)
        assert not empty.mask.any() and np.allclose(empty.depth, 3.0)
        assert np.allclose(empty.rgb, 1.0)
        out = r.render(_pose([0, 0, 0], [0, 0, 0.5]))
        assert out.mask.any() and (out.depth[out.mask] < 0.6).all()
        assert np.allclose(out.depth[~out.mask], 3.0)
        with pytest.raises(ValueError, match="finite"):
            r.render(np.full((4, 4), np.nan))


def test_missing_gl_names_the_system_packages(monkeypatch) -> None:
    import moderngl

    def fail(*args, **kwargs):
        raise RuntimeError("eglGetDisplay failed")

    monkeypatch.setattr(moderngl, "create_standalone_context", fail)
    apt = "apt-get install -y libegl1 libgl1 libgl1-mesa-dri libgbm1"
    with pytest.raises(RendererUnavailableError, match=apt):
        Renderer(CAM)
