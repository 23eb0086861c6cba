"""The tracker's compiled step runs with a distorted event camera: they apply (no longer
declined) and give the step-by-step trajectory and counts (``Tracker.step_runs`` off), the
poses and twists to 1e-9 relative, every counter the same."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import ORACLE_NOISE, TEST_TRACKER, stream

from evtrack.camera import PinholeCamera
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.tracker import Tracker
from evtrack.tracking.trajectory import STATUS_TRACKING


def _distorted(camera: PinholeCamera) -> PinholeCamera:
    """``camera`` with a barrel distortion of a few pixels at the corners."""
    return PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                         camera.height, dist=[-0.12, 0.03, 4e-4, -3e-4, 0.0])


def _tracker(seq, runs: bool) -> Tracker:
    source = OraclePoseSource.from_sequence(seq, seed=0, **ORACLE_NOISE)
    tracker = Tracker(TrackerConfig.from_dict({**TEST_TRACKER, "method": "full"}),
                      camera=_distorted(seq.meta.event_camera), mesh=seq.mesh_file,
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
