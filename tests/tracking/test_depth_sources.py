"""Depth sources (evtrack.tracking.depth_sources): RoI depth medians against a nanmedian
reference, depth shares in a silhouette, sensor depth reprojected against a rendering."""

from __future__ import annotations

import cv2
import numpy as np
from tracker_helpers import SMALL_CAM, rigid_pose

from evtrack.camera import PinholeCamera
from evtrack.tracking.depth_sources import SensorDepth, patch_offsets, roi_depth


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
    T_event_rgb = rigid_pose([0.0, 0.05, 0.0], [0.03, 0.0, 0.0])
    T_obj_rgb = rigid_pose([0.4, 0.2, 0.1], [0.0, 0.0, 0.5])
    T_obj_ev = T_event_rgb @ T_obj_rgb
    with Renderer(rgb_cam) as r:
        r.set_object(box)
        d_rgb = r.render(T_obj_rgb).depth
    with Renderer(SMALL_CAM) as r:
        r.set_object(box)
        ref = r.render(T_obj_ev)
    src = SensorDepth(SMALL_CAM, rgb_cam, T_event_rgb, radius=0, stride=1)
    src.set_frame(0, d_rgb)
    inner = cv2.erode(ref.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    got = src.map[inner]
    ok = np.isfinite(got)
    assert ok.mean() > 0.8  # a denser RGB camera leaves few holes
    # nearest-pixel splatting on slanted faces: a few mm (1 px ~ 4 mm across here)
    diff = np.abs(got[ok] - ref.depth[inner][ok])
    assert np.quantile(diff, 0.95) < 3e-3 and diff.max() < 1.5e-2
    assert np.isnan(src.map[~ref.mask & (ref.depth == 0)]).mean() > 0.99
