"""Compiled step 2 of the registration (numba): Eq. 3, the constraint lines and their fit,
group by group, in parallel over the groups (:func:`solve_kernel`).

The exact integer Eq. 3 cost of the hypotheses is evaluated for the one nearest the median
first, then for the others in rank order, each abandoned once its partial sum shows it cannot
win (the arg-min, ties to the smallest rank, is that of the full evaluation); then come the
events' constraint lines, the inlier count and the IRLS intersection of the lines.

The hypotheses after the first are evaluated side by side in lanes of up to ``_MAX_LANES``
(:func:`_lane_costs`): one pass over the group's candidates updates every lane's per-event
minimum, a loop over the lanes that the compiler turns into SIMD instructions, and the
rounding of those minima is branch-free per lane. A lane is abandoned against the bound of
the best cost when its block starts, which is never below the bound the one-by-one order
would give it, so the arg-min is unchanged; an abandoned lane leaves the SIMD loop at once
(the active lanes stay packed). The events' nearest candidate to ``F`` is found from the
smallest float32 squared distance, rounding only the candidates that can round to the same
value (:func:`_nearest`).
"""

from __future__ import annotations

import numpy as np

from evtrack.flow.numba_support import filled, kernel, prange

__all__ = ["solve_kernel", "rounded_distance", "NO_BOUND"]

NO_BOUND = np.int64(1) << 62
"""A cost bound no hypothesis reaches."""
_MAX_LANES = 48
"""Most hypotheses evaluated side by side in one block (the flow's default caps try 48)."""


@kernel()
def rounded_distance(d2: float, cost_scale: float, q_max: float) -> int:
    """:func:`evtrack.flow.registration_tensor.rounded_distance` of one float32 ``d2``."""
    dd = np.float64(d2) * (cost_scale * cost_scale)
    if dd >= q_max * q_max:
        return np.int64(q_max)
    n = np.round(np.sqrt(dd))
    up, down = (n + 0.5) * (n + 0.5), (n - 0.5) * (n - 0.5)
    if dd > up:
        n += 1.0
    elif dd < down and n > 0.0:
        n -= 1.0
    if n % 2.0 == 1.0:  # a tie goes to the even neighbour
        up, down = (n + 0.5) * (n + 0.5), (n - 0.5) * (n - 0.5)
        if dd == up:
            n += 1.0
        elif dd == down:
            n -= 1.0
    return np.int64(n)


@kernel()
def _hypothesis_cost(hx, hy, c_x, c_y, c_event, c0, c1, bound, cost_scale, q_max):
    """``sum_events min_c rounded_distance(|h - c|^2)`` over candidates ``c0..c1`` (events
    contiguous), or any value ``>= bound`` as soon as the partial sum reaches ``bound`` (the
    terms are >= 0, so such a hypothesis cannot win)."""
    total = np.int64(0)
    best = np.float32(np.inf)
    e = c_event[c0]
    for c in range(c0, c1):
        if c_event[c] != e:
            total += rounded_distance(best, cost_scale, q_max)
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
    return total + rounded_distance(best, cost_scale, q_max)


@kernel()
def _rounded_lanes(mins, out, n_lanes, cost_scale, q_max):
    """``out[l] = rounded_distance(mins[l])`` for ``l < n_lanes``, without branches (the same
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


@kernel()
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


@kernel()
def _not_parallel(c_x, c_y, i, ax, ay, a2, eps2):
    """Whether candidate ``b = c[i]`` is not parallel to ``a``: ``cross(b, a)^2 > eps2 |b|^2
    |a|^2`` in float64 (products of float32 values are exact there)."""
    bx, by = np.float64(c_x[i]), np.float64(c_y[i])
    cross = bx * ay - by * ax
    return cross * cross > eps2 * (bx * bx + by * by) * a2


@kernel()
def _filtered_distance2(c_x, c_y, i, fx, fy, nonparallel_to_a, ax, ay, a2, eps2):
    """Candidate ``i``'s float32 squared distance to ``(fx, fy)`` (separate IEEE
    operations), or -1 when ``nonparallel_to_a`` and it is parallel to ``a``."""
    if nonparallel_to_a and not _not_parallel(c_x, c_y, i, ax, ay, a2, eps2):
        return np.float32(-1.0)
    dx = c_x[i] - fx
    dy = c_y[i] - fy
    d2 = dx * dx
    return d2 + dy * dy


@kernel()
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
    q_min = rounded_distance(best, cost_scale, q_max)
    edge = (np.float64(q_min) + 0.5) * (np.float64(q_min) + 0.5)
    cs2 = cost_scale * cost_scale
    for i in range(i0, i1):
        d2 = _filtered_distance2(c_x, c_y, i, fx, fy, nonparallel_to_a, ax, ay, a2, eps2)
        if d2 < 0:
            continue
        if q_min < q_max and np.float64(d2) * cs2 > edge:
            continue  # rounds above q_min
        if rounded_distance(d2, cost_scale, q_max) == q_min:
            return i, d2
    return -1, np.float32(np.nan)  # not reached: the smallest d2 rounds to q_min


@kernel()
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


@kernel()
def _first_hypothesis(hx, hy, nh, scratch):
    """The hypothesis nearest (L1) the median of the ``nh`` hypotheses' flows: usually the
    winner or close, so evaluated first its cost cuts the others short."""
    mx, my = _median_small(hx, nh, scratch), _median_small(hy, nh, scratch)
    first = 0
    for j in range(1, nh):
        if abs(hx[j] - mx) + abs(hy[j] - my) < abs(hx[first] - mx) + abs(hy[first] - my):
            first = j
    return first


@kernel()
def _event_pointers(c_event, c0, c1, n_ev, ev_ptr):
    """``ev_ptr[e]..ev_ptr[e + 1]``: the candidates of the group's event ``e`` (its candidates
    ``c0..c1``, events contiguous; ``n_ev`` events)."""
    e = 0
    for c in range(c0, c1):
        if c > c0 and c_event[c] != c_event[c - 1]:
            e += 1
            ev_ptr[e] = c
    ev_ptr[0], ev_ptr[n_ev] = c0, c1


@kernel()
def _best_hypothesis(hx, hy, nh, first, g_best, c_x, c_y, ev_ptr, n_ev, cost_scale, q_max,
                     lx, ly, l_rank, l_bound, l_total, l_min, l_q, s_act, s_x, s_y, s_bound,
                     s_total):
    """The arg-min ``(cost, rank)`` of a group's ``nh`` hypotheses ``(hx, hy)``, given the
    cost ``g_best`` of hypothesis ``first``; the others in rank order, in blocks of lanes of
    about equal size (:func:`_lane_costs`; the arrays after ``q_max`` are its scratch).

    A lane's bound is taken when its block starts: the best only improves during the block,
    so that bound is never below the one-by-one bound and a lane abandoned against it could
    not have won; the lanes are then compared in rank order with the one-by-one rule (a tie
    goes to the smaller rank)."""
    best_rank = first
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
    return g_best, best_rank


@kernel()
def _constraint_lines(c_x, c_y, ev_ptr, n_ev, fx, fy, lim2, cost_scale, q_max, eps2, ln_x,
                      ln_y, ln_s):
    """One constraint line ``n . F = s`` per event that agrees with ``F = (fx, fy)`` (its
    nearest candidate within ``d2 <= lim2``), through that candidate and its nearest
    non-parallel one, into ``ln_x, ln_y, ln_s`` (``s >= 0``). Returns ``(inliers, lines)``."""
    n_inliers = 0
    n_lines = 0
    for e in range(n_ev):
        e0, e1 = ev_ptr[e], ev_ptr[e + 1]
        i1, d2_1 = _nearest(c_x, c_y, e0, e1, fx, fy, cost_scale, q_max)
        if np.float64(d2_1) > lim2:
            continue  # disagrees with F: neither an inlier nor a line
        n_inliers += 1
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
    return n_inliers, n_lines


@kernel()
def _fit_lines(g, ln_x, ln_y, ln_s, n_lines, fx, fy, irls_delta, refine_iters, fit_flow, ratio,
               major, normal_speed):
    """Group ``g``'s IRLS intersection of its ``n_lines`` lines from ``F = (fx, fy)``, and the
    eigen-decomposition of their weighted scatter (see :mod:`evtrack.flow.registration`),
    written into ``fit_flow, ratio, major, normal_speed``."""
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


@kernel()
def _solve_group(g, h_cand, h_start, h_count, c_x, c_y, c_event, counts, c_start, ev_per_group,
                 cost_scale, q_max, gate2, eps2, irls_delta, refine_iters, full, has, best_cost,
                 inliers, lines, fit_flow, ratio, major, normal_speed, hx, hy, ev_ptr, lx, ly,
                 l_rank, l_bound, l_total, l_min, l_q, s_act, s_x, s_y, s_bound, s_total, ln_x,
                 ln_y, ln_s):
    """Group ``g`` of :func:`solve_kernel`, its results written into the outputs; the
    arrays after ``normal_speed`` are scratch of at least the group's hypotheses (``ev_ptr``:
    its events + 1; ``ln_*``: its events)."""
    major[g, 0] = 1.0  # the tensor path's direction without lines (theta = 0)
    if h_count[g] == 0:
        return
    # arg-min of (cost, rank): the hypothesis nearest the median flow first, then the others
    # in rank order
    c0, c1 = c_start[g], c_start[g] + counts[g]
    h0, nh = h_start[g], h_count[g]
    for j in range(nh):
        hx[j], hy[j] = c_x[h_cand[h0 + j]], c_y[h_cand[h0 + j]]
    first = _first_hypothesis(hx, hy, nh, l_min)  # (l_min: scratch here, the lanes' minima below)
    g_best = _hypothesis_cost(hx[first], hy[first], c_x, c_y, c_event, c0, c1, NO_BOUND,
                              cost_scale, q_max)
    n_ev = ev_per_group[g]
    _event_pointers(c_event, c0, c1, n_ev, ev_ptr)
    g_best, best_rank = _best_hypothesis(hx, hy, nh, first, g_best, c_x, c_y, ev_ptr, n_ev,
                                         cost_scale, q_max, lx, ly, l_rank, l_bound, l_total,
                                         l_min, l_q, s_act, s_x, s_y, s_bound, s_total)
    chosen = h_cand[h0 + best_rank]
    has[g] = True
    best_cost[g] = g_best
    fx, fy = c_x[chosen], c_y[chosen]
    full[g, 0], full[g, 1] = fx, fy
    f2 = fx * fx
    f2 = f2 + fy * fy
    inliers[g], lines[g] = _constraint_lines(c_x, c_y, ev_ptr, n_ev, fx, fy,
                                             gate2 * max(np.float64(f2), 1.0), cost_scale,
                                             q_max, eps2, ln_x, ln_y, ln_s)
    _fit_lines(g, ln_x, ln_y, ln_s, lines[g], fx, fy, irls_delta, refine_iters, fit_flow, ratio,
               major, normal_speed)


@kernel(parallel=True)
def solve_kernel(h_cand: np.ndarray, h_start: np.ndarray, h_count: np.ndarray, c_x: np.ndarray,
                 c_y: np.ndarray, c_event: np.ndarray, counts: np.ndarray, c_start: np.ndarray,
                 ev_per_group: np.ndarray, cost_scale: float, q_max: float, parallel_eps: float,
                 line_gate: float, irls_delta: float, refine_iters: int, threads: int
                ) -> tuple[np.ndarray, ...]:
    """Step 2 of the module docstring, in parallel over the groups: a few tasks per thread
    (``threads``: numba's thread count), each a run of consecutive groups with scratch arrays
    of its own (allocated once per task, not a dozen times per group).

    Each hypothesis is evaluated only until its partial cost shows it cannot beat the best so
    far (a later rank must be strictly cheaper, an earlier one at most as costly), so the
    arg-min and its cost are those of the full evaluation.
    """
    n_groups = counts.shape[0]
    full = filled((n_groups, 2), np.nan, np.float32)
    has = filled(n_groups, False, np.bool_)
    best_cost = filled(n_groups, 0, np.int64)
    inliers = filled(n_groups, 0, np.int64)
    lines = filled(n_groups, 0, np.int64)
    fit_flow = filled((n_groups, 2), 0.0, np.float64)
    ratio = filled(n_groups, 1.0, np.float64)
    major = filled((n_groups, 2), 0.0, np.float64)
    normal_speed = filled(n_groups, 0.0, np.float64)
    gate2 = line_gate * line_gate
    eps2 = parallel_eps * parallel_eps
    n_tasks = min(n_groups, 4 * max(threads, 1))
    for task in prange(n_tasks):
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
