"""Compiled step 1 of the registration (numba): the caps and the layout of what they keep.

Per group, the data term keeps the ``max_events`` events with the smallest hash of their
stream index (ties to the earlier event) and the hypotheses are the ``max_hypotheses`` kept
candidates with the smallest hash of (stream index, ordinal) (ties to the earlier candidate),
in rank order: the selections of :func:`evtrack.flow.registration_tensor.arrange`. Both keep
the smallest ``(hash << 31) | position`` keys by insertion into a short sorted buffer
(:func:`insert_smallest`): the same keys as a sort (they are distinct), without sorting the
rest; the buffers are allocated once per call, not once per group (~80 ns each).

One thread: its loops are short per group, and in parallel loops the thread pool's start
cost more than they saved (a tracker's call, 330 groups of 35 candidates: 0.32-0.37 ms on one
thread, 0.38-0.43 ms on two; a 10k-event call of the fast-object flow, 53 groups of 190:
0.48-0.51 against 0.54-0.56 ms).
"""

from __future__ import annotations

import numpy as np

from evtrack.flow.hashing import hash32_kernel
from evtrack.flow.numba_support import filled, kernel

__all__ = ["arrange_kernel", "group_positions", "insert_smallest"]

_POS_BITS = 31  # (hash << 31) | position: a hash < 2^32 and a position < 2^31 fit in int64
_POS_MASK = (1 << _POS_BITS) - 1


@kernel()
def insert_smallest(buf: np.ndarray, filled: int, cap: int, key: int) -> int:
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


@kernel()
def _event_runs(seq):
    """``run_first`` (R + 1,): the first candidate of each of the R events (runs of equal
    stream index), then the candidates' count."""
    m = seq.shape[0]
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
    return run_first


@kernel()
def _exclusive_sum(values):
    """``(starts, total)``: the running sum of ``values`` before each entry, and their sum."""
    n = values.shape[0]
    starts = filled(n, 0, np.int64)
    for g in range(1, n):
        starts[g] = starts[g - 1] + values[g - 1]
    return starts, (starts[n - 1] + values[n - 1] if n else 0)


@kernel()
def _runs_by_group(group, run_first, n_groups):
    """The events of each group, in stream order: ``(group_run_start (G + 1,),
    runs_by_group (R,))``, group ``g``'s events at ``group_run_start[g]..[g + 1]``."""
    n_runs = run_first.shape[0] - 1
    runs_per_group = filled(n_groups, 0, np.int64)
    for r in range(n_runs):
        runs_per_group[group[run_first[r]]] += 1
    group_run_start = filled(n_groups + 1, 0, np.int64)
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
    return group_run_start, runs_by_group


@kernel()
def _cap_events(seq, run_first, group_run_start, runs_by_group, max_events):
    """The data-term cap: ``(keep (R,), ev_per_group (G,), counts (G,))``, whether each event
    is kept (per group the ``max_events`` smallest ``(hash << 31) | position`` keys), the
    kept events and their candidates per group."""
    n_groups = group_run_start.shape[0] - 1
    keep = filled(run_first.shape[0] - 1, True, np.bool_)
    ev_per_group = filled(n_groups, 0, np.int64)
    counts = filled(n_groups, 0, np.int64)
    kept = np.empty(max(max_events, 1), np.int64)  # every capped group's selection, in turn
    for g in range(n_groups):
        r0, r1 = group_run_start[g], group_run_start[g + 1]
        if r1 - r0 > max_events:
            filled_to = 0
            for j in range(r1 - r0):
                key = (hash32_kernel(seq[run_first[runs_by_group[r0 + j]]]) << _POS_BITS) | j
                filled_to = insert_smallest(kept, filled_to, max_events, key)
            for j in range(r0, r1):
                keep[runs_by_group[j]] = False
            for j in range(max_events):
                keep[runs_by_group[r0 + (kept[j] & _POS_MASK)]] = True
        for j in range(r0, r1):
            rr = runs_by_group[j]
            if keep[rr]:
                ev_per_group[g] += 1
                counts[g] += run_first[rr + 1] - run_first[rr]
    return keep, ev_per_group, counts


@kernel()
def _lay_out(seq, ordinal, flow, n_ordinals, run_first, group_run_start, runs_by_group, keep,
             c_start, n_kept, h_count, h_start, n_h, max_hypotheses):
    """The kept candidates by group, events in stream order (``c_x, c_y`` (float32 px/s),
    ``c_event``: the event's index within its group), and the hypotheses: per group the
    smallest (hash, position), in that order (the rank order; ``h_cand``: candidate
    indices)."""
    c_x = np.empty(n_kept, np.float32)
    c_y = np.empty(n_kept, np.float32)
    c_event = np.empty(n_kept, np.int64)
    h_cand = np.empty(n_h, np.int64)
    first = np.empty(max(max_hypotheses, 1), np.int64)  # every group's hypotheses, in turn
    for g in range(h_count.shape[0]):
        h = h_count[g]
        if h == 0:
            continue
        c0 = c_start[g]
        c = c0
        e = 0
        filled_to = 0
        for j in range(group_run_start[g], group_run_start[g + 1]):
            rr = runs_by_group[j]
            if not keep[rr]:
                continue
            for i in range(run_first[rr], run_first[rr + 1]):
                c_x[c] = flow[i, 0]
                c_y[c] = flow[i, 1]
                c_event[c] = e
                key = (hash32_kernel(seq[i] * n_ordinals + ordinal[i]) << _POS_BITS) | (c - c0)
                filled_to = insert_smallest(first, filled_to, h, key)
                c += 1
            e += 1
        for j in range(h):
            h_cand[h_start[g] + j] = c0 + (first[j] & _POS_MASK)
    return c_x, c_y, c_event, h_cand


@kernel()
def arrange_kernel(group: np.ndarray, seq: np.ndarray, ordinal: np.ndarray, flow: np.ndarray,
                   n_groups: int, max_events: int, max_hypotheses: int, n_ordinals: int
                  ) -> tuple[np.ndarray, ...]:
    """The caps and the layout (module docstring). Candidates of one event are consecutive
    in the input and events come in stream order.

    Returns ``(c_x, c_y, c_event, counts, c_start, ev_per_group, h_cand, h_start, h_count)``:
    the kept candidates' flows (float32 px/s) and event index within their group, per group
    the kept candidates, the first of them and the kept events, each hypothesis' candidate,
    per group the first hypothesis and their number."""
    run_first = _event_runs(seq)
    group_run_start, runs_by_group = _runs_by_group(group, run_first, n_groups)
    keep, ev_per_group, counts = _cap_events(seq, run_first, group_run_start, runs_by_group,
                                             max_events)
    c_start, n_kept = _exclusive_sum(counts)
    h_count = np.empty(n_groups, np.int64)
    for g in range(n_groups):
        h_count[g] = min(counts[g], max_hypotheses)
    h_start, n_h = _exclusive_sum(h_count)
    c_x, c_y, c_event, h_cand = _lay_out(seq, ordinal, flow, n_ordinals, run_first,
                                         group_run_start, runs_by_group, keep, c_start, n_kept,
                                         h_count, h_start, n_h, max_hypotheses)
    return c_x, c_y, c_event, counts, c_start, ev_per_group, h_cand, h_start, h_count


@kernel()
def group_positions(keys: np.ndarray, gkey: np.ndarray, slack: int, floor: int) -> np.ndarray:
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
