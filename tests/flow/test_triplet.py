"""TripletFlow end to end: known flow, aperture, streaming, bad input, config."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events, concatenate
from evtrack.flow import FlowConfig, FlowResult, TripletFlow
from evtrack.flow.config import search_offsets
from evtrack.flow.scenes import moving_stripes, translating_texture

SIZE = (64, 48)
TRACKER_LIKE = {"roi_size": 12, "window_us": 1_000, "min_support": 2, "history": 1,
                "max_span_us": 40_000, "tolerance_rel": 0.05}
"""Small, short RoI windows as the tracker's flow has them: some report without a line."""


@pytest.fixture(scope="module")
def texture():
    return translating_texture(SIZE, velocity=(700.0, -450.0), duration_us=25_000, seed=4)


@pytest.fixture(scope="module")
def stripes():
    return moving_stripes(SIZE, normal_angle=1.1, speed=800.0, duration_us=25_000, seed=2)


def _rel_error(flow, truth):
    return (flow - truth).norm(dim=1) / truth.norm()


def test_translating_texture_flow_within_a_few_percent(texture):
    ev, gt = texture
    res = TripletFlow(roi_size=32, window_us=5_000)(ev)
    assert len(res) >= 12
    full = ~res.normal
    # a RoI window may see one edge orientation only: it is then (rightly) normal flow
    assert float(full.float().mean()) > 0.8
    err = _rel_error(res.flow[full], gt[0])
    assert float(err.median()) < 0.05
    assert float((err < 0.15).float().mean()) > 0.8
    n = res.normal_dir[res.normal]
    normal_err = ((res.flow[res.normal] * n).sum(1) - n @ gt[0]).abs() / gt[0].norm()
    assert float(normal_err.max()) < 0.2  # few of them, some in the start-up window
    # shapes and units of the documented fields
    assert res.xy.shape == (len(res), 2) and res.t.dtype == torch.int64
    assert bool((res.support >= 5).all()) and bool((res.support <= res.n_events).all())
    assert torch.isfinite(res.cost).all()
    assert set(res.t.tolist()) <= {2_500 + 5_000 * w for w in range(6)}


def test_moving_stripes_give_normal_flow(stripes):
    ev, gt = stripes
    res = TripletFlow(roi_size=32, window_us=5_000)(ev)
    assert len(res) >= 12
    assert float(res.normal.float().mean()) > 0.9
    truth_n = torch.tensor([math.cos(1.1), math.sin(1.1)])
    n = res.normal_dir[res.normal]
    assert float((n @ truth_n).abs().min()) > 0.99
    err = _rel_error(res.flow[res.normal], gt[0])  # the true flow is the normal flow here
    assert float(err.median()) < 0.08


def _random_events(size, n, duration_us, seed):
    rng = np.random.default_rng(seed)
    w, h = size
    return Events(torch.as_tensor(rng.integers(0, w, n), dtype=torch.int32),
                  torch.as_tensor(rng.integers(0, h, n), dtype=torch.int32),
                  torch.as_tensor(np.sort(rng.integers(0, duration_us, n))),
                  torch.as_tensor(rng.choice([-1, 1], n), dtype=torch.int8), size)


def test_windows_without_consensus_are_refused(texture):
    noise = _random_events(SIZE, 60_000, 100_000, seed=0)
    # random events still give chance triplets; their candidates agree on no flow
    assert len(TripletFlow(roi_size=32, window_us=5_000, min_inlier_fraction=0.0)(noise)) > 20
    assert len(TripletFlow(roi_size=32, window_us=5_000)(noise)) == 0
    # a rigid motion keeps (almost) all its windows
    ev, _ = texture
    every = TripletFlow(roi_size=32, window_us=5_000, min_inlier_fraction=0.0)(ev)
    gated = TripletFlow(roi_size=32, window_us=5_000)(ev)
    assert len(gated) >= 0.75 * len(every)
    kept = set(zip(gated.window.tolist(), gated.roi.tolist(), strict=True))
    assert kept <= set(zip(every.window.tolist(), every.roi.tolist(), strict=True))


def test_min_lines_keeps_a_subset_of_the_windows_unchanged(texture):
    """``min_lines`` only removes windows (those whose events gave no constraint line, which
    chance triplets of noise do more often than a rigid motion); the windows it keeps have
    the same flows."""
    ev, _ = texture
    noise = _random_events(SIZE, 20_000, 25_000, seed=3)
    every = TripletFlow(**TRACKER_LIKE)(ev)
    kept = TripletFlow(**TRACKER_LIKE, min_lines=1)(ev)
    rows = {k: i for i, k in enumerate(zip(every.window.tolist(), every.roi.tolist(),
                                            strict=True))}
    idx = [rows[k] for k in zip(kept.window.tolist(), kept.roi.tolist(), strict=True)]
    torch.testing.assert_close(kept.flow, every.flow[idx], equal_nan=True)
    assert 0.8 * len(every) < len(kept) < len(every)  # a rigid motion: lines almost everywhere
    loose = TripletFlow(roi_size=16, window_us=2_000, min_support=2, min_inlier_fraction=0.0)
    strict = TripletFlow(roi_size=16, window_us=2_000, min_support=2, min_inlier_fraction=0.0,
                         min_lines=1)
    noisy, checked = len(loose(noise)), len(strict(noise))
    assert noisy > 20 and checked < 0.9 * noisy


@pytest.mark.parametrize("backend", ["torch", "compiled"])
def test_lineless_share_judges_each_time_window_on_its_own(texture, backend):
    """``max_lineless_share`` 0: a time window with any line-less RoI window is judged as with
    ``min_lines`` 1 and ``fit_min_lines`` 1, every other one as by default."""
    ev, _ = texture
    kw = {**TRACKER_LIKE, "backend": backend}
    default = TripletFlow(**kw)(ev)
    strict = TripletFlow(**kw, min_lines=1, fit_min_lines=1)(ev)
    shared = TripletFlow(**kw, max_lineless_share=0.0)(ev)

    def rows(res):
        return {(w, r): i for i, (w, r) in enumerate(zip(res.window.tolist(), res.roi.tolist(),
                                                          strict=True))}

    d, s, m = rows(default), rows(strict), rows(shared)
    judged = {w for (w, r) in d if (w, r) not in s}  # windows with a line-less RoI window
    assert judged and judged != {w for w, _ in d}
    for (w, r), i in m.items():
        ref, j = (strict, s[(w, r)]) if w in judged else (default, d[(w, r)])
        assert torch.equal(shared.flow[i], ref.flow[j]) and shared.normal[i] == ref.normal[j]
    assert set(m) == {k for k in s if k[0] in judged} | {k for k in d if k[0] not in judged}


def test_streaming_equals_one_call(texture):
    ev, _ = texture
    cfg = FlowConfig(roi_size=24, window_us=3_000, chunk_size=1_500, max_events_per_roi=16,
                     max_hypotheses=12)
    whole = TripletFlow(cfg, return_event_flow=True)(ev)
    flow = TripletFlow(cfg, return_event_flow=True)
    cuts = [0, 1, 1, 900, 4_000, 4_001, 11_000, len(ev)]
    parts = [flow.update(ev[a:b]) for a, b in zip(cuts, cuts[1:], strict=False)]
    parts.append(flow.flush())
    joined = FlowResult.cat(parts)
    for name in ("xy", "t", "flow", "support", "cost", "normal", "roi", "window", "n_events"):
        torch.testing.assert_close(getattr(joined, name), getattr(whole, name), equal_nan=True)
    torch.testing.assert_close(joined.event_flow, whole.event_flow, equal_nan=True)
    assert whole.event_flow.shape == (len(ev), 2) and joined.event_start == 0


@pytest.mark.parametrize("with_events", [False, True])
def test_joining_results_skips_empty_parts(with_events):
    """``FlowResult.cat`` equals field-by-field concatenation, with the first part's event
    start, whichever parts are empty (a single non-empty part is returned as it is)."""
    g = torch.Generator().manual_seed(0)

    def part(rows: int, events: int, start: int) -> FlowResult:
        r = FlowResult.empty(event_start=start, with_events=with_events)
        kw = {name: torch.rand((rows, *getattr(r, name).shape[1:]), generator=g).to(
            getattr(r, name).dtype) for name in ("xy", "t", "flow", "support", "cost",
                                                  "normal", "normal_dir", "full_flow",
                                                  "n_events", "roi", "window")}
        flows = torch.rand(events, 2, generator=g) if with_events else None
        return FlowResult(**kw, event_start=start, event_flow=flows)

    layouts = [[(0, 0)], [(0, 0), (3, 2)], [(0, 0), (3, 2), (0, 0)], [(2, 0), (0, 4), (5, 1)],
               [(0, 0), (0, 0)], [(0, 3), (0, 0)]]
    for layout in layouts:
        start, parts = 7, []
        for rows, events in layout:
            events = events if with_events else 0
            parts.append(part(rows, events, start))
            start += events
        joined = FlowResult.cat(parts)
        assert joined.event_start == 7
        for name in ("xy", "t", "flow", "support", "cost", "normal", "normal_dir",
                     "full_flow", "n_events", "roi", "window"):
            assert torch.equal(getattr(joined, name),
                               torch.cat([getattr(p, name) for p in parts])), (layout, name)
        if with_events:
            assert torch.equal(joined.event_flow, torch.cat([p.event_flow for p in parts]))
        else:
            assert joined.event_flow is None
    with pytest.raises(ValueError, match="per-event"):
        FlowResult.cat([FlowResult.empty(), FlowResult.empty(with_events=True)])


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_long_open_windows_keep_memory_bounded_and_the_same_flow(texture, backend):
    """One window spans the whole stream, given in many small calls: its pending candidates
    are pruned to the events the registration's cap can use once they exceed 4 chunk sizes,
    and the flow equals that of one call."""
    ev, _ = texture
    cfg = FlowConfig(roi_size=24, window_us=1_000_000, chunk_size=300, max_events_per_roi=16,
                     max_hypotheses=12, backend=backend)
    whole = TripletFlow(cfg)(ev)
    flow = TripletFlow(cfg)
    parts, pending = [], []
    for a in range(0, len(ev), 250):
        parts.append(flow.update(ev[a:a + 250]))
        pending.append(flow._pending.gkey.numel())
    parts.append(flow.flush())
    cols, rows = flow.num_rois
    worst_event = len(search_offsets(cfg.radius)) * cfg.history ** 2  # candidates per event
    bound = 4 * cfg.chunk_size + cols * rows * cfg.max_events_per_roi * worst_event
    assert max(pending) <= bound
    assert min(pending[5:]) < max(pending)  # pruned on the way
    joined = FlowResult.cat(parts)
    assert len(whole) > 0
    for name in ("xy", "t", "flow", "support", "cost", "normal", "roi", "window", "n_events"):
        torch.testing.assert_close(getattr(joined, name), getattr(whole, name), equal_nan=True)


@pytest.mark.parametrize("backend", ["torch", "auto"])
@pytest.mark.parametrize("event_flow", [False, True])
def test_until_reports_windows_by_time_with_the_same_results(texture, backend, event_flow):
    ev, _ = texture
    cfg = FlowConfig(roi_size=24, window_us=3_000, max_events_per_roi=16, max_hypotheses=12,
                     backend=backend)
    whole = TripletFlow(cfg, return_event_flow=event_flow)(ev)
    flow = TripletFlow(cfg, return_event_flow=event_flow)
    # time batches: some end on a window boundary, some inside a window, one holds no event
    ends = [int(ev.t[0]) + d for d in (2_000, 6_000, 6_500, 7_000, 15_000, 21_000)]
    ends.append(int(ev.t[-1]) + 1)
    parts, start = [], 0
    for end in ends:
        stop = int(torch.searchsorted(ev.t, torch.tensor([end]))[0])
        part = flow.update(ev[start:stop], until_us=end)
        window_end = (part.window + 1) * cfg.window_us
        assert bool((window_end <= end).all())            # only windows that are over
        # every window that is over is reported now, not at a later call
        closed_now = part.window.unique().tolist()
        assert all(w * cfg.window_us < end for w in closed_now)
        parts.append(part)
        start = stop
    assert start == len(ev)
    parts.append(flow.flush())
    joined = FlowResult.cat(parts)
    assert len(joined) == len(whole) > 10
    for name in ("xy", "t", "flow", "support", "cost", "normal", "roi", "window", "n_events"):
        torch.testing.assert_close(getattr(joined, name), getattr(whole, name), equal_nan=True)
    if event_flow:
        torch.testing.assert_close(joined.event_flow, whole.event_flow, equal_nan=True)
    # windows over by the last promise were all reported before the flush
    last_done = ends[-1] // cfg.window_us
    assert not bool((parts[-1].window < last_done).any())


def test_until_is_a_promise_about_later_events(texture):
    ev, _ = texture
    flow = TripletFlow(FlowConfig(roi_size=24, window_us=3_000))
    t_mid = int(ev.t[len(ev) // 2])
    with pytest.raises(EventsError, match="until_us"):
        flow.update(ev[: len(ev) // 2 + 1], until_us=t_mid - 1)   # an event after the promise
    assert len(flow.update(ev)) > 0                               # nothing was taken in
    flow = TripletFlow(FlowConfig(roi_size=24, window_us=3_000))
    cut = int(torch.searchsorted(ev.t, torch.tensor([t_mid]))[0])
    flow.update(ev[:cut], until_us=t_mid + 500)
    with pytest.raises(EventsError, match="before"):
        flow.update(ev[cut:])                                     # starts before the promise


def test_hypothesis_selection_does_not_depend_on_the_chunking():
    """The hash keys of the capped hypotheses use a fixed bound on the candidate ordinals;
    one taken from each registration batch made this scene's flows depend on the chunking."""
    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    out = []
    for chunk in (5_000, 1_733):
        flow = TripletFlow(FlowConfig(sensor_size=(64, 48), roi_size=16, window_us=2_000,
                                      backend="torch"))
        parts = [flow.update(ev[i:i + chunk]) for i in range(0, len(ev), chunk)]
        out.append(FlowResult.cat([*parts, flow.flush()]))
    assert len(out[0]) > 100
    for name in ("flow", "cost", "support", "roi", "window"):
        torch.testing.assert_close(getattr(out[0], name), getattr(out[1], name), rtol=0, atol=0)


def test_event_flows_are_candidates_near_the_roi_flow(texture):
    ev, gt = texture
    res = TripletFlow(roi_size=32, window_us=5_000, return_event_flow=True)(ev)
    ef = res.event_flow
    has = ~torch.isnan(ef[:, 0])
    assert 0.05 < float(has.float().mean()) < 1.0  # skipped burst events have none
    err = _rel_error(ef[has], gt[0])
    assert float(err.median()) < 0.2


def test_chunk_size_does_not_change_the_result(texture):
    ev, _ = texture
    ev = ev[:8_000]
    a = TripletFlow(roi_size=32, window_us=4_000, chunk_size=100_000)(ev)
    b = TripletFlow(roi_size=32, window_us=4_000, chunk_size=333, block_size=50)(ev)
    torch.testing.assert_close(a.flow, b.flow, equal_nan=True)
    torch.testing.assert_close(a.support, b.support)


def test_search_ahead_in_a_thread_gives_the_same_bits(texture, monkeypatch):
    """With the compiled search and several pieces per update, the next piece is searched in a
    worker thread while this one is registered; every output equals the one-at-a-time run."""
    from evtrack.flow import numba_support

    if not numba_support.available():
        pytest.skip("numba is not installed: no compiled search")
    ev, _ = texture
    ev = ev[:12_000]
    cfg = {"roi_size": 32, "window_us": 2_000, "chunk_size": 1_000, "backend": "compiled",
           "return_event_flow": True}
    threads = []
    search_piece = TripletFlow._search_piece

    def recorded(self, piece):
        import threading

        threads.append(threading.current_thread().name)
        return search_piece(self, piece)

    monkeypatch.setattr(TripletFlow, "_search_piece", recorded)
    ahead = TripletFlow(**cfg)
    a = FlowResult.cat([ahead.update(ev[:7_000]), ahead.update(ev[7_000:], until_us=int(
        ev.t[-1]) + 1), ahead.flush()])
    assert sum(name.startswith("evtrack-flow") for name in threads) == 12
    monkeypatch.setattr(TripletFlow, "_searched", lambda self, pieces: (
        self._search_piece(p) for p in pieces))
    plain = TripletFlow(**cfg)
    b = FlowResult.cat([plain.update(ev[:7_000]), plain.update(ev[7_000:], until_us=int(
        ev.t[-1]) + 1), plain.flush()])
    assert len(a) >= 5
    for name in ("flow", "full_flow", "cost", "support", "normal", "roi", "window",
                 "event_flow"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(getattr(b, name).float(), 1e30)), name


def test_empty_and_single_event_inputs():
    flow = TripletFlow(sensor_size=SIZE)
    assert len(flow(Events.empty(SIZE))) == 0
    one = Events([3], [4], [10], [1], SIZE)
    assert len(flow(one)) == 0
    flow.reset()
    assert len(flow.update(Events.empty(SIZE))) == 0
    assert len(flow.update(one)) == 0
    assert len(flow.flush()) == 0
    res = TripletFlow(sensor_size=SIZE, return_event_flow=True)(one)
    assert res.event_flow.shape == (1, 2) and bool(torch.isnan(res.event_flow).all())


def test_bad_inputs_raise_events_error():
    flow = TripletFlow()
    with pytest.raises(EventsError, match="sensor size is unknown"):
        flow(Events([1], [1], [0], [1]))
    with pytest.raises(EventsError, match="backwards"):
        flow(Events([1, 2], [1, 1], [10, 5], [1, 1], SIZE))
    with pytest.raises(EventsError, match="outside the sensor"):
        flow(Events([1, 64], [1, 1], [1, 2], [1, 1], SIZE))
    with pytest.raises(EventsError, match="polarity"):
        flow(Events([1, 2], [1, 1], [1, 2], [1, 0], SIZE))
    stream = TripletFlow(sensor_size=SIZE)
    stream.update(Events([1], [1], [100], [1], SIZE))
    with pytest.raises(EventsError, match="before the last event"):
        stream.update(Events([1], [1], [99], [1], SIZE))
    with pytest.raises(EventsError, match="sensor size"):
        stream.update(Events([1], [1], [200], [1], (32, 32)))


def test_burst_of_100x_rate_is_processed_in_bounded_chunks(texture, monkeypatch):
    ev, _ = texture
    burst = Events(ev.x, ev.y, ev.t // 100, ev.p, ev.sensor_size)
    # the same scene 100x faster: speeds and time constants scaled accordingly
    flow = TripletFlow(roi_size=32, window_us=100, chunk_size=2_000, refractory_us=20,
                       tolerance_us=1, max_speed=1e6, min_speed=1000.0)
    seen = []
    original = TripletFlow._search_piece

    def spy(self, chunk):
        seen.append(len(chunk[0]))  # (events, search mask)
        return original(self, chunk)

    monkeypatch.setattr(TripletFlow, "_search_piece", spy)
    res = flow(burst)
    assert max(seen) <= 2_000 and sum(seen) == len(ev)
    assert len(res) > 0


def test_config_loading_and_errors(tmp_path):
    path = tmp_path / "flow.yaml"
    path.write_text("flow:\n  radius: 2\n  window_us: 1000\n  tolerance_rel: 0.2\n")
    cfg = FlowConfig.from_yaml(path)
    assert (cfg.radius, cfg.window_us, cfg.tolerance_permille) == (2, 1000, 200)
    assert FlowConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="unknown field"):
        FlowConfig.from_dict({"radios": 2})
    with pytest.raises(ConfigError, match="'history'"):
        FlowConfig.from_dict({"history": 0})
    with pytest.raises(ConfigError, match="flow config: window_us: expected an integer"):
        FlowConfig.from_dict({"window_us": 1.5})
    with pytest.raises(ConfigError, match="'max_speed'"):
        FlowConfig(min_speed=100.0, max_speed=50.0)
    with pytest.raises(ConfigError, match="'max_span_us'"):
        FlowConfig.from_dict({"max_span_us": -5})
    with pytest.raises(ConfigError, match="'lookup'.*'sortd'"):
        FlowConfig.from_dict({"lookup": "sortd"})
    assert FlowConfig().resolved_lookup("cuda") == "sorted"
    assert FlowConfig().resolved_lookup("cpu") == "passes"
    assert FlowConfig(lookup="sorted").resolved_lookup("cpu") == "sorted"
    bad = tmp_path / "bad.yaml"
    bad.write_text("- not a mapping\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        FlowConfig.from_yaml(bad)


def test_saving_results(tmp_path, texture):
    ev, _ = texture
    res = TripletFlow(roi_size=32, window_us=5_000)(ev[:6_000])
    for name in ("f.csv", "f.npz", "f.h5"):
        res.save(tmp_path / name)
        assert (tmp_path / name).stat().st_size > 0
    lines = (tmp_path / "f.csv").read_text().splitlines()
    assert lines[0].startswith("t_us,window,roi,x,y,flow_x,flow_y") and len(lines) == len(res) + 1
    with pytest.raises(ValueError, match="unknown flow output format"):
        res.save(tmp_path / "f.txt")
    assert not list(tmp_path.glob(".f.txt*"))  # nothing half-written left behind


def test_concatenated_events_match_separate_updates(texture):
    ev, _ = texture
    a, b = ev[:5_000], ev[5_000:9_000]
    one = TripletFlow(roi_size=32, window_us=5_000)(concatenate([a, b]))
    flow = TripletFlow(roi_size=32, window_us=5_000)
    two = FlowResult.cat([flow.update(a), flow.update(b), flow.flush()])
    torch.testing.assert_close(one.flow, two.flow, equal_nan=True)


def test_shipped_config_file_holds_the_defaults():
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "configs" / "flow.yaml"
    assert FlowConfig.from_yaml(path) == FlowConfig()


def test_flow_on_the_test_device(device, texture):
    ev, gt = texture
    res = TripletFlow(roi_size=32, window_us=5_000, device=str(device))(ev[:20_000].to(device))
    assert res.flow.device.type == device.type
    full = ~res.normal
    assert float(_rel_error(res.flow[full].cpu(), gt[0]).median()) < 0.1


def test_roi_centres_are_cached_but_never_shared():
    flow = TripletFlow(sensor_size=(40, 30), roi_size=16)
    first = flow.roi_centres()
    assert first.shape == (3 * 2, 2) and first[-1].tolist() == [(32 + 39) / 2, (16 + 29) / 2]
    first += 1000.0  # the caller's copy: the flow's own centres are unchanged
    assert torch.equal(flow.roi_centres(), first - 1000.0)
    flow.config = flow.config.replace(roi_size=8)  # a changed grid is computed again
    assert flow.roi_centres().shape == (5 * 4, 2)
