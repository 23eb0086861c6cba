"""Streaming windows equal Events.windows on the whole stream, however it is chunked."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evtrack.events import Events, concatenate
from evtrack.io.reader import rewindow


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
