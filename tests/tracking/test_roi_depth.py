"""RoI depth (evtrack.tracking.roi_depth): one lookup per depth map for a step group gives
what the per-step lookup gives; the depth range widens with the pose filter's uncertainty."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tracker_helpers import SMALL_CAM, make_tracker, stream

from evtrack.tracking.depth_sources import SensorDepth
from evtrack.tracking.roi_depth import DEPTH_TOLERANCE_M, RoiDepth
from evtrack.tracking.silhouette import SilhouettePolygon
from evtrack.tracking.step_flows import StepFlows
from evtrack.tracking.tracker import Tracker


def test_group_depth_lookup_equals_step_by_step(fast_sequence, monkeypatch):
    """The sensor depth of a step group's RoIs is looked up once per depth map
    (RoiDepth.step); with frames dropped (depth maps that expire and arrive inside a
    group) it must give what the per-step lookup gives: the same trajectory, bit for bit, and
    the same fallbacks."""
    seq = fast_sequence
    times = seq.rgb_times_us.numpy()
    dropped = ((times >= 150_000) & (times < 400_000)) | (
        np.random.default_rng(1).random(len(times)) < 0.5)

    def run():
        tracker, _ = make_tracker(seq, method="full")
        return stream(tracker, seq, keep_frame=lambda i: not dropped[i]), tracker.stats

    grouped, st_grouped = run()
    calls = []

    def per_step(self, flows, k, poly, pose, t_now):
        calls.append(k)
        return self.lookup(flows.step(k)[0], poly, pose, t_now)

    monkeypatch.setattr(RoiDepth, "step", per_step)
    stepped, st_stepped = run()
    assert calls  # the patched lookup was used
    assert st_grouped.depth_fallbacks == st_stepped.depth_fallbacks > 0
    assert st_grouped.roi_flows == st_stepped.roi_flows
    assert torch.equal(grouped.poses.nan_to_num(7.0), stepped.poses.nan_to_num(7.0))


def _drifted_setup(range_sigmas: float):
    """A depth frame that sees the object at 0.80 m everywhere, and the silhouette of a pose
    that drifted 0.2 m nearer (its depth range 0.58-0.62 m, its origin at 0.60 m)."""
    source = SensorDepth(SMALL_CAM, radius=4, stride=2)
    source.set_frame(1000, np.full((SMALL_CAM.height, SMALL_CAM.width), 0.8, np.float32))
    depth = RoiDepth(source, max_depth_age_ms=100.0, range_sigmas=range_sigmas)
    W, H = SMALL_CAM.size
    poly = SilhouettePolygon(np.array([[0.0, 0.0], [W, 0.0], [W, H], [0.0, H]]), (0.58, 0.62),
                             1.0)
    pose = np.eye(4)
    pose[2, 3] = 0.6
    uv = np.array([[40.0, 30.0], [80.0, 60.0], [120.0, 90.0]])
    return depth, poly, pose, uv


def test_depth_range_widens_with_pose_uncertainty():
    """The object's true depths lie 0.18 m beyond the drifted pose's range: with the fixed
    margin every RoI falls back to the drifted origin's depth; with the filter's depth
    uncertainty (0.06 m, 3 sigmas: margin 0.23 m) the sensor's depths are used."""
    depth, poly, pose, uv = _drifted_setup(range_sigmas=3.0)
    assert depth.range_margin_m == DEPTH_TOLERANCE_M
    z = depth.lookup(uv, poly, pose, t_now=2000)
    np.testing.assert_array_equal(z, 0.6)  # the fallback
    assert depth.stats.depth_fallbacks == 3
    depth.set_pose_uncertainty(0.06)
    assert depth.range_margin_m == pytest.approx(DEPTH_TOLERANCE_M + 0.18)
    assert depth.depth_range(poly) == pytest.approx((0.58 - 0.23, 0.62 + 0.23))
    np.testing.assert_allclose(depth.lookup(uv, poly, pose, t_now=2000), 0.8, rtol=1e-6)
    assert depth.stats.depth_fallbacks == 3  # none more
    depth.reset()
    assert depth.range_margin_m == DEPTH_TOLERANCE_M


@pytest.mark.parametrize("sigmas, std", [(0.0, 0.5), (3.0, math.nan), (3.0, math.inf)])
def test_depth_range_fixed_margin_when_off_or_unknown(sigmas, std):
    """``range_sigmas: 0`` keeps the fixed margin whatever the uncertainty; a non-finite
    uncertainty (a filter without a pose) keeps it too."""
    depth, poly, pose, uv = _drifted_setup(range_sigmas=sigmas)
    depth.set_pose_uncertainty(std)
    assert depth.range_margin_m == DEPTH_TOLERANCE_M
    np.testing.assert_array_equal(depth.lookup(uv, poly, pose, t_now=2000), 0.6)


def test_group_lookup_follows_a_new_margin():
    """The group lookup (RoiDepth.run) keeps its depths while map, silhouette and margin stay
    the same, and looks up afresh when the margin changes."""
    depth, poly, pose, uv = _drifted_setup(range_sigmas=3.0)
    flows = StepFlows.__new__(StepFlows)
    flows.uv = np.concatenate([uv, uv])
    flows.bounds = np.array([0, 3, 6])
    flows.depth_cache = None
    z, missing = depth.run(flows, 0, 1, poly, pose, t_now=2000)
    np.testing.assert_array_equal(z, 0.6)
    assert missing.all()
    depth.set_pose_uncertainty(0.06)
    z, missing = depth.run(flows, 1, 2, poly, pose, t_now=2000)
    np.testing.assert_allclose(z, 0.8, rtol=1e-6)
    assert not missing.any()


def test_tracker_passes_the_filters_depth_uncertainty(fast_sequence, monkeypatch):
    """At each segment's start the tracker hands the RoI depth the pose filter's standard
    deviation of the object origin's camera z, read from the filter at that moment."""
    seen = []
    original = RoiDepth.set_pose_uncertainty

    def spy(self, depth_std_m):
        seen.append((depth_std_m, math.sqrt(float(tracker.ukf.cov[0, 2, 2]))))
        original(self, depth_std_m)

    monkeypatch.setattr(RoiDepth, "set_pose_uncertainty", spy)
    tracker, _ = make_tracker(fast_sequence, method="full")
    assert isinstance(tracker, Tracker) and tracker.roi_depth.range_sigmas == 3.0
    stream(tracker, fast_sequence)
    assert len(seen) > 10
    given = np.array([g for g, _ in seen])
    np.testing.assert_allclose(given, [f for _, f in seen], rtol=1e-12)
    assert given.min() < given.max()  # it follows the filter: small after a pose, larger later
    assert tracker.roi_depth.range_margin_m == pytest.approx(DEPTH_TOLERANCE_M + 3.0 * given[-1])
