"""The compiled CPU backend of the flow (numba) against the sequential reference, the torch
backend, and exact arithmetic."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from flow_helpers import random_stream, reference_rows
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evtrack.errors import ConfigError, EvtrackError
from evtrack.flow import FlowConfig, FlowResult, TripletFlow, compiled, numba_support
from evtrack.flow import arrange_kernels as ak
from evtrack.flow import solve_kernels as sk
from evtrack.flow.backends import resolve
from evtrack.flow.constants import COST_SCALE
from evtrack.flow.registration import register_groups
from evtrack.flow.registration_compiled import CompiledRegistration
from evtrack.flow.registration_tensor import rounded_distance
from evtrack.flow.scenes import translating_texture

if not numba_support.available():
    pytest.skip("numba is not installed: the compiled backend cannot run", allow_module_level=True)

FIELDS = ("event", "offset", "age_j", "age_i", "seq_j", "seq_i", "dt_us")


def _search_in_chunks(cfg, x, y, t, p, cuts, strips=None, tight=False):
    search = compiled.CompiledSearch(cfg, strips=strips)
    if tight:  # outputs of one event's worst case: the loops stop and resume many times
        search.rows_per_event = 0
        search.min_rows = 0
    parts = []
    bounds = [0, *sorted(set(cuts)), len(t)]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b > a:
            parts.append(search(x[a:b], y[a:b], t[a:b], p[a:b]))
    assert search.next_seq == len(t)
    rows, flows = [], []
    for c in parts:
        rows += list(zip(*(getattr(c, f).tolist() for f in FIELDS), strict=True))
        flows.append(c.flow)
    return rows, torch.cat(flows) if flows else torch.zeros(0, 2)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(0, 300), radius=st.integers(1, 3),
       history=st.integers(1, 3), refractory=st.sampled_from([0, 40, 400]),
       max_gap=st.sampled_from([0, 3, 60]), span=st.sampled_from([0, 300, 2000]),
       cuts=st.lists(st.integers(0, 300), max_size=4), strips=st.sampled_from([1, 2, 3, 7]),
       tight=st.booleans())
def test_random_streams_equal_the_reference(seed, n, radius, history, refractory, max_gap,
                                            span, cuts, strips, tight):
    size = (9, 7)
    x, y, t, p = random_stream(np.random.default_rng(seed), n, size, max_gap)
    cfg = FlowConfig(sensor_size=size, radius=radius, history=history, refractory_us=refractory,
                     tolerance_us=5, tolerance_rel=0.2, min_speed=100.0, max_speed=1e6,
                     max_span_us=span)
    rows, flow = _search_in_chunks(cfg, x, y, t, p, [c for c in cuts if c <= n], strips, tight)
    ref = reference_rows(x, y, t, p, cfg)
    assert rows == [r[:7] for r in ref]
    if ref:
        torch.testing.assert_close(flow.double(), torch.tensor([r[7:] for r in ref],
                                                               dtype=torch.float64),
                                   rtol=1e-6, atol=1e-3)


def test_textured_scene_equals_the_reference_and_the_torch_search():
    ev, _ = translating_texture((40, 30), velocity=(900.0, -400.0), duration_us=12_000, seed=3)
    ev = ev[:3000]
    cfg = FlowConfig(sensor_size=(40, 30))
    rows, flow = _search_in_chunks(cfg, ev.x, ev.y, ev.t, ev.p, [1, 700, 701, 2000])
    ref = reference_rows(ev.x, ev.y, ev.t, ev.p, cfg)
    assert len(ref) > 100 and rows == [r[:7] for r in ref]
    from evtrack.flow.candidates import CandidateSearch

    tensor_search = CandidateSearch(cfg.replace(backend="torch"))(ev.x, ev.y, ev.t, ev.p)
    assert torch.equal(tensor_search.flow, flow)  # same float32 flows, bit for bit


@pytest.mark.parametrize("strips", [1, 2])
@pytest.mark.parametrize("cuts", [list(range(150, 2100, 150)), []])
def test_long_streams_move_the_time_base_without_changing_the_result(strips, cuts):
    """The compiled state holds int32 times relative to a base: crossing its limit
    (2^29 µs), a jump longer than the history keeps, and one call spanning more than
    ``MAX_SPAN_US`` (searched in pieces) keep the candidates of the sequential reference,
    with the refractory period at work across the moves."""
    from evtrack.flow.constants import MAX_SPAN_US, T_LIMIT

    ev, _ = translating_texture((40, 30), velocity=(900.0, -400.0), duration_us=12_000, seed=3)
    ev = ev[:2100]
    t = ev.t.clone()
    # the second part crosses the base's limit at event k ~ 1050, amid a dense stretch
    k = 1050 + int(torch.nonzero(t[1050:] > t[1049:-1])[0])
    t[700:] += T_LIMIT + int(t[0]) - int(t[k])
    assert t[k - 1] - t[0] < T_LIMIT <= t[k] - t[0]
    t[1400:] += 1 << 30            # the third jumps by more than the history keeps
    t[1750:] += MAX_SPAN_US // 2   # and one call may span several MAX_SPAN_US
    t[1900:] += MAX_SPAN_US
    cfg = FlowConfig(sensor_size=(40, 30), refractory_us=40)
    rows, flow = _search_in_chunks(cfg, ev.x, ev.y, t, ev.p, cuts, strips)
    ref = reference_rows(ev.x, ev.y, t, ev.p, cfg)
    assert any(r[0] >= 1400 for r in ref) and any(700 <= r[0] < 1400 for r in ref)
    assert rows == [r[:7] for r in ref]


def test_compiled_search_refuses_events_before_its_time_base():
    search = compiled.CompiledSearch(FlowConfig(sensor_size=(8, 8)))
    one = torch.tensor([3])
    search(one, one, torch.tensor([1_000]), torch.tensor([1]))
    with pytest.raises(ValueError, match="stream order"):
        search(one, one, torch.tensor([999]), torch.tensor([1]))


@pytest.mark.parametrize("strips", [2, 5])
@pytest.mark.parametrize("tight", [False, True])
def test_strips_equal_the_reference_on_a_textured_scene(strips, tight):
    """Horizontal strips searched in parallel, each with private copies of the rows around it,
    merged back into stream order: the candidates of the sequential loop, bit for bit (also
    when the outputs overflow and the strips resume in larger ones)."""
    ev, _ = translating_texture((40, 30), velocity=(900.0, -400.0), duration_us=12_000, seed=3)
    ev = ev[:3000]
    cfg = FlowConfig(sensor_size=(40, 30), history=3)
    cuts = [1, 700, 701, 2000]
    rows, flow = _search_in_chunks(cfg, ev.x, ev.y, ev.t, ev.p, cuts, strips, tight)
    ref = reference_rows(ev.x, ev.y, ev.t, ev.p, cfg)
    assert len(ref) > 100 and rows == [r[:7] for r in ref]
    _, whole = _search_in_chunks(cfg, ev.x, ev.y, ev.t, ev.p, cuts, 1)
    assert torch.equal(flow, whole)


@pytest.mark.parametrize("strips", [2, 3])
def test_strips_on_a_narrow_sweep_equal_the_reference(strips):
    """A vertical edge sweeps right and each batch holds a column or two of it: its triplets
    reach back to columns no event of the batch lies on, in the rows copied around the strip
    cuts (only the batch's columns and their search reach are copied)."""
    rng = np.random.default_rng(8)
    w, h = 40, 30
    xs, ys, ts = [], [], []
    for col in range(w):  # the edge reaches column col at 500 µs per column, +- 20 µs
        for row in range(h):
            xs.append(col)
            ys.append(row)
            ts.append(500 * col + int(rng.integers(-20, 21)))
    order = np.argsort(ts, kind="stable")
    x, y, t = (torch.as_tensor(np.asarray(v)[order]) for v in (xs, ys, ts))
    p = torch.ones_like(t)
    cfg = FlowConfig(sensor_size=(w, h), history=2)
    cuts = list(range(25, len(t), 25))  # about one column per batch
    rows, _ = _search_in_chunks(cfg, x, y, t, p, cuts, strips)
    ref = reference_rows(x, y, t, p, cfg)
    assert len(ref) > 1000 and rows == [r[:7] for r in ref]


def test_strips_are_chosen_by_thread_count_and_balanced():
    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    cfg = FlowConfig(sensor_size=(64, 48))
    search = compiled.CompiledSearch(cfg)
    y = ev.y.numpy().astype(np.int64)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        search.parallel_min_events = len(y) + 1
        lo, hi, own = search._strip_rows(y)
        assert (lo.tolist(), hi.tolist(), own.tolist()) == ([0], [48], [len(y)])  # small: one
        search.parallel_min_events = 1
        lo, hi, own = search._strip_rows(y)
    finally:
        torch.set_num_threads(threads)
    expected = min(3, numba_support.numba.config.NUMBA_NUM_THREADS)  # numba's pool caps it
    assert len(lo) == expected and lo[0] == 0 and hi[-1] == 48 and (lo[1:] == hi[:-1]).all()
    assert own.sum() == len(y) and own.tolist() == [int(((y >= a) & (y < b)).sum())
                                                    for a, b in zip(lo, hi, strict=True)]
    assert own.min() > 0.75 * len(y) / expected  # about equal shares
    # more strips asked than rows: at most one per row, still a partition
    lo, hi, own = compiled.CompiledSearch(cfg.replace(sensor_size=(64, 2)), strips=5)._strip_rows(
        np.array([0, 1, 1, 1], np.int64))
    assert lo.tolist() == [0, 1] and hi.tolist() == [1, 2] and own.tolist() == [1, 3]
    with pytest.raises(ValueError, match="strips"):
        compiled.CompiledSearch(cfg, strips=0)


def _numpy_strip_cuts(y, height, count):
    """The strips' cuts in plain NumPy (bincount, cumsum, searchsorted)."""
    n = y.shape[0]
    cum = np.cumsum(np.bincount(y, minlength=height))
    target = np.arange(1, count) * (n / count)
    row = np.searchsorted(cum, target)
    below = np.where(row > 0, cum[np.maximum(row - 1, 0)], 0)
    cuts = np.where(target - below < cum[row] - target, row, row + 1)
    ends = np.unique(np.clip(np.append(cuts, height), 1, height))
    own = np.diff(np.concatenate([[0], cum[ends - 1]]))
    return np.concatenate([[0], ends[:-1]]), ends, own


def test_compiled_strip_cuts_equal_numpy():
    """The compiled cuts equal the NumPy formula: spread, clustered and one-row events, more
    strips than rows, empty rows at either end."""
    rng = np.random.default_rng(3)
    for trial in range(200):
        height = int(rng.integers(1, 40))
        n = int(rng.integers(1, 300))
        kind = trial % 3
        y = (rng.integers(0, height, n) if kind == 0 else
             np.clip(rng.normal(height / 2, 2, n).round(), 0, height - 1) if kind == 1 else
             np.full(n, rng.integers(0, height)))
        y = np.sort(y.astype(np.int64)) if trial % 2 else y.astype(np.int64)
        count = int(rng.integers(2, 9))
        from evtrack.flow.search_kernels import strip_cuts

        got = strip_cuts(y, height, count)
        for a, b in zip(got, _numpy_strip_cuts(y, height, count), strict=True):
            assert a.tolist() == b.tolist(), (trial, height, count)


def test_automatic_strips_give_the_flow_of_one_strip():
    """``TripletFlow`` on the compiled backend splits large batches into strips on its own:
    the same flow as the sequential search."""
    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    cfg = FlowConfig(sensor_size=(64, 48), roi_size=16, window_us=2_000, backend="compiled")
    out = []
    for min_events in (1, 10**9):
        flow = TripletFlow(cfg)
        flow._search.parallel_min_events = min_events
        threads = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            out.append(flow(ev))
        finally:
            torch.set_num_threads(threads)
    a, b = out
    assert len(a) > 20
    for name in ("flow", "full_flow", "cost", "support", "roi", "window"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(getattr(b, name).float(), 1e30)), name


SMALL_WINDOWS = {"roi_size": 12, "window_us": 1_000, "min_support": 2, "history": 1,
                 "max_span_us": 40_000, "tolerance_rel": 0.05}  # some have no line


@pytest.mark.parametrize("options", [
    {"roi_size": 16, "window_us": 2_000}, {**SMALL_WINDOWS, "min_lines": 1, "fit_min_lines": 1},
    {**SMALL_WINDOWS, "max_lineless_share": 0.1}], ids=["default", "line-rules", "lineless-share"])
def test_both_backends_give_the_same_flow_bit_for_bit(options):
    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    out = {}
    for backend, chunk in (("torch", 5_000), ("compiled", 1_733)):
        flow = TripletFlow(FlowConfig(sensor_size=(64, 48), backend=backend, **options),
                           return_event_flow=True)
        parts = [flow.update(ev[i:i + chunk]) for i in range(0, len(ev), chunk)]
        out[backend] = FlowResult.cat([*parts, flow.flush()])
    a, b = out["torch"], out["compiled"]
    assert len(a) > 20
    for name in ("flow", "full_flow", "cost", "support", "normal", "roi", "window",
                 "event_flow"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(getattr(b, name).float(), 1e30)), name


def _random_registration_input(seed: int):
    """Candidates of events in groups, with what makes registration hard: groups over both
    caps, repeated flows (ties in every arg-min), collinear candidates (one constraint line:
    aperture), a zero flow, and events with one candidate."""
    rng = np.random.default_rng(seed)
    n_groups = 40
    group, seq, ordinal, flow = [], [], [], []
    ev = 0
    for _ in range(int(rng.integers(200, 900))):
        g = int(rng.integers(0, n_groups)) if rng.random() < 0.8 else 3  # group 3: crowded
        base = rng.normal(0, 400, 2) if g % 4 else np.array([300.0, -120.0])
        kind = rng.random()
        k = int(rng.integers(1, 7))
        if kind < 0.3:    # candidates on one line through base: s d / (n . d)
            normal = np.array([np.cos(g), np.sin(g)])
            dirs = rng.normal(0, 1, (k, 2))
            dirs = dirs[(dirs @ normal) > 0.3] if len(dirs) else dirs
            cands = [float(normal @ base) * d / float(normal @ d) for d in dirs]
        elif kind < 0.4:  # exact repeats (ties)
            cands = [np.round(base / 50.0) * 50.0] * k
        elif kind < 0.45:
            cands = [np.zeros(2)]
        else:
            cands = list(base + rng.normal(0, 60, (k, 2)))
        for o, c in enumerate(cands):
            group.append(g)
            seq.append(ev)
            ordinal.append(int(rng.integers(0, 50)) * 8 + o)
            flow.append(c)
        ev += 1
    for g in range(n_groups, n_groups + 8):  # two events, one candidate each: a cost tie
        a = rng.normal(0, 300, 2)
        for o, c in enumerate((a, -a)):
            group.append(g)
            seq.append(ev)
            ordinal.append(o)
            flow.append(c)
            ev += 1
    return (torch.tensor(group), torch.tensor(seq), torch.tensor(ordinal),
            torch.tensor(np.array(flow), dtype=torch.float32), n_groups + 8)


@pytest.mark.parametrize("seed", range(6))
def test_compiled_registration_equals_the_tensor_registration(seed):
    group, seq, ordinal, flow, n_groups = _random_registration_input(seed)
    args = (group, seq, ordinal, flow, n_groups, 12, 9, 0.05, 10_000)
    kw = {"refine": True, "line_gate": 0.35, "refine_iters": 5, "n_ordinals": 1024}
    a = register_groups(*args, **kw)
    b = register_groups(*args, backend=CompiledRegistration(), **kw)
    assert int((a.used_events == 12).sum()) >= 1, "a group should exceed the event cap"
    assert int(a.normal.sum()) >= 1 and int((~a.normal & (a.lines >= 2)).sum()) >= 1
    for name in ("full_flow", "cost", "used_events", "inliers", "lines"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(getattr(b, name).float(), 1e30)), name
    # through sqrt / atan2 / cos / sin and their own summation order: float rounding only
    torch.testing.assert_close(a.ratio, b.ratio, rtol=1e-5, atol=1e-6)
    clear = (a.ratio - 0.05).abs() > 1e-4  # away from the aperture threshold
    assert torch.equal(a.normal[clear], b.normal[clear])
    torch.testing.assert_close(a.flow[clear], b.flow[clear], rtol=1e-4, atol=1e-3,
                               equal_nan=True)
    torch.testing.assert_close(a.normal_dir[clear], b.normal_dir[clear], rtol=1e-5,
                               atol=1e-5, equal_nan=True)


def test_compiled_registration_breaks_cost_ties_by_rank_after_the_median_start():
    """Collinear events: every flow between the two middle ones costs the same. The compiled
    solver starts from the candidate nearest the median (here the right one of the tied
    pair); the tie must still go to the smaller hash rank, as in the tensor solver, which
    evaluates every hypothesis in full."""
    xs = [0.0, 1.0, 10.0, 13.0, 29.0, 30.0]
    winners = set()
    for trial in range(40):
        rng = np.random.default_rng(trial)
        seq = np.cumsum(rng.integers(1, 1000, len(xs)))
        group, sq, ordinal, flow = [], [], [], []
        for k, x in enumerate(xs):
            cands = [(x, 0.0)] + ([(12.9, 1000.0)] if k == 0 else [])  # moves the median
            for o, c in enumerate(cands):
                group.append(0)
                sq.append(int(seq[k]))
                ordinal.append(o)
                flow.append(c)
        args = (torch.tensor(group), torch.tensor(sq), torch.tensor(ordinal),
                torch.tensor(flow, dtype=torch.float32), 1, 64, 48, 0.05, 10_000)
        a = register_groups(*args, n_ordinals=8)
        b = register_groups(*args, n_ordinals=8, backend=CompiledRegistration())
        assert torch.equal(a.full_flow, b.full_flow) and torch.equal(a.cost, b.cost), trial
        winners.add(float(a.full_flow[0, 0]))
    assert winners == {10.0, 13.0}  # both ranks orders occurred


def test_compiled_flow_leaves_torch_threads_as_set():
    """numba's OpenMP layer resets the process's thread count when it first starts; the flow
    must leave the caller's ``torch.set_num_threads`` in place (fresh process: first start)."""
    import subprocess
    import sys

    code = (
        "import torch\n"
        "from evtrack.flow import FlowConfig, TripletFlow\n"
        "from evtrack.flow.scenes import translating_texture\n"
        "ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=20_000,"
        " seed=5)\n"
        "torch.set_num_threads(1)\n"
        "res = TripletFlow(FlowConfig(sensor_size=(64, 48), roi_size=16, backend='compiled'))(ev)"
        "\n"
        "assert len(res) > 0\n"
        "print(torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True)
    assert out.stdout.strip().splitlines()[-1] == "1", out.stdout + out.stderr


def _exact_rounded(d2: float) -> int:
    """round(sqrt(d2) * COST_SCALE), ties to even, capped, in rational arithmetic."""
    cap = 1 << 25
    if not math.isfinite(d2) or d2 * COST_SCALE ** 2 >= float(cap) ** 2:
        return cap
    big = Fraction(d2) * int(COST_SCALE) ** 2
    n = math.isqrt(int(big))
    for c in range(max(n - 2, 0), n + 3):
        lo = Fraction(2 * c - 1, 2) ** 2 if c > 0 else Fraction(-1)
        hi = Fraction(2 * c + 1, 2) ** 2
        if lo < big < hi or (big == lo and c % 2 == 0):
            return c
        if big == hi:
            return c if c % 2 == 0 else c + 1
    raise AssertionError(d2)


def test_rounded_distance_is_exact_in_both_backends():
    rng = np.random.default_rng(1)
    ties = (rng.integers(0, 4000, 300) + 0.5) ** 2 / COST_SCALE ** 2  # exactly between
    d2 = np.concatenate([rng.random(2000) * 1e8, ties, rng.random(300) * 10,
                         [0.0, 1e-30, np.inf, 1e30]]).astype(np.float32)
    expected = np.array([_exact_rounded(float(v)) for v in d2])
    assert np.array_equal(rounded_distance(torch.from_numpy(d2)).numpy(), expected)
    got = [sk.rounded_distance(np.float32(v), COST_SCALE, float(1 << 25)) for v in d2]
    assert np.array_equal(np.array(got), expected)


def test_lane_rounding_equals_the_scalar_rounding():
    """The branch-free rounding of the registration's lanes is the exact scalar rule: ties
    between two integers, zero, tiny, capped and infinite distances."""
    rng = np.random.default_rng(4)
    ties = (rng.integers(0, 4000, 300) + 0.5) ** 2 / COST_SCALE ** 2
    d2 = np.concatenate([rng.random(2000) * 1e8, ties, rng.random(300) * 10,
                         [0.0, 1e-30, np.inf, 1e30, float(1 << 25) ** 2 / 256]]
                        ).astype(np.float32)
    out = np.empty(d2.shape[0], np.int64)
    sk._rounded_lanes(d2, out, d2.shape[0], COST_SCALE, float(1 << 25))
    assert np.array_equal(out, [_exact_rounded(float(v)) for v in d2])


@pytest.mark.parametrize("order", ["random", "ascending", "descending"])
@pytest.mark.parametrize("cap", [1, 5, 16])
def test_insertion_selection_keeps_the_smallest_keys_sorted(order, cap):
    """The registration's selections (the data-term cap, the hypotheses) keep the ``cap``
    smallest distinct keys, ascending, as sorting all and taking the first ``cap`` would."""
    rng = np.random.default_rng(cap)
    for n in (0, 1, cap - 1, cap, cap + 1, 200):
        keys = rng.choice(1 << 40, size=max(n, 0), replace=False).astype(np.int64)
        if order != "random":
            keys = np.sort(keys)[::1 if order == "ascending" else -1]
        buf = np.full(cap, -7, np.int64)
        filled = 0
        for key in keys:
            filled = ak.insert_smallest(buf, filled, cap, key)
        assert filled == min(n, cap)
        assert np.array_equal(buf[:filled], np.sort(keys)[:cap])


@pytest.mark.parametrize("n", [1, 2, 3, 4, 15, 16, 17, 48])
def test_small_median_equals_numpy_median(n):
    """The registration's allocation-free median of the hypotheses (which one it evaluates
    first) is NumPy's, float64 of the float32 values, even counts the mean of the middle
    two; ties and repeated values included."""
    rng = np.random.default_rng(n)
    scratch = np.full(n, np.float32(1e30), np.float32)
    for values in (rng.normal(0, 300, n), rng.integers(-3, 3, n), np.full(n, 7.25)):
        values = np.asarray(values, np.float32)
        before = values.copy()
        got = sk._median_small(values, n, scratch)
        want = np.median(values.astype(np.float64)) if n % 2 else np.float64(
            np.float32(np.sort(values)[n // 2 - 1] + np.sort(values)[n // 2])) / 2
        assert got == want and np.array_equal(values, before)


def _first_nearest(cx, cy, fx, fy, allowed):
    """Brute force: the first allowed candidate with the smallest rounded distance."""
    best, arg = None, -1
    for i in range(cx.shape[0]):
        if not allowed[i]:
            continue
        dx, dy = np.float32(cx[i] - fx), np.float32(cy[i] - fy)
        q = sk.rounded_distance(np.float32(dx * dx) + np.float32(dy * dy),
                                COST_SCALE, float(1 << 25))
        if best is None or q < best:
            best, arg = q, i
    return arg


@pytest.mark.parametrize("seed", range(40))
def test_nearest_candidate_is_the_first_of_the_smallest_rounded_distance(seed):
    """The registration's nearest candidate to F (smallest float32 distance first, then only
    the candidates that round alike) equals rounding every candidate; ties of the rounded
    distance with different float distances go to the earlier candidate."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    fx, fy = np.float32(rng.normal(0, 300)), np.float32(rng.normal(0, 300))
    # distances a fraction of 1/COST_SCALE apart: many round to the same integer
    radius = rng.choice([0.0, 0.01, 0.5, 3.0, 300.0])
    angle = rng.random(n) * 2 * np.pi
    dist = radius + rng.integers(0, 3, n) / COST_SCALE + rng.random(n) * (0.9 / COST_SCALE)
    cx = (fx + dist * np.cos(angle)).astype(np.float32)
    cy = (fy + dist * np.sin(angle)).astype(np.float32)
    if seed % 5 == 0:  # exact repeats and a parallel pair
        cx[-1], cy[-1] = cx[0], cy[0]
        cx[n // 2], cy[n // 2] = cx[0] * np.float32(2), cy[0] * np.float32(2)
    i1, d2 = sk._nearest(cx, cy, 0, n, fx, fy, COST_SCALE, float(1 << 25))
    assert i1 == _first_nearest(cx, cy, fx, fy, np.ones(n, bool))
    dx, dy = cx[i1] - fx, cy[i1] - fy
    assert d2 == np.float32(dx * dx) + np.float32(dy * dy)
    ax, ay = np.float64(cx[i1]), np.float64(cy[i1])
    eps2 = 1e-3 * 1e-3
    bx, by = cx.astype(np.float64), cy.astype(np.float64)
    nonpar = (bx * ay - by * ax) ** 2 > eps2 * (bx * bx + by * by) * (ax * ax + ay * ay)
    i2, _ = sk._nearest(cx, cy, 0, n, fx, fy, COST_SCALE, float(1 << 25), True, ax, ay, eps2)
    assert i2 == _first_nearest(cx, cy, fx, fy, nonpar)


@pytest.mark.parametrize("lanes", [1, 5, 47])
def test_lane_costs_equal_the_one_by_one_costs(lanes):
    """Hypotheses evaluated side by side give each lane's exact cost, or a partial sum at or
    above the lane's bound: a lane is dropped once it reaches its bound, the others go on."""
    rng = np.random.default_rng(lanes)
    n_ev = 30
    sizes = rng.integers(1, 9, n_ev)
    ev_ptr = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    c_event = np.repeat(np.arange(n_ev), sizes).astype(np.int64)
    c_x = rng.normal(0, 200, ev_ptr[-1]).astype(np.float32)
    c_y = rng.normal(0, 200, ev_ptr[-1]).astype(np.float32)
    pick = rng.integers(0, ev_ptr[-1], lanes)
    hx, hy = c_x[pick].copy(), c_y[pick].copy()
    exact = np.array([sk._hypothesis_cost(hx[k], hy[k], c_x, c_y, c_event, 0, ev_ptr[-1],
                                          sk.NO_BOUND, COST_SCALE, float(1 << 25))
                      for k in range(lanes)])
    total, mins, q = (np.empty(lanes, np.int64), np.empty(lanes, np.float32),
                      np.empty(lanes, np.int64))

    def lane_costs(bound):  # into ``total``, with fresh scratch
        sk._lane_costs(hx, hy, lanes, c_x, c_y, ev_ptr, n_ev, bound, total, mins, q,
                       COST_SCALE, float(1 << 25), np.empty(lanes, np.int64),
                       np.empty(lanes, np.float32), np.empty(lanes, np.float32),
                       np.empty(lanes, np.int64), np.empty(lanes, np.int64))

    no_bound = np.full(lanes, sk.NO_BOUND, np.int64)
    lane_costs(no_bound)
    assert np.array_equal(total, exact)
    bound = np.full(lanes, int(np.median(exact)), np.int64)  # some lanes above, some below
    lane_costs(bound)
    below = exact < bound
    assert np.array_equal(total[below], exact[below])
    assert (total[~below] >= bound[~below]).all()
    if lanes > 1:  # dropped lanes stopped early while the lanes below went on
        assert (total[~below] < exact[~below]).any()
    # every lane at or above its bound: the evaluation stops early, above the bounds
    bound = np.full(lanes, int(exact.min()) // 2, np.int64)
    lane_costs(bound)
    assert (total >= bound).all() and (total < exact).any()


def test_backend_choice_and_errors():
    assert resolve(FlowConfig(backend="auto"), "cpu").name == "compiled"
    assert resolve(FlowConfig(backend="torch"), "cpu").name == "torch"
    assert resolve(FlowConfig(backend="compiled"), "cpu").search is compiled.CompiledSearch
    assert resolve(FlowConfig(backend="auto"), "meta").name == "torch"
    with pytest.raises(ConfigError, match="'backend'"):
        FlowConfig(backend="fast")
    with pytest.raises(ConfigError, match="runs on CPU .* and CUDA"):
        resolve(FlowConfig(backend="compiled"), "mps")
    flow = TripletFlow(FlowConfig(sensor_size=(32, 24), backend="compiled"))
    ev, _ = translating_texture((32, 24), velocity=(500.0, 0.0), duration_us=5_000, seed=1)
    flow.update(ev)
    with pytest.raises(EvtrackError, match="compiled CPU backend"):
        flow.to("meta")
    assert flow.device.type == "cpu" and flow.config.device == "cpu"  # left as it was
    fresh = TripletFlow(FlowConfig(sensor_size=(32, 24))).to("meta")  # no events yet: fine
    assert fresh.config.device == "meta"


def test_backends_without_numba(monkeypatch):
    """Without numba ``auto`` runs the tensor code on CPU and ``compiled`` is an error."""
    monkeypatch.setattr(numba_support, "numba", None)
    assert resolve(FlowConfig(backend="auto"), "cpu").name == "torch"
    with pytest.raises(ConfigError, match="needs numba"):
        resolve(FlowConfig(backend="compiled"), "cpu")
    with pytest.raises(ConfigError, match="needs numba"):
        TripletFlow(FlowConfig(sensor_size=(32, 24), backend="compiled"))


def test_triton_backend_choice_and_errors(monkeypatch):
    from evtrack.flow import registration_triton

    cuda = torch.device("cuda")  # resolve only looks at the type: no GPU needed
    assert resolve(FlowConfig(backend="torch"), cuda).name == "torch"
    assert resolve(FlowConfig(backend="auto"), cuda).name == (
        "triton" if registration_triton.triton is not None else "torch")
    assert resolve(FlowConfig(backend="auto"), cuda).search is not compiled.CompiledSearch
    # caps beyond one program's registers run the tensor registration
    assert registration_triton.fits(64, 48) and not registration_triton.fits(1000, 48)
    group, seq, ordinal, flow, n_groups = _random_registration_input(0)

    def refuse(*args, **kwargs):
        raise AssertionError("the Triton kernel must not run for caps above MAX_CAP")

    monkeypatch.setattr(registration_triton, "solve_groups", refuse)
    big = registration_triton.MAX_CAP + 1
    a = register_groups(group, seq, ordinal, flow, n_groups, big, 9, 0.05, 10_000)
    b = register_groups(group, seq, ordinal, flow, n_groups, big, 9, 0.05, 10_000,
                        backend=registration_triton.TritonRegistration())
    assert torch.equal(torch.nan_to_num(a.full_flow, 1e30), torch.nan_to_num(b.full_flow, 1e30))
    monkeypatch.setattr(registration_triton, "triton", None)
    assert resolve(FlowConfig(backend="auto"), cuda).name == "torch"  # the tensor code
    with pytest.raises(ConfigError, match="needs triton"):
        resolve(FlowConfig(backend="compiled"), cuda)
    monkeypatch.setattr(registration_triton, "available", lambda device_type: True)
    assert resolve(FlowConfig(backend="compiled"), cuda).name == "triton"
    assert resolve(FlowConfig(backend="auto"), "cpu").name == "compiled"  # never on CPU


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize("spread", [50, 10**12])  # dense table / sort and binary search
def test_group_key_helpers_equal_torch(spread, numpy_on_cpu, monkeypatch):
    from evtrack.flow import pending
    from evtrack.flow.pending import positions, unique_inverse

    monkeypatch.setattr(pending, "NUMPY_ON_CPU", numpy_on_cpu)

    rng = np.random.default_rng(spread % 97)
    for n in (0, 1, 7, 5000):
        values = torch.as_tensor(rng.integers(3, 3 + spread, n), dtype=torch.int64)
        keys, inv = unique_inverse(values)
        ref_keys, ref_inv = torch.unique(values, return_inverse=True)
        assert torch.equal(keys, ref_keys) and torch.equal(inv, ref_inv)
        picked = values[torch.as_tensor(rng.integers(0, max(n, 1), 3 * n if n else 0))]
        assert torch.equal(positions(keys, picked), torch.searchsorted(keys, picked))


@pytest.mark.parametrize("spread", [40, 10**9])
def test_compiled_group_positions_equal_searchsorted(spread):
    """The registration's compiled group positions (a dense table over a small key range,
    binary search over a wide one) equal ``torch.searchsorted``."""

    rng = np.random.default_rng(spread % 89)
    for n in (0, 1, 7, 5000):
        keys = np.unique(rng.integers(-spread, spread, max(n // 3, 1)))
        values = keys[rng.integers(0, keys.shape[0], n)]
        got = ak.group_positions(keys, values, 8, 0 if spread > 100 else 65_536)
        assert got.tolist() == torch.searchsorted(torch.from_numpy(keys),
                                                  torch.from_numpy(values)).tolist()


def test_compiled_group_keys_equal_the_torch_formula():
    """The compiled group keys divide with the floor, as torch's ``rounding_mode="floor"``
    (negative timestamps included), and the candidates' keys, ordinals and supported groups
    follow their events."""
    from evtrack.flow import pending

    rng = np.random.default_rng(11)
    n, cols, rows, s, w_us = 500, 7, 5, 16, 2_000
    x = rng.integers(0, cols * s, n)
    y = rng.integers(0, rows * s, n)
    roi_of_x = np.arange(cols * s) // s
    roi_of_y = np.arange(rows * s) // s * cols
    # sorted (windows change between events, gaps of several windows), then in any order
    for t in (np.sort(rng.integers(-50_000, 50_000, n)), rng.integers(-50_000, 50_000, n)):
        out = np.empty(n, np.int64)
        pending.event_group_keys(x, y, t, w_us, roi_of_x, roi_of_y, cols * rows, out)
        tx, ty, tt = (torch.from_numpy(v) for v in (x, y, t))
        expected = (torch.div(tt, w_us, rounding_mode="floor") * (cols * rows)
                    + torch.div(ty, s, rounding_mode="floor") * cols
                    + torch.div(tx, s, rounding_mode="floor"))
        assert torch.equal(torch.from_numpy(out), expected)
    seq0, k = 1000, 3
    event = np.sort(rng.integers(seq0, seq0 + n, 2000))
    offset, aj, ai = rng.integers(0, 48, 2000), rng.integers(0, k, 2000), rng.integers(0, k, 2000)
    c_g, ordinal, supported = (np.empty(2000, np.int64) for _ in range(3))
    n_sup = pending.candidate_group_keys(event, offset, aj, ai, seq0, out, k, c_g, ordinal,
                                         supported)
    assert np.array_equal(c_g, out[event - seq0])
    assert np.array_equal(ordinal, (offset * k + aj) * k + ai)
    first = np.concatenate([[True], event[1:] != event[:-1]])
    assert n_sup == first.sum() and np.array_equal(supported[:n_sup], c_g[first])


@pytest.mark.parametrize("spread", [40, 10**9])
def test_compiled_group_count_merge_equals_the_torch_merge(spread):
    """The pending groups' union and counts (compiled, through a table over the keys'
    range) equal the sort-based torch form; a range too wide for a table gives None."""
    from evtrack.flow import pending

    rng = np.random.default_rng(spread % 13)
    tables = 0
    for n_old, n_new in ((0, 0), (0, 5), (6, 0), (30, 200), (1, 1)):
        old = np.unique(rng.integers(0, spread, n_old)).astype(np.int64)
        old_events = rng.integers(1, 9, old.shape[0]).astype(np.int64)
        old_support = rng.integers(0, 5, old.shape[0]).astype(np.int64)
        new = rng.integers(0, spread, n_new).astype(np.int64)
        supported = new[rng.random(n_new) < 0.6]
        got = pending.merge_group_counts(old, old_events, old_support, new, supported,
                                         pending.DENSE_SLACK, pending.DENSE_FLOOR)
        every = np.concatenate([old, new, supported])
        if not len(every) or np.ptp(every) + 1 > (pending.DENSE_SLACK * len(every)
                                                  + pending.DENSE_FLOOR):
            assert got is None  # the caller sorts instead
            continue
        keys, inv = torch.unique(torch.from_numpy(every), return_inverse=True)
        events = torch.zeros_like(keys).index_add_(0, inv[:len(old)], torch.from_numpy(
            old_events)).index_add_(0, inv[len(old):len(old) + n_new],
                                    torch.ones(n_new, dtype=torch.int64))
        support = torch.zeros_like(keys).index_add_(0, inv[:len(old)], torch.from_numpy(
            old_support)).index_add_(0, inv[len(old) + n_new:],
                                     torch.ones(len(supported), dtype=torch.int64))
        assert [a.tolist() for a in got] == [keys.tolist(), events.tolist(), support.tolist()]
        tables += 1
    assert tables == (4 if spread < 1000 else 0)


@pytest.mark.parametrize("backend", ["compiled", "torch"])
def test_numpy_bookkeeping_on_cpu_gives_the_torch_flow(backend, monkeypatch):
    """The flow's CPU bookkeeping (the events' and candidates' group keys and ordinals in
    compiled loops, or in NumPy without numba; the dense tables in NumPy;
    ``pending.NUMPY_ON_CPU``) gives the same RoI flows and per-event flows as the torch
    bookkeeping that CUDA runs, streamed in uneven batches."""
    from evtrack.flow import pending

    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    cfg = FlowConfig(sensor_size=(64, 48), roi_size=16, window_us=2_000, backend=backend)
    out = []
    for numpy_on_cpu, compiled_keys in ((False, False), (True, True), (True, False)):
        monkeypatch.setattr(pending, "NUMPY_ON_CPU", numpy_on_cpu)
        monkeypatch.setattr(pending, "jit_available", lambda c=compiled_keys: c)
        flow = TripletFlow(cfg, return_event_flow=True)
        parts = [flow.update(ev[a:b]) for a, b in ((0, 700), (700, 3001), (3001, len(ev)))]
        out.append(FlowResult.cat([*parts, flow.flush()]))
    reference = out[0]
    assert len(reference) > 20
    for other in out[1:]:
        for name in ("flow", "full_flow", "cost", "support", "roi", "window", "event_flow",
                     "xy", "t", "normal", "normal_dir", "n_events"):
            a, b = getattr(reference, name), getattr(other, name)
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert torch.equal(torch.nan_to_num(a.double(), 1e30),
                               torch.nan_to_num(b.double(), 1e30)), name
