"""Searching a sample of the events (``search=``) and the per-RoI-window hash sample
(:func:`evtrack.flow.sampled_search`): the history stays whole, both backends match the
sequential reference, and dense windows register the same flow as unsampled."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from flow_helpers import random_stream, reference_rows
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evtrack.flow import (
    CandidateSearch,
    FlowConfig,
    FlowResult,
    TripletFlow,
    numba_support,
    sampled_search,
)
from evtrack.flow.compiled import CompiledSearch
from evtrack.flow.hashing import hash32
from evtrack.flow.scenes import translating_texture

FIELDS = ("event", "offset", "age_j", "age_i", "seq_j", "seq_i", "dt_us")


def _rows(cands):
    return list(zip(*(getattr(cands, f).tolist() for f in FIELDS), strict=True))


def _search_in_pieces(search_obj, x, y, t, p, mask, cuts):
    bounds = [0, *sorted(set(cuts)), len(t)]
    rows = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b > a:
            rows += _rows(search_obj(x[a:b], y[a:b], t[a:b], p[a:b], mask[a:b]))
    return rows


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(0, 300), radius=st.integers(1, 3),
       history=st.integers(1, 3), refractory=st.sampled_from([0, 40]),
       max_gap=st.sampled_from([3, 60]), keep=st.sampled_from([0.0, 0.3, 0.8]),
       cuts=st.lists(st.integers(0, 300), max_size=3), strips=st.sampled_from([1, 2, 3]))
def test_searching_a_sample_equals_the_reference_on_both_backends(
        seed, n, radius, history, refractory, max_gap, keep, cuts, strips):
    """Unsearched events still enter the history: the candidates of the searched events are
    exactly those of the full search (the reference says so too), on the compiled and the
    torch search, in any chunking and any number of strips."""
    rng = np.random.default_rng(seed)
    size = (9, 7)
    x, y, t, p = random_stream(rng, n, size, max_gap)
    mask = torch.as_tensor(rng.random(n) < keep)
    cfg = FlowConfig(sensor_size=size, radius=radius, history=history, refractory_us=refractory,
                     tolerance_us=5, tolerance_rel=0.2, min_speed=100.0, max_speed=1e6)
    full = [r[:7] for r in reference_rows(x, y, t, p, cfg)]
    sampled = [r[:7] for r in reference_rows(x, y, t, p, cfg, mask)]
    # the reference's own sample: the full search's rows of the searched events
    assert sampled == [r for r in full if bool(mask[r[0]])]
    cuts = [c for c in cuts if c <= n]
    if numba_support.available():
        assert _search_in_pieces(CompiledSearch(cfg, strips=strips),
                                 x, y, t, p, mask, cuts) == sampled
    assert _search_in_pieces(CandidateSearch(cfg), x, y, t, p, mask, cuts) == sampled


def test_sampled_search_keeps_sparse_windows_and_samples_dense_ones():
    """Windows of at most ``per_window`` events are searched whole; a dense one keeps about
    ``per_window`` events, exactly those whose hash lies below ``per_window / count`` of the
    hash range, whatever the first stream index."""
    rng = np.random.default_rng(3)
    # RoI 0 (x, y < 16) of window 0: 40 events; RoI 1 (x in 16..31): 2000 events
    x = np.concatenate([rng.integers(0, 16, 40), rng.integers(16, 32, 2000)])
    y = rng.integers(0, 16, x.size)
    order = rng.permutation(x.size)
    x, y = torch.as_tensor(x[order]), torch.as_tensor(y[order])
    t = torch.sort(torch.as_tensor(rng.integers(0, 1000, x.numel()))).values
    for first in (0, 123_457):
        keep = sampled_search(x, y, t, first, roi_size=16, window_us=1000, sensor_width=64,
                              per_window=100)
        sparse = x < 16
        assert bool(keep[sparse].all())
        dense_kept = int(keep[~sparse].sum())
        assert 70 <= dense_kept <= 130, dense_kept  # binomial(2000, 0.05): sd ~9.7
        seq = torch.arange(first, first + x.numel())
        expected = hash32(seq[~sparse]) * 2000 < 100 * (1 << 32)
        assert torch.equal(keep[~sparse], expected)


def test_sampled_search_counts_each_window_and_roi_on_its_own():
    """The same pixels in the next window, and a dense RoI beside a sparse one, are counted
    apart."""
    x = torch.tensor([1] * 500 + [40] * 5 + [1] * 5)
    y = torch.zeros(510, dtype=torch.int64)
    t = torch.tensor([10] * 500 + [20] * 5 + [1500] * 5)
    keep = sampled_search(x, y, t, 0, roi_size=32, window_us=1000, sensor_width=64,
                          per_window=50)
    assert keep[500:].all() and 20 < int(keep[:500].sum()) < 90


def test_sampled_search_bad_and_empty_input():
    empty = torch.zeros(0, dtype=torch.int64)
    assert sampled_search(empty, empty, empty, 0, roi_size=8, window_us=100, sensor_width=32,
                          per_window=4).shape == (0,)
    one = torch.zeros(1, dtype=torch.int64)
    for bad in ({"per_window": -1}, {"per_window": 4, "budget": -1},
                {"per_window": 4, "cell_rois": 0}):
        with pytest.raises(ValueError, match="per_window and budget"):
            sampled_search(one, one, one, 0, roi_size=8, window_us=100, sensor_width=32,
                           **bad)
    outside = torch.tensor([3, 32])
    with pytest.raises(ValueError, match=r"\[0, 32\)"):
        sampled_search(outside, outside * 0, outside * 0, 0, roi_size=8, window_us=100,
                       sensor_width=32, per_window=4)
    with pytest.raises(ValueError, match="non-negative"):
        sampled_search(outside * 0, -outside, outside * 0, 0, roi_size=8, window_us=100,
                       sensor_width=32, per_window=4)


@pytest.fixture(scope="module")
def dense_texture():
    events, _ = translating_texture((96, 72), velocity=(900.0, -400.0), duration_us=20_000,
                                    seed=5)
    return events


def _whole_and_fresh_flow(ev, backend: str, roi_size: int):
    """The flow config of the dense-texture tests on ``backend`` (skips without numba for
    "compiled"), the whole search's result on ``ev``, and a fresh flow to feed in calls."""
    if backend == "compiled":
        if not numba_support.available():
            pytest.skip("numba is not installed")
    cfg = FlowConfig(roi_size=roi_size, window_us=2000, max_events_per_roi=16,
                     max_hypotheses=16, min_support=2, backend=backend)
    return cfg, TripletFlow(cfg)(ev), TripletFlow(cfg)


@pytest.mark.parametrize("backend", ["torch", "compiled"])
def test_dense_windows_register_the_same_flow_when_sampled(dense_texture, backend):
    """With ``search`` from :func:`sampled_search`, every window whose sampled support still
    reaches ``max_events_per_roi`` reports the same flow, cost and inliers as the full
    search (the data term takes the smallest hashes, which are all searched); the sample
    searches well under half of the events; sparser windows keep at most their support (and
    may pass or fail the consensus test differently: their data term differs)."""
    ev = dense_texture
    cfg, full, flow = _whole_and_fresh_flow(ev, backend, roi_size=24)
    step = 4000  # calls end on window boundaries, as the tracker's groups do
    parts = []
    for t0 in range(0, int(ev.t_end) + 1, step):
        sel = (ev.t >= t0) & (ev.t < t0 + step)
        piece = ev[sel]
        search = sampled_search(piece.x, piece.y, piece.t, flow.events_seen, roi_size=24,
                                window_us=2000, sensor_width=96, per_window=300)
        assert search.numel() == len(piece)
        parts.append(flow.update(piece, until_us=t0 + step, search=search))
        if t0 == 0:
            searched_share = float(search.float().mean())
    parts.append(flow.flush())
    sampled = FlowResult.cat(parts)
    assert searched_share < 0.5
    key_full = {(w, r): i for i, (w, r) in enumerate(zip(full.window.tolist(),
                                                         full.roi.tolist(), strict=True))}
    same = 0
    for j, (w, r) in enumerate(zip(sampled.window.tolist(), sampled.roi.tolist(),
                                       strict=True)):
        i = key_full.get((w, r))
        if i is not None:
            assert int(sampled.support[j]) <= int(full.support[i])
        if int(sampled.support[j]) >= cfg.max_events_per_roi:
            assert i is not None  # the same data term passes the same consensus test
            assert torch.equal(sampled.flow[j], full.flow[i])
            assert sampled.cost[j] == full.cost[i]
            same += 1
    print(f"searched {searched_share:.0%}; {same} of {len(full)} windows the same")
    assert same >= 0.5 * len(full), (same, len(full))


def test_update_refuses_a_search_mask_of_the_wrong_shape(dense_texture):
    ev = dense_texture[:100]
    with pytest.raises(ValueError, match="search"):
        TripletFlow(roi_size=16).update(ev, search=torch.ones(99, dtype=torch.bool))
    flow = TripletFlow(roi_size=16)
    with pytest.raises(ValueError, match="search"):
        flow.update(ev, search=torch.ones(100, dtype=torch.int64))
    # refused before anything changed: the same events are then taken
    assert flow.events_seen == 0
    flow.update(ev, search=torch.ones(100, dtype=torch.bool))
    assert flow.events_seen == 100


def test_compiled_and_tensor_samples_agree(monkeypatch):
    """The compiled CPU pass and the tensor form give the same sample (int16 coordinates, as
    :class:`~evtrack.events.Events` holds them; windows and RoIs of every density)."""
    from evtrack.flow import sampling

    if not sampling.jit_available():
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(8)
    n = 20_000
    x = torch.as_tensor(rng.integers(0, 200, n), dtype=torch.int16)
    y = torch.as_tensor(np.minimum(rng.exponential(30, n), 149).astype(np.int16))
    t = torch.sort(torch.as_tensor(rng.integers(5_000, 12_000, n))).values
    for per_window in (1, 10, 300):
        args = dict(roi_size=16, window_us=1000, per_window=per_window)
        fast = sampled_search(x, y, t, 987_654, sensor_width=200, **args)
        slow = sampling._sample_torch(x, y, t, 987_654, args["roi_size"], args["window_us"],
                                      13, per_window)
        assert fast.dtype == torch.bool and torch.equal(fast, slow)
        assert 0 < int(fast.sum()) < n or per_window == 300
    monkeypatch.setattr(sampling, "jit_available", lambda: False)  # the tensor form throughout
    for per_window, budget, cell_rois in ((0, 5000, 2), (10, 1000, 1), (300, 20, 3),
                                          (0, n, 2), (10, 1, 2)):
        args = dict(roi_size=16, window_us=1000, sensor_width=200, per_window=per_window,
                    budget=budget, cell_rois=cell_rois)
        slow = sampled_search(x, y, t, 987_654, **args)
        monkeypatch.setattr(sampling, "jit_available", lambda: True)
        fast = sampled_search(x, y, t, 987_654, **args)
        monkeypatch.setattr(sampling, "jit_available", lambda: False)
        assert torch.equal(fast, slow), args
        assert int(fast.sum()) <= budget


def _cell_order(n_cells: int) -> list[int]:
    """The budget's cell order, independently: by the hash of the cell index, then the
    index."""
    return sorted(range(n_cells), key=lambda c: (int(hash32(torch.tensor(c))), c))


@pytest.mark.parametrize("per_window", [0, 8])
@pytest.mark.parametrize("budget", [1, 150, 900, 5000])
def test_budget_takes_whole_cells_in_the_hash_order(per_window, budget):
    """With ``budget``, the searched events are those of the per-window sample in the cells
    that a first fit over the fixed cell order takes: whole cells, at most ``budget`` events,
    and every left-out cell holding sampled events would not have fitted when visited."""
    rng = np.random.default_rng(budget)
    n, width, height, roi, cell_rois = 4000, 80, 60, 8, 2
    x = torch.as_tensor(rng.integers(0, width, n))
    y = torch.as_tensor(np.minimum(rng.exponential(20, n), height - 1).astype(np.int64))
    t = torch.sort(torch.as_tensor(rng.integers(0, 3000, n))).values
    args = dict(roi_size=roi, window_us=1000, sensor_width=width, per_window=per_window)
    sample = (sampled_search(x, y, t, 77, **args) if per_window
              else torch.ones(n, dtype=torch.bool))
    keep = sampled_search(x, y, t, 77, budget=budget, cell_rois=cell_rois, **args)
    side = roi * cell_rois
    cols = -(-width // side)
    cell = (y // side * cols + x // side).tolist()
    per_cell = np.bincount(np.asarray(cell)[sample.numpy()], minlength=cols * 4)
    taken, used = set(), 0
    for c in _cell_order(cols * (max(cell) // cols + 1)):
        if int(sample.sum()) <= budget or (per_cell[c] and used + per_cell[c] <= budget):
            taken.add(c)
            used += int(per_cell[c])
    assert int(keep.sum()) <= budget
    expected = [bool(sample[i]) and c in taken for i, c in enumerate(cell)]
    assert keep.tolist() == expected
    if budget >= int(sample.sum()):
        assert torch.equal(keep, sample)
    else:
        assert 0 <= int(keep.sum()) < int(sample.sum())


@pytest.mark.parametrize("backend", ["torch", "compiled"])
def test_budget_keeps_the_flow_of_the_rois_of_taken_cells(dense_texture, backend):
    """All events enter the history, so a RoI whose cell the budget takes registers exactly
    the flow of the whole search (its events are all searched, and their triplets are the
    whole stream's), and a RoI of a left-out cell registers none: the budget trades RoIs, not
    their accuracy."""
    ev = dense_texture
    cfg, full, flow = _whole_and_fresh_flow(ev, backend, roi_size=12)
    step = 4000
    parts, budget, shares = [], 8000, []  # ~24k events per call, ~2k per cell
    for t0 in range(0, int(ev.t_end) + 1, step):
        piece = ev[(ev.t >= t0) & (ev.t < t0 + step)]
        search = sampled_search(piece.x, piece.y, piece.t, flow.events_seen, roi_size=12,
                                window_us=2000, sensor_width=96, per_window=0, budget=budget,
                                cell_rois=2)
        assert int(search.sum()) <= budget
        shares.append(float(search.float().mean()) if len(piece) else 1.0)
        parts.append(flow.update(piece, until_us=t0 + step, search=search))
    parts.append(flow.flush())
    cut = FlowResult.cat(parts)
    assert max(shares) < 0.6  # the budget did cut
    key_full = {(w, r): i for i, (w, r) in enumerate(zip(full.window.tolist(),
                                                         full.roi.tolist(), strict=True))}
    assert 0 < len(cut) < len(full)
    for j, (w, r) in enumerate(zip(cut.window.tolist(), cut.roi.tolist(), strict=True)):
        i = key_full[(w, r)]
        assert torch.equal(cut.flow[j], full.flow[i])
        assert cut.cost[j] == full.cost[i] and cut.support[j] == full.support[i]


@pytest.mark.parametrize("jit", [True, False])
def test_budget_edges(monkeypatch, jit):
    """A cell whose events fill the budget exactly is taken; one event more and it is not,
    but a later cell of the order that fits still is (first fit)."""
    from evtrack.flow import sampling

    if jit and not sampling.jit_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(sampling, "jit_available", lambda: jit)
    order = _cell_order(4)  # a 32 x 32 sensor of 16 px cells (8 px RoIs, 2 x 2)
    first, second = order[0], order[1]

    def events_in(cells_counts):
        xs, ys = [], []
        for c, k in cells_counts:
            xs += [(c % 2) * 16 + 3] * k
            ys += [(c // 2) * 16 + 5] * k
        x, y = torch.tensor(xs), torch.tensor(ys)
        return x, y, torch.arange(len(xs), dtype=torch.int64)

    args = dict(roi_size=8, window_us=10_000, sensor_width=32, per_window=0, cell_rois=2)
    x, y, t = events_in([(second, 6), (first, 10)])
    first_events = torch.tensor([False] * 6 + [True] * 10)
    keep = sampled_search(x, y, t, 0, budget=10, **args)  # the first exactly, not the second
    assert torch.equal(keep, first_events)
    keep = sampled_search(x, y, t, 0, budget=9, **args)  # not the first: the second fits
    assert torch.equal(keep, ~first_events)
    assert int(sampled_search(x, y, t, 0, budget=16, **args).sum()) == 16
    assert int(sampled_search(x, y, t, 0, budget=5, **args).sum()) == 0
