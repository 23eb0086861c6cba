"""Streaming windows equal Events.windows on the whole stream, however it is chunked."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evtrack.events import Events, concatenate
from evtrack.io.reader import _window_bounds, rewindow


def _stream(ts: list[int]) -> Events:
    n = len(ts)
    return Events(np.zeros(n, np.int16), np.zeros(n, np.int16), np.sort(np.array(ts, np.int64)),
                  np.ones(n, np.int8), (4, 4))


def _chunks(ev: Events, cuts: list[int]):
    bounds = sorted({0, len(ev), *[c % (len(ev) + 1) for c in cuts]})
    return iter([ev[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)])


@settings(max_examples=100, deadline=None)
@given(
    ts=st.lists(st.integers(0, 5000), max_size=60),
    cuts=st.lists(st.integers(0, 100), max_size=6),
    window=st.integers(1, 800),
    include_empty=st.booleans(),
    lead=st.integers(0, 900),
)
def test_time_windows_match(ts, cuts, window, include_empty, lead):
    ev = _stream(ts)
    start = None if not len(ev) or lead == 0 else ev.t_start - lead
    got = list(rewindow(_chunks(ev, cuts), window_us=window, t_start_us=start,
                        include_empty=include_empty, sensor_size=(4, 4)))
    want = list(ev.windows(window, t_start_us=start, include_empty=include_empty))
    assert len(got) == len(want)
    assert all(g == w for g, w in zip(got, want, strict=True))
    if got:
        assert concatenate(got) == ev


@settings(max_examples=50, deadline=None)
@given(ts=st.lists(st.integers(0, 5000), max_size=60),
       cuts=st.lists(st.integers(0, 100), max_size=6), count=st.integers(1, 25))
def test_count_windows_match(ts, cuts, count):
    ev = _stream(ts)
    got = list(rewindow(_chunks(ev, cuts), count=count))
    want = list(ev.windows(count=count))
    assert len(got) == len(want) and all(g == w for g, w in zip(got, want, strict=True))


@settings(max_examples=200, deadline=None)
@given(
    ts=st.lists(st.integers(0, 100_000), min_size=1, max_size=80),
    window=st.integers(1, 5000),
    lead=st.integers(0, 3000),
)
def test_window_bounds_equal_the_per_event_division(ts, window, lead):
    """Both branches (binary search of the window edges, and the per-event pass when the chunk
    spans more windows than events) give the cuts of ``(t - start) // window``."""
    t = np.sort(np.array(ts, np.int64))
    start = int(t[0]) - lead
    widx = (t - start) // window
    expected = [0, *(np.flatnonzero(widx[1:] != widx[:-1]) + 1).tolist(), len(t)]
    assert _window_bounds(t, start, window) == expected


def test_window_bounds_on_inputs_of_either_branch():
    """A dense chunk (fewer windows than events: the binary search) and a chunk with a long gap
    (more windows than events: the per-event pass)."""
    dense = np.arange(0, 10_000, 3, dtype=np.int64)          # 3334 events in 10 windows
    gap = np.array([0, 1, 5_000_000, 5_000_001], np.int64)   # 4 events over 5001 windows
    for t, window in ((dense, 1000), (gap, 1000)):
        widx = (t - 0) // window
        cuts = (np.flatnonzero(widx[1:] != widx[:-1]) + 1).tolist()
        assert _window_bounds(t, 0, window) == [0, *cuts, len(t)]
