"""``continue_bursts``: the first event of each pixel of a batch taken as the continuation of a
burst, checked against the sequential reference with that pixel's previous event set to the
same polarity 1 µs before it, for the torch search (both lookups), the compiled search and
:class:`~evtrack.flow.TripletFlow`."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from flow_helpers import random_stream
from flow_reference import reference_candidates
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evtrack.events import Events
from evtrack.flow import FlowConfig, TripletFlow
from evtrack.flow.candidates import CandidateSearch
from evtrack.runtime.jit import available as numba_available

SIZE = (9, 7)
FIELDS = ("event", "offset", "age_j", "age_i", "seq_j", "seq_i", "dt_us")


def _config(refractory: int, history: int, **kw) -> FlowConfig:
    return FlowConfig(sensor_size=SIZE, radius=2, history=history, refractory_us=refractory,
                      tolerance_us=5, tolerance_rel=0.2, min_speed=100.0, max_speed=1e6, **kw)


def _reference_rows(x, y, t, p, cfg, cut):
    """Reference rows of the stream with the first event of each pixel from ``cut`` on made a
    burst continuation (its pixel's last event: same polarity, 1 µs earlier)."""
    kw = dict(radius=cfg.radius, history=cfg.history, refractory_us=cfg.refractory_us,
              tolerance_us=cfg.tolerance_us, tolerance_permille=cfg.tolerance_permille,
              min_speed=cfg.min_speed, max_speed=cfg.max_speed, max_span_us=cfg.max_span_us)
    first, state = reference_candidates(x[:cut], y[:cut], t[:cut], p[:cut], SIZE, **kw)
    seen = set()
    for xk, yk, tk, pk in zip(x[cut:], y[cut:], t[cut:], p[cut:], strict=True):
        if (yk, xk) not in seen:
            seen.add((yk, xk))
            state["last"][(yk, xk)] = (tk - 1, pk)
    rest, _ = reference_candidates(x[cut:], y[cut:], t[cut:], p[cut:], SIZE, state=state, **kw)
    return [r[:7] for r in first + rest]


def _rows(cands) -> list[tuple]:
    return list(zip(*(getattr(cands, f).tolist() for f in FIELDS), strict=True))


def _first_per_pixel(x, y):
    pixel = np.asarray(y) * SIZE[0] + np.asarray(x)
    return np.sort(np.unique(pixel, return_index=True)[1])


def _searches():
    out = [("torch passes", lambda cfg: CandidateSearch(cfg.replace(lookup="passes"))),
           ("torch sorted", lambda cfg: CandidateSearch(cfg.replace(lookup="sorted")))]
    if numba_available():
        from evtrack.flow.compiled import CompiledSearch

        out.append(("compiled", lambda cfg: CompiledSearch(cfg)))
    return out


@pytest.mark.parametrize(("name", "make"), _searches(), ids=[n for n, _ in _searches()])
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(2, 250), refractory=st.sampled_from([40, 400]),
       history=st.integers(1, 2), cut_share=st.floats(0.0, 1.0))
def test_searches_equal_the_reference(name, make, seed, n, refractory, history, cut_share):
    _check_against_the_reference(name, make, seed, n, refractory, history, cut_share)


@pytest.mark.parametrize(("name", "make"), _searches(), ids=[n for n, _ in _searches()])
def test_a_continuation_at_the_streams_first_microsecond(name, make):
    """The first batch is one event at t = 5 µs, and the second's first event, continued,
    is at 5 µs too: its previous event is set 1 µs before the compiled search's time base
    (found by hypothesis: the compiled search refused it as out of order)."""
    x, _, t, _ = random_stream(np.random.default_rng(389), 2, SIZE, 30)
    assert t.tolist() == [5, 5] and x[0] != x[1]
    _check_against_the_reference(name, make, 389, 2, 40, 1, 0.5)


def _check_against_the_reference(name, make, seed, n, refractory, history, cut_share):
    x, y, t, p = random_stream(np.random.default_rng(seed), n, SIZE, 30)
    cut = int(cut_share * n)
    cfg = _config(refractory, history)
    search = make(cfg)
    got = _rows(search(x[:cut], y[:cut], t[:cut], p[:cut])) if cut else []
    first = torch.from_numpy(cut + _first_per_pixel(x[cut:], y[cut:]))
    search.continue_bursts(*(v.index_select(0, first) for v in (x, y, t, p)))
    got += _rows(search(x[cut:], y[cut:], t[cut:], p[cut:]))
    ref = _reference_rows(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg, cut)
    assert got == ref


def test_the_continued_events_give_no_candidates() -> None:
    """An edge sweeping a row, one event per pixel: 12 candidates (d = 1 px from the third
    pixel on, d = 2 px from the fifth); continued, none of them is searched or stored, so no
    candidate at all; a second sweep of the other polarity (onsets again) gives the first
    sweep's candidates."""
    xs = np.arange(9)
    t = 1000 + 100 * xs
    sweep = (torch.as_tensor(xs), torch.full((9,), 3), torch.as_tensor(t),
             torch.ones(9, dtype=torch.int64))
    cfg = _config(400, 1)
    plain = CandidateSearch(cfg)(*sweep)
    assert len(plain) == 12
    search = CandidateSearch(cfg)
    search.continue_bursts(*sweep)
    assert len(search(*sweep)) == 0
    back = (sweep[0], sweep[1], sweep[2] + 1000, -sweep[3])
    again = search(*back)
    assert [r[1:4] + r[6:] for r in _rows(again)] == [r[1:4] + r[6:] for r in _rows(plain)]


def _flow_run(backend: str, continued: bool):
    x, y, t, p = random_stream(np.random.default_rng(7), 600, SIZE, 20)
    cut = 250
    cfg = _config(400, 1, window_us=500, roi_size=3, min_support=1, backend=backend)
    events = Events(x=x, y=y, t=t, p=p, sensor_size=SIZE)
    flow = TripletFlow(cfg)
    first = flow.update(events[:cut], until_us=int(t[cut]))
    if continued:
        flow.continue_bursts(events[cut:])
        assert flow.events_seen == cut  # nothing was searched or counted
    rest = flow.update(events[cut:], until_us=int(t[-1]) + 1)  # the same events next: no error
    return first, rest


def test_triplet_flow_backends_agree_and_the_call_matters() -> None:
    if not numba_available():
        pytest.skip("numba is not installed")
    first_t, rest_t = _flow_run("torch", True)
    first_c, rest_c = _flow_run("compiled", True)
    for a, b in ((first_t, first_c), (rest_t, rest_c)):
        assert torch.equal(a.t, b.t) and torch.equal(a.xy, b.xy)
        assert torch.equal(a.support, b.support)
        torch.testing.assert_close(a.flow, b.flow)
    _, rest_plain = _flow_run("torch", False)
    assert not (torch.equal(rest_plain.support, rest_t.support)
                and torch.equal(rest_plain.t, rest_t.t))


def test_no_burst_filter_no_change() -> None:
    """With ``refractory_us = 0`` there is no burst to continue: the call changes nothing."""
    x, y, t, p = random_stream(np.random.default_rng(3), 200, SIZE, 30)
    events = Events(x=x, y=y, t=t, p=p, sensor_size=SIZE)
    cfg = _config(0, 1, window_us=500, roi_size=3, min_support=1, backend="torch")
    a, b = TripletFlow(cfg), TripletFlow(cfg)
    ra = a.update(events[:100], until_us=int(t[100]))
    rb = b.update(events[:100], until_us=int(t[100]))
    b.continue_bursts(events[100:])
    ra2 = a.update(events[100:], until_us=int(t[-1]) + 1)
    rb2 = b.update(events[100:], until_us=int(t[-1]) + 1)
    for r1, r2 in ((ra, rb), (ra2, rb2)):
        assert torch.equal(r1.flow, r2.flow) and torch.equal(r1.t, r2.t)
