"""The batched candidate search equals the sequential reference, bit for bit, for any chunking."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from flow_reference import reference_candidates, reference_offsets
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evtrack.flow.candidates import Candidates, CandidateSearch, pass_bounds, pass_starts
from evtrack.flow.config import FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.scenes import translating_texture

FIELDS = ("event", "offset", "age_j", "age_i", "seq_j", "seq_i", "dt_us")


def _rows(c):
    return list(zip(*(getattr(c, f).tolist() for f in FIELDS), strict=True))


def _reference(x, y, t, p, cfg, state=None):
    return reference_candidates(
        x, y, t, p, cfg.sensor_size, radius=cfg.radius, history=cfg.history,
        refractory_us=cfg.refractory_us, tolerance_us=cfg.tolerance_us,
        tolerance_permille=cfg.tolerance_permille, min_speed=cfg.min_speed,
        max_speed=cfg.max_speed, max_span_us=cfg.max_span_us, state=state)


def _assert_same(cands, ref_rows):
    assert _rows(cands) == [r[:7] for r in ref_rows]
    if ref_rows:
        ref_flow = torch.tensor([r[7:] for r in ref_rows], dtype=torch.float64)
        torch.testing.assert_close(cands.flow.to("cpu", torch.float64), ref_flow,
                                   rtol=1e-6, atol=1e-3)


def _random_stream(seed, n, size, max_gap):
    rng = np.random.default_rng(seed)
    w, h = size
    # a few moving blobs plus noise, so that triplets actually occur
    t = np.cumsum(rng.integers(0, max_gap + 1, n))
    x = rng.integers(0, w, n)
    y = rng.integers(0, h, n)
    p = rng.choice([-1, 1], n)
    return [torch.as_tensor(a) for a in (x, y, t, p)]


def _structured_stream(n_max=3000):
    ev, _ = translating_texture((40, 30), velocity=(900.0, -400.0), duration_us=12_000, seed=3)
    ev = ev[:n_max]
    return ev.x, ev.y, ev.t, ev.p


def test_offsets_and_bounds_match_their_definition():
    for r in (1, 2, 3):
        assert search_offsets(r).tolist() == [list(o) for o in reference_offsets(r)]
    offsets = search_offsets(3)
    bounds = dt_bounds_us(offsets, 37.0, 9000.0)
    for (dx, dy), (lo, hi) in zip(offsets.tolist(), bounds.tolist(), strict=True):
        dist = float(np.hypot(2 * dx, 2 * dy))
        def ok(dt, dist=dist):
            return 37.0 <= dist * 1e6 / dt <= 9000.0
        assert ok(lo) and ok(hi) and not ok(lo - 1) and not ok(hi + 1)
    # a span bound caps hi; one below every fitting dt leaves the displacement empty
    capped = dt_bounds_us(offsets, 37.0, 9000.0, max_span_us=1000)
    assert (capped[:, 0] == bounds[:, 0]).all() | (capped[:, 0] > capped[:, 1]).all()
    for (lo, hi), (lo_c, hi_c) in zip(bounds.tolist(), capped.tolist(), strict=True):
        if lo <= 1000:
            assert (lo_c, hi_c) == (lo, min(hi, 1000))
        else:
            assert lo_c > hi_c


def test_span_bound_drops_long_triplets_only():
    """A triplet spanning more than max_span_us gives no candidate; a shorter one does."""
    # one pixel row, an edge moving at 100 px/s: 10 ms per pixel, 20 ms per triplet (d = 1)
    x, y = torch.tensor([0, 1, 2]), torch.zeros(3, dtype=torch.int64)
    t, p = torch.tensor([0, 10_000, 20_000]), torch.ones(3, dtype=torch.int64)
    base = dict(sensor_size=(3, 1), radius=1, history=1, min_speed=20.0)
    kept = CandidateSearch(FlowConfig(**base, max_span_us=20_000))(x, y, t, p)
    assert kept.dt_us.tolist() == [20_000]
    torch.testing.assert_close(kept.flow, torch.tensor([[100.0, 0.0]]))
    assert len(CandidateSearch(FlowConfig(**base, max_span_us=19_999))(x, y, t, p)) == 0
    assert len(CandidateSearch(FlowConfig(**base, max_span_us=0))(x, y, t, p)) == 1


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(0, 250), chunk=st.integers(1, 300),
       block=st.integers(1, 64), radius=st.integers(1, 3), history=st.integers(1, 3),
       repeats=st.integers(1, 4), refractory=st.sampled_from([0, 40, 400]),
       max_gap=st.sampled_from([0, 3, 60]), span=st.sampled_from([0, 300, 2000]),
       lookup=st.sampled_from(["passes", "sorted"]))
def test_random_streams_equal_reference(seed, n, chunk, block, radius, history, repeats,
                                        refractory, max_gap, span, lookup):
    size = (9, 7)
    x, y, t, p = _random_stream(seed, n, size, max_gap)
    cfg = FlowConfig(sensor_size=size, radius=radius, history=history, pass_repeats=repeats,
                     lookup=lookup, refractory_us=refractory, chunk_size=chunk, block_size=block,
                     tolerance_us=5, tolerance_rel=0.2, min_speed=100.0, max_speed=1e6,
                     max_span_us=span)
    got = CandidateSearch(cfg)(x, y, t, p)
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    _assert_same(got, ref)


@pytest.mark.parametrize("lookup", ["passes", "sorted"])
@pytest.mark.parametrize("chunk", [1, 13, 500, 100_000])
@pytest.mark.parametrize("block", [7, 4096])
def test_structured_stream_equals_reference_for_any_chunking(chunk, block, lookup):
    x, y, t, p = _structured_stream()
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=chunk, block_size=block, lookup=lookup)
    got = CandidateSearch(cfg)(x, y, t, p)
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    assert len(ref) > 100  # the scene really produces triplets
    _assert_same(got, ref)


@pytest.mark.parametrize(("repeats", "lookup"), [(1, "passes"), (3, "passes"), (1, "sorted")])
def test_long_streams_move_the_time_base_without_changing_the_result(repeats, lookup):
    """Relative int32 times: crossing the base's limit (2^29 µs) keeps the result exact."""
    x, y, t, p = _structured_stream(2000)
    t = t.clone()
    t[1000:] += (1 << 29) + int(t[0]) - int(t[1200])  # the second half crosses the limit
    assert t[1199] - t[0] < (1 << 29) <= t[1200] - t[0]  # at event 1200, amid dense events
    t[1500:] += 1 << 30            # and jumps by more than the history keeps
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=300, refractory_us=0,
                     pass_repeats=repeats, lookup=lookup)
    got = CandidateSearch(cfg)(x, y, t, p)
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    assert any(r[0] >= 1500 for r in ref) and any(1000 <= r[0] < 1500 for r in ref)
    _assert_same(got, ref)


@pytest.mark.parametrize("tabulated", [True, False])
@pytest.mark.parametrize("tolerance_rel", [0.1, 0.9997])  # 0.9997: 1000 per mille
def test_tolerance_interval_equals_reference(monkeypatch, tabulated, tolerance_rel):
    import evtrack.flow.candidates as candidates

    if not tabulated:
        monkeypatch.setattr(candidates, "_TABLE_MAX", 0)
    x, y, t, p = _structured_stream(1500)
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=400, refractory_us=0,
                     tolerance_rel=tolerance_rel, tolerance_us=3)
    search = CandidateSearch(cfg)
    assert (search._tol_tables is not None) == tabulated
    got = search(x, y, t, p)
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    assert len(ref) > 100
    _assert_same(got, ref)


def test_a_stream_can_switch_lookup_between_chunks():
    """Both lookups leave the same rings between chunks, so a flow moved to another device
    (``TripletFlow.to``, which may change the lookup) mid-stream stays exact."""
    x, y, t, p = _structured_stream()
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=400, lookup="passes")
    first = CandidateSearch(cfg)
    half = len(t) // 2
    got_1 = first(x[:half], y[:half], t[:half], p[:half])
    second = CandidateSearch(cfg.replace(lookup="sorted"))
    second.history.load_state_dict(first.history.state_dict())
    second.next_seq, second.last_t, second.last_p = first.next_seq, first.last_t, first.last_p
    got_2 = second(x[half:], y[half:], t[half:], p[half:])
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    assert len(got_2) > 50
    _assert_same(Candidates.cat([got_1, got_2]), ref)


def test_streaming_calls_equal_one_call():
    x, y, t, p = _structured_stream(2000)
    cfg = FlowConfig(sensor_size=(40, 30), refractory_us=0, chunk_size=97)
    whole = CandidateSearch(cfg)(x, y, t, p)
    search = CandidateSearch(cfg)
    parts = [search(x[a:b], y[a:b], t[a:b], p[a:b])
             for a, b in [(0, 1), (1, 1), (1, 700), (700, 1500), (1500, 2000)]]
    assert [r for part in parts for r in _rows(part)] == _rows(whole)


def test_causal_prefix_is_unchanged_by_later_events():
    """Candidates of the first m events do not depend on what comes after them."""
    x, y, t, p = _structured_stream(2000)
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=4096)
    full = _rows(CandidateSearch(cfg)(x, y, t, p))
    m = 1200
    prefix = _rows(CandidateSearch(cfg)(x[:m], y[:m], t[:m], p[:m]))
    assert [r for r in full if r[0] < m] == prefix
    # reversing later events' polarity changes nothing before m either
    p2 = p.clone()
    p2[m:] = -p2[m:]
    changed = _rows(CandidateSearch(cfg)(x, y, t, p2))
    assert [r for r in changed if r[0] < m] == prefix


def test_same_timestamp_events_see_only_earlier_ones():
    # e_i, e_j, then two events at e_k's time: only stream order decides what is visible
    cfg = FlowConfig(sensor_size=(8, 3), radius=1, history=1, refractory_us=0,
                     tolerance_us=0, tolerance_rel=0.0, min_speed=1.0, max_speed=1e7)
    x = torch.tensor([1, 2, 3, 3, 2])
    y = torch.tensor([1, 1, 1, 1, 1])
    t = torch.tensor([0, 100, 200, 200, 200])
    p = torch.tensor([1, 1, 1, 1, 1])
    got = _rows(CandidateSearch(cfg.replace(chunk_size=5))(x, y, t, p))
    # event 2 matches (0, 1); event 3 (same pixel, same time) too; event 4 at x=2 sees event
    # 1 as its own pixel's past, not as a neighbour, and nothing at x=1/x=0 fits.
    assert [(r[0], r[4], r[5]) for r in got] == [(2, 1, 0), (3, 1, 0)]
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    assert [r[:7] for r in ref] == got


def test_passes_hold_at_most_L_events_per_cell_and_are_maximal():
    rng = np.random.default_rng(0)
    cell = torch.as_tensor(rng.integers(0, 20, 3000))
    for repeats in (1, 2, 5):
        _, next_end = pass_starts(cell, repeats)
        bounds = pass_bounds(next_end)
        assert bounds[0][0] == 0 and bounds[-1][1] == cell.numel()
        for (a, b), nxt in zip(bounds, bounds[1:] + [None], strict=True):
            counts = torch.bincount(cell[a:b])
            assert int(counts.max()) <= repeats
            if nxt is not None:  # one more event would break the cap
                assert int(torch.bincount(cell[a:b + 1]).max()) == repeats + 1


def test_burst_memory_is_bounded_by_block_size(monkeypatch):
    """A burst at 100x the rate is split into blocks no larger than block_size."""
    ev, _ = translating_texture((40, 30), velocity=(900.0, 300.0), duration_us=6_000, seed=1)
    burst_t = ev.t // 100  # the same events squeezed into 1/100 of the time
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=5000, block_size=256, refractory_us=0)
    search = CandidateSearch(cfg)
    sizes = []
    for name in ("_block", "_block_slots"):  # general and pass_repeats == 1 paths
        original = getattr(CandidateSearch, name)

        def spy(self, x, *args, original=original):
            sizes.append(int(x.shape[0]))
            return original(self, x, *args)

        monkeypatch.setattr(CandidateSearch, name, spy)
    chunk_sizes = []
    original_chunk = CandidateSearch._chunk

    def spy_chunk(self, x, *args):
        chunk_sizes.append(int(x.shape[0]))
        return original_chunk(self, x, *args)

    monkeypatch.setattr(CandidateSearch, "_chunk", spy_chunk)
    search(ev.x, ev.y, burst_t, ev.p)
    assert sum(sizes) == len(ev)
    assert max(sizes) <= 256
    assert max(chunk_sizes) <= 5000


@pytest.mark.parametrize("lookup", ["passes", "sorted"])
def test_search_on_the_test_device_equals_reference(device, lookup):
    """Run with ``pytest --device cuda`` to check the CUDA path against the reference."""
    x, y, t, p = _structured_stream(2500)
    cfg = FlowConfig(sensor_size=(40, 30), chunk_size=900, block_size=300, device=str(device),
                     lookup=lookup)
    got = CandidateSearch(cfg, device)(x.to(device), y.to(device), t.to(device), p.to(device))
    ref, _ = _reference(x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg)
    _assert_same(got.select(torch.arange(len(got), device=device)), ref)
    assert got.flow.device.type == device.type
