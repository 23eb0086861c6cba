"""The step scheduler (evtrack.tracking.scheduler): step groups covering a span, the runs of
steps that nothing falls between against a step-by-step reference, and the filters' compiled
step runs equal to step by step through the tracker."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from robustness_scenes import VisibleOnlySource
from tracker_helpers import ORACLE_NOISE, TEST_TRACKER, make_tracker, stream

from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.scheduler import group_spans, quiet_end
from evtrack.tracking.tracker import Tracker


@pytest.mark.parametrize(("start", "end", "group"), [(0, 40_000, 10_000), (3_000, 47_000, 10_000),
                                                     (5_000, 5_000, 10_000), (7, 8, 40)])
def test_group_spans_cover_the_span_cut_at_the_group_multiples(start, end, group) -> None:
    spans = group_spans(start, end, group)
    if start >= end:
        assert spans == []
        return
    assert spans[0][0] == start and spans[-1][1] == end
    assert all(a1 == b0 for (_, a1), (b0, _) in zip(spans, spans[1:], strict=False))
    assert all(g1 % group == 0 for _, g1 in spans[:-1])
    assert all(0 < g1 - g0 <= group for g0, g1 in spans)


def _quiet_end_reference(t0, k, n_steps, step, frame, due, expires) -> int:
    """Step by step from ``k``: step ``j`` joins the run while no frame is taken at its start
    (for ``j > k``: the frames before its end, ``t0 + (j + 1) step``, are; step k's were taken
    before the run), no measurement is due at its end, and the depth map read at its start
    (``t0 + j step``) has not expired."""
    j = k
    while j < n_steps:
        end_j = t0 + (j + 1) * step
        frame_ok = j == k or frame is None or frame >= end_j
        due_ok = due is None or due > end_j
        depth_ok = expires is None or t0 + j * step <= expires
        if not (frame_ok and due_ok and depth_ok):
            break
        j += 1
    return j


def test_quiet_end_equals_the_step_by_step_reference() -> None:
    rng = np.random.default_rng(0)
    step = 1000
    for _ in range(5000):
        t0 = int(rng.integers(0, 50)) * 40_000
        n_steps = int(rng.integers(1, 41))
        k = int(rng.integers(0, n_steps))
        frame = None if rng.random() < 0.3 else t0 + int(rng.integers(-5_000, 60_000))
        due = None if rng.random() < 0.3 else t0 + int(rng.integers(-5_000, 60_000))
        expires = None if rng.random() < 0.3 else t0 + float(rng.integers(-5_000, 60_000))
        got = quiet_end(t0, k, n_steps, step, frame, due, expires)
        ref = _quiet_end_reference(t0, k, n_steps, step, frame, due, expires)
        # an end at or before k means no step is quiet (the scheduler then runs no run)
        assert max(got, k) == ref, (t0, k, n_steps, frame, due, expires, got, ref)


def test_quiet_end_without_anything_pending_is_the_group_end() -> None:
    assert quiet_end(0, 3, 40, 1000, None, None, None) == 40
    assert quiet_end(0, 3, 40, 1000, None, None, 1e9) == 40


# ---------------------------------------------------------------------------- step runs
def _same_runs(make, feed) -> tuple[Tracker, list[tuple[int, bool]]]:
    """Track with the filters' compiled step runs and step by step (``Tracker.step_runs``):
    the trajectories must be equal bit for bit and every counter the same. Returns the run
    tracker and its compiled runs (steps done, whether the object was lost in the run)."""
    results = []
    inside: list[tuple[int, bool]] = []
    for runs in (True, False):
        tracker = make()
        tracker.step_runs = runs
        step_run = tracker.scheduler.step_run

        def watched(t0, k, end, poly, pose, tracker=tracker, step_run=step_run):
            lost_before = tracker.stats.lost
            done = step_run(t0, k, end, poly, pose)
            if done is not None:
                inside.append((done - k, tracker.stats.lost > lost_before))
            return done

        tracker.scheduler.step_run = watched
        results.append((feed(tracker), tracker))
    (fast, fast_tracker), (slow, slow_tracker) = results
    assert torch.equal(fast.t_us, slow.t_us) and torch.equal(fast.status, slow.status)
    assert torch.equal(fast.poses.nan_to_num(7.0), slow.poses.nan_to_num(7.0))
    assert torch.equal(fast.twists, slow.twists)
    fast_stats, slow_stats = fast_tracker.stats.to_dict(), slow_tracker.stats.to_dict()
    fast_stats.pop("time_s"), slow_stats.pop("time_s")
    assert fast_stats == slow_stats
    return fast_tracker, inside


def test_step_runs_equal_steps_with_dropped_frames_in_chunks(fast_sequence) -> None:
    """Streamed in random chunks, with RGB-D frames dropped (depth maps that expire, and
    arrive, inside a step group): the compiled runs give the per-step trajectory exactly."""
    seq = fast_sequence
    times = seq.rgb_times_us.numpy()
    dropped = ((times >= 150_000) & (times < 400_000)) | (
        np.random.default_rng(1).random(len(times)) < 0.5)
    tracker, inside = _same_runs(
        lambda: make_tracker(seq, method="full")[0],
        lambda tr: stream(tr, seq, np.random.default_rng(5), keep_frame=lambda i: not dropped[i]))
    assert tracker.stats.depth_fallbacks > 0
    assert sum(n for n, _ in inside) > 0.5 * tracker.stats.steps  # most steps in runs
    assert tracker.stats.steps_remeasured > 50  # the late first pose's steps: runs of a group


@pytest.mark.parametrize("depth_source", ["sensor", "model"])
def test_step_runs_equal_steps_when_a_late_first_pose_measures_again(fast_sequence,
                                                                     depth_source) -> None:
    """The first pose (100 ms late) has the steps since its frame measured again, a step
    group per compiled run (``remeasure.on_pose``), with sensor depth (the frames dropped in
    that span: depth maps that expire inside a group) and with model depth (no live runs):
    the same trajectory and counts as step by step."""
    seq = fast_sequence
    times = seq.rgb_times_us.numpy()
    dropped = (times >= 20_000) & (times < 90_000)
    tracker, _ = _same_runs(
        lambda: make_tracker(seq, method="full", depth={"source": depth_source})[0],
        lambda tr: stream(tr, seq, np.random.default_rng(2), keep_frame=lambda i: not dropped[i]))
    assert tracker.stats.steps_remeasured > 50


@pytest.mark.parametrize("lost_after_ms", [5.0, 12.0, 23.0])
def test_step_runs_equal_steps_when_the_object_leaves_the_view(exit_sequence, box,
                                                               lost_after_ms) -> None:
    """The object leaves the image and is lost by its predicted silhouette (no misses
    counted; lost once 5% of it has been out of the image for ``lost_after_ms``): the loss
    falls inside a run (at its first step or a later one, by the delay), whose later steps
    are then done step by step, with the same trajectory (the held pose included) as step
    by step throughout."""
    seq = exit_sequence

    def make() -> Tracker:
        oracle = OraclePoseSource.from_sequence(seq, seed=0, **ORACLE_NOISE)
        source = VisibleOnlySource(oracle, np.asarray(box.vertices), seq.meta.event_camera, 0.3)
        cfg = TrackerConfig.from_dict({**TEST_TRACKER, "lost_after_misses": 0,
                                       "min_visible_fraction": 0.95,
                                       "lost_after_ms": lost_after_ms})
        return Tracker.for_sequence(seq, cfg, source)

    tracker, inside = _same_runs(make, lambda tr: tr.track(seq))
    assert tracker.stats.lost >= 1
    assert any(lost for _, lost in inside)  # lost at a step of a run
