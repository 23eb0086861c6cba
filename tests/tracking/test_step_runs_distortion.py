"""The tracker's compiled step runs with a distorted event camera: they apply (no longer
declined) and give the step-by-step trajectory and counts (``Tracker.step_runs`` off), the
poses and twists to 1e-9 relative, every counter the same. The compiled view check answers
with the lens's view rectangle and changes nothing, to the bit."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import ORACLE_NOISE, TEST_TRACKER, stream

from evtrack.camera import PinholeCamera
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.tracker import Tracker
from evtrack.tracking.trajectory import STATUS_TRACKING

BARREL = (-0.12, 0.03, 4e-4, -3e-4, 0.0)
"""A barrel distortion of a few pixels at the corners."""


def _distorted(camera: PinholeCamera, dist: tuple[float, ...] = BARREL) -> PinholeCamera:
    """``camera`` with the distortion ``dist`` (OpenCV coefficients)."""
    return PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                         camera.height, dist=dist)


def _tracker(seq, runs: bool, dist: tuple[float, ...] = BARREL) -> Tracker:
    source = OraclePoseSource.from_sequence(seq, seed=0, **ORACLE_NOISE)
    tracker = Tracker(TrackerConfig.from_dict({**TEST_TRACKER, "method": "full"}),
                      camera=_distorted(seq.meta.event_camera, dist), mesh=seq.mesh_file,
                      pose_source=source, rgb_camera=seq.meta.rgb_camera,
                      T_event_rgb=seq.meta.T_event_rgb)
    tracker.step_runs = runs
    return tracker


def test_step_runs_apply_and_equal_steps_with_a_distorted_camera(fast_sequence) -> None:
    seq = fast_sequence
    results = []
    for runs in (True, False):
        tracker = _tracker(seq, runs)
        done: list[int] = []
        step_run = tracker.scheduler.step_run

        def watched(t0, k, end, poly, pose, step_run=step_run, done=done):
            out = step_run(t0, k, end, poly, pose)
            if out is not None:
                done.append(out - k)
            return out

        tracker.scheduler.step_run = watched
        traj = stream(tracker, seq, np.random.default_rng(3))
        results.append((traj, tracker, done))
    (fast, fast_tracker, in_runs), (slow, slow_tracker, _) = results
    assert not fast_tracker.scheduler.runs_declined
    assert sum(in_runs) > 0.5 * fast_tracker.stats.steps  # most steps in runs
    assert torch.equal(fast.t_us, slow.t_us) and torch.equal(fast.status, slow.status)
    assert int((fast.status == STATUS_TRACKING).sum()) > 100
    for got, want in ((fast.poses, slow.poses), (fast.twists, slow.twists)):
        got, want = got.nan_to_num(7.0), want.nan_to_num(7.0)
        scale = want.abs().max()
        assert float((got - want).abs().max()) <= 1e-9 * float(scale)
    fast_stats, slow_stats = fast_tracker.stats.to_dict(), slow_tracker.stats.to_dict()
    fast_stats.pop("time_s"), slow_stats.pop("time_s")
    assert fast_stats == slow_stats
    assert fast_stats["velocity_updates"] > 100


def test_view_rectangle_changes_no_bit_of_the_track(fast_sequence) -> None:
    """The compiled view check with a distorted camera (``Silhouette.box_in_image`` and
    ``boxes_in_image`` through the lens's view rectangle) answers many steps, and the
    trajectory, twists and counts are those with the rectangle taken away (every step's view
    from the silhouette projected through the lens), array by array, to the bit. A strong
    barrel: its rectangle is wider than the image, and the object, which fills much of this
    small image and often touches its border, is whole in view at some steps (with a
    pincushion, as with no distortion, its box never is here)."""
    dist = (-0.3, 0.08, 4e-4, -3e-4, 0.0)
    results = []
    for rectangle in (True, False):
        tracker = _tracker(fast_sequence, True, dist)
        sil = tracker.silhouette
        if not rectangle:
            sil._view_rect = None
        assert (sil._view_rect is not None) == rectangle
        fast = [0, 0]  # poses asked, answered True

        def one(t, q, box_in_image=sil.box_in_image, fast=fast):
            got = box_in_image(t, q)
            fast[0] += 1
            fast[1] += got
            return got

        def many(t, q, boxes_in_image=sil.boxes_in_image, fast=fast):
            got = boxes_in_image(t, q)
            fast[0] += len(got)
            fast[1] += int(got.sum())
            return got

        sil.box_in_image, sil.boxes_in_image = one, many
        traj = stream(tracker, fast_sequence, np.random.default_rng(3))
        results.append((traj, tracker, fast))
    (with_rect, tracker, (asked, fast)), (without, exact_tracker, (_, none)) = results
    # the object fills much of the small image: both paths answer many steps
    assert none == 0 and 50 < fast < asked - 50
    assert int((with_rect.status == STATUS_TRACKING).sum()) > 100
    for name in ("t_us", "status", "poses", "twists"):
        got, want = getattr(with_rect, name), getattr(without, name)
        if got.is_floating_point():
            assert torch.equal(got.isnan(), want.isnan()), name
            got, want = got.nan_to_num(7.0), want.nan_to_num(7.0)
        assert got.dtype == want.dtype and torch.equal(got, want), name
    stats, exact_stats = tracker.stats.to_dict(), exact_tracker.stats.to_dict()
    stats.pop("time_s"), exact_stats.pop("time_s")
    assert stats == exact_stats
