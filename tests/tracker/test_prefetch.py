"""The tracker's one-frame-ahead reader (offline depth frames)."""

from __future__ import annotations

import threading

import pytest

from evtrack.tracker import _Prefetched


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


def test_a_skipped_or_repeated_frame_is_read_directly():
    calls: list[int] = []

    def read(i: int) -> int:
        calls.append(i)
        return i

    reader = _Prefetched(read, 10)
    try:
        assert reader(0) == 0
        assert reader(5) == 5  # frame 1 was read ahead in vain
        assert reader(5) == 5  # frame 6 likewise
        assert reader(6) == 6
    finally:
        reader.close()
    assert sorted(calls)[:3] == [0, 1, 5]


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
