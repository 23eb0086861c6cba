"""Silhouette mask, depth lookup and reprojection, pose sources, frame flow, GE event timing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.geometry import integrate_twist
from evtrack.tracking.baselines.frame_flow import DenseFlow, twist_adjoint
from evtrack.tracking.depth_sources import SensorDepth, patch_offsets, roi_depth
from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource
from evtrack.tracking.silhouette import Silhouette, pixels_in_polygon, points_in_polygon

CAM = PinholeCamera(120.0, 110.0, 79.5, 59.5, 160, 120)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


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

    sil = Silhouette(box.vertices, CAM)
    with Renderer(CAM) as r:
        r.set_object(box)
        for T in [_pose([0.3, -0.5, 0.2], [0.02, -0.01, 0.5]),
                  _pose([1.2, 0.4, -0.9], [0.1, 0.05, 0.7])]:
            out = r.render(T)
            v, u = np.nonzero(out.mask)
            poly = sil.polygon(T)
            assert poly.contains(np.stack([u, v], 1), 1.0).all()
            # tight: the hull of a box's projection is its silhouette, up to pixel coverage
            area = cv2.contourArea(poly.vertices.astype(np.float32))
            assert abs(area - out.mask.sum()) < 0.05 * out.mask.sum() + 2 * len(poly.vertices)
            z = out.depth[out.mask]
            assert poly.z_range[0] <= z.min() + 1e-4 and z.max() <= poly.z_range[1] + 1e-4
    assert sil.polygon(_pose([0, 0, 0], [0, 0, -1.0])) is None  # behind the camera
    outside = sil.polygon(_pose([0, 0, 0], [5.0, 0, 1.0]))
    assert outside.visible_fraction == 0.0


def test_hull_of_two_silhouettes_is_the_swept_area(box) -> None:
    """The hull of a convex silhouette at two positions of a translation parallel to the
    image holds every position in between (the swept area, the event mask of a step group)
    and nothing farther than either, with the depth range of both."""
    sil = Silhouette(box.vertices, CAM)
    start = _pose([0.3, -0.5, 0.2], [-0.03, 0.0, 0.5])
    end = _pose([0.3, -0.5, 0.2], [0.03, 0.01, 0.5])
    a, b = sil.polygon(start), sil.polygon(end)
    swept = sil.hull([a, b])
    for s in np.linspace(0.0, 1.0, 11):
        mid = start.copy()
        mid[:3, 3] = (1 - s) * start[:3, 3] + s * end[:3, 3]
        assert swept.contains(sil.polygon(mid).vertices, 1e-3).all()
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [CAM.width, CAM.height], (4000, 2))
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
    sil = Silhouette(points, CAM)
    partly = whole = 0
    for _ in range(300):
        T = _pose(rng.normal(0, 1, 3), [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3),
                                        rng.uniform(0.2, 0.8)])
        poly = sil.polygon(T)
        expected = 0.0 if poly is None else poly.visible_fraction
        partly += 0.0 < expected < 1.0
        whole += expected == 1.0
        assert sil.visible_fraction(T) == pytest.approx(expected, abs=1e-6)
    assert partly > 10 and whole > 10  # both the shortcut and the polygon were exercised
    assert sil.visible_fraction(_pose([0, 0, 0], [0, 0, -1.0])) == 0.0  # behind the camera
    assert sil.visible_fraction(_pose([0, 0, 0], [np.nan, 0, 1.0])) == 0.0


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
    sil = Silhouette(points, CAM)
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
            u = CAM.fx * P[:, 0] / P[:, 2] + CAM.cx
            v = CAM.fy * P[:, 1] / P[:, 2] + CAM.cy
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
            assert sil.visible_fraction(_pose(rot.as_rotvec(), t)) == 1.0
    assert inside > 20 and outside > 20
    # the batched form (the tracker's compiled step runs) says the same at every pose
    batched = sil.boxes_in_image(np.array(ts), np.array(qs))
    assert batched.dtype == bool and batched.tolist() == gots
    assert sil.boxes_in_image(np.zeros((0, 3)), np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        sil.boxes_in_image(np.zeros((2, 3)), np.zeros((3, 4)))
    distorted = PinholeCamera(120.0, 110.0, 79.5, 59.5, 160, 120, dist=[0.01, 0, 0, 0, 0])
    assert not Silhouette(points, distorted).box_in_image((0.0, 0.0, 0.5), (1.0, 0.0, 0.0, 0.0))
    assert not Silhouette(points, distorted).boxes_in_image(
        np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.0, 0.0]])).any()


@pytest.fixture(params=["compiled", "numpy"])
def depth_form(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a depth-lookup test with the compiled patch medians (numba) and with NumPy."""
    import evtrack.tracking.depth_sources as depth_sources

    if request.param == "compiled" and not depth_sources.numba_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(depth_sources, "COMPILED", request.param == "compiled")
    return request.param


def test_roi_depth_median_range_and_missing(depth_form: str) -> None:
    depth = np.full((20, 30), 2.0, np.float32)
    depth[5:15, 5:15] = 0.5
    depth[9, 9] = np.nan
    depth[8, 8] = 0.55
    off = patch_offsets(2, 1)
    z = roi_depth(depth, np.array([[9.0, 9.0], [25.0, 2.0], [14.6, 9.0]]), off, (0.3, 1.0))
    assert z[0] == 0.5 and np.isnan(z[1])
    # at the border of the object: only the object pixels count
    assert z[2] == 0.5
    assert roi_depth(depth, np.array([[14.6, 9.0]]), off, None)[0] == 2.0


def test_roi_depth_equals_a_nanmedian_reference(depth_form: str) -> None:
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.2, 2.0, (40, 50)).astype(np.float32)
    depth[rng.random((40, 50)) < 0.3] = np.nan          # holes
    depth[rng.random((40, 50)) < 0.1] = 0.0             # invalid zeros
    depth[:12, :12] = np.nan                            # a patch with no depth at all
    depth[rng.random((40, 50)) < 0.03] = np.inf         # invalid infinities
    off = patch_offsets(3, 1)
    uv = np.concatenate([rng.uniform(-4, 54, (300, 2)), [[4.0, 4.0]]])
    for z_range in (None, (0.5, 1.5)):
        got = roi_depth(depth, uv, off, z_range)
        centre = np.rint(uv).astype(int)
        for i, (cx, cy) in enumerate(centre):   # brute force, point by point
            vals = []
            for dx, dy in off:
                x, y = cx + dx, cy + dy
                if 0 <= x < 50 and 0 <= y < 40:
                    v = float(depth[y, x])
                    if np.isfinite(v) and v > 0 and (z_range is None
                                                     or z_range[0] <= v <= z_range[1]):
                        vals.append(v)
            if vals:
                assert got[i] == np.median(vals), i
            else:
                assert np.isnan(got[i]), i
    assert np.isnan(roi_depth(depth, uv[-1:], off)[0])
    assert np.isnan(roi_depth(depth, np.array([[np.nan, 20.0]]), off)[0])  # no pixel


def test_roi_depth_of_repeated_points_equals_one_by_one(depth_form: str) -> None:
    """A batch repeating its points (a step group's RoIs at every step: each distinct pixel is
    looked up once), with points far outside the map and NaN, gives each point's own lookup."""
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.2, 2.0, (40, 50)).astype(np.float32)
    depth[rng.random((40, 50)) < 0.2] = np.nan
    off = patch_offsets(3, 1)
    grid = rng.uniform(-2, 52, (20, 2))
    uv = np.concatenate([grid[rng.integers(0, 20, 120)], grid[:3] + 0.2,  # same pixels
                         [[1e6, 5.0], [-1e6, -1e6], [np.nan, 3.0], [3.0, np.nan], [-4.0, 20.0],
                          [55.0, 20.0], [20.0, 44.0]]])
    for z_range in (None, (0.5, 1.5)):
        got = roi_depth(depth, uv, off, z_range)
        one_by_one = np.array([roi_depth(depth, p[None], off, z_range)[0] for p in uv])
        np.testing.assert_array_equal(got, one_by_one)
    assert np.isfinite(got[:120]).any() and np.isnan(got[-7:-2]).all()


def test_silhouette_depth_share_counts_the_depths_in_the_pose_range() -> None:
    """A 40 x 40 px object at 1.0 m before a wall at 2.0 m: a pose there is fully supported,
    a pose on the wall not at all, an occluder over half of the object halves the share; the
    samples lie on the image's 4-px grid inside the polygon; no depth: no judgement."""
    from evtrack.tracking.depth_sources import silhouette_depth_share
    from evtrack.tracking.silhouette import SilhouettePolygon

    depth = np.full((120, 160), 2.0, np.float32)
    depth[40:80, 60:100] = 1.0
    square = np.array([[60.0, 40.0], [99.0, 40.0], [99.0, 79.0], [60.0, 79.0]])
    on_object = SilhouettePolygon(square, (0.98, 1.05), 1.0)
    share, count = silhouette_depth_share(depth, on_object, 0.06)
    assert share == 1.0 and count == 10 * 10  # columns 60..96 and rows 40..76, every 4 px
    on_wall = SilhouettePolygon(square - [50.0, 0.0], (0.98, 1.05), 1.0)
    assert silhouette_depth_share(depth, on_wall, 0.06)[0] == 0.0
    assert silhouette_depth_share(depth, on_wall, 1.0)[0] == 1.0  # the tolerance widens it
    occluded = depth.copy()
    occluded[40:60, 60:100] = 0.5  # the upper half, nearer
    assert silhouette_depth_share(occluded, on_object, 0.06)[0] == 0.5
    holes = depth.copy()
    holes[40:60, 60:100] = np.nan  # missing depth is not counted
    assert silhouette_depth_share(holes, on_object, 0.06) == (1.0, 50)
    assert np.isnan(silhouette_depth_share(np.full_like(depth, np.nan), on_object, 0.06)[0])
    outside = SilhouettePolygon(square + [500.0, 0.0], (0.98, 1.05), 0.0)
    assert silhouette_depth_share(depth, outside, 0.06)[1] == 0


def test_sensor_depth_reprojection_against_rendering(box) -> None:
    """Depth rendered in an RGB camera, carried into a different event camera, equals the
    depth rendered in the event camera (away from the silhouette's edge)."""
    from evtrack.sim.renderer import Renderer

    rgb_cam = PinholeCamera(150.0, 150.0, 99.5, 74.5, 200, 150)
    T_event_rgb = _pose([0.0, 0.05, 0.0], [0.03, 0.0, 0.0])
    T_obj_rgb = _pose([0.4, 0.2, 0.1], [0.0, 0.0, 0.5])
    T_obj_ev = T_event_rgb @ T_obj_rgb
    with Renderer(rgb_cam) as r:
        r.set_object(box)
        d_rgb = r.render(T_obj_rgb).depth
    with Renderer(CAM) as r:
        r.set_object(box)
        ref = r.render(T_obj_ev)
    src = SensorDepth(CAM, rgb_cam, T_event_rgb, radius=0, stride=1)
    src.set_frame(0, d_rgb)
    inner = cv2.erode(ref.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    got = src.map[inner]
    ok = np.isfinite(got)
    assert ok.mean() > 0.8  # a denser RGB camera leaves few holes
    # nearest-pixel splatting on slanted faces: a few mm (1 px ~ 4 mm across here)
    diff = np.abs(got[ok] - ref.depth[inner][ok])
    assert np.quantile(diff, 0.95) < 3e-3 and diff.max() < 1.5e-2
    assert np.isnan(src.map[~ref.mask & (ref.depth == 0)]).mean() > 0.99


def test_oracle_is_deterministic_per_frame_and_noisy() -> None:
    truth = _pose([0.1, 0.2, 0.3], [0.0, 0.0, 0.6])
    src = OraclePoseSource(lambda t: torch.from_numpy(truth), std_translation=0.01,
                           std_rotation=0.02, seed=5)
    a = [src(t) for t in range(0, 100_000, 1000)]
    b = [src(t) for t in reversed(range(0, 100_000, 1000))][::-1]
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x.pose, y.pose)
    dt = np.array([(m.pose[:3, 3].numpy() - truth[:3, 3]) for m in a])
    assert 0.006 < dt.std() < 0.014
    out = OraclePoseSource(lambda t: torch.from_numpy(truth), outlier_rate=1.0, seed=1)(7)
    assert np.linalg.norm(out.pose[:3, 3].numpy() - truth[:3, 3]) > 0
    assert OraclePoseSource(lambda t: torch.from_numpy(truth), dropout_rate=1.0)(7) is None


def test_network_source_takes_the_best_detection_into_the_event_camera() -> None:
    class Det:
        def __init__(self, pose, c):
            self.pose, self.confidence = pose, c

    T_er = _pose([0, 0.1, 0], [0.05, 0, 0])
    dets = [Det(_pose([0, 0, 0], [0, 0, 1.0]), 0.4), Det(_pose([0, 0, 0.2], [0, 0.1, 0.8]), 0.9)]
    src = NetworkPoseSource(lambda rgb: dets, T_event_rgb=torch.from_numpy(T_er),
                            min_confidence=0.5)
    m = src(10, np.zeros((8, 8, 3), np.uint8))
    np.testing.assert_allclose(m.pose.numpy(), T_er @ dets[1].pose)
    assert m.confidence == 0.9
    assert NetworkPoseSource(lambda rgb: dets, min_confidence=0.95)(0, None) is None
    assert m.alternatives == ()  # detections without alternatives give none


def test_network_source_hands_on_the_detections_alternatives() -> None:
    """A detection's alternatives become the measurement's, mapped into the event camera like
    the pose; those below ``min_confidence`` are left out, invalid ones counted."""
    class Det:
        def __init__(self, pose, c, alternatives=()):
            self.pose, self.confidence, self.alternatives = pose, c, alternatives

    T_er = _pose([0, 0.1, 0], [0.05, 0, 0])
    sheared = _pose([0, 0, 0], [0, 0, 1.0])
    sheared[0, 1] = 0.5  # not a rotation
    alts = (Det(_pose([0.1, 0, 0], [0, 0, 0.9]), 0.6), Det(sheared, 0.55),
            Det(_pose([0, 0.2, 0], [0, 0, 1.1]), 0.3))
    src = NetworkPoseSource(lambda rgb: [Det(_pose([0, 0, 0.2], [0, 0.1, 0.8]), 0.9, alts)],
                            T_event_rgb=torch.from_numpy(T_er), min_confidence=0.5)
    m = src(10, np.zeros((8, 8, 3), np.uint8))
    (alt,) = m.alternatives
    np.testing.assert_allclose(alt.pose.numpy(), T_er @ alts[0].pose)
    assert alt.t_us == 10 and alt.confidence == 0.6 and src.invalid == 1


def test_network_source_hands_the_prior_to_the_estimator_in_the_rgb_camera() -> None:
    """With a prior (event camera frame), an estimator with ``estimate_near`` gets it in its
    own (RGB) camera frame; without one, or for a plain callable, the whole-image call."""
    class Det:
        def __init__(self, pose, c):
            self.pose, self.confidence, self.alternatives = pose, c, ()

    class Estimator:
        def __init__(self):
            self.calls = []

        def __call__(self, rgb):
            self.calls.append(("image", None))
            return [Det(_pose([0, 0, 0], [0, 0, 1.0]), 0.9)]

        def estimate_near(self, rgb, prior):
            self.calls.append(("near", prior))
            return [Det(prior, 0.8)]

    T_er = _pose([0, 0.1, 0], [0.05, 0, 0])
    est = Estimator()
    src = NetworkPoseSource(est, T_event_rgb=torch.from_numpy(T_er))
    assert src.accepts_prior
    prior_event = _pose([0.2, -0.1, 0.3], [0.02, 0.01, 0.7])
    m = src(10, np.zeros((8, 8, 3), np.uint8), None, prior=prior_event)
    (kind, got), = est.calls
    assert kind == "near"
    np.testing.assert_allclose(got, np.linalg.inv(T_er) @ prior_event, atol=1e-12)
    np.testing.assert_allclose(m.pose.numpy(), prior_event, atol=1e-12)  # back in the event frame
    src(20, np.zeros((8, 8, 3), np.uint8))
    assert est.calls[-1] == ("image", None)
    plain = NetworkPoseSource(lambda rgb: [Det(_pose([0, 0, 0], [0, 0, 1.0]), 0.9)])
    assert plain(0, None, prior=prior_event).pose[2, 3] == 1.0


def test_twist_adjoint_against_moving_points() -> None:
    """A twist mapped by the adjoint moves points of the other frame identically."""
    T_ab = torch.from_numpy(_pose([0.3, -0.2, 0.5], [0.1, 0.2, -0.3]))
    V_b = torch.tensor([0.2, -0.4, 0.1, 1.0, 0.5, -0.7], dtype=torch.float64)
    V_a = twist_adjoint(T_ab) @ V_b
    P_obj = torch.eye(4, dtype=torch.float64)
    P_obj[:3, 3] = torch.tensor([0.05, -0.02, 0.6])
    dt = 0.01
    moved_b = integrate_twist(P_obj, V_b, dt)
    moved_a = integrate_twist(T_ab @ P_obj, V_a, dt)
    torch.testing.assert_close(moved_a, T_ab @ moved_b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("algorithm", ["dis", "farneback"])
def test_dense_flow_measures_a_shift(algorithm) -> None:
    from evtrack.tracking.config import FrameFlowConfig

    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (140, 180)).astype(np.float32), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    a = np.repeat(tex[10:130, 10:170, None], 3, 2)
    b = np.repeat(tex[8:128, 13:173, None], 3, 2)  # content moves by (-3, +2) px
    flow = DenseFlow(FrameFlowConfig(algorithm=algorithm))
    assert flow.push(0, a) is None
    pair = flow.push(20_000, b)
    uv, f = pair.sample(np.array([[80, 60], [60, 50], [100, 70]]))
    np.testing.assert_allclose(f, np.tile([-150.0, 100.0], (3, 1)), atol=25.0)  # px/s
    assert flow.push(200_000, a) is None  # gap longer than max_gap_ms


def test_ge_previous_event_times_against_a_loop() -> None:
    from evtrack.events import Events
    from evtrack.filters.config import VelocityKFConfig
    from evtrack.tracking.baselines.ge_model import GEVelocity
    from evtrack.tracking.config import GEConfig

    rng = np.random.default_rng(0)
    cam = PinholeCamera(10.0, 10.0, 3.5, 2.5, 8, 6)
    ge = GEVelocity(cam, GEConfig(), VelocityKFConfig())
    last = {}
    for chunk in range(3):
        n = 200
        x, y = rng.integers(0, 8, n), rng.integers(0, 6, n)
        t = np.sort(rng.integers(chunk * 1000, (chunk + 1) * 1000, n))
        prev = ge._previous_times(x, y, t)
        for i in range(n):
            key = (x[i], y[i])
            assert prev[i] == last.get(key, -(1 << 62))
            last[key] = t[i]
    ev = Events(np.array([1]), np.array([1]), np.array([5000]), np.array([1]), (8, 6))
    assert ge.step(1e-3, ev, None, lambda uv: np.ones(len(uv))).shape == (1, 6)


@pytest.mark.parametrize("velocity", [(300.0, 100.0), (-200.0, 150.0)])
def test_ge_measures_a_translating_texture(velocity) -> None:
    """Ideal case: a textured plane at 1 m translating in the image, gradient from a rendered
    frame, true poses for the warp. The 1-DoF model gets the direction and overestimates the
    speed (measured: +40% and +30%), from the smoothed gradient of sharp edges."""
    import math

    from evtrack.filters import VelocityKFConfig, interaction_matrix
    from evtrack.flow.scenes import render_events, texture_waves
    from evtrack.sim.frames import linear_to_srgb
    from evtrack.tracking.baselines.ge_model import GEVelocity
    from evtrack.tracking.config import GEConfig

    W, H, f, C = 96, 72, 80.0, 0.15
    cam = PinholeCamera(f, f, (W - 1) / 2, (H - 1) / 2, W, H)
    waves = texture_waves(12, (12.0, 40.0), 0)
    norm = float(np.sqrt(0.5 * np.sum(waves[:, 3] ** 2)))

    def L(x, y, t):
        u, v = x - velocity[0] * t, y - velocity[1] * t
        field = sum(a * np.sin(kx * u + ky * v + ph) for kx, ky, ph, a in waves)
        return np.log(0.5 + 0.4 * np.tanh(3.0 * field / norm))

    ev, _ = render_events(lambda x, y, t: torch.from_numpy(L(x.numpy(), y.numpy(), t)),
                          (W, H), 40_000, math.hypot(*velocity), C)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)

    def pose(t_s):
        return _pose([0, 0, 0], [velocity[0] * t_s / f, velocity[1] * t_s / f, 1.0])

    ge = GEVelocity(cam, GEConfig(contrast=C), VelocityKFConfig())
    for k in range(40):
        if k % 16 == 0:
            img = linear_to_srgb(np.exp(L(xs, ys, k * 1e-3)))
            ge.set_frame(k * 1000, np.repeat(img[..., None], 3, 2), pose(k * 1e-3))
        V = ge.step(1e-3, ev.between(k * 1000, (k + 1) * 1000), pose((k + 1) * 1e-3),
                    lambda uv: np.ones(len(uv)))
    J = interaction_matrix(torch.tensor([[47.5, 35.5]], dtype=torch.float64),
                           torch.tensor([1.0], dtype=torch.float64), cam)
    flow = (J[0] @ V[0]).numpy()
    true = np.array(velocity)
    cos = flow @ true / np.linalg.norm(flow) / np.linalg.norm(true)
    ratio = np.linalg.norm(flow) / np.linalg.norm(true)
    assert cos > np.cos(np.radians(15)) and 0.8 < ratio < 1.7


def test_moved_pose_equals_integrate_twist() -> None:
    """The tracker's float path for one pose moved by a twist (``moved_pose``) against the
    tensor one (kornia's SE(3) exponential), large and tiny rotations, either sign of dt."""
    from evtrack.geometry import integrate_twist
    from evtrack.tracking.tracker import moved_pose

    rng = np.random.default_rng(4)
    for scale in (5.0, 1e-5, 0.0):
        for dt in (0.04, -0.013, 0.0):
            T = _pose(rng.normal(size=3), rng.normal(size=3))
            twist = rng.normal(size=6) * np.array([1, 1, 1, scale, scale, scale])
            ref = integrate_twist(torch.from_numpy(T), torch.from_numpy(twist), dt).numpy()
            np.testing.assert_allclose(moved_pose(T, twist, dt), ref, rtol=0, atol=1e-12)
