"""Which events the flow searches: a hash sample of each dense RoI window.

The registration uses at most ``FlowConfig.max_events_per_roi`` events of a RoI window in its
data term: the candidate-bearing events with the smallest :func:`~evtrack.flow.registration.hash32`
of their stream index (:mod:`evtrack.flow.registration`). On a densely textured object a
window holds hundreds of events, and the candidate search, the dominant cost of the flow, is
spent mostly on events the registration then leaves out.

:func:`sampled_search` picks, per RoI window, the events whose hash lies below
``per_window / count * 2^32`` (all events of windows of at most ``per_window`` events):
about ``per_window`` of them, spread over the window, chosen by the *same* hash as the data
term. Given to :meth:`TripletFlow.update(..., search=...) <evtrack.flow.TripletFlow.update>`,
the other events still enter the search's history (their trails serve the triplets of later
events) but are not searched themselves. Hence:

* a window whose sampled events still include ``max_events_per_roi`` candidate-bearing ones
  has the same data term, the same hypotheses and so the same flow as without the sample
  (the smallest hashes are all below the threshold); only its ``support`` is smaller;
* a sparser window loses data-term events, and a window of at most ``per_window`` events
  loses none.

With a ``budget``, the events so chosen are then cut down to at most ``budget`` per call by
whole cells of ``cell_rois`` x ``cell_rois`` RoIs: the cells are visited in one fixed
pseudo-random order (the same hash of the cell's index) and each is taken, with all its chosen
events, if they still fit in the budget (first fit); the others are left out. Every event still
enters the history, so a taken cell's triplets and RoI flows are those it would have without the
budget, however the taken cells change from call to call (unlike thinning the events, which
leaves the kept pixels' trails with gaps), and a RoI's flow does not depend on whether its
neighbours are searched. This bounds the search and the registration, the flow's dominant costs,
per call whatever the event rate; the RoIs of the left-out cells give no flow in that call.

The counts are those of the events given in one call, so the sample depends on how the
stream was cut unless each call ends on a window boundary (as the tracker's step groups do).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.registration import hash32
from evtrack.flow.registration_compiled import _hash32
from evtrack.jit import available as jit_available
from evtrack.jit import njit

__all__ = ["sampled_search"]

_HASH_RANGE = 1 << 32


def sampled_search(x: Tensor, y: Tensor, t: Tensor, first_seq: int, *, roi_size: int,
                   window_us: int, sensor_width: int, per_window: int, budget: int = 0,
                   cell_rois: int = 2) -> Tensor:
    """(N,) bool: about ``per_window`` events of each RoI window, by the hash of their
    stream index, and at most ``budget`` in all, by cells of RoIs (see the module docstring).

    Args:
        x, y: (N,) integer pixel coordinates (non-negative; ``x < sensor_width``).
        t: (N,) int64 timestamps in µs, non-decreasing.
        first_seq: the flow's stream index of the first event (``TripletFlow.events_seen``
            before the call).
        roi_size: the flow's RoI side in pixels.
        window_us: the flow's registration window in µs.
        sensor_width: sensor width in pixels (the RoI grid's column count follows from it).
        per_window: events searched per RoI window at most, about; 0: all of each window.
        budget: events searched in this call at most, by whole cells; 0: no bound.
        cell_rois: a budget cell's side in RoIs.

    Returns:
        (N,) bool on ``t``'s device; all True where a window has at most ``per_window``
        events and the call at most ``budget``. On CPU with numba, compiled passes;
        otherwise tensor operations (the same result).

    Raises:
        ValueError: ``per_window`` or ``budget`` negative, ``cell_rois < 1``, or coordinates
            outside ``[0, sensor_width)`` (x) or negative (y).
    """
    if per_window < 0 or budget < 0 or cell_rois < 1:
        raise ValueError(f"sampled_search: per_window and budget must be >= 0 and cell_rois "
                         f">= 1, got {per_window}, {budget}, {cell_rois}")
    n = int(t.shape[0])
    if n == 0:
        return torch.zeros(0, dtype=torch.bool, device=t.device)
    cols = -(-int(sensor_width) // roi_size)
    lo, hi = int(torch.minimum(x.min(), y.min())), int(x.max())
    if lo < 0 or hi >= sensor_width:
        raise ValueError(f"sampled_search: pixel coordinates must lie in [0, {sensor_width}) "
                         f"horizontally and be non-negative; got x in [{int(x.min())}, {hi}], "
                         f"y from {int(y.min())}")
    if (per_window == 0 or n <= per_window) and (budget == 0 or n <= budget):
        return torch.ones(n, dtype=torch.bool, device=t.device)
    cell = roi_size * cell_rois
    cell_cols = -(-int(sensor_width) // cell)
    cell_rows = (int(y.max()) // cell) + 1
    rank = _cell_rank(cell_cols * cell_rows)
    if t.device.type == "cpu" and jit_available():
        keep = _sample_compiled(x.numpy(), y.numpy(), t.numpy(), int(first_seq), int(roi_size),
                                int(window_us), cols, int(per_window), int(budget), cell,
                                cell_cols, rank)
        return torch.from_numpy(keep)
    keep = _sample_torch(x, y, t, int(first_seq), roi_size, window_us, cols, per_window)
    if budget and int(keep.sum()) > budget:
        keep &= _cells_within_torch(x, y, keep, budget, cell, cell_cols,
                                    torch.tensor(rank, device=t.device))
    return keep


@functools.lru_cache(maxsize=8)
def _cell_rank(n_cells: int) -> np.ndarray:
    """(n_cells,) int64: each cell's place in the budget's fixed order (by the hash of the
    cell index, ties by the index). Read-only: shared between calls."""
    index = np.arange(n_cells, dtype=np.int64)
    order = np.lexsort((index, hash32(torch.from_numpy(index)).numpy()))
    rank = np.empty(n_cells, np.int64)
    rank[order] = index
    rank.flags.writeable = False
    return rank


def _cells_within_torch(x: Tensor, y: Tensor, keep: Tensor, budget: int, cell: int,
                        cell_cols: int, rank: Tensor) -> Tensor:
    """(N,) bool: the events of the cells taken by the budget (any device; the first-fit
    pass over the cells' counts runs on the CPU)."""
    c = (torch.div(y.to(torch.int64), cell, rounding_mode="floor") * cell_cols
         + torch.div(x.to(torch.int64), cell, rounding_mode="floor"))
    by_rank = torch.zeros(rank.shape[0], dtype=torch.int64, device=x.device)
    by_rank.index_add_(0, rank[c[keep]], torch.ones_like(c[keep]))
    counts = by_rank.cpu().numpy()
    taken = np.zeros(counts.shape[0], np.bool_)  # first fit, in the cells' order
    used = 0
    for r in np.flatnonzero(counts).tolist():
        if used + counts[r] <= budget:
            used += int(counts[r])
            taken[r] = True
    return torch.from_numpy(taken).to(x.device)[rank[c]]


def _sample_torch(x: Tensor, y: Tensor, t: Tensor, first_seq: int, roi_size: int,
                  window_us: int, cols: int, per_window: int) -> Tensor:
    """:func:`sampled_search`'s per-window sample by tensor operations (any device)."""
    n = int(t.shape[0])
    if per_window == 0:
        return torch.ones(n, dtype=torch.bool, device=t.device)
    t = t.to(torch.int64)
    window = torch.div(t, window_us, rounding_mode="floor")
    w0 = int(window[0])
    n_windows = int(window[-1]) - w0 + 1
    roi = (torch.div(y.to(torch.int64), roi_size, rounding_mode="floor") * cols
           + torch.div(x.to(torch.int64), roi_size, rounding_mode="floor"))
    rows = int(roi.max()) // cols + 1
    key = (window - w0) * (rows * cols) + roi
    count = torch.bincount(key, minlength=n_windows * rows * cols)[key]
    seq = torch.arange(first_seq, first_seq + n, dtype=torch.int64, device=t.device)
    # hash < per_window / count * 2^32, in exact integers (hash < 2^32, count < 2^31)
    return (count <= per_window) | (hash32(seq) * count < per_window * _HASH_RANGE)


@njit
def _sample_compiled(x, y, t, first_seq, roi_size, window_us, cols, per_window, budget, cell,
                     cell_cols, rank):
    """:func:`sampled_search` in passes over NumPy arrays: the RoI of each event by lookup
    tables, its window by the time-sorted order (a division only where a window starts),
    the counts, the per-window test, then the budget's cells."""
    n = t.shape[0]
    w0 = t[0] // window_us
    n_windows = t[n - 1] // window_us - w0 + 1
    y_max = 0
    for i in range(n):
        y_max = max(y_max, np.int64(y[i]))
    rows = y_max // roi_size + 1
    per = rows * cols
    row_base = np.empty(y_max + 1, np.int64)
    for v in range(y_max + 1):
        row_base[v] = (v // roi_size) * cols
    col_of = np.empty(cols * roi_size, np.int64)
    for v in range(cols * roi_size):
        col_of[v] = v // roi_size
    keep = np.ones(n, np.bool_)
    if per_window > 0:
        key = np.empty(n, np.int64)
        count = np.zeros(n_windows * per, np.int64)
        base = np.int64(0)
        next_start = (w0 + 1) * window_us
        for i in range(n):
            if t[i] >= next_start:
                w = t[i] // window_us
                base = (w - w0) * per
                next_start = (w + 1) * window_us
            k = base + row_base[y[i]] + col_of[x[i]]
            key[i] = k
            count[k] += 1
        bound = np.int64(per_window) << 32
        for i in range(n):
            c = count[key[i]]
            keep[i] = c <= per_window or _hash32(first_seq + i) * c < bound
    if budget > 0:
        cell_col = np.empty(cols * roi_size, np.int64)
        for v in range(cols * roi_size):
            cell_col[v] = v // cell
        cell_row = np.empty(y_max + 1, np.int64)
        for v in range(y_max + 1):
            cell_row[v] = (v // cell) * cell_cols
        by_rank = np.zeros(rank.shape[0], np.int64)
        ranks = np.empty(n, np.int64)
        total = 0
        for i in range(n):
            if keep[i]:
                r = rank[cell_row[y[i]] + cell_col[x[i]]]
                ranks[i] = r
                by_rank[r] += 1
                total += 1
        if total > budget:
            taken = np.zeros(by_rank.shape[0], np.bool_)  # first fit, in the cells' order
            used = 0
            for r in range(by_rank.shape[0]):
                if by_rank[r] and used + by_rank[r] <= budget:
                    used += by_rank[r]
                    taken[r] = True
            for i in range(n):
                if keep[i] and not taken[ranks[i]]:
                    keep[i] = False
    return keep
