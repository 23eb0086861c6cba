"""The object's silhouette (evtrack.tracking.silhouette): point and pixel tests against OpenCV
and each other, coverage of the rendered mask, hulls, visible fractions, boxes in the image
(with and without lens distortion)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from tracker_helpers import SMALL_CAM, rigid_pose

from evtrack.camera import PinholeCamera
from evtrack.tracking.silhouette import (
    Silhouette,
    ideal_view_rectangle,
    pixels_in_polygon,
    points_in_polygon,
)

BARREL_CAM = PinholeCamera(1042.33, 1041.62, 595.39, 405.73, 1280, 720,
                           dist=[-0.4431, 0.2566, -1.084e-3, 6.42e-4, -0.0937])
"""A Prophesee 1280 x 720 event camera's calibration (YCB-Ev): a strong barrel, ~100 px at the
image's sides, its corners beyond the reach of the lens model."""

PINCUSHION_CAM = PinholeCamera(250.0, 240.0, 159.5, 119.5, 320, 240,
                               dist=[0.3, 0.05, 1e-3, -1e-3, 0.0])
"""A strong pincushion: ~20 px at the image's corners."""


def test_points_in_polygon_against_opencv() -> None:
    rng = np.random.default_rng(0)
    poly = cv2.convexHull(rng.uniform(20, 100, (12, 2)).astype(np.float32)).reshape(-1, 2)
    pts = rng.uniform(0, 120, (2000, 2))
    for margin in (0.0, 5.0):
        ours = points_in_polygon(poly[::-1], pts, margin)  # either orientation
        dist = np.array([cv2.pointPolygonTest(poly, (float(x), float(y)), True) for x, y in pts])
        # inside the exact offset region -> inside ours (ours is the mitred, larger offset)
        assert ours[dist >= -margin + 1e-6].all()
        if margin == 0:
            np.testing.assert_array_equal(ours[np.abs(dist) > 1e-6], dist[np.abs(dist) > 1e-6] > 0)


def _random_polygon(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    kind = rng.random()
    if kind < 0.25:  # axis-aligned: horizontal edges (no span from them) and vertical ones
        x0, x1 = np.sort(rng.integers(-20, w + 20, 2) + rng.choice([0.0, 0.5], 2))
        y0, y1 = np.sort(rng.integers(-20, h + 20, 2) + rng.choice([0.0, 0.5], 2))
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)
    if kind < 0.35:  # an edge crossing a row mid-image at slope ~1e-16: which pixels of
        # that row are in is decided by rounding, and dividing by n_x gives no span end
        row, mid, e = float(h // 2), w / 2, 1e-9 * rng.random()
        return np.array([[mid - 1e7, row - e], [mid + 1e7, row + e], [mid, h + 5.0]])
    pts = rng.normal([w / 2, h / 2], [w / 3 * rng.random() + 1, h / 3 * rng.random() + 1],
                     (int(rng.integers(3, 30)), 2))
    if rng.random() < 0.3:  # vertices on pixels: spans end exactly on them
        pts = np.round(pts)
    return cv2.convexHull(pts.astype(np.float32))[:, 0].astype(np.float64)


@pytest.mark.parametrize("compiled", [True, False])
def test_pixels_in_polygon_equals_the_point_test_bit_for_bit(compiled, monkeypatch) -> None:
    """The row-span test answers exactly as the half-plane test on every pixel of the image
    (vertices on pixels, margins that put span ends on pixels, flat and huge polygons), in
    its compiled and its NumPy form."""
    import evtrack.tracking.silhouette as silhouette_module

    if compiled and not silhouette_module.jit_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(silhouette_module, "jit_available", lambda: compiled)
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(600):
        w, h = int(rng.integers(1, 90)), int(rng.integers(1, 90))
        poly = _random_polygon(rng, w, h)
        if len(poly) < 3:
            continue
        poly = poly[::-1] if rng.random() < 0.5 else poly
        margin = float(rng.choice([0.0, 1.0, 2.5, 32.0, 10 * rng.random()]))
        yy, xx = np.mgrid[0:h, 0:w]
        x, y = xx.ravel(), yy.ravel()
        expected = points_in_polygon(poly, np.stack([x, y], 1), margin)
        got = pixels_in_polygon(poly, x, y, margin, (w, h))
        np.testing.assert_array_equal(got, expected)
        checked += int(expected.sum()) * int((~expected).sum()) > 0
    assert checked > 300  # most cases have pixels on both sides
    # degenerate inputs: no pixels, a segment
    assert pixels_in_polygon(poly, np.zeros(0, int), np.zeros(0, int), 1.0, (4, 4)).shape == (0,)
    seg = np.array([[1.0, 1.0], [3.0, 1.0]])
    np.testing.assert_array_equal(pixels_in_polygon(seg, np.array([2, 2]), np.array([1, 3]), 0.5,
                                                    (4, 4)), [True, False])


def test_silhouette_covers_the_rendered_mask(box) -> None:
    from evtrack.sim.renderer import Renderer

    sil = Silhouette(box.vertices, SMALL_CAM)
    with Renderer(SMALL_CAM) as r:
        r.set_object(box)
        for T in [rigid_pose([0.3, -0.5, 0.2], [0.02, -0.01, 0.5]),
                  rigid_pose([1.2, 0.4, -0.9], [0.1, 0.05, 0.7])]:
            out = r.render(T)
            v, u = np.nonzero(out.mask)
            poly = sil.polygon(T)
            assert poly.contains(np.stack([u, v], 1), 1.0).all()
            # tight: the hull of a box's projection is its silhouette, up to pixel coverage
            area = cv2.contourArea(poly.vertices.astype(np.float32))
            assert abs(area - out.mask.sum()) < 0.05 * out.mask.sum() + 2 * len(poly.vertices)
            z = out.depth[out.mask]
            assert poly.z_range[0] <= z.min() + 1e-4 and z.max() <= poly.z_range[1] + 1e-4
    assert sil.polygon(rigid_pose([0, 0, 0], [0, 0, -1.0])) is None  # behind the camera
    outside = sil.polygon(rigid_pose([0, 0, 0], [5.0, 0, 1.0]))
    assert outside.visible_fraction == 0.0


def test_hull_of_two_silhouettes_is_the_swept_area(box) -> None:
    """The hull of a convex silhouette at two positions of a translation parallel to the
    image holds every position in between (the swept area, the event mask of a step group)
    and nothing farther than either, with the depth range of both."""
    sil = Silhouette(box.vertices, SMALL_CAM)
    start = rigid_pose([0.3, -0.5, 0.2], [-0.03, 0.0, 0.5])
    end = rigid_pose([0.3, -0.5, 0.2], [0.03, 0.01, 0.5])
    a, b = sil.polygon(start), sil.polygon(end)
    swept = sil.hull([a, b])
    for s in np.linspace(0.0, 1.0, 11):
        mid = start.copy()
        mid[:3, 3] = (1 - s) * start[:3, 3] + s * end[:3, 3]
        assert swept.contains(sil.polygon(mid).vertices, 1e-3).all()
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [SMALL_CAM.width, SMALL_CAM.height], (4000, 2))
    inside = swept.contains(pts)
    assert (inside >= (a.contains(pts) | b.contains(pts))).all()
    area = cv2.contourArea(swept.vertices.astype(np.float32))
    moved = np.linalg.norm(b.vertices.mean(0) - a.vertices.mean(0))
    assert area > cv2.contourArea(a.vertices.astype(np.float32)) + 0.5 * moved  # it grew
    # nothing beyond both: every hull vertex is a vertex of one of them
    both = np.concatenate([a.vertices, b.vertices])
    assert all(np.abs(both - v).max(1).min() < 1e-3 for v in swept.vertices)
    assert swept.z_range == (min(a.z_range[0], b.z_range[0]), max(a.z_range[1], b.z_range[1]))
    assert swept.visible_fraction == 1.0
    same = sil.hull([a])
    np.testing.assert_allclose(cv2.contourArea(same.vertices.astype(np.float32)),
                               cv2.contourArea(a.vertices.astype(np.float32)), rtol=1e-6)
    with pytest.raises(ValueError, match="at least one polygon"):
        sil.hull([])


@pytest.mark.parametrize("shape", ["cube", "blob"])
def test_visible_fraction_equals_the_polygons(shape) -> None:
    rng = np.random.default_rng(3)
    if shape == "cube":  # the hull is its own bounding box
        points = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05)
                           for z in (-.05, .05)])
    else:  # a hull well inside its bounding box: the box corners leave the image first
        points = rng.normal(0, 0.03, (200, 3)) * [1.0, 2.0, 0.5]
    sil = Silhouette(points, SMALL_CAM)
    partly = whole = 0
    for _ in range(300):
        T = rigid_pose(rng.normal(0, 1, 3), [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3),
                                        rng.uniform(0.2, 0.8)])
        poly = sil.polygon(T)
        expected = 0.0 if poly is None else poly.visible_fraction
        partly += 0.0 < expected < 1.0
        whole += expected == 1.0
        assert sil.visible_fraction(T) == pytest.approx(expected, abs=1e-6)
    assert partly > 10 and whole > 10  # both the shortcut and the polygon were exercised
    assert sil.visible_fraction(rigid_pose([0, 0, 0], [0, 0, -1.0])) == 0.0  # behind the camera
    assert sil.visible_fraction(rigid_pose([0, 0, 0], [np.nan, 0, 1.0])) == 0.0


@pytest.mark.parametrize("shape", ["cube", "blob"])
def test_box_in_image_against_the_projected_corners(shape) -> None:
    """``box_in_image(t, q)`` (compiled, the tracker's per-step test) and its batched form
    ``boxes_in_image`` say True exactly when the 8 corners of the hull's bounding box,
    projected with NumPy, are in front of the camera and inside the image; then the
    silhouette is whole in view (visible fraction 1)."""
    rng = np.random.default_rng(4)
    if shape == "cube":
        points = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05)
                           for z in (-.05, .05)])
    else:
        points = rng.normal(0, 0.03, (200, 3)) * [1.0, 2.0, 0.5]
    sil = Silhouette(points, SMALL_CAM)
    lo, hi = sil.points.min(0), sil.points.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    inside = outside = 0
    ts, qs, gots = [], [], []
    for k in range(400):
        rot = Rotation.from_rotvec(rng.normal(0, 1, 3))
        t = [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(-0.05, 0.8)]
        if k < 2:  # not finite; behind the camera (the corners would project inside)
            t = [[np.nan, 0.0, 0.5], [0.0, 0.0, -0.5]][k]
        x, y, z, w = rot.as_quat()
        P = corners @ rot.as_matrix().T + t
        with np.errstate(invalid="ignore", divide="ignore"):
            u = SMALL_CAM.fx * P[:, 0] / P[:, 2] + SMALL_CAM.cx
            v = SMALL_CAM.fy * P[:, 1] / P[:, 2] + SMALL_CAM.cy
            expected = bool((P[:, 2] >= 1e-3).all() and (u >= -0.5).all() and (u < 159.5).all()
                            and (v >= -0.5).all() and (v < 119.5).all())
        got = sil.box_in_image(tuple(t), (w, x, y, z))
        assert got == expected, (k, t)
        ts.append(t)
        qs.append((w, x, y, z))
        gots.append(got)
        inside += got
        outside += not got
        if got:
            assert sil.visible_fraction(rigid_pose(rot.as_rotvec(), t)) == 1.0
    assert inside > 20 and outside > 20
    # the batched form (the tracker's compiled step runs) says the same at every pose
    batched = sil.boxes_in_image(np.array(ts), np.array(qs))
    assert batched.dtype == bool and batched.tolist() == gots
    assert sil.boxes_in_image(np.zeros((0, 3)), np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        sil.boxes_in_image(np.zeros((2, 3)), np.zeros((3, 4)))
    # a lens without a view rectangle: never True (the exact path answers)
    distorted = Silhouette(points, PinholeCamera(120.0, 110.0, 79.5, 59.5, 160, 120,
                                                 dist=[0.01, 0, 0, 0, 0]))
    assert distorted.box_in_image((0.0, 0.0, 0.5), (1.0, 0.0, 0.0, 0.0))
    distorted._view_rect = None
    assert not distorted.box_in_image((0.0, 0.0, 0.5), (1.0, 0.0, 0.0, 0.0))
    assert not distorted.boxes_in_image(
        np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.0, 0.0]])).any()
    assert distorted.visible_fraction(rigid_pose([0, 0, 0], [0, 0, 0.5])) == 1.0


def test_view_rectangle_maps_inside_the_image() -> None:
    """:func:`ideal_view_rectangle`: the image itself without distortion; with a strong barrel
    or pincushion, dense random ideal pixels in it all distort into the image, and it spans
    nearly the image's undistortion (wider than the image for the barrel, narrower for the
    pincushion)."""
    assert ideal_view_rectangle(SMALL_CAM) == (-0.5, 159.5, -0.5, 119.5)
    rng = np.random.default_rng(5)
    for cam in (BARREL_CAM, PINCUSHION_CAM):
        rect = ideal_view_rectangle(cam)
        assert rect is not None
        u_lo, u_hi, v_lo, v_hi = rect
        ideal = np.stack([rng.uniform(u_lo, u_hi, 200_000), rng.uniform(v_lo, v_hi, 200_000)], 1)
        ideal[:4] = [[u_lo, v_lo], [u_hi, v_lo], [u_lo, v_hi], [u_hi, v_hi]]
        uv = cam.distort_points(torch.from_numpy(ideal))
        assert bool(cam.in_image(uv).all())
        # each side's middle lands within a pixel of the image's edge
        mid_u, mid_v = 0.5 * (u_lo + u_hi), 0.5 * (v_lo + v_hi)
        sides = torch.tensor([[u_lo, cam.cy], [u_hi, cam.cy], [cam.cx, v_lo], [cam.cx, v_hi]],
                             dtype=torch.float64)
        edges = cam.distort_points(sides)
        if cam is BARREL_CAM:
            assert u_lo < -100 and u_hi > cam.width + 100 and v_lo < -20 and v_hi > cam.height
            edge = torch.tensor([edges[0, 0], edges[1, 0], edges[2, 1], edges[3, 1]])
            assert torch.allclose(edge, torch.tensor([-0.5, 1279.5, -0.5, 719.5],
                                                     dtype=torch.float64), atol=1.0)
        else:  # the corners bind
            assert 0 < u_lo < mid_u < u_hi < cam.width and 0 < v_lo < mid_v < v_hi < cam.height
            corners = cam.distort_points(torch.tensor([[u_lo, v_lo], [u_hi, v_hi]],
                                                      dtype=torch.float64))
            assert float((corners[0] + 0.5).min()) < 1.0
            assert float((torch.tensor([319.5, 239.5]) - corners[1]).min()) < 1.0


@pytest.mark.parametrize("camera", [BARREL_CAM, PINCUSHION_CAM], ids=["barrel", "pincushion"])
def test_box_in_image_with_distortion_is_conservative(camera) -> None:
    """With a distorted camera, ``box_in_image`` says True only where the exact silhouette
    (hull projected through the lens) is whole in the image (visible fraction exactly 1, every
    vertex in the image), and it does so for most poses whose silhouette lies well inside;
    ``boxes_in_image`` says the same pose by pose; ``visible_fraction`` is that of the exact
    path (no view rectangle) to the bit."""
    rng = np.random.default_rng(6)
    points = rng.normal(0, 0.03, (200, 3)) * [1.0, 2.0, 0.5]
    sil = Silhouette(points, camera)
    exact = Silhouette(points, camera)
    exact._view_rect = None  # box_in_image always False: visible_fraction from the polygon
    w, h = camera.size
    fast_count = well_inside = well_inside_fast = partly = 0
    ts, qs, gots = [], [], []
    for _ in range(1500):
        rot = Rotation.from_rotvec(rng.normal(0, 1, 3))
        z = rng.uniform(0.3, 1.5)
        t = [rng.uniform(-0.8, 0.8) * z, rng.uniform(-0.5, 0.5) * z, z]
        x, y, qz, qw = rot.as_quat()
        T = rigid_pose(rot.as_rotvec(), t)
        fast = sil.box_in_image(tuple(t), (qw, x, y, qz))
        ts.append(t)
        qs.append((qw, x, y, qz))
        gots.append(fast)
        poly = sil.polygon(T)
        fraction = 0.0 if poly is None else poly.visible_fraction
        assert sil.visible_fraction(T) == exact.visible_fraction(T) == fraction
        partly += 0.0 < fraction < 1.0
        if fast:
            fast_count += 1
            assert fraction == 1.0
            assert camera.in_image(torch.from_numpy(poly.vertices)).all()
        if poly is not None:  # 5 % of the width inside the image, or more
            m = 0.05 * w
            v = poly.vertices
            well = bool((v >= m).all() and (v[:, 0] <= w - 1 - m).all()
                        and (v[:, 1] <= h - 1 - m).all())
            well_inside += well
            well_inside_fast += well and fast
    assert fast_count > 300 and partly > 100
    assert well_inside > 300 and well_inside_fast > 0.8 * well_inside
    assert sil.boxes_in_image(np.array(ts), np.array(qs)).tolist() == gots
