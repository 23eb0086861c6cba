"""RoI registration: one flow per region of interest and time window (the paper's Eq. 3).

For a group (RoI, window) with events ``i = 1..n`` and their candidate sets ``M_i``::

    F = argmin_{F' in M} sum_i min_{c in M_i} |F' - F_ic|

with ``|.|`` the **Euclidean** norm of the 2-D difference (px/s): the sum of norms is the
robust "L1-type" registration cost, invariant to image rotation. ``F`` is a medoid-like
candidate: it is one of the candidate flows.

Evaluated batched over many groups, exactly and deterministically:

* distances are rounded to ``1 / COST_SCALE`` px/s and summed in int64, so costs (and thus the
  arg-min) do not depend on summation order, batch composition or device atomics;
* ties go to the hypothesis with the smallest hash (see below);
* caps keep the O(|M|^2) cost bounded: at most ``max_events_per_roi`` events enter the data
  term (those with the smallest hash of their stream index) and at most ``max_hypotheses``
  candidates of those events are tried as ``F'`` (those with the smallest hash of
  (stream index, candidate ordinal)). Hash selection is deterministic, independent of how
  the stream was chunked, and spreads the kept events over the whole window.

Aperture test: with ``u_c`` the unit vectors from ``F`` to the kept candidates (those farther
than ``APERTURE_EPS`` relative), the 2x2 scatter ``S = sum_c u_c u_c^T`` has eigenvalues
``l_min <= l_max``. Candidates of an edge all lie on its constraint line ``n . F = s``, which
passes through ``F``, so ``S`` is rank one; a textured region has several constraint lines
through ``F``. The flow is flagged *normal* when ``l_min / l_max < aperture_ratio``; it is
then reported as the normal flow ``(F . n) n``, with ``n`` the eigenvector of ``l_min``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Registration", "register_groups", "hash32", "COST_SCALE", "APERTURE_EPS",
           "select_smallest"]

COST_SCALE = 16.0
"""Distances are rounded to 1/COST_SCALE px/s before the exact int64 sums."""
APERTURE_EPS = 1e-3
"""Candidates closer to F than this fraction of ``max(|F|, 1 px/s)`` carry no direction."""
_GOLDEN = 2654435761
_RANK_BITS = 20


def hash32(value: Tensor) -> Tensor:
    """A deterministic 32-bit multiplicative hash of int64 values (no overflow)."""
    return ((value & 0x7FFFFFFF) * _GOLDEN) & 0xFFFFFFFF


def select_smallest(group: Tensor, key: Tensor, cap: int) -> Tensor:
    """Per group, which items have one of the ``cap`` smallest keys (ties: earlier item).

    Args:
        group: (M,) int64 group ids >= 0.
        key: (M,) int64 keys in ``[0, 2^32)``.
        cap: how many to keep per group.

    Returns:
        (M,) bool mask of the kept items.
    """
    m = group.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.bool, device=group.device)
    order = torch.sort((group << 32) | key, stable=True).indices
    g_sorted = group[order]
    pos = torch.arange(m, device=group.device)
    first = torch.ones(m, dtype=torch.bool, device=group.device)
    first[1:] = g_sorted[1:] != g_sorted[:-1]
    start = torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
    keep = torch.zeros(m, dtype=torch.bool, device=group.device)
    keep[order] = (pos - start) < cap
    return keep


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
    """

    flow: Tensor
    full_flow: Tensor
    cost: Tensor
    used_events: Tensor
    ratio: Tensor
    normal: Tensor
    normal_dir: Tensor


def _runs(values: Tensor) -> tuple[Tensor, Tensor]:
    """Run ids of consecutive equal values, and the number of runs."""
    m = values.shape[0]
    change = torch.ones(m, dtype=torch.int64, device=values.device)
    change[1:] = (values[1:] != values[:-1]).to(torch.int64)
    rid = torch.cumsum(change, 0) - 1
    return rid, int(rid[-1]) + 1 if m else 0


def register_groups(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, n_groups: int,
                    max_events: int, max_hypotheses: int, aperture_ratio: float,
                    pair_budget: int) -> Registration:
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

    Returns:
        The :class:`Registration` of every group.
    """
    dev = flow.device
    g_count = n_groups
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    out = Registration(flow=nan2.clone(), full_flow=nan2.clone(),
                       cost=torch.full((g_count,), float("nan"), device=dev),
                       used_events=torch.zeros(g_count, dtype=torch.int64, device=dev),
                       ratio=torch.ones(g_count, device=dev),
                       normal=torch.zeros(g_count, dtype=torch.bool, device=dev),
                       normal_dir=nan2.clone())
    if group.numel() == 0 or g_count == 0:
        return out
    # --- data term: cap the events per group by the hash of their stream index
    run, n_runs = _runs(seq)
    run_first = torch.zeros(n_runs, dtype=torch.int64, device=dev)
    run_first.scatter_reduce_(0, run, torch.arange(seq.numel(), device=dev), "amin",
                              include_self=False)
    run_group = group[run_first]
    run_keep = select_smallest(run_group, hash32(seq[run_first]), max_events)
    keep = run_keep[run]
    c_group, c_seq, c_ord, c_flow = group[keep], seq[keep], ordinal[keep], flow[keep]
    # gather kept candidates by group (stable: events stay in stream order)
    order = torch.sort(c_group, stable=True).indices
    c_group, c_seq, c_ord, c_flow = c_group[order], c_seq[order], c_ord[order], c_flow[order]
    c_run, n_ev_total = _runs(c_seq)  # kept events, contiguous per group
    m = c_group.numel()
    counts = torch.bincount(c_group, minlength=g_count)
    c_start = torch.cumsum(counts, 0) - counts
    ev_first = torch.zeros(n_ev_total, dtype=torch.int64, device=dev)
    ev_first.scatter_reduce_(0, c_run, torch.arange(m, device=dev), "amin", include_self=False)
    ev_group = c_group[ev_first]
    ev_per_group = torch.bincount(ev_group, minlength=g_count)
    ev_start = torch.cumsum(ev_per_group, 0) - ev_per_group
    c_local_ev = c_run - ev_start[c_group]
    out.used_events = ev_per_group
    # --- hypotheses: cap by candidate hash; rank within group gives the tie-break order
    n_ord = int(ordinal.max()) + 1
    h_key = hash32(c_seq * n_ord + c_ord)
    h_keep = select_smallest(c_group, h_key, max_hypotheses)
    h_idx = torch.nonzero(h_keep).reshape(-1)
    h_group = c_group[h_idx]
    h_rank_order = torch.sort((h_group << 32) | h_key[h_idx], stable=True).indices
    h_idx, h_group = h_idx[h_rank_order], h_group[h_rank_order]
    h_first = torch.ones_like(h_group, dtype=torch.bool)
    h_first[1:] = h_group[1:] != h_group[:-1]
    hpos = torch.arange(h_idx.numel(), device=dev)
    h_rank = hpos - torch.cummax(torch.where(h_first, hpos, torch.zeros_like(hpos)), 0).values
    cost = _hypothesis_costs(h_idx, h_group, c_flow, counts, c_start, c_local_ev,
                             ev_per_group, ev_start, pair_budget)
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
    out.full_flow = full
    out.cost = torch.where(has, best_cost.to(torch.float64) / COST_SCALE
                           / ev_per_group.clamp_min(1), torch.nan).to(torch.float32)
    # --- aperture test on the kept candidates
    diff = c_flow - full[c_group]
    dist = diff.norm(dim=1)
    scale = full[c_group].norm(dim=1).clamp_min(1.0)
    informative = dist > APERTURE_EPS * scale
    u = torch.where(informative[:, None], diff / dist.clamp_min(1e-30)[:, None],
                    torch.zeros_like(diff)).to(torch.float64)
    s = torch.zeros(g_count, 3, dtype=torch.float64, device=dev)
    s.index_add_(0, c_group, torch.stack([u[:, 0] * u[:, 0], u[:, 0] * u[:, 1],
                                          u[:, 1] * u[:, 1]], 1))
    a, b, c = s[:, 0], s[:, 1], s[:, 2]
    half_tr = 0.5 * (a + c)
    rad = torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    l_max, l_min = half_tr + rad, half_tr - rad
    ratio = torch.where(l_max > 0, (l_min / l_max.clamp_min(1e-300)).clamp_min(0.0),
                        torch.ones_like(l_max))
    normal = has & (ratio < aperture_ratio)
    theta = 0.5 * torch.atan2(2 * b, a - c) + 0.5 * torch.pi  # minor axis
    n_dir = torch.stack([torch.cos(theta), torch.sin(theta)], 1).to(torch.float32)
    proj = (full * n_dir).sum(1, keepdim=True) * n_dir
    out.ratio = ratio.to(torch.float32)
    out.normal = normal
    out.normal_dir = torch.where(normal[:, None], n_dir, nan2)
    out.flow = torch.where(normal[:, None], proj, full)
    return out


def _hypothesis_costs(h_idx: Tensor, h_group: Tensor, c_flow: Tensor, counts: Tensor,
                      c_start: Tensor, c_local_ev: Tensor, ev_per_group: Tensor,
                      ev_start: Tensor, pair_budget: int) -> Tensor:
    """Exact int64 cost ``sum_i min_c round(|F_h - F_ic| * COST_SCALE)`` per hypothesis."""
    dev = c_flow.device
    n_h = h_idx.numel()
    cost = torch.zeros(n_h, dtype=torch.int64, device=dev)
    if n_h == 0:
        return cost
    per_h = counts[h_group]
    cum = torch.cumsum(per_h, 0)
    cum_host = cum.cpu()
    start = 0
    while start < n_h:
        # largest batch of hypotheses within the pair budget (at least one)
        base = int(cum_host[start - 1]) if start else 0
        stop = int(torch.searchsorted(cum_host, torch.tensor([base + pair_budget]),
                                      right=True)[0])
        stop = min(n_h, max(stop, start + 1))
        hb = torch.arange(start, stop, device=dev)
        cnt = per_h[start:stop]
        pair_h = torch.repeat_interleave(hb - start, cnt)
        offs = torch.cumsum(cnt, 0) - cnt
        within = torch.arange(pair_h.numel(), device=dev) - offs[pair_h]
        g = h_group[start:stop]
        pair_c = c_start[g][pair_h] + within
        d = (c_flow[h_idx[start:stop]][pair_h] - c_flow[pair_c]).norm(dim=1)
        q = torch.round(d.to(torch.float64) * COST_SCALE).to(torch.int64)
        e_cnt = ev_per_group[g]
        e_base = torch.cumsum(e_cnt, 0) - e_cnt
        slots = torch.full((int(e_cnt.sum()),), torch.iinfo(torch.int64).max,
                           dtype=torch.int64, device=dev)
        slots.scatter_reduce_(0, e_base[pair_h] + c_local_ev[pair_c], q, "amin")
        slot_h = torch.repeat_interleave(torch.arange(stop - start, device=dev), e_cnt)
        part = torch.zeros(stop - start, dtype=torch.int64, device=dev)
        part.index_add_(0, slot_h, slots)
        cost[start:stop] = part
        start = stop
    return cost
