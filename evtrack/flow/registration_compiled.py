"""Compiled CPU form of :func:`evtrack.flow.registration.register_groups` (numba).

The tensor registration is a chain of sorts, scatters and masks over all candidates of a
batch; on a CPU its cost is mostly the passes and the per-call overhead, not arithmetic
(the tracker registers a few thousand events every few milliseconds). Here the same rule
runs group by group in compiled loops:

1. :func:`_arrange_kernel`: the data-term cap (per group, the ``max_events`` events with the
   smallest hash of their stream index, ties to the earlier event), the kept candidates laid
   out by group with events in stream order, and the hypotheses (per group, the
   ``max_hypotheses`` candidates with the smallest hash of (stream index, ordinal), ties to
   the earlier candidate) in rank order;
2. :func:`_solve_kernel`, in parallel over the groups: the exact integer Eq. 3 cost of the
   hypotheses (the one nearest the median first, then the others in rank order), each
   abandoned once its partial sum shows it cannot win (the arg-min, ties to the smallest
   rank, is that of the full evaluation), then the events' constraint lines, the inlier
   count and the IRLS intersection of the lines.

   The hypotheses after the first are evaluated side by side in lanes of up to
   ``_MAX_LANES`` (:func:`_lane_costs`): one pass over the group's candidates updates every
   lane's per-event minimum, a loop over the lanes that the compiler turns into SIMD
   instructions, and the rounding of those minima is branch-free per lane. A lane is
   abandoned against the bound of the best cost when its block starts, which is never below
   the bound the one-by-one order would give it, so the arg-min is unchanged; an abandoned
   lane leaves the SIMD loop at once (the active lanes stay packed). The events'
   nearest candidate to ``F`` is found from the smallest float32 squared distance, rounding
   only the candidates that can round to the same value (:func:`_nearest`).

Everything up to the lines is integer or exactly specified float arithmetic (float32 squared
distances with separate IEEE operations, :func:`~evtrack.flow.registration.rounded_distance`,
float64 comparisons), so ``full_flow``, ``cost``, ``used_events``, ``inliers`` and ``lines``
equal the tensor path's bit for bit. The refined ``flow``, ``ratio`` and ``normal_dir`` go
through ``sqrt``, ``atan2``, ``cos`` and ``sin`` and a summation order of their own; they agree
with the tensor path to float rounding (``tests/flow/test_flow_backends.py`` pins both).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.compiled import (
    _filled,
    _njit,
    _prange,
    _rounded_distance,
    numba,
    torch_thread_count,
)
from evtrack.flow.registration import _IRLS_DELTA, _PARALLEL_EPS, _Q_MAX, COST_SCALE

__all__ = ["register_closed_groups", "register_groups_compiled"]

_GOLDEN = 2654435761
_NO_BOUND = np.int64(1) << 62
_POS_BITS = 31  # (hash << 31) | position: a hash < 2^32 and a position < 2^31 fit in int64
_POS_MASK = (1 << _POS_BITS) - 1
_MAX_LANES = 48
"""Most hypotheses evaluated side by side in one block (the flow's default caps try 48)."""


@_njit()
def _hash32(value):
    return ((value & 0x7FFFFFFF) * _GOLDEN) & 0xFFFFFFFF


@_njit()
def _insert_smallest(buf, filled, cap, key):
    """Add ``key`` to ``buf[:filled]`` (ascending, at most ``cap`` keys), keeping the ``cap``
    smallest; returns the new fill. Keys are distinct (they carry their position)."""
    if filled == cap:
        if key >= buf[cap - 1]:
            return filled
        j = cap - 1
    else:
        j = filled
        filled += 1
    while j > 0 and buf[j - 1] > key:
        buf[j] = buf[j - 1]
        j -= 1
    buf[j] = key
    return filled


@_njit()
def _arrange_kernel(group, seq, ordinal, flow, n_groups, max_events, max_hypotheses, n_ordinals):
    """Step 1 of the module docstring. Candidates of one event are consecutive in the input
    and events come in stream order. One thread: its loops are short per group, and in
    parallel loops the thread pool's start cost more than they saved (a tracker's call, 330
    groups of 35 candidates: 0.32-0.37 ms on one thread, 0.38-0.43 ms on two; a 10k-event
    call of the fast-object flow, 53 groups of 190: 0.48-0.51 against 0.54-0.56 ms).

    Both selections (the events of the data-term cap, the hypotheses) keep the smallest
    ``(hash << 31) | position`` keys by insertion into a short sorted buffer: the same keys
    as a sort (they are distinct), without sorting the rest; the buffers are allocated once
    per call, not once per group (~80 ns each)."""
    m = group.shape[0]
    # events (runs of equal stream index)
    n_runs = 0
    for i in range(m):
        if i == 0 or seq[i] != seq[i - 1]:
            n_runs += 1
    run_first = np.empty(n_runs + 1, np.int64)
    r = 0
    for i in range(m):
        if i == 0 or seq[i] != seq[i - 1]:
            run_first[r] = i
            r += 1
    run_first[n_runs] = m
    # the events of each group, in stream order
    runs_per_group = _filled(n_groups, 0, np.int64)
    for r in range(n_runs):
        runs_per_group[group[run_first[r]]] += 1
    group_run_start = _filled(n_groups + 1, 0, np.int64)
    for g in range(n_groups):
        group_run_start[g + 1] = group_run_start[g] + runs_per_group[g]
    fill = np.empty(n_groups, np.int64)
    for g in range(n_groups):
        fill[g] = group_run_start[g]
    runs_by_group = np.empty(n_runs, np.int64)
    for r in range(n_runs):
        g = group[run_first[r]]
        runs_by_group[fill[g]] = r
        fill[g] += 1
    # data-term cap (the max_events smallest keys of each group's events), then the counts
    keep = _filled(n_runs, True, np.bool_)
    ev_per_group = _filled(n_groups, 0, np.int64)
    counts = _filled(n_groups, 0, np.int64)
    kept = np.empty(max(max_events, 1), np.int64)  # every capped group's selection, in turn
    for g in range(n_groups):
        r0, r1 = group_run_start[g], group_run_start[g + 1]
        k = r1 - r0
        if k > max_events:
            filled = 0
            for j in range(k):
                key = (_hash32(seq[run_first[runs_by_group[r0 + j]]]) << _POS_BITS) | j
                filled = _insert_smallest(kept, filled, max_events, key)
            for j in range(r0, r1):
                keep[runs_by_group[j]] = False
            for j in range(max_events):
                keep[runs_by_group[r0 + (kept[j] & _POS_MASK)]] = True
        for j in range(r0, r1):
            rr = runs_by_group[j]
            if keep[rr]:
                ev_per_group[g] += 1
                counts[g] += run_first[rr + 1] - run_first[rr]
    c_start = _filled(n_groups, 0, np.int64)
    for g in range(1, n_groups):
        c_start[g] = c_start[g - 1] + counts[g - 1]
    n_kept = c_start[n_groups - 1] + counts[n_groups - 1] if n_groups else 0
    h_count = np.empty(n_groups, np.int64)
    for g in range(n_groups):
        h_count[g] = min(counts[g], max_hypotheses)
    h_start = _filled(n_groups, 0, np.int64)
    for g in range(1, n_groups):
        h_start[g] = h_start[g - 1] + h_count[g - 1]
    n_h = h_start[n_groups - 1] + h_count[n_groups - 1] if n_groups else 0
    c_x = np.empty(n_kept, np.float32)
    c_y = np.empty(n_kept, np.float32)
    c_event = np.empty(n_kept, np.int64)
    h_cand = np.empty(n_h, np.int64)
    # the kept candidates by group, events in stream order; the hypotheses: per group the
    # smallest (hash, position), in that order (the rank order)
    first = np.empty(max(max_hypotheses, 1), np.int64)  # every group's hypotheses, in turn
    for g in range(n_groups):
        h = h_count[g]
        if h == 0:
            continue
        c0 = c_start[g]
        c = c0
        e = 0
        filled = 0
        for j in range(group_run_start[g], group_run_start[g + 1]):
            rr = runs_by_group[j]
            if not keep[rr]:
                continue
            for i in range(run_first[rr], run_first[rr + 1]):
                c_x[c] = flow[i, 0]
                c_y[c] = flow[i, 1]
                c_event[c] = e
                key = (_hash32(seq[i] * n_ordinals + ordinal[i]) << _POS_BITS) | (c - c0)
                filled = _insert_smallest(first, filled, h, key)
                c += 1
            e += 1
        for j in range(h):
            h_cand[h_start[g] + j] = c0 + (first[j] & _POS_MASK)
    return c_x, c_y, c_event, counts, c_start, ev_per_group, h_cand, h_start, h_count



@_njit()
def _hypothesis_cost(hx, hy, c_x, c_y, c_event, c0, c1, bound, cost_scale, q_max):
    """``sum_events min_c rounded_distance(|h - c|^2)`` over candidates ``c0..c1`` (events
    contiguous), or any value ``>= bound`` as soon as the partial sum reaches ``bound`` (the
    terms are >= 0, so such a hypothesis cannot win)."""
    total = np.int64(0)
    best = np.float32(np.inf)
    e = c_event[c0]
    for c in range(c0, c1):
        if c_event[c] != e:
            total += _rounded_distance(best, cost_scale, q_max)
            if total >= bound:
                return total
            e = c_event[c]
            best = np.float32(np.inf)
        dx = hx - c_x[c]
        dy = hy - c_y[c]
        d2 = dx * dx
        d2 = d2 + dy * dy
        if d2 < best:
            best = d2
    return total + _rounded_distance(best, cost_scale, q_max)


@_njit()
def _rounded_lanes(mins, out, n_lanes, cost_scale, q_max):
    """``out[l] = _rounded_distance(mins[l])`` for ``l < n_lanes``, without branches (the same
    exact rule: a ``sqrt`` guess corrected by exact float64 squares, ties to even)."""
    cs2 = cost_scale * cost_scale
    qm2 = q_max * q_max
    for lane in range(n_lanes):
        dd = np.float64(mins[lane]) * cs2
        capped = dd >= qm2
        dd = 0.0 if capped else dd
        n = np.floor(np.sqrt(dd) + 0.5)
        up = (n + 0.5) * (n + 0.5)
        down = (n - 0.5) * (n - 0.5)
        n = n + (1.0 if dd > up else 0.0) - (1.0 if (dd < down and n > 0.0) else 0.0)
        up = (n + 0.5) * (n + 0.5)
        down = (n - 0.5) * (n - 0.5)
        odd = (np.int64(n) & 1) == 1
        n = n + (1.0 if (odd and dd == up) else 0.0) - (1.0 if (odd and dd == down) else 0.0)
        out[lane] = np.int64(q_max) if capped else np.int64(n)


@_njit()
def _lane_costs(hx, hy, n_lanes, c_x, c_y, ev_ptr, n_ev, bound, total, mins, q,
                cost_scale, q_max, act, ax, ay, a_bound, a_total):
    """:func:`_hypothesis_cost` of ``n_lanes`` hypotheses at once.

    Events ``e < n_ev`` hold the candidates ``ev_ptr[e]..ev_ptr[e + 1]``. On return
    ``total[l]`` is lane ``l``'s exact cost, or a value ``>= bound[l]``: a lane whose partial
    sum reaches its bound is dropped from the lanes still evaluated (the active lanes are
    kept packed at the front, so the SIMD loop runs over those only), and the evaluation
    stops once every lane has reached its bound. ``act, ax, ay, a_bound, a_total``: scratch of
    at least ``n_lanes`` (the original lane of each active slot, its hypothesis, bound and
    partial sum)."""
    for lane in range(n_lanes):
        act[lane], ax[lane], ay[lane] = lane, hx[lane], hy[lane]
        a_bound[lane], a_total[lane] = bound[lane], 0
    n_act = n_lanes
    for e in range(n_ev):
        for j in range(n_act):
            mins[j] = np.float32(np.inf)
        for c in range(ev_ptr[e], ev_ptr[e + 1]):
            cx = c_x[c]
            cy = c_y[c]
            for j in range(n_act):  # SIMD over the active lanes
                dx = ax[j] - cx
                dy = ay[j] - cy
                d2 = dx * dx
                d2 = d2 + dy * dy
                mins[j] = d2 if d2 < mins[j] else mins[j]
        _rounded_lanes(mins, q, n_act, cost_scale, q_max)
        done = 0
        for j in range(n_act):
            a_total[j] += q[j]
            done += 1 if a_total[j] >= a_bound[j] else 0
        if done:  # drop the lanes that reached their bound (their totals are final)
            k = 0
            for j in range(n_act):
                if a_total[j] >= a_bound[j]:
                    total[act[j]] = a_total[j]
                else:
                    act[k], ax[k], ay[k] = act[j], ax[j], ay[j]
                    a_bound[k], a_total[k] = a_bound[j], a_total[j]
                    k += 1
            n_act = k
            if n_act == 0:
                return
    for j in range(n_act):
        total[act[j]] = a_total[j]


@_njit()
def _not_parallel(c_x, c_y, i, ax, ay, a2, eps2):
    """Whether candidate ``b = c[i]`` is not parallel to ``a``: ``cross(b, a)^2 > eps2 |b|^2
    |a|^2`` in float64 (products of float32 values are exact there)."""
    bx, by = np.float64(c_x[i]), np.float64(c_y[i])
    cross = bx * ay - by * ax
    return cross * cross > eps2 * (bx * bx + by * by) * a2


@_njit()
def _filtered_distance2(c_x, c_y, i, fx, fy, nonparallel_to_a, ax, ay, a2, eps2):
    """Candidate ``i``'s float32 squared distance to ``(fx, fy)`` (separate IEEE
    operations), or -1 when ``nonparallel_to_a`` and it is parallel to ``a``."""
    if nonparallel_to_a and not _not_parallel(c_x, c_y, i, ax, ay, a2, eps2):
        return np.float32(-1.0)
    dx = c_x[i] - fx
    dy = c_y[i] - fy
    d2 = dx * dx
    return d2 + dy * dy


@_njit()
def _nearest(c_x, c_y, i0, i1, fx, fy, cost_scale, q_max, nonparallel_to_a=False, ax=0.0,
             ay=0.0, eps2=0.0):
    """The first candidate of ``i0..i1`` with the smallest rounded distance to ``(fx, fy)``,
    and its float32 squared distance; ``(-1, nan)`` if there is none. With
    ``nonparallel_to_a``, only the candidates not parallel to ``a = (ax, ay)`` count.

    The smallest squared distance gives that rounded distance ``q`` (the rounding is
    monotone); only candidates with ``d2 * COST_SCALE^2 <= (q + 0.5)^2`` can round to it too,
    and only those are rounded."""
    a2 = ax * ax + ay * ay
    best = np.float32(np.inf)
    found = False
    for i in range(i0, i1):
        d2 = _filtered_distance2(c_x, c_y, i, fx, fy, nonparallel_to_a, ax, ay, a2, eps2)
        if d2 < 0:
            continue
        found = True
        if d2 < best:
            best = d2
    if not found:
        return -1, np.float32(np.nan)
    q_min = _rounded_distance(best, cost_scale, q_max)
    edge = (np.float64(q_min) + 0.5) * (np.float64(q_min) + 0.5)
    cs2 = cost_scale * cost_scale
    for i in range(i0, i1):
        d2 = _filtered_distance2(c_x, c_y, i, fx, fy, nonparallel_to_a, ax, ay, a2, eps2)
        if d2 < 0:
            continue
        if q_min < q_max and np.float64(d2) * cs2 > edge:
            continue  # rounds above q_min
        if _rounded_distance(d2, cost_scale, q_max) == q_min:
            return i, d2
    return -1, np.float32(np.nan)  # not reached: the smallest d2 rounds to q_min


@_njit()
def _median_small(values, n, scratch):
    """``np.median(values[:n])`` (n >= 1) as numba computes it, for the few hypotheses of
    a group: sorted by insertion into ``scratch`` (at least ``n`` long) instead of the copy
    and selection ``np.median`` allocates at every call (~240 ns a call; the solve of the
    cracker box's groups ran ~9 % faster on 2 cores of an AMD EPYC, 2026-12-02)."""
    for i in range(n):
        v = values[i]
        j = i
        while j > 0 and scratch[j - 1] > v:
            scratch[j] = scratch[j - 1]
            j -= 1
        scratch[j] = v
    half = n >> 1
    if n & 1 == 0:
        return (scratch[half - 1] + scratch[half]) / 2
    return scratch[half] / 1  # the same float64 as the even case's


@_njit()
def _solve_group(g, h_cand, h_start, h_count, c_x, c_y, c_event, counts, c_start, ev_per_group,
                 cost_scale, q_max, gate2, eps2, irls_delta, refine_iters, full, has, best_cost,
                 inliers, lines, fit_flow, ratio, major, normal_speed, hx, hy, ev_ptr, lx, ly,
                 l_rank, l_bound, l_total, l_min, l_q, s_act, s_x, s_y, s_bound, s_total, ln_x,
                 ln_y, ln_s):
    """Group ``g`` of :func:`_solve_kernel`, its results written into the outputs; the
    arrays after ``normal_speed`` are scratch of at least the group's hypotheses (``ev_ptr``:
    its events + 1; ``ln_*``: its events)."""
    major[g, 0] = 1.0  # the tensor path's direction without lines (theta = 0)
    if h_count[g] == 0:
        return
    # arg-min of (cost, rank). The hypothesis nearest the median flow goes first (it is
    # usually the winner or close, so the bound cuts the others short); then the others
    # in rank order. A tie goes to the smaller rank.
    c0, c1 = c_start[g], c_start[g] + counts[g]
    h0, nh = h_start[g], h_count[g]
    for j in range(nh):
        hx[j], hy[j] = c_x[h_cand[h0 + j]], c_y[h_cand[h0 + j]]
    # (l_min: scratch here, the lanes' minima below)
    mx, my = _median_small(hx, nh, l_min), _median_small(hy, nh, l_min)
    first = 0
    for j in range(1, nh):
        if abs(hx[j] - mx) + abs(hy[j] - my) < abs(hx[first] - mx) + abs(hy[first] - my):
            first = j
    g_best = _hypothesis_cost(hx[first], hy[first], c_x, c_y, c_event, c0, c1, _NO_BOUND,
                              cost_scale, q_max)
    best_rank = first
    # the group's events: candidates ev_ptr[e]..ev_ptr[e + 1]
    n_ev = ev_per_group[g]
    e = 0
    for c in range(c0, c1):
        if c > c0 and c_event[c] != c_event[c - 1]:
            e += 1
            ev_ptr[e] = c
    ev_ptr[0], ev_ptr[n_ev] = c0, c1
    # the others in rank order, in blocks of lanes of about equal size. A lane's bound
    # is taken when its block starts: the best only improves during the block, so that
    # bound is never below the one-by-one bound and a lane abandoned against it could not
    # have won; the lanes are then compared in rank order with the one-by-one rule.
    n_blocks = (nh - 2 + _MAX_LANES) // _MAX_LANES
    per_block = (nh - 2 + n_blocks) // n_blocks if n_blocks else 1
    j = 0
    while j < nh:
        n_lanes = 0
        while j < nh and n_lanes < per_block:
            if j != first:
                lx[n_lanes], ly[n_lanes], l_rank[n_lanes] = hx[j], hy[j], j
                # an earlier rank also wins a tie: it must reach best + 1 to lose
                l_bound[n_lanes] = g_best + 1 if j < best_rank else g_best
                n_lanes += 1
            j += 1
        if n_lanes == 0:
            continue
        _lane_costs(lx, ly, n_lanes, c_x, c_y, ev_ptr, n_ev, l_bound, l_total, l_min,
                    l_q, cost_scale, q_max, s_act, s_x, s_y, s_bound, s_total)
        for lane in range(n_lanes):
            rank = l_rank[lane]
            bound = g_best + 1 if rank < best_rank else g_best
            if l_total[lane] < l_bound[lane] and l_total[lane] < bound:
                g_best, best_rank = l_total[lane], rank
    chosen = h_cand[h0 + best_rank]
    has[g] = True
    best_cost[g] = g_best
    fx, fy = c_x[chosen], c_y[chosen]
    full[g, 0], full[g, 1] = fx, fy
    f2 = fx * fx
    f2 = f2 + fy * fy
    lim2 = gate2 * max(np.float64(f2), 1.0)
    # one constraint line per kept event that agrees with F
    n_lines = 0
    for e in range(n_ev):
        e0, e1 = ev_ptr[e], ev_ptr[e + 1]
        i1, d2_1 = _nearest(c_x, c_y, e0, e1, fx, fy, cost_scale, q_max)
        if np.float64(d2_1) > lim2:
            continue  # disagrees with F: neither an inlier nor a line
        inliers[g] += 1
        ax, ay = np.float64(c_x[i1]), np.float64(c_y[i1])
        # the nearest not parallel to the first (the first itself is parallel)
        i2, _ = _nearest(c_x, c_y, e0, e1, fx, fy, cost_scale, q_max, True, ax, ay, eps2)
        if i2 >= 0:
            tx = ax - np.float64(c_x[i2])
            ty = ay - np.float64(c_y[i2])
            length = max(np.sqrt(tx * tx + ty * ty), 1e-30)
            nx, ny = -ty / length, tx / length
            s = nx * ax + ny * ay
            if s < 0:
                nx, ny, s = -nx, -ny, -s
            ln_x[n_lines], ln_y[n_lines], ln_s[n_lines] = nx, ny, s
            n_lines += 1
    lines[g] = n_lines
    # IRLS intersection of the lines, from the Eq. 3 solution
    vx, vy = np.float64(fx), np.float64(fy)
    delta = irls_delta * max(np.sqrt(vx * vx + vy * vy), 1.0)
    for _ in range(max(1, refine_iters)):
        a = b = cc = r0 = r1 = 0.0
        for i in range(n_lines):
            nx, ny, s = ln_x[i], ln_y[i], ln_s[i]
            w = 1.0 / max(abs(nx * vx + ny * vy - s), delta)
            a += w * (nx * nx)
            b += w * (nx * ny)
            cc += w * (ny * ny)
            r0 += (w * s) * nx
            r1 += (w * s) * ny
        half_tr = 0.5 * (a + cc)
        rad = np.sqrt((0.5 * (a - cc)) ** 2 + b * b)
        l_max, l_min = half_tr + rad, half_tr - rad
        ratio[g] = max(l_min / max(l_max, 1e-300), 0.0) if l_max > 0 else 1.0
        theta = 0.5 * np.arctan2(2 * b, a - cc)
        major[g, 0], major[g, 1] = np.cos(theta), np.sin(theta)
        normal_speed[g] = (major[g, 0] * r0 + major[g, 1] * r1) / max(l_max, 1e-300)
        det = a * cc - b * b
        if n_lines >= 2 and det > 1e-12 * max(l_max, 1e-300) ** 2:
            vx = (cc * r0 - b * r1) / det
            vy = (a * r1 - b * r0) / det
    fit_flow[g, 0], fit_flow[g, 1] = vx, vy


@_njit(parallel=True)
def _solve_kernel(h_cand, h_start, h_count, c_x, c_y, c_event, counts, c_start,
                  ev_per_group, cost_scale, q_max, parallel_eps, line_gate, irls_delta,
                  refine_iters, threads):
    """Step 2 of the module docstring, in parallel over the groups: a few tasks per thread
    (``threads``: numba's thread count), each a run of consecutive groups with scratch arrays
    of its own (allocated once per task, not a dozen times per group).

    Each hypothesis is evaluated only until its partial cost shows it cannot beat the best so
    far (a later rank must be strictly cheaper, an earlier one at most as costly), so the
    arg-min and its cost are those of the full evaluation.
    """
    n_groups = counts.shape[0]
    full = _filled((n_groups, 2), np.nan, np.float32)
    has = _filled(n_groups, False, np.bool_)
    best_cost = _filled(n_groups, 0, np.int64)
    inliers = _filled(n_groups, 0, np.int64)
    lines = _filled(n_groups, 0, np.int64)
    fit_flow = _filled((n_groups, 2), 0.0, np.float64)
    ratio = _filled(n_groups, 1.0, np.float64)
    major = _filled((n_groups, 2), 0.0, np.float64)
    normal_speed = _filled(n_groups, 0.0, np.float64)
    gate2 = line_gate * line_gate
    eps2 = parallel_eps * parallel_eps
    n_tasks = min(n_groups, 4 * max(threads, 1))
    for task in _prange(n_tasks):
        g0, g1 = task * n_groups // n_tasks, (task + 1) * n_groups // n_tasks
        max_h, max_ev = 1, 1
        for g in range(g0, g1):
            max_h = max(max_h, h_count[g])
            max_ev = max(max_ev, ev_per_group[g])
        hx, hy = np.empty(max_h, np.float32), np.empty(max_h, np.float32)
        ev_ptr = np.empty(max_ev + 1, np.int64)
        lx, ly = np.empty(max_h, np.float32), np.empty(max_h, np.float32)
        l_rank, l_bound = np.empty(max_h, np.int64), np.empty(max_h, np.int64)
        l_total, l_min = np.empty(max_h, np.int64), np.empty(max_h, np.float32)
        l_q, s_act = np.empty(max_h, np.int64), np.empty(max_h, np.int64)
        s_x, s_y = np.empty(max_h, np.float32), np.empty(max_h, np.float32)
        s_bound, s_total = np.empty(max_h, np.int64), np.empty(max_h, np.int64)
        ln_x, ln_y = np.empty(max_ev, np.float64), np.empty(max_ev, np.float64)
        ln_s = np.empty(max_ev, np.float64)
        for g in range(g0, g1):
            _solve_group(g, h_cand, h_start, h_count, c_x, c_y, c_event, counts, c_start,
                         ev_per_group, cost_scale, q_max, gate2, eps2, irls_delta,
                         refine_iters, full, has, best_cost, inliers, lines, fit_flow, ratio,
                         major, normal_speed, hx, hy, ev_ptr, lx, ly, l_rank, l_bound,
                         l_total, l_min, l_q, s_act, s_x, s_y, s_bound, s_total, ln_x, ln_y,
                         ln_s)
    return full, has, best_cost, inliers, lines, fit_flow, ratio, major, normal_speed


@_njit()
def _report_rows(keys, support, n_events, has, full, best_cost, used_events, inliers, lines,
                 fit_flow, ratio, major, normal_speed, n_roi, window_us, centres, cost_scale,
                 aperture_ratio, min_support, min_inlier_fraction):
    """The reported rows of registered groups (CPU, compiled): what
    :func:`~evtrack.flow.registration.register_groups` (with ``refine``) makes of the compiled
    registration's outputs, the report test of ``TripletFlow._finalise`` and the rows of
    ``TripletFlow._rows``, in one pass and with the same float32 / float64 operations.
    ``centres``: (R, 2) float32 RoI centres; ``n_roi`` RoIs per window.

    Returns ``reported`` (G,) and the rows' ``xy, t, flow, support, cost, normal, normal_dir,
    full_flow, n_events, roi, window``."""
    n_groups = keys.shape[0]
    reported = np.empty(n_groups, np.bool_)
    n_rows = 0
    for g in range(n_groups):
        agree = np.float64(inliers[g]) >= min_inlier_fraction * np.float64(used_events[g])
        reported[g] = support[g] >= min_support and not np.isnan(full[g, 0]) and agree
        n_rows += reported[g]
    xy = np.empty((n_rows, 2), np.float32)
    t = np.empty(n_rows, np.int64)
    flow = np.empty((n_rows, 2), np.float32)
    sup = np.empty(n_rows, np.int64)
    cost = np.empty(n_rows, np.float32)
    normal = np.empty(n_rows, np.bool_)
    normal_dir = np.empty((n_rows, 2), np.float32)
    full_flow = np.empty((n_rows, 2), np.float32)
    n_ev = np.empty(n_rows, np.int64)
    roi = np.empty(n_rows, np.int64)
    window = np.empty(n_rows, np.int64)
    r = 0
    for g in range(n_groups):
        if not reported[g]:
            continue
        w = keys[g] // n_roi
        roi[r] = keys[g] - w * n_roi
        window[r] = w
        xy[r, 0], xy[r, 1] = centres[roi[r], 0], centres[roi[r], 1]
        t[r] = w * window_us + window_us // 2
        sup[r] = support[g]
        n_ev[r] = n_events[g]
        full_flow[r, 0], full_flow[r, 1] = full[g, 0], full[g, 1]
        cost[r] = (np.float32(np.float64(best_cost[g]) / cost_scale
                              / np.float64(max(used_events[g], 1))) if has[g] else np.nan)
        fitted = has[g] and lines[g] >= 2
        normal[r] = fitted and ratio[g] < aperture_ratio
        nx, ny = np.float32(major[g, 0]), np.float32(major[g, 1])
        if normal[r]:
            speed = np.float32(normal_speed[g])
            flow[r, 0], flow[r, 1] = speed * nx, speed * ny
            normal_dir[r, 0], normal_dir[r, 1] = nx, ny
        else:
            if fitted:
                flow[r, 0], flow[r, 1] = np.float32(fit_flow[g, 0]), np.float32(fit_flow[g, 1])
            else:
                flow[r, 0], flow[r, 1] = full[g, 0], full[g, 1]
            normal_dir[r, 0] = normal_dir[r, 1] = np.nan
        r += 1
    return reported, xy, t, flow, sup, cost, normal, normal_dir, full_flow, n_ev, roi, window


@_njit()
def _group_positions(keys, gkey, slack, floor):
    """Position of each ``gkey`` in the sorted, distinct ``keys`` (every value occurs there):
    through a table over the keys' range when it spans at most ``slack * count + floor``,
    else by binary search."""
    n_k, m = keys.shape[0], gkey.shape[0]
    out = np.empty(m, np.int64)
    if n_k == 0 or m == 0:
        return out
    lo = keys[0]
    span = keys[n_k - 1] - lo + 1
    if span > slack * (n_k + m) + floor:
        for i in range(m):
            out[i] = np.searchsorted(keys, gkey[i])
        return out
    table = np.empty(span, np.int64)
    for j in range(n_k):
        table[keys[j] - lo] = j
    for i in range(m):
        out[i] = table[gkey[i] - lo]
    return out


@_njit()
def _register_kernel(group, seq, ordinal, flow, n_groups, max_events, max_hypotheses,
                     n_ordinals, cost_scale, q_max, parallel_eps, line_gate, irls_delta,
                     refine_iters, threads):
    """Steps 1 and 2 of the module docstring: ``(used events per group,)`` + the outputs of
    :func:`_solve_kernel`."""
    (c_x, c_y, c_event, counts, c_start, ev_per_group, h_cand, h_start,
     h_count) = _arrange_kernel(group, seq, ordinal, flow, n_groups, max_events,
                                max_hypotheses, n_ordinals)
    return (ev_per_group,) + _solve_kernel(h_cand, h_start, h_count, c_x, c_y, c_event,
                                           counts, c_start, ev_per_group, cost_scale, q_max,
                                           parallel_eps, line_gate, irls_delta, refine_iters,
                                           threads)


@_njit()
def _register_closed_kernel(keys, gkey, seq, ordinal, flow, support, n_events, centres, n_roi,
                            window_us, max_events, max_hypotheses, n_ordinals, line_gate,
                            refine_iters, aperture_ratio, min_support, min_inlier_fraction,
                            cost_scale, q_max, parallel_eps, irls_delta, slack, floor,
                            threads):
    group = _group_positions(keys, gkey, slack, floor)
    (ev_per_group, full, has, best_cost, inliers, lines, fit_flow, ratio, major,
     normal_speed) = _register_kernel(group, seq, ordinal, flow, keys.shape[0], max_events,
                                      max_hypotheses, n_ordinals, cost_scale, q_max,
                                      parallel_eps, line_gate, irls_delta, refine_iters,
                                      threads)
    (reported, xy, t, flow_out, sup, cost, normal, normal_dir, full_flow, n_ev, roi,
     window) = _report_rows(keys, support, n_events, has, full, best_cost, ev_per_group,
                            inliers, lines, fit_flow, ratio, major, normal_speed, n_roi,
                            window_us, centres, cost_scale, aperture_ratio, min_support,
                            min_inlier_fraction)
    return (group, reported, full, xy, t, flow_out, sup, cost, normal, normal_dir, full_flow,
            n_ev, roi, window)


def register_closed_groups(keys: np.ndarray, gkey: np.ndarray, seq: np.ndarray,
                           ordinal: np.ndarray, flow: np.ndarray, support: np.ndarray,
                           n_events: np.ndarray, centres: np.ndarray, n_roi: int,
                           window_us: int, max_events: int, max_hypotheses: int,
                           n_ordinals: int, line_gate: float, refine_iters: int,
                           aperture_ratio: float, min_support: int,
                           min_inlier_fraction: float) -> tuple[np.ndarray, ...]:
    """Register the closed RoI windows of the flow and make their reported rows, in one
    compiled call (CPU): the group position of each candidate, the caps and Eq. 3
    (:func:`_arrange_kernel`, :func:`_solve_kernel`), the line fit and the rows
    (:func:`_report_rows`, with the refined flow).

    Args:
        keys: (G,) sorted distinct group keys ``window * n_roi + roi`` of the closed windows.
        gkey: (M,) int64 group key of each candidate (each in ``keys``); candidates of one
            event consecutive, events in stream order.
        seq, ordinal: (M,) int64 stream index of the candidate's event, its ordinal
            (``< n_ordinals``).
        flow: (M, 2) float32 candidate flows, px/s.
        support, n_events: (G,) int64 events with candidates, all events, per group.
        centres: (n_roi, 2) float32 RoI centres, px.
        n_roi, window_us: RoIs per window, window length (µs).
        max_events, max_hypotheses, n_ordinals, line_gate, refine_iters: as
            :func:`evtrack.flow.registration.register_groups`.
        aperture_ratio, min_support, min_inlier_fraction: the flow config's report rules.

    Returns:
        ``(position (M,), reported (G,), full (G, 2), xy, t, flow, support, cost, normal,
        normal_dir, full_flow, n_events, roi, window)``, the last eleven over the reported
        rows (the :class:`~evtrack.flow.result.FlowResult` columns).

    Raises:
        ValueError: an ordinal ``>= n_ordinals``.
    """
    if numba is None:
        raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
    if ordinal.shape[0] and int(ordinal.max()) >= n_ordinals:
        raise ValueError(f"candidate ordinals must be < n_ordinals ({n_ordinals})")
    as64 = [np.ascontiguousarray(v, dtype=np.int64)
            for v in (keys, gkey, seq, ordinal, support, n_events)]
    with torch_thread_count():
        return _register_closed_kernel(
            *as64[:4], np.ascontiguousarray(flow, dtype=np.float32), *as64[4:],
            np.ascontiguousarray(centres, dtype=np.float32), int(n_roi), int(window_us),
            int(max_events), int(max_hypotheses), int(n_ordinals), float(line_gate),
            int(refine_iters), float(aperture_ratio), int(min_support),
            float(min_inlier_fraction), float(COST_SCALE), float(_Q_MAX),
            float(_PARALLEL_EPS), float(_IRLS_DELTA), _POSITION_SLACK, _POSITION_FLOOR,
            numba.get_num_threads())


_POSITION_SLACK = 8
_POSITION_FLOOR = 65_536
"""Key ranges up to ``_POSITION_SLACK * count + _POSITION_FLOOR`` get a dense position table
(as ``triplet._positions``)."""


_RESULT_NAMES = ("full", "has", "best_cost", "inliers", "lines", "fit_flow", "ratio", "major",
                 "normal_speed")


def register_groups_compiled_arrays(group: np.ndarray, seq: np.ndarray, ordinal: np.ndarray,
                                    flow: np.ndarray, n_groups: int, max_events: int,
                                    max_hypotheses: int, n_ordinals: int, line_gate: float,
                                    refine_iters: int, cost_scale: float, q_max: int,
                                    parallel_eps: float, irls_delta: float
                                    ) -> dict[str, np.ndarray]:
    """:func:`register_groups_compiled` on NumPy arrays (int64 ``group``, ``seq``,
    ``ordinal``; (M, 2) float32 ``flow``), returning NumPy arrays."""
    if numba is None:
        raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
    with torch_thread_count():
        as64 = [np.ascontiguousarray(v, dtype=np.int64) for v in (group, seq, ordinal)]
        ev_per_group, *out = _register_kernel(
            *as64, np.ascontiguousarray(flow, dtype=np.float32), int(n_groups),
            int(max_events), int(max_hypotheses), int(n_ordinals), float(cost_scale),
            float(q_max), float(parallel_eps), float(line_gate), float(irls_delta),
            int(refine_iters), numba.get_num_threads())
    res = dict(zip(_RESULT_NAMES, out, strict=True))
    res["used_events"] = ev_per_group
    return res


def register_groups_compiled(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor,
                             n_groups: int, max_events: int, max_hypotheses: int,
                             n_ordinals: int, line_gate: float, refine_iters: int,
                             cost_scale: float, q_max: int, parallel_eps: float,
                             irls_delta: float) -> dict[str, Tensor]:
    """The per-group solution of Eq. 3 and the line fit, compiled (CPU tensors in and out).

    Args: as :func:`evtrack.flow.registration.register_groups` (``group`` in
    ``[0, n_groups)``, candidates of one event consecutive, events in stream order), with the
    registration's constants. The kernels run on ``torch.get_num_threads()`` threads.

    Returns:
        A dict of (G,)-leading tensors: ``full`` (float32 arg-min candidate, NaN without
        one), ``has``, ``best_cost`` (int64, scaled), ``used_events``, ``inliers``, ``lines``,
        ``fit_flow`` (float64 IRLS intersection), ``ratio``, ``major`` (float64 unit
        dominant normal), ``normal_speed``.
    """
    res = register_groups_compiled_arrays(
        *(v.detach().cpu().numpy() for v in (group, seq, ordinal, flow)), n_groups,
        max_events, max_hypotheses, n_ordinals, line_gate, refine_iters, cost_scale, q_max,
        parallel_eps, irls_delta)
    return {k: torch.from_numpy(v) for k, v in res.items()}
