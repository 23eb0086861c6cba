"""Measuring again the steps before the first pose (evtrack.tracking.remeasure): the check that
the late pose explains the kept events, against hand-made RoI flows. The re-measuring itself is
pinned through the tracker (test_tracking, test_robustness: compiled runs equal steps)."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import SMALL_CAM, rigid_pose

from evtrack.filters import PoseUKF, VelocityKF
from evtrack.tracking import remeasure
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_sources import SensorDepth
from evtrack.tracking.pose_timeline import PoseTimeline
from evtrack.tracking.remeasure import Remeasurer, UnposedStep
from evtrack.tracking.roi_depth import RoiDepth
from evtrack.tracking.silhouette import Silhouette

CUBE = np.array([[x, y, z] for x in (-.1, .1) for y in (-.1, .1) for z in (-.1, .1)])
POSE = rigid_pose([0, 0, 0], [0, 0, 0.6])


def _remeasurer() -> Remeasurer:
    cfg = TrackerConfig()
    filt = PoseUKF(1, cfg.pose_ukf)
    depth = RoiDepth(SensorDepth(SMALL_CAM, SMALL_CAM, None, 16, 4), cfg.depth.max_age_ms)
    return Remeasurer(cfg, VelocityKF(SMALL_CAM, 1, cfg.velocity_kf),
                      PoseTimeline(filt, 1_000_000), depth, Silhouette(CUBE, SMALL_CAM),
                      segment_pose=lambda: (POSE, None), past_pose=lambda t_us: POSE)


def _step(uv: np.ndarray, support: int = 10) -> UnposedStep:
    n = len(uv)
    return UnposedStep(uv.astype(np.float64), torch.zeros(n, 2), torch.zeros(n, dtype=torch.bool),
                       (None, None), np.full(n, support))


def _kept(n_inside: int, n_outside: int, **kw) -> dict[int, UnposedStep]:
    inside = np.tile([[79.5, 59.5]], (n_inside, 1))  # the image centre: on the cube
    outside = np.tile([[2.0, 2.0]], (n_outside, 1))  # a corner, far off its silhouette
    return {1000: _step(np.concatenate([inside, outside]), **kw)}


def test_a_pose_explains_the_events_inside_its_silhouette() -> None:
    r = _remeasurer()
    assert r.explains_events(0, _kept(99, 1))
    assert not r.explains_events(0, _kept(90, 10))  # below remeasure_min_inside (0.98)
    assert r.explains_events(0, _kept(0, remeasure.CHECK_MIN_ROIS - 1))  # too few to judge
    # weakly supported RoI flows are not counted (sensor noise off the object)
    assert r.explains_events(0, _kept(0, 50, support=remeasure.CHECK_MIN_SUPPORT - 1))
    # only the steps of CHECK_US after the pose count
    late = {remeasure.CHECK_US + 2000: _kept(0, 50)[1000]}
    assert r.explains_events(0, late)


def test_without_the_check_other_objects_flows_do_not_refuse_the_pose() -> None:
    """``check_events`` off (the multi-object tracker): a pose whose silhouette holds none of
    the kept flows (another object's) is still used to measure them again."""
    for check, skipped in ((True, 1), (False, 0)):
        r = _remeasurer()
        r.check_events = check
        r.unposed = _kept(0, 50)
        r.remeasure(0, step_runs=False)
        assert r.stats.remeasures_skipped == skipped
        assert r.unposed == {}
