"""Tracker.track sets torch's thread count from its config, within the free cores, and puts
the caller's count back; the pose source may run in a worker thread of the tracker."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
import torch
from tracker_helpers import make_tracker, stream

from evtrack import utils
from evtrack.tracking import tracker as tracker_module


@pytest.mark.parametrize(("configured", "cores", "expected"), [
    (2, 4, 2), (2, 1, 1), (3, 2, 2), (0, 2, None),  # None: the caller's count is left alone
])
def test_track_runs_on_the_configured_threads(static_sequence, monkeypatch, configured, cores,
                                              expected) -> None:
    tracker, _ = make_tracker(static_sequence, method="pose", torch_threads=configured)
    seen: list[int] = []
    monkeypatch.setattr(tracker_module, "push_sequence",
                        lambda *args: seen.append(torch.get_num_threads()))
    monkeypatch.setattr(utils, "usable_cpu_count", lambda: cores)
    before = torch.get_num_threads()
    # a caller's count that differs from every expected value, so a leak would show
    torch.set_num_threads(5)
    try:
        tracker.track(static_sequence)
        assert seen == [5 if expected is None else expected]
        assert torch.get_num_threads() == 5
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("streaming", [False, True])
def test_blas_runs_on_the_configured_threads_while_tracking(static_sequence, streaming) -> None:
    """numpy's BLAS is limited to ``blas_threads`` while the tracker works (offline and in the
    streaming calls) and the caller's setting is back afterwards."""
    threadpoolctl = pytest.importorskip("threadpoolctl")

    def blas() -> set[int]:
        return {p["num_threads"] for p in threadpoolctl.threadpool_info()
                if p["user_api"] == "blas"}

    if not blas():
        pytest.skip("threadpoolctl finds no BLAS library in this process")
    tracker, source = make_tracker(static_sequence, method="pose", blas_threads=1)
    seen: list[set[int]] = []
    inner = source.__call__

    class Recording:
        uses_depth = False

        def __call__(self, *args):
            seen.append(blas())
            return inner(*args)

    tracker.pose_source = Recording()
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        if blas() != {2}:
            pytest.skip("this BLAS cannot run 2 threads")
        if streaming:  # the object at rest: frames only
            times = static_sequence.rgb_times_us.tolist()
            for i, t in enumerate(times):
                tracker.push_frame(t, rgb=lambda i=i: static_sequence.rgb(i))
            tracker.advance(times[-1] + 1)
            tracker.flush()
        else:
            tracker.track(static_sequence)
        assert blas() == {2}
    assert seen and all(s == {1} for s in seen)


def _same_track(a, b) -> None:
    assert torch.equal(a.t_us, b.t_us)
    assert torch.equal(torch.nan_to_num(a.poses, 1e9), torch.nan_to_num(b.poses, 1e9))
    assert torch.equal(a.twists, b.twists)


@pytest.mark.parametrize("method", ["full", "pose", "velocity", "ge", "frame-flow"])
def test_pose_source_in_a_worker_gives_the_same_track(fast_sequence, method) -> None:
    """``pose_async``: in ``track`` the pose source runs in the tracker's worker thread and
    its results are taken when due; the trajectory and the statistics are those of the calls
    in the caller's thread, with outliers, dropped detections and low-confidence poses
    (misses) among them. The streaming calls keep the caller's thread."""
    oracle = {"std_translation": 0.01, "std_rotation": 0.03, "outlier_rate": 0.2,
              "dropout_rate": 0.2}
    out = {}
    for pose_async in (False, True):
        tracker, source = make_tracker(fast_sequence, oracle=oracle, method=method,
                                       pose_async=pose_async, pose_gate={"min_confidence": 0.5},
                                       pose_rate_hz=30.0)
        inner = source.__call__
        threads: set[str] = set()

        def low_confidence_every_third(t_us, rgb, depth=None, inner=inner, threads=threads):
            threads.add(threading.current_thread().name)
            if 250_000 <= t_us < 400_000:  # misses in a row: the object is lost
                return None
            m = inner(t_us, rgb, depth)
            if m is not None and (t_us // 1000) % 3 == 0:
                m = dataclasses.replace(m, confidence=0.1)
            return m

        tracker.pose_source = low_confidence_every_third
        traj = tracker.track(fast_sequence)
        stats = {k: v for k, v in tracker.stats.to_dict().items() if k != "time_s"}
        out[pose_async] = (traj, stats, set(threads))
    (sync, sync_stats, sync_threads), (asyn, async_stats, async_threads) = out[False], out[True]
    if method == "velocity":  # poses only until the first one initialises the track
        assert sync_stats["poses"] >= 1
    else:
        assert sync_stats["pose_misses"] >= 6 and sync_stats["poses"] >= 4
        assert sync_stats["lost"] >= 1
    assert async_stats == sync_stats
    _same_track(sync, asyn)
    assert sync_threads == {threading.main_thread().name}
    assert async_threads and all(name.startswith("evtrack-pose") for name in async_threads)
    streamed, source = make_tracker(fast_sequence, oracle=oracle, method=method,
                                    pose_async=True)
    streaming_threads: set[str] = set()
    inner = source.__call__

    def recording(t_us, rgb, depth=None):
        streaming_threads.add(threading.current_thread().name)
        return inner(t_us, rgb, depth)

    streamed.pose_source = recording
    stream(streamed, fast_sequence, np.random.default_rng(2), t_end_us=300_000)
    assert streaming_threads == {threading.main_thread().name}


def test_pose_source_errors_surface_from_the_worker(fast_sequence) -> None:
    tracker, _ = make_tracker(fast_sequence, method="pose", pose_async=True)

    def broken(t_us, rgb, depth=None):
        raise RuntimeError("pose network failed")

    tracker.pose_source = broken
    with pytest.raises(RuntimeError, match="pose network failed"):
        tracker.track(fast_sequence)


def test_depth_maps_prepared_in_the_reader_thread_equal_set_frame(fast_sequence,
                                                                  monkeypatch) -> None:
    """``track`` prepares each sensor depth frame's event-camera map in its reader thread;
    the maps the depth source takes are those ``set_frame`` makes from the same frames."""
    from evtrack.tracking.depth_sources import SensorDepth

    tracker, _ = make_tracker(fast_sequence, method="full")
    assert isinstance(tracker.roi_depth.source, SensorDepth)
    taken: list[tuple[int, np.ndarray, str]] = []
    inner = SensorDepth.set_prepared

    def spy(self, t_us, event_map):
        taken.append((t_us, event_map, threading.current_thread().name))
        inner(self, t_us, event_map)

    prepared_in: set[str] = set()
    prepare = SensorDepth.prepare

    def prepare_spy(self, t_us, depth):
        prepared_in.add(threading.current_thread().name)
        return prepare(self, t_us, depth)

    class WithHoles:  # the sequence, with a corner of missing depth (0) in every frame
        def __getattr__(self, name):
            return getattr(fast_sequence, name)

        def depth(self, index):
            frame = fast_sequence.depth(index).copy()
            frame[:8, :8] = 0.0
            return frame

    monkeypatch.setattr(SensorDepth, "set_prepared", spy)
    monkeypatch.setattr(SensorDepth, "prepare", prepare_spy)
    seq = WithHoles()
    tracker.track(seq)
    times = fast_sequence.depth_times_us.tolist()
    assert len(taken) == len(times)
    reference = SensorDepth(tracker.camera, tracker.rgb_camera, tracker.T_event_rgb)
    differs_from_raw = 0
    for t_us, event_map, _ in taken:
        raw = seq.depth(times.index(t_us))
        inner(reference, t_us, prepare(reference, t_us, raw))
        assert np.array_equal(event_map, reference.map, equal_nan=True)
        differs_from_raw += not np.array_equal(event_map, raw, equal_nan=True)
    assert differs_from_raw == len(taken)  # missing depth (0) became NaN: a map, not the raw
    assert any(name.startswith("evtrack-frames") for name in prepared_in)


class _PriorRecorder:
    """An oracle pose source that takes a prior (``accepts_prior``) and records what it got;
    no detections between 250 and 400 ms (the object is lost there)."""

    accepts_prior = True

    def __init__(self, inner, tracker=None) -> None:
        self.inner = inner
        self.tracker = tracker  # in the caller's thread: its pose is read at the call
        self.priors: dict[int, np.ndarray | None] = {}
        self.track_poses: dict[int, np.ndarray] = {}

    def __call__(self, t_us, rgb, depth=None, prior=None):
        self.priors[t_us] = None if prior is None else np.array(prior)
        if self.tracker is not None and self.tracker.initialized:
            self.track_poses[t_us] = np.array(self.tracker.pose(t_us))
        if 250_000 <= t_us < 400_000:
            return None
        return self.inner(t_us, rgb, depth)


@pytest.mark.parametrize("pose_async", [False, True])
def test_the_pose_source_gets_the_tracks_pose_as_its_prior(fast_sequence, pose_async) -> None:
    """``pose_prior``: the tracker hands a source that accepts one its pose at the frame's
    time while the track holds, nothing before the first pose and after a loss; the same
    priors whether the source runs in the worker or in the caller's thread."""
    priors = {}
    for run_async in (False, pose_async):
        tracker, source = make_tracker(fast_sequence, method="full", pose_prior=True,
                                       pose_async=run_async, pose_rate_hz=30.0,
                                       pose_gate={"min_confidence": 0.5})
        recorder = _PriorRecorder(source, None if run_async else tracker)
        tracker.pose_source = recorder
        tracker.track(fast_sequence)
        assert tracker.stats.lost >= 1
        priors[run_async] = recorder.priors
        if not run_async:  # exactly the track's pose at the frame's time
            assert recorder.track_poses.keys() == {
                t for t, p in recorder.priors.items() if p is not None}
            for t, pose in recorder.track_poses.items():
                np.testing.assert_array_equal(recorder.priors[t], pose)
    got = priors[pose_async]
    times = sorted(got)
    assert got[times[0]] is None  # no track yet
    with_prior = [t for t in times if got[t] is not None]
    assert len(with_prior) >= len(times) // 2
    # the misses lose the object (once they are due, a latency later): no prior until a
    # pose has started the track again
    after_loss = [t for t in times if t >= 400_000]
    assert any(got[t] is None for t in after_loss) and got[after_loss[-1]] is not None
    gt = fast_sequence.ground_truth
    for t in with_prior:
        truth = gt.pose_at(t).numpy()
        assert got[t].shape == (4, 4)
        assert np.linalg.norm(got[t][:3, 3] - truth[:3, 3]) < 0.1  # a pose near the truth
    assert priors[False].keys() == got.keys()
    for t in times:
        a, b = priors[False][t], got[t]
        assert (a is None) == (b is None) and (a is None or np.array_equal(a, b))


def test_a_source_without_accepts_prior_is_called_as_before(fast_sequence) -> None:
    tracker, source = make_tracker(fast_sequence, method="full", pose_prior=True)
    calls = []

    def plain(t_us, rgb, depth=None):  # takes no prior: passing one would raise
        calls.append(t_us)
        return source(t_us, rgb, depth)

    tracker.pose_source = plain
    tracker.track(fast_sequence)
    assert len(calls) >= 2 and tracker.stats.poses >= 2
