"""Tracker shortcuts that must not change results: the read-ahead reader of offline
depth frames and the grouped depth lookup of a step group's RoIs."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch
from tracker_helpers import make_tracker, stream

from evtrack.tracking.tracker import Tracker, _Prefetched


def test_gives_every_frame_and_reads_the_next_one_in_a_worker():
    threads: list[str] = []

    def read(i: int) -> int:
        threads.append(threading.current_thread().name)
        return 10 * i

    reader = _Prefetched(read, 4)
    try:
        assert [reader(i) for i in range(4)] == [0, 10, 20, 30]
    finally:
        reader.close()
    assert threads[0] == threading.current_thread().name  # the first frame: nothing ahead
    assert all(name.startswith("evtrack-frames") for name in threads[1:])
    assert len(threads) == 4  # nothing read twice, nothing past the end


@pytest.mark.parametrize("ahead", [1, 3])
def test_a_skipped_or_repeated_frame_is_read_directly(ahead):
    calls: list[tuple[int, str]] = []
    here = threading.current_thread().name

    def read(i: int) -> int:
        calls.append((i, threading.current_thread().name))
        return i

    reader = _Prefetched(read, 10, ahead=ahead)
    try:
        assert reader(0) == 0
        assert reader(5) == 5  # frames 1.. were read ahead in vain
        assert reader(5) == 5  # frame 6.. likewise
        assert reader(6) == 6
    finally:
        reader.close()
    direct = [i for i, name in calls if name == here]
    assert direct == [0, 5, 5]  # frame 6 came from the worker, read once
    assert [i for i, _ in calls].count(6) == 1
    assert max(i for i, _ in calls) <= 6 + ahead  # nothing read farther ahead


def test_reads_the_next_frames_ahead_in_the_worker():
    started = threading.Event()
    reads: list[int] = []

    def read(i: int) -> int:
        reads.append(i)
        if i == 3:
            started.set()
        return i

    reader = _Prefetched(read, 10, ahead=3)
    try:
        assert reader(0) == 0
        assert started.wait(5.0)  # frames 1, 2 and 3 read without being asked for
        assert reads == [0, 1, 2, 3]
        assert [reader(i) for i in range(1, 10)] == list(range(1, 10))
    finally:
        reader.close()
    assert sorted(reads) == list(range(10))  # each once, none past the end


def test_an_error_reaches_the_call_that_asks_for_that_frame():
    def read(i: int) -> int:
        if i == 2:
            raise OSError("depth/000002.png: truncated file")
        return i

    reader = _Prefetched(read, 5)
    try:
        assert reader(0) == 0
        assert reader(1) == 1  # frame 2 fails in the worker, silently for now
        with pytest.raises(OSError, match="000002.png"):
            reader(2)
    finally:
        reader.close()


def test_group_depth_lookup_equals_step_by_step(fast_sequence, monkeypatch):
    """The sensor depth of a step group's RoIs is looked up once per depth map
    (Tracker._step_depth); with frames dropped (depth maps that expire and arrive inside a
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

    def per_step(self, flows, k, poly, pose):
        calls.append(k)
        return self._roi_depth(flows.step(k)[0], poly, pose)

    monkeypatch.setattr(Tracker, "_step_depth", per_step)
    stepped, st_stepped = run()
    assert calls  # the patched lookup was used
    assert st_grouped.depth_fallbacks == st_stepped.depth_fallbacks > 0
    assert st_grouped.roi_flows == st_stepped.roi_flows
    assert torch.equal(grouped.poses.nan_to_num(7.0), stepped.poses.nan_to_num(7.0))


def test_a_closed_reader_reads_in_the_callers_thread():
    threads: list[str] = []

    def read(i: int) -> int:
        threads.append(threading.current_thread().name)
        return i

    reader = _Prefetched(read, 5)
    assert reader(0) == 0
    reader.close()
    assert reader(1) == 1  # the frame read ahead was dropped: read again, here
    assert reader(2) == 2
    assert threads[-2:] == [threading.current_thread().name] * 2


def test_track_takes_the_last_frames_with_long_step_groups(fast_sequence):
    """With 40 ms step groups the last frames are reached only by the final advance, after
    the frame loop: the depth reader must still give them (it used to be closed by then,
    and ``track`` failed on the last depth frame)."""
    counts = []
    for steps in (10, 40):
        tracker, _ = make_tracker(fast_sequence, method="full", flow_batch_steps=steps)
        traj = tracker.track(fast_sequence)
        assert bool(traj.tracked.any()) and bool(torch.isfinite(traj.poses[traj.tracked]).all())
        counts.append((tracker.stats.frames, tracker.stats.frames_without_depth))
    assert counts[0] == counts[1]  # every frame taken, each with its depth


def _mask_coverage(seq, monkeypatch, swept: bool) -> tuple[float, int]:
    """Share of the object's events (inside the true silhouette at their time, 1 px margin)
    that the tracker's event masks kept, over the step groups it masked; and their number."""
    masks = []
    sweep = Tracker._swept_mask

    def recording(self, poly, pose, span_us):
        mask = sweep(self, poly, pose, span_us) if swept else poly
        masks.append((self._t, self._t + span_us, mask))
        return mask

    monkeypatch.setattr(Tracker, "_swept_mask", recording)
    tracker, _ = make_tracker(seq, method="full")
    tracker.track(seq)
    monkeypatch.undo()
    ev = seq.events
    x, y, t = ev.x.numpy(), ev.y.numpy(), ev.t.numpy()
    sil, size, margin = tracker.silhouette, tracker.camera.size, tracker.config.mask_margin_px
    hit = total = 0
    for t0, t1, mask in masks:
        lo, hi = np.searchsorted(t, [t0, t1])
        keep = mask.contains_pixels(x[lo:hi], y[lo:hi], margin, size)
        on_object = np.zeros(hi - lo, bool)
        for a in range(t0, t1, 2000):  # the true silhouette every 2 ms
            sel = (t[lo:hi] >= a) & (t[lo:hi] < a + 2000)
            poly = sil.polygon(seq.ground_truth.pose_at(a + 1000).numpy())
            if sel.any() and poly is not None:
                on_object[sel] = poly.contains_pixels(x[lo:hi][sel], y[lo:hi][sel], 1.0, size)
        hit += int((keep & on_object).sum())
        total += int(on_object.sum())
    assert total > 1000
    return hit / total, total


def test_the_group_mask_sweeps_with_the_object(fast_sequence, monkeypatch):
    """A step group's events are masked with the hull of the silhouettes predicted at its
    start and at its end (Tracker._swept_mask): with 40 ms groups and the tests' 8 px margin
    the object moves out of its starting silhouette within a group, and the start's
    silhouette alone loses the events of its leading edges."""
    swept, n = _mask_coverage(fast_sequence, monkeypatch, swept=True)
    start_only, n0 = _mask_coverage(fast_sequence, monkeypatch, swept=False)
    print(f"object events kept: swept {swept:.4f} of {n}, start only {start_only:.4f} of {n0}")
    # measured 0.995 and 0.990 on two installs whose renders differ in their last bits (start
    # only: 0.967 and 0.957); the margin is for that spread
    assert swept > 0.98
    assert swept > start_only + 0.02
