"""RoI registration: one flow per region of interest and time window (the paper's Eq. 3).

For a group (RoI, window) with events ``i = 1..n`` and their candidate sets ``M_i``::

    F = argmin_{F' in M} sum_i min_{c in M_i} |F' - F_ic|

with ``|.|`` the **Euclidean** norm of the 2-D difference (px/s): the sum of norms is the
robust "L1-type" registration cost, invariant to image rotation. ``F`` is a medoid-like
candidate: it is one of the candidate flows.

Evaluated batched over many groups, exactly and deterministically:

* a distance is ``d2 = dx * dx + dy * dy`` in float32 (separate IEEE operations), then
  ``round(sqrt(d2) * COST_SCALE)`` (half to even), capped at ``_Q_MAX``, found with exact
  float64 comparisons (:func:`rounded_distance`; library ``sqrt`` need not be correctly
  rounded, and torch's CPU ``sqrt`` is not), and summed in int64, so costs (and thus the
  arg-min) do not depend on summation order, batch composition, device or backend;
* ties go to the hypothesis with the smallest hash (see below);
* caps keep the O(|M|^2) cost bounded: at most ``max_events_per_roi`` events enter the data
  term (those with the smallest hash of their stream index) and at most ``max_hypotheses``
  candidates of those events are tried as ``F'`` (those with the smallest hash of
  (stream index, candidate ordinal)). Hash selection is deterministic, independent of how
  the stream was chunked, and spreads the kept events over the whole window.

Constraint lines, aperture test and refinement. All candidates of one event lie on the
event's constraint line ``n . F = s`` (a local edge with unit normal ``n`` moving at normal
speed ``s`` matches along any displacement ``d`` with ``n . d > 0``, giving ``s d / (n . d)``).
An event gives its line through its candidate nearest to ``F`` (which must lie within
``line_gate * |F|`` of it) and its candidate nearest to ``F`` from a non-parallel
displacement. With the IRLS weights ``w_i`` of the robust
fit below, the 2x2 scatter ``A = sum_i w_i n_i n_i^T`` has eigenvalues ``l_min <= l_max``:

* **aperture**: ``l_min / l_max < aperture_ratio`` (all lines share one normal: an edge). The
  flow is then reported as normal flow ``s_hat * e`` along the dominant normal ``e`` (the
  eigenvector of ``l_max``), ``s_hat = e . b / l_max`` with ``b = sum_i w_i s_i n_i``;
* **refinement** (``refine``): otherwise the flow is the robust intersection of the lines,
  ``argmin_F sum_i |n_i . F - s_i|`` by IRLS started at the Eq. 3 solution. Eq. 3 alone picks
  one candidate, whose direction is quantised to the integer displacements (up to ~9° off for
  radius 3); the intersection removes that quantisation. ``full_flow`` keeps the Eq. 3
  solution.

Consensus. An event *agrees* with ``F`` (is an inlier) when its candidate nearest to ``F`` lies
within ``line_gate * max(|F|, 1)`` of it; ``inliers`` counts them per group. Where the events
were not caused by one rigid motion (illumination changes on a textureless face, flicker,
noise) their candidates are unrelated and few agree with any ``F``: the caller may refuse
such groups (``FlowConfig.min_inlier_fraction``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Registration", "register_groups", "hash32", "COST_SCALE", "select_smallest",
           "run_starts"]

COST_SCALE = 16.0
"""Distances are rounded to 1/COST_SCALE px/s before the exact int64 sums."""
_PARALLEL_EPS = 1e-3
_IRLS_DELTA = 0.01
_GOLDEN = 2654435761
_RANK_BITS = 20
_Q_MAX = 1 << 25
"""Rounded distances are capped here (2^25 / COST_SCALE = 2.1 M px/s, beyond any plausible
difference of flows); below it ``(n +- 0.5)^2`` is exact in float64."""


def rounded_distance(d2: Tensor) -> Tensor:
    """``min(round(sqrt(d2) * COST_SCALE), _Q_MAX)`` exactly (ties to even), as int64.

    ``sqrt`` only gives the starting guess ``n``; with ``D = d2 * COST_SCALE^2`` (exact: a
    float32 value times a power of two, in float64) the result is the integer ``n`` with
    ``(n - 0.5)^2 <= D <= (n + 0.5)^2``, those squares being exact in float64 below
    ``_Q_MAX``. A guess within one unit in the last place is off by at most one.

    Args:
        d2: float32 squared distances (px/s)^2, >= 0 (``inf`` allowed).
    """
    big = float(_Q_MAX) ** 2
    dd = d2.to(torch.float64) * (COST_SCALE * COST_SCALE)
    capped = dd >= big
    dd = torch.where(capped, 0.0, dd)
    n = torch.round(torch.sqrt(dd))
    n = (n + (dd > (n + 0.5) * (n + 0.5)).to(n.dtype)
         - ((dd < (n - 0.5) * (n - 0.5)) & (n > 0)).to(n.dtype))
    odd = torch.remainder(n, 2.0) == 1.0  # a tie goes to the even neighbour
    n = (n + ((dd == (n + 0.5) * (n + 0.5)) & odd).to(n.dtype)
         - ((dd == (n - 0.5) * (n - 0.5)) & odd).to(n.dtype))
    return torch.where(capped, _Q_MAX, n.to(torch.int64))


def hash32(value: Tensor) -> Tensor:
    """A deterministic 32-bit multiplicative hash of int64 values (no overflow)."""
    return ((value & 0x7FFFFFFF) * _GOLDEN) & 0xFFFFFFFF


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


@dataclass
class Registration:
    """Per-group registration output (G groups).

    Attributes:
        flow: (G, 2) float32 px/s; the normal flow where ``normal``; NaN without candidates.
        full_flow: (G, 2) float32 px/s, the arg-min candidate F itself.
        cost: (G,) float32 mean over the kept events of ``min_c |F - F_ic|`` (px/s).
        used_events: (G,) int64 events in the data term (after the cap).
        ratio: (G,) float32 eigenvalue ratio of the aperture test (1 when undefined).
        normal: (G,) bool aperture flag.
        normal_dir: (G, 2) float32 unit normal ``n`` where ``normal``, else NaN.
        lines: (G,) int64 events that gave a constraint line.
        inliers: (G,) int64 events of the data term that agree with ``full_flow`` (their
            candidate nearest to it lies within ``line_gate * max(|F|, 1)``).
    """

    flow: Tensor
    full_flow: Tensor
    cost: Tensor
    used_events: Tensor
    ratio: Tensor
    normal: Tensor
    normal_dir: Tensor
    lines: Tensor
    inliers: Tensor


def _runs(values: Tensor) -> tuple[Tensor, Tensor]:
    """Run ids of consecutive equal values, and the number of runs."""
    m = values.shape[0]
    change = torch.ones(m, dtype=torch.int64, device=values.device)
    change[1:] = (values[1:] != values[:-1]).to(torch.int64)
    rid = torch.cumsum(change, 0) - 1
    return rid, int(rid[-1]) + 1 if m else 0


def register_groups(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, n_groups: int,
                    max_events: int, max_hypotheses: int, aperture_ratio: float,
                    pair_budget: int, refine: bool = True, line_gate: float = 0.35,
                    refine_iters: int = 5, compiled: bool = False,
                    n_ordinals: int = 1 << 20, triton: bool = False) -> Registration:
    """Solve Eq. 3 for ``n_groups`` groups at once.

    Args:
        group: (M,) int64 group id of each candidate, in ``[0, n_groups)``.
        seq: (M,) int64 stream index of the candidate's event; candidates of one event are
            consecutive and events appear in stream order.
        ordinal: (M,) int64 ordinal of the candidate within its event (distinct per event).
        flow: (M, 2) float32 candidate flows in px/s.
        n_groups: G.
        max_events, max_hypotheses: the caps of the data term and of the tried solutions.
        aperture_ratio: threshold of the aperture test.
        pair_budget: most (hypothesis, candidate) distances evaluated at once.
        refine: replace F by the robust intersection of the events' constraint lines.
        line_gate: an event's line uses its two candidates nearest to F, both within
            ``line_gate * |F|`` of it.
        refine_iters: IRLS iterations of the refinement.
        n_ordinals: a bound on the ordinals, the same for every call on one stream (the
            hypotheses' hash keys are ``seq * n_ordinals + ordinal``: a bound taken from the
            batch would make the selection depend on how the stream was chunked).
        compiled: run the compiled CPU form
            (:mod:`evtrack.flow.registration_compiled`): the same ``full_flow``, ``cost``,
            ``used_events``, ``inliers`` and ``lines`` bit for bit; ``flow``, ``ratio`` and
            ``normal_dir`` to float rounding.
        triton: solve each group in one program of a Triton kernel (CUDA;
            :mod:`evtrack.flow.registration_triton`) after the tensor code's caps: the same
            results as ``compiled`` relative to the tensor path. Caps above
            ``registration_triton.MAX_CAP`` run the tensor path instead.

    Returns:
        The :class:`Registration` of every group.
    """
    dev = flow.device
    g_count = n_groups
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    if group.numel() == 0 or g_count == 0:
        return Registration(flow=nan2.clone(), full_flow=nan2.clone(),
                            cost=torch.full((g_count,), float("nan"), device=dev),
                            used_events=torch.zeros(g_count, dtype=torch.int64, device=dev),
                            ratio=torch.ones(g_count, device=dev),
                            normal=torch.zeros(g_count, dtype=torch.bool, device=dev),
                            normal_dir=nan2.clone(),
                            lines=torch.zeros(g_count, dtype=torch.int64, device=dev),
                            inliers=torch.zeros(g_count, dtype=torch.int64, device=dev))
    if ordinal.numel() and int(ordinal.max()) >= n_ordinals:
        raise ValueError(f"candidate ordinals must be < n_ordinals ({n_ordinals})")
    if compiled:
        from evtrack.flow.registration_compiled import register_groups_compiled

        res = register_groups_compiled(group, seq, ordinal, flow, g_count, max_events,
                                       max_hypotheses, n_ordinals, line_gate, refine_iters,
                                       COST_SCALE, _Q_MAX, _PARALLEL_EPS, _IRLS_DELTA)
        has, full, best_cost = res["has"], res["full"], res["best_cost"]
        ev_per_group, inliers, count = res["used_events"], res["inliers"], res["lines"]
        fit = {"flow": res["fit_flow"].to(torch.float32), "ratio": res["ratio"],
               "count": count, "major": res["major"].to(torch.float32),
               "normal_speed": res["normal_speed"].to(torch.float32)}
    else:
        if triton:
            from evtrack.flow.registration_triton import fits

            triton = fits(max_events, max_hypotheses)
        has, full, best_cost, ev_per_group, inliers, fit = _solve_tensor(
            group, seq, ordinal, flow, g_count, max_events, max_hypotheses, pair_budget,
            line_gate, refine_iters, n_ordinals, triton)
    cost = torch.where(has, best_cost.to(torch.float64) / COST_SCALE
                       / ev_per_group.clamp_min(1), torch.nan).to(torch.float32)
    # --- aperture test and refinement
    ratio = fit["ratio"]
    fitted = has & (fit["count"] >= 2)
    normal = fitted & (ratio < aperture_ratio)
    n_dir = fit["major"]
    if refine:
        refined = torch.where(fitted[:, None], fit["flow"], full)
        along = fit["normal_speed"][:, None] * n_dir  # the lines' own normal speed
    else:
        refined = full
        along = (refined * n_dir).sum(1, keepdim=True) * n_dir  # F projected on the normal
    return Registration(flow=torch.where(normal[:, None], along, refined), full_flow=full,
                        cost=cost, used_events=ev_per_group, ratio=ratio.to(torch.float32),
                        normal=normal, normal_dir=torch.where(normal[:, None], n_dir, nan2),
                        lines=fit["count"], inliers=inliers)


def _solve_tensor(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
                  max_events: int, max_hypotheses: int, pair_budget: int, line_gate: float,
                  refine_iters: int, n_ordinals: int, triton: bool = False
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, dict[str, Tensor]]:
    """The tensor form of the caps, Eq. 3, the constraint lines and their fit (with
    ``triton``, the caps only: the rest runs in :mod:`evtrack.flow.registration_triton`).

    Returns:
        ``has`` (G,) bool, ``full`` (G, 2) float32 arg-min candidate (NaN without one),
        ``best_cost`` (G,) int64 scaled cost, ``used_events`` (G,), ``inliers`` (G,), and the
        line fit of :func:`_fit_lines`.
    """
    dev = flow.device
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
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
    h_idx, h_group = take(h_idx, 0, h_rank_order), take(h_group, 0, h_rank_order)
    if triton:
        return _solve_triton(c_flow, ev_first, ev_start, ev_per_group, h_idx, h_group,
                             g_count, max_events, max_hypotheses, line_gate, refine_iters)
    hpos = torch.arange(h_idx.numel(), device=dev)
    h_rank = hpos - run_starts(h_group)
    c_event = c_run - take(ev_start, 0, c_group)
    cost = _hypothesis_costs(h_idx, h_group, c_flow, counts, c_start, c_event,
                             ev_per_group, pair_budget)
    # --- arg-min per group, ties to the smallest rank
    combo = (cost << _RANK_BITS) | h_rank
    best = torch.full((g_count,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=dev)
    best.scatter_reduce_(0, h_group, combo, "amin")
    has = best != torch.iinfo(torch.int64).max
    best_cost = best >> _RANK_BITS
    best_rank = best & ((1 << _RANK_BITS) - 1)
    g_first_h = torch.full((g_count,), h_idx.numel(), dtype=torch.int64, device=dev)
    g_first_h.scatter_reduce_(0, h_group, hpos, "amin")
    chosen = h_idx[(g_first_h + best_rank).clamp_max(max(h_idx.numel() - 1, 0))]
    full = torch.where(has[:, None], c_flow[chosen], nan2)
    # --- constraint lines and their robust intersection
    lines = _event_lines(c_group, c_run, c_flow, full, n_ev_total, ev_group, line_gate)
    inliers = torch.bincount(ev_group[lines["agree"]], minlength=g_count)
    fit = _fit_lines(lines, full, g_count, refine_iters)
    return has, full, best_cost, ev_per_group, inliers, fit


def _solve_triton(c_flow: Tensor, ev_first: Tensor, ev_start: Tensor, ev_per_group: Tensor,
                  h_idx: Tensor, h_group: Tensor, g_count: int, max_events: int,
                  max_hypotheses: int, line_gate: float, refine_iters: int
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, dict[str, Tensor]]:
    """:func:`_solve_tensor`'s outputs from the capped, arranged candidates, by the Triton
    kernel (one program per group; no host synchronisation)."""
    from evtrack.flow.registration_triton import solve_groups

    dev = c_flow.device
    h_count = torch.bincount(h_group, minlength=g_count)
    h_first = torch.cumsum(h_count, 0) - h_count
    ev_ptr = torch.cat([ev_first, torch.full((1,), c_flow.shape[0], dtype=torch.int64,
                                             device=dev)])
    res = solve_groups(c_flow, ev_ptr, ev_start, ev_per_group, h_idx, h_first, h_count,
                       max_events, max_hypotheses, COST_SCALE, _Q_MAX, _PARALLEL_EPS,
                       line_gate, _IRLS_DELTA, refine_iters, _RANK_BITS)
    has = h_count > 0
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    full = torch.where(has[:, None], c_flow[res["chosen"].clamp(0, c_flow.shape[0] - 1)],
                       nan2)
    fit = {"flow": res["fit_flow"].to(torch.float32), "ratio": res["ratio"],
           "count": res["lines"], "major": res["major"].to(torch.float32),
           "normal_speed": res["normal_speed"].to(torch.float32)}
    return has, full, res["best_cost"], ev_per_group, res["inliers"], fit


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
    nonpar = cross * cross > _PARALLEL_EPS * _PARALLEL_EPS * norm2_c * norm2_a
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
    delta = _IRLS_DELTA * flow.norm(dim=1).clamp_min(1.0)
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
