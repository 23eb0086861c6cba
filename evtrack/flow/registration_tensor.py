"""The registration's tensor backend (any device): the caps, Eq. 3, the constraint lines
and their robust fit by batched tensor operations (see :mod:`evtrack.flow.registration` for
the rule), and the exact primitives the other backends reproduce (:func:`rounded_distance`,
:func:`select_smallest`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evtrack.flow.constants import COST_SCALE, IRLS_DELTA, PARALLEL_EPS, Q_MAX, RANK_BITS
from evtrack.flow.hashing import hash32
from evtrack.flow.solution import GroupSolution

__all__ = ["TensorRegistration", "Arrangement", "arrange", "rounded_distance",
           "select_smallest", "run_starts"]


def rounded_distance(d2: Tensor) -> Tensor:
    """``min(round(sqrt(d2) * COST_SCALE), Q_MAX)`` exactly (ties to even), as int64.

    ``sqrt`` only gives the starting guess ``n``; with ``D = d2 * COST_SCALE^2`` (exact: a
    float32 value times a power of two, in float64) the result is the integer ``n`` with
    ``(n - 0.5)^2 <= D <= (n + 0.5)^2``, those squares being exact in float64 below
    ``Q_MAX``. A guess within one unit in the last place is off by at most one.

    Args:
        d2: float32 squared distances (px/s)^2, >= 0 (``inf`` allowed).
    """
    big = float(Q_MAX) ** 2
    dd = d2.to(torch.float64) * (COST_SCALE * COST_SCALE)
    capped = dd >= big
    dd = torch.where(capped, 0.0, dd)
    n = torch.round(torch.sqrt(dd))
    n = (n + (dd > (n + 0.5) * (n + 0.5)).to(n.dtype)
         - ((dd < (n - 0.5) * (n - 0.5)) & (n > 0)).to(n.dtype))
    odd = torch.remainder(n, 2.0) == 1.0  # a tie goes to the even neighbour
    n = (n + ((dd == (n + 0.5) * (n + 0.5)) & odd).to(n.dtype)
         - ((dd == (n - 0.5) * (n - 0.5)) & odd).to(n.dtype))
    return torch.where(capped, Q_MAX, n.to(torch.int64))


def select_smallest(group: Tensor, key: Tensor, cap: int, n_groups: int | None = None
                    ) -> Tensor:
    """Per group, which items have one of the ``cap`` smallest keys (ties: earlier item).

    Args:
        group: (M,) int64 group ids >= 0.
        key: (M,) int64 keys in ``[0, 2^32)``.
        cap: how many to keep per group.
        n_groups: a bound on the group ids, when they are small: items of groups with at most
            ``cap`` items are then kept without sorting (the same answer, faster when most
            groups are under the cap).

    Returns:
        (M,) bool mask of the kept items.
    """
    m = group.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.bool, device=group.device)
    if n_groups is not None:
        over = torch.bincount(group, minlength=n_groups)[group] > cap
        idx = torch.nonzero(over).reshape(-1)
        keep = torch.ones(m, dtype=torch.bool, device=group.device)
        if idx.numel():
            keep[idx] = _select_smallest_sorted(group[idx], key[idx], cap)
        return keep
    return _select_smallest_sorted(group, key, cap)


def _select_smallest_sorted(group: Tensor, key: Tensor, cap: int) -> Tensor:
    """:func:`select_smallest` by one stable sort of (group, key)."""
    m = group.shape[0]
    order = torch.sort((group << 32) | key, stable=True).indices
    g_sorted = group[order]
    pos = torch.arange(m, device=group.device)
    keep = torch.zeros(m, dtype=torch.bool, device=group.device)
    keep[order] = (pos - run_starts(g_sorted)) < cap
    return keep


def run_starts(values: Tensor, by_search: bool | None = None) -> Tensor:
    """For each item of the non-decreasing (M,) ``values``, the position of the first item
    equal to it.

    Args:
        values: (M,) sorted int64 tensor.
        by_search: binary search (``searchsorted``) or a running maximum of the runs' first
            positions (``cummax``); ``None``: search on CUDA (torch's int64 ``cummax`` scan
            is slow there: 1.3 ms per million items on an H200), running maximum elsewhere.
    """
    if by_search is None:
        by_search = values.is_cuda
    if by_search:
        return torch.searchsorted(values, values)
    m = values.shape[0]
    pos = torch.arange(m, device=values.device)
    first = torch.ones(m, dtype=torch.bool, device=values.device)
    first[1:] = values[1:] != values[:-1]
    return torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values


def _runs(values: Tensor) -> tuple[Tensor, Tensor]:
    """Run ids of consecutive equal values, and the number of runs."""
    m = values.shape[0]
    change = torch.ones(m, dtype=torch.int64, device=values.device)
    change[1:] = (values[1:] != values[:-1]).to(torch.int64)
    rid = torch.cumsum(change, 0) - 1
    return rid, int(rid[-1]) + 1 if m else 0


@dataclass
class Arrangement:
    """The capped candidates of G groups laid out for the solve (tensor form).

    Attributes:
        c_group: (M,) int64 group of each kept candidate; candidates grouped by group,
            events contiguous and in stream order within a group.
        c_run: (M,) int64 index of each kept candidate's event among all kept events.
        c_flow: (M, 2) float32 kept candidate flows, px/s.
        counts, c_start: (G,) int64 kept candidates per group and the first of each.
        n_events: E, the kept events.
        ev_first: (E,) int64 first candidate of each kept event.
        ev_group: (E,) int64 group of each kept event.
        ev_per_group, ev_start: (G,) int64 kept events per group and the first of each.
        h_idx: (H,) int64 candidate index of each hypothesis, grouped by group, in rank order
            (ascending hash).
        h_group: (H,) int64 group of each hypothesis.
    """

    c_group: Tensor
    c_run: Tensor
    c_flow: Tensor
    counts: Tensor
    c_start: Tensor
    n_events: int
    ev_first: Tensor
    ev_group: Tensor
    ev_per_group: Tensor
    ev_start: Tensor
    h_idx: Tensor
    h_group: Tensor


def arrange(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
            max_events: int, max_hypotheses: int, n_ordinals: int) -> Arrangement:
    """The caps of the registration and the layout of what they keep.

    The data term keeps, per group, the ``max_events`` events with the smallest
    :func:`~evtrack.flow.hashing.hash32` of their stream index; the hypotheses are, per
    group, the ``max_hypotheses`` kept candidates with the smallest hash of
    ``seq * n_ordinals + ordinal`` (ties to the earlier item in both), in rank order.

    Args:
        group: (M,) int64 group id of each candidate, in ``[0, g_count)``.
        seq: (M,) int64 stream index of the candidate's event; candidates of one event are
            consecutive and events appear in stream order.
        ordinal: (M,) int64 ordinal of the candidate within its event (``< n_ordinals``).
        flow: (M, 2) float32 candidate flows in px/s.
        g_count: G.
        max_events, max_hypotheses: the caps.
        n_ordinals: a bound on the ordinals, the same for every call on one stream.
    """
    dev = flow.device
    # --- data term: cap the events per group by the hash of their stream index
    run, n_runs = _runs(seq)
    run_first = torch.zeros(n_runs, dtype=torch.int64, device=dev)
    run_first.scatter_reduce_(0, run, torch.arange(seq.numel(), device=dev), "amin",
                              include_self=False)
    take = torch.index_select  # faster than advanced indexing on CPU
    run_group = take(group, 0, run_first)
    run_keep = select_smallest(run_group, hash32(take(seq, 0, run_first)), max_events,
                               n_groups=g_count)
    keep = torch.nonzero(take(run_keep, 0, run)).reshape(-1)
    # gather kept candidates by group (stable: events stay in stream order)
    order = take(keep, 0, torch.sort(take(group, 0, keep), stable=True).indices)
    c_group, c_seq, c_ord, c_flow = (take(v, 0, order) for v in (group, seq, ordinal, flow))
    c_run, n_ev_total = _runs(c_seq)  # kept events, contiguous per group
    m = c_group.numel()
    counts = torch.bincount(c_group, minlength=g_count)
    c_start = torch.cumsum(counts, 0) - counts
    ev_first = torch.zeros(n_ev_total, dtype=torch.int64, device=dev)
    ev_first.scatter_reduce_(0, c_run, torch.arange(m, device=dev), "amin", include_self=False)
    ev_group = take(c_group, 0, ev_first)
    ev_per_group = torch.bincount(ev_group, minlength=g_count)
    ev_start = torch.cumsum(ev_per_group, 0) - ev_per_group
    # --- hypotheses: cap by candidate hash; rank within group gives the tie-break order
    h_key = hash32(c_seq * n_ordinals + c_ord)
    h_keep = select_smallest(c_group, h_key, max_hypotheses, n_groups=g_count)
    h_idx = torch.nonzero(h_keep).reshape(-1)
    h_group = take(c_group, 0, h_idx)
    h_rank_order = torch.sort((h_group << 32) | take(h_key, 0, h_idx), stable=True).indices
    return Arrangement(c_group=c_group, c_run=c_run, c_flow=c_flow, counts=counts,
                       c_start=c_start, n_events=n_ev_total, ev_first=ev_first,
                       ev_group=ev_group, ev_per_group=ev_per_group, ev_start=ev_start,
                       h_idx=take(h_idx, 0, h_rank_order), h_group=take(h_group, 0, h_rank_order))


class TensorRegistration:
    """The registration's per-group solve by tensor operations (any device)."""

    reports_rows: bool = False
    """No compiled report of the rows (see
    :class:`~evtrack.flow.backends.RegistrationBackend`)."""

    def solve(self, group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
              max_events: int, max_hypotheses: int, pair_budget: int, line_gate: float,
              refine_iters: int, n_ordinals: int) -> GroupSolution:
        """The caps (:func:`arrange`), Eq. 3, the constraint lines and their fit.

        Args: as :func:`evtrack.flow.registration.register_groups`; ``pair_budget``: the
        most (hypothesis, candidate) distances evaluated at once.
        """
        return solve_arranged(arrange(group, seq, ordinal, flow, g_count, max_events,
                                      max_hypotheses, n_ordinals),
                              g_count, pair_budget, line_gate, refine_iters)


def solve_arranged(arr: Arrangement, g_count: int, pair_budget: int, line_gate: float,
                   refine_iters: int) -> GroupSolution:
    """Eq. 3 (the exact int64 costs of :func:`_hypothesis_costs`, arg-min ties to the
    smallest rank), the events' constraint lines and their robust fit, by tensors."""
    dev = arr.c_flow.device
    h_idx, h_group, c_flow = arr.h_idx, arr.h_group, arr.c_flow
    hpos = torch.arange(h_idx.numel(), device=dev)
    h_rank = hpos - run_starts(h_group)
    c_event = arr.c_run - torch.index_select(arr.ev_start, 0, arr.c_group)
    cost = _hypothesis_costs(h_idx, h_group, c_flow, arr.counts, arr.c_start, c_event,
                             arr.ev_per_group, pair_budget)
    # --- arg-min per group, ties to the smallest rank
    combo = (cost << RANK_BITS) | h_rank
    best = torch.full((g_count,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=dev)
    best.scatter_reduce_(0, h_group, combo, "amin")
    has = best != torch.iinfo(torch.int64).max
    best_rank = best & ((1 << RANK_BITS) - 1)
    g_first_h = torch.full((g_count,), h_idx.numel(), dtype=torch.int64, device=dev)
    g_first_h.scatter_reduce_(0, h_group, hpos, "amin")
    chosen = h_idx[(g_first_h + best_rank).clamp_max(max(h_idx.numel() - 1, 0))]
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    full = torch.where(has[:, None], c_flow[chosen], nan2)
    # --- constraint lines and their robust intersection
    lines = _event_lines(arr.c_group, arr.c_run, c_flow, full, arr.n_events, arr.ev_group,
                         line_gate)
    inliers = torch.bincount(arr.ev_group[lines["agree"]], minlength=g_count)
    fit = _fit_lines(lines, full, g_count, refine_iters)
    return GroupSolution(has=has, full=full, best_cost=best >> RANK_BITS,
                         used_events=arr.ev_per_group, inliers=inliers, lines=fit["count"],
                         fit_flow=fit["flow"], ratio=fit["ratio"], major=fit["major"],
                         normal_speed=fit["normal_speed"])


def _event_lines(c_group: Tensor, c_run: Tensor, c_flow: Tensor, full: Tensor, n_events: int,
                 ev_group: Tensor, gate: float) -> dict[str, Tensor]:
    """One constraint line ``n . F = s`` per event, through two of its candidates.

    The first is the event's candidate nearest to the group's flow F and must lie within
    ``gate * max(|F|, 1)`` of it (the event agrees with F); the second is its nearest
    candidate to F from a non-parallel displacement. Events without such a pair give no line.

    Every test is exactly specified, so that the compiled form
    (:mod:`evtrack.flow.registration_compiled`) makes the same choices: nearness is
    :func:`rounded_distance` of the float32 ``dx * dx + dy * dy`` (ties to the earlier
    candidate), agreement compares that float32 ``d2`` with ``gate^2 * max(|F|^2, 1)`` in
    float64, and "non-parallel" is ``cross^2 > eps^2 |c|^2 |c_1|^2`` in float64 (products
    of float32 values are exact there).
    """
    dev = c_flow.device
    m = c_flow.shape[0]
    f0 = full[c_group]
    dx = c_flow[:, 0] - f0[:, 0]
    dy = c_flow[:, 1] - f0[:, 1]
    d2 = dx * dx
    d2 = d2 + dy * dy
    q = rounded_distance(torch.nan_to_num(d2, nan=float("inf")))
    idx = torch.arange(m, device=dev)
    combo = (q << 32) | idx
    big = torch.iinfo(torch.int64).max
    best1 = torch.full((n_events,), big, dtype=torch.int64, device=dev)
    best1.scatter_reduce_(0, c_run, combo, "amin")
    i1 = best1 & 0xFFFFFFFF
    c64 = c_flow.to(torch.float64)
    a = c64[i1]                                   # (E, 2) first candidate of each event
    a_c = a[c_run]
    cross = c64[:, 0] * a_c[:, 1] - c64[:, 1] * a_c[:, 0]
    norm2_c = c64[:, 0] * c64[:, 0] + c64[:, 1] * c64[:, 1]
    norm2_a = a_c[:, 0] * a_c[:, 0] + a_c[:, 1] * a_c[:, 1]
    nonpar = cross * cross > PARALLEL_EPS * PARALLEL_EPS * norm2_c * norm2_a
    best2 = torch.full((n_events,), big, dtype=torch.int64, device=dev)
    best2.scatter_reduce_(0, c_run[nonpar], combo[nonpar], "amin")
    has2 = best2 != big
    i2 = torch.where(has2, best2 & 0xFFFFFFFF, i1)
    fg = full[ev_group]
    f2 = fg[:, 0] * fg[:, 0]
    f2 = f2 + fg[:, 1] * fg[:, 1]
    limit2 = (gate * gate) * f2.to(torch.float64).clamp_min(1.0)
    agree = d2[i1].to(torch.float64) <= limit2
    ok = has2 & agree
    tangent = a - c64[i2]
    length = torch.sqrt(tangent[:, 0] * tangent[:, 0]
                        + tangent[:, 1] * tangent[:, 1]).clamp_min(1e-30)
    normal = torch.stack([-tangent[:, 1], tangent[:, 0]], 1) / length[:, None]
    offset = normal[:, 0] * a[:, 0] + normal[:, 1] * a[:, 1]
    flip = torch.where(offset < 0, -1.0, 1.0).to(torch.float64)
    return {"normal": (normal * flip[:, None])[ok], "offset": (offset * flip)[ok],
            "group": ev_group[ok], "agree": agree}


def _fit_lines(lines: dict[str, Tensor], start: Tensor, g_count: int, iters: int
               ) -> dict[str, Tensor]:
    """Robust (IRLS, L1-like) intersection of each group's constraint lines.

    Minimises ``sum_i |n_i . F - s_i|`` from ``start``; where the normals span one direction
    only (eigenvalue ratio below the caller's threshold), only the normal speed is defined.
    """
    dev = start.device
    n, s, g = (lines["normal"].to(torch.float64), lines["offset"].to(torch.float64),
               lines["group"])
    count = torch.bincount(g, minlength=g_count)
    flow = torch.nan_to_num(start.to(torch.float64))
    delta = IRLS_DELTA * flow.norm(dim=1).clamp_min(1.0)
    nn_ = torch.stack([n[:, 0] * n[:, 0], n[:, 0] * n[:, 1], n[:, 1] * n[:, 1]], 1)
    ratio = torch.ones(g_count, dtype=torch.float64, device=dev)
    major = torch.zeros(g_count, 2, dtype=torch.float64, device=dev)
    normal_speed = torch.zeros(g_count, dtype=torch.float64, device=dev)
    for _ in range(max(1, iters)):
        r = (n * flow[g]).sum(1) - s
        w = 1.0 / torch.maximum(r.abs(), delta[g])
        a_m = torch.zeros(g_count, 3, dtype=torch.float64, device=dev)
        a_m.index_add_(0, g, w[:, None] * nn_)
        rhs = torch.zeros(g_count, 2, dtype=torch.float64, device=dev)
        rhs.index_add_(0, g, (w * s)[:, None] * n)
        a, b, c = a_m[:, 0], a_m[:, 1], a_m[:, 2]
        half_tr = 0.5 * (a + c)
        rad = torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        l_max, l_min = half_tr + rad, half_tr - rad
        ratio = torch.where(l_max > 0, (l_min / l_max.clamp_min(1e-300)).clamp_min(0.0),
                            torch.ones_like(l_max))
        theta = 0.5 * torch.atan2(2 * b, a - c)
        major = torch.stack([torch.cos(theta), torch.sin(theta)], 1)
        normal_speed = (major * rhs).sum(1) / l_max.clamp_min(1e-300)
        det = a * c - b * b
        solvable = (count >= 2) & (det > 1e-12 * l_max.clamp_min(1e-300) ** 2)
        full = torch.stack([c * rhs[:, 0] - b * rhs[:, 1], a * rhs[:, 1] - b * rhs[:, 0]], 1)
        full = full / torch.where(det.abs() > 0, det, torch.ones_like(det))[:, None]
        flow = torch.where(solvable[:, None], full, flow)
    return {"flow": flow.to(torch.float32), "ratio": ratio, "count": count,
            "major": major.to(torch.float32), "normal_speed": normal_speed.to(torch.float32)}


def _hypothesis_costs(h_idx: Tensor, h_group: Tensor, c_flow: Tensor, counts: Tensor,
                      c_start: Tensor, c_event: Tensor, ev_per_group: Tensor,
                      pair_budget: int) -> Tensor:
    """Exact int64 cost ``sum_i min_c round(|F_h - F_ic| * COST_SCALE)`` per hypothesis.

    Dense per batch of groups: the hypotheses (padded to the batch's most, ``Hm``) against the
    candidates (padded to ``Cm``), ``(groups, Hm, Cm)`` squared distances, a per-event minimum
    (a scatter-min of each candidate onto its event; ``min`` is exact in any order) and a sum
    over the events. Groups are batched in order of their candidate count (little
    padding) within ``pair_budget`` distances. Squared distances are ``dx * dx + dy * dy`` in
    float32 with separate IEEE operations, so every value is the same whatever the batch
    layout or device. ``sqrt``, the scaling by a power of two, rounding and the cap are all
    monotone non-decreasing, so they are applied to the per-event minimum only: the result is
    bit for bit ``min_c rounded_distance(dx * dx + dy * dy)``.

    Args:
        h_idx: (H,) candidate index of each hypothesis, grouped by group (``h_group``).
        c_flow: (M, 2) float32 candidate flows, grouped by group, events contiguous.
        counts, c_start: (G,) candidates per group and the first of each.
        c_event: (M,) index of each candidate's event among its group's kept events.
        ev_per_group: (G,) kept events per group.
    """
    dev = c_flow.device
    n_h = h_idx.numel()
    cost = torch.zeros(n_h, dtype=torch.int64, device=dev)
    if n_h == 0:
        return cost
    c_x = c_flow[:, 0].contiguous()
    c_y = c_flow[:, 1].contiguous()
    h_x = c_x[h_idx]
    h_y = c_y[h_idx]
    grp, h_per = torch.unique_consecutive(h_group, return_counts=True)
    h_first = torch.cumsum(h_per, 0) - h_per
    order = torch.argsort(counts[grp], stable=True)
    sizes_c = counts[grp][order].tolist()
    sizes_h = h_per[order].tolist()
    sizes_e = ev_per_group[grp][order].tolist()
    n_g = len(sizes_c)
    start = 0
    while start < n_g:
        # greedy batch: as many groups (by candidate count) as the budget allows, at least one
        stop, cm, hm = start + 1, sizes_c[start], sizes_h[start]
        while stop < n_g:
            c2, h2 = max(cm, sizes_c[stop]), max(hm, sizes_h[stop])
            if (stop + 1 - start) * c2 * h2 > pair_budget:
                break
            cm, hm, stop = c2, h2, stop + 1
        em = max(sizes_e[start:stop])
        sel = order[start:stop]
        g = grp[sel]
        n_b = stop - start
        ar_c = torch.arange(cm, device=dev)
        c_n = counts[g]
        c_i = torch.where(ar_c < c_n[:, None], c_start[g][:, None] + ar_c, 0)
        ar_h = torch.arange(hm, device=dev)
        h_valid = ar_h < h_per[sel][:, None]
        h_pos = torch.where(h_valid, h_first[sel][:, None] + ar_h, 0)
        d2 = h_x[h_pos][:, :, None] - c_x[c_i][:, None, :]  # (n_b, hm, cm)
        dy = h_y[h_pos][:, :, None] - c_y[c_i][:, None, :]
        d2.mul_(d2)
        dy.mul_(dy)
        d2.add_(dy)
        del dy
        # per-event minimum: each candidate onto its event, the padding onto a dummy event em
        ar_e = torch.arange(em, device=dev)
        e_valid = ar_e < ev_per_group[g][:, None]
        ev_of = torch.where(ar_c < c_n[:, None], c_event[c_i], em)
        mins = torch.full((n_b, hm, em + 1), float("inf"), dtype=d2.dtype, device=dev)
        mins.scatter_reduce_(2, ev_of[:, None, :].expand(n_b, hm, cm), d2, "amin")
        mins = mins[:, :, :em]
        del d2
        q = rounded_distance(mins)
        part = torch.where(e_valid[:, None, :], q, 0).sum(2, dtype=torch.int64)
        cost[h_pos[h_valid]] = part[h_valid]
        start = stop
    return cost
