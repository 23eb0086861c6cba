"""RoI registration (Eq. 3) against brute force, determinism of the caps, aperture test."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evtrack.flow.constants import COST_SCALE
from evtrack.flow.registration import register_groups
from evtrack.flow.registration_compiled import CompiledRegistration
from evtrack.flow.registration_tensor import TensorRegistration, run_starts, select_smallest


def _groups(seed, n_groups=5, max_events=12, max_cands=6):
    rng = np.random.default_rng(seed)
    group, seq, ordinal, flow = [], [], [], []
    s = 0
    for _ in range(n_groups * max_events):
        g = int(rng.integers(0, n_groups))
        for o in sorted(rng.choice(40, int(rng.integers(1, max_cands + 1)), replace=False)):
            group.append(g)
            seq.append(s)
            ordinal.append(int(o))
            flow.append(rng.normal(0, 300, 2) + [500, -200])
        s += int(rng.integers(1, 4))
    return (torch.tensor(group), torch.tensor(seq), torch.tensor(ordinal),
            torch.tensor(np.array(flow), dtype=torch.float32))


def _brute_force_costs(group, seq, flow, g):
    """Eq. 3 cost of every candidate of group g as a hypothesis (plain Python, float64)."""
    rows = [(int(s), [float(v) for v in f]) for gg, s, f in
            zip(group.tolist(), seq.tolist(), flow.tolist(), strict=True) if gg == g]
    events = {}
    for s, f in rows:
        events.setdefault(s, []).append(f)
    costs = []
    for _, h in rows:
        costs.append(sum(min(math.dist(h, c) for c in cands) for cands in events.values()))
    return rows, costs, len(events)


def test_eq3_solution_minimises_the_cost_like_brute_force():
    for seed in range(4):
        group, seq, ordinal, flow = _groups(seed)
        reg = register_groups(group, seq, ordinal, flow, 5, max_events=1000,
                              max_hypotheses=1000, aperture_ratio=0.0, pair_budget=97,
                              refine=False)
        for g in range(5):
            rows, costs, n_ev = _brute_force_costs(group, seq, flow, g)
            if not rows:
                assert torch.isnan(reg.full_flow[g]).all()
                continue
            chosen = reg.full_flow[g].tolist()
            chosen_cost = min(c for (_, f), c in zip(rows, costs, strict=True)
                              if np.allclose(f, chosen))
            # exact up to the 1/COST_SCALE px/s rounding of each event's distance
            assert chosen_cost <= min(costs) + n_ev / COST_SCALE + 1e-6
            assert abs(float(reg.cost[g]) * n_ev - min(costs)) <= n_ev / COST_SCALE + 1e-3
            assert int(reg.used_events[g]) == n_ev


def test_pair_budget_does_not_change_the_result():
    group, seq, ordinal, flow = _groups(7)
    a = register_groups(group, seq, ordinal, flow, 5, 1000, 1000, 0.05, 10**9)
    b = register_groups(group, seq, ordinal, flow, 5, 1000, 1000, 0.05, 1)
    torch.testing.assert_close(a.flow, b.flow, equal_nan=True)
    torch.testing.assert_close(a.cost, b.cost, equal_nan=True)


def test_caps_select_by_hash_independently_of_other_groups():
    group, seq, ordinal, flow = _groups(3, n_groups=3, max_events=40)
    full = register_groups(group, seq, ordinal, flow, 3, 8, 10, 0.05, 10**6)
    for g in range(3):
        m = group == g
        alone = register_groups(torch.zeros_like(group[m]), seq[m], ordinal[m], flow[m], 1, 8,
                                10, 0.05, 10**6)
        torch.testing.assert_close(alone.flow[0], full.flow[g], equal_nan=True)
        assert int(full.used_events[g]) <= 8


def test_select_smallest_keeps_cap_per_group():
    group = torch.tensor([0, 1, 0, 0, 1, 0, 2])
    key = torch.tensor([5, 1, 3, 3, 0, 9, 4])
    keep = select_smallest(group, key, 2)
    # group 0: keys 3 (idx 2) and 3 (idx 3) win over 5 and 9; ties keep the earlier item
    assert keep.tolist() == [False, True, True, True, True, False, True]
    assert select_smallest(group, key, 2, n_groups=3).tolist() == keep.tolist()


@pytest.mark.parametrize("cap", [1, 3, 8])
def test_select_smallest_skips_groups_under_the_cap_with_the_same_answer(cap):
    g = torch.Generator().manual_seed(cap)
    group = torch.randint(0, 50, (2000,), generator=g) ** 2 % 50   # uneven group sizes
    key = torch.randint(0, 40, (2000,), generator=g)                 # many ties
    brute = []
    for i in range(2000):  # kept iff fewer than cap items of its group come before it
        same = (group == group[i]).nonzero().reshape(-1).tolist()
        before = sum(1 for j in same if (int(key[j]), j) < (int(key[i]), i))
        brute.append(before < cap)
    assert select_smallest(group, key, cap).tolist() == brute
    assert select_smallest(group, key, cap, n_groups=50).tolist() == brute


def _line_candidates(normals, speeds, directions, seed=0):
    """Candidates s d / (n . d) of events on constraint lines n . F = s (one event per line)."""
    group, seq, ordinal, flow = [], [], [], []
    for e, (n, s) in enumerate(zip(normals, speeds, strict=True)):
        o = 0
        for d in directions:
            nd = float(np.dot(n, d))
            if nd > 0.2:
                group.append(0)
                seq.append(e)
                ordinal.append(o)
                flow.append(s * np.asarray(d, dtype=float) / nd)
            o += 1
    return (torch.tensor(group), torch.tensor(seq), torch.tensor(ordinal),
            torch.tensor(np.array(flow), dtype=torch.float32))


DIRECTIONS = [(dx, dy) for dx in range(-3, 4) for dy in range(-3, 4) if (dx, dy) != (0, 0)]


def test_lines_through_one_point_recover_it_exactly():
    truth = np.array([830.0, 310.0])
    rng = np.random.default_rng(1)
    angles = rng.uniform(-1.2, 1.2, 30) + math.atan2(truth[1], truth[0])
    normals = np.stack([np.cos(angles), np.sin(angles)], 1)
    speeds = normals @ truth
    group, seq, ordinal, flow = _line_candidates(normals, speeds, DIRECTIONS)
    reg = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6, refine=True,
                          line_gate=0.5)
    assert not bool(reg.normal[0])
    assert np.allclose(reg.flow[0].numpy(), truth, rtol=2e-3)
    # Eq. 3 alone is limited by the direction of the integer displacements
    eq3 = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6, refine=False)
    assert np.linalg.norm(eq3.flow[0].numpy() - truth) < 0.1 * np.linalg.norm(truth)


def test_a_single_edge_is_flagged_as_normal_flow():
    n = np.array([math.cos(0.4), math.sin(0.4)])
    normals = np.tile(n, (20, 1))
    speeds = np.full(20, 700.0)
    group, seq, ordinal, flow = _line_candidates(normals, speeds, DIRECTIONS)
    reg = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6)
    assert bool(reg.normal[0])
    direction = reg.normal_dir[0].numpy()
    assert abs(abs(float(direction @ n)) - 1.0) < 1e-4
    assert np.allclose(reg.flow[0].numpy(), 700.0 * n, rtol=1e-3)
    # without the refinement: F itself, projected on the edge's normal
    for backend in (TensorRegistration(), CompiledRegistration()):
        plain = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6,
                                refine=False, backend=backend)
        f = plain.full_flow[0].numpy().astype(np.float64)
        d = plain.normal_dir[0].numpy().astype(np.float64)
        assert bool(plain.normal[0])
        assert np.allclose(plain.flow[0].numpy(), (f @ d) * d, rtol=1e-5, atol=1e-3)
        assert abs(float(plain.flow[0].numpy() @ n) - 700.0) < 0.1 * 700.0


@pytest.mark.parametrize("backend", [TensorRegistration(), CompiledRegistration()],
                         ids=["tensor", "compiled"])
def test_one_constraint_line_gives_its_normal_flow_with_fit_min_lines_1(backend):
    """One event: all its candidates lie on its line n . F = s, so Eq. 3 picks one arbitrary
    point along it. Fitted from one line (``fit_min_lines=1``) the group reports that line's
    normal flow ``s n``; by default (two lines needed) the candidate itself."""
    n = np.array([math.cos(-0.7), math.sin(-0.7)])
    group, seq, ordinal, flow = _line_candidates(n[None], np.array([450.0]), DIRECTIONS)
    kw = {"backend": backend, "line_gate": 0.5}
    default = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6, **kw)
    assert int(default.lines[0]) == 1
    assert not bool(default.normal[0])
    assert torch.equal(default.flow[0], default.full_flow[0])
    assert abs(float(default.full_flow[0].numpy() @ n) - 450.0) < 1e-2  # a point of the line
    assert np.linalg.norm(default.full_flow[0].numpy() - 450.0 * n) > 50.0  # not the normal

    one = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6,
                          fit_min_lines=1, **kw)
    assert bool(one.normal[0])
    assert abs(abs(float(one.normal_dir[0].numpy() @ n)) - 1.0) < 1e-5
    assert np.allclose(one.flow[0].numpy(), 450.0 * n, rtol=1e-4)
    assert torch.equal(one.full_flow[0], default.full_flow[0])


def test_inliers_count_the_events_near_the_solution_like_brute_force():
    gate = 0.35
    for seed in range(3):
        group, seq, ordinal, flow = _groups(seed)
        reg = register_groups(group, seq, ordinal, flow, 5, 1000, 1000, 0.05, 10**6,
                              line_gate=gate)
        for g in range(5):
            f = reg.full_flow[g].double().numpy()
            if np.isnan(f).any():
                assert int(reg.inliers[g]) == 0
                continue
            limit = gate * max(float(np.linalg.norm(f)), 1.0)
            nearest = {}
            for gg, s, c in zip(group.tolist(), seq.tolist(), flow.tolist(), strict=True):
                if gg == g:
                    d = float(np.linalg.norm(np.asarray(c, dtype=np.float32) - f))
                    nearest[s] = min(nearest.get(s, math.inf), d)
            expected = sum(d <= limit * (1 + 1e-6) for d in nearest.values())
            assert abs(int(reg.inliers[g]) - expected) <= sum(
                abs(d - limit) < 1e-3 * limit for d in nearest.values())  # float32 ties
            assert 0 <= int(reg.inliers[g]) <= int(reg.used_events[g])


def test_events_on_lines_through_one_point_all_agree():
    truth = np.array([-420.0, 650.0])
    rng = np.random.default_rng(5)
    angles = rng.uniform(-1.2, 1.2, 25) + math.atan2(truth[1], truth[0])
    normals = np.stack([np.cos(angles), np.sin(angles)], 1)
    group, seq, ordinal, flow = _line_candidates(normals, normals @ truth, DIRECTIONS)
    reg = register_groups(group, seq, ordinal, flow, 1, 100, 400, 0.05, 10**6, line_gate=0.35)
    # every event has a candidate within ~9 degrees of the truth, hence near the Eq. 3 solution
    assert int(reg.inliers[0]) == int(reg.used_events[0]) == 25


@pytest.mark.parametrize("by_search", [True, False])
def test_run_starts_give_the_first_position_of_each_run(by_search):
    rng = np.random.default_rng(7)
    values = torch.from_numpy(np.sort(rng.integers(0, 40, 500)))
    got = run_starts(values, by_search=by_search)
    expected = [int(np.searchsorted(values.numpy(), v)) for v in values.numpy()]
    assert got.tolist() == expected
    assert run_starts(torch.zeros(0, dtype=torch.int64), by_search=by_search).numel() == 0
