"""Offline tracking (evtrack.tracking.offline): the read-ahead frame reader gives every frame
in order from a worker, raises a read's error at the call that asks for it, and the last
frames of a sequence are still read with long step groups."""

from __future__ import annotations

import threading

import pytest
import torch
from tracker_helpers import make_tracker

from evtrack.tracking.offline import Prefetched


def test_gives_every_frame_and_reads_the_next_one_in_a_worker():
    threads: list[str] = []

    def read(i: int) -> int:
        threads.append(threading.current_thread().name)
        return 10 * i

    reader = Prefetched(read, 4)
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

    reader = Prefetched(read, 10, ahead=ahead)
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

    reader = Prefetched(read, 10, ahead=3)
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

    reader = Prefetched(read, 5)
    try:
        assert reader(0) == 0
        assert reader(1) == 1  # frame 2 fails in the worker, silently for now
        with pytest.raises(OSError, match="000002.png"):
            reader(2)
    finally:
        reader.close()


def test_a_closed_reader_reads_in_the_callers_thread():
    threads: list[str] = []

    def read(i: int) -> int:
        threads.append(threading.current_thread().name)
        return i

    reader = Prefetched(read, 5)
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
