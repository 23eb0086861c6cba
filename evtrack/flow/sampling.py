"""Which events the flow searches: a hash sample of each dense RoI window.

The registration uses at most ``FlowConfig.max_events_per_roi`` events of a RoI window in its
data term: the candidate-bearing events with the smallest :func:`~evtrack.flow.hashing.hash32`
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

from evtrack.flow.constants import HASH_RANGE
from evtrack.flow.hashing import hash32, hash32_kernel
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["sampled_search"]


def sampled_search(x: Tensor, y: Tensor, t: Tensor, first_seq: int, *, roi_size: int,
                   window_us: int, sensor_width: int, per_window: int, budget: int = 0,
                   cell_rois: int = 1) -> Tensor:
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
        cell_rois: a budget cell's side in RoIs. Single RoIs use the budget best: a RoI's
            flow does not depend on whether its neighbours are searched (on the cracker box
            `faster`, 2000 events per 1 ms step: 4.13 cm / 5.23 deg with single RoIs, 4.69 /
            5.12 with cells of 2 x 2; oracle poses).

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
    on_cpu = t.device.type == "cpu"
    xs, ys = (x.numpy(), y.numpy()) if on_cpu else (x, y)  # NumPy's reductions: faster here
    x_lo, x_hi, y_lo, y_max = (int(v) for v in (xs.min(), xs.max(), ys.min(), ys.max()))
    if min(x_lo, y_lo) < 0 or x_hi >= sensor_width:
        raise ValueError(f"sampled_search: pixel coordinates must lie in [0, {sensor_width}) "
                         f"horizontally and be non-negative; got x in [{x_lo}, {x_hi}], "
                         f"y from {y_lo}")
    if (per_window == 0 or n <= per_window) and (budget == 0 or n <= budget):
        return torch.ones(n, dtype=torch.bool, device=t.device)
    rows = y_max // roi_size + 1
    if on_cpu and jit_available():
        keep = _sample_compiled(xs, ys, t.numpy(), int(first_seq), int(roi_size),
                                int(window_us), cols, rows, int(per_window), int(budget),
                                _roi_rank(cols, rows, int(cell_rois)))
        return torch.from_numpy(keep)
    keep = _sample_torch(x, y, t, int(first_seq), roi_size, window_us, cols, per_window)
    if budget and int(keep.sum()) > budget:
        roi = (torch.div(y.to(torch.int64), roi_size, rounding_mode="floor") * cols
               + torch.div(x.to(torch.int64), roi_size, rounding_mode="floor"))
        keep &= _cells_within_torch(roi, keep, budget,
                                    torch.tensor(_roi_rank(cols, rows, int(cell_rois)),
                                                 device=t.device))
    return keep


@functools.lru_cache(maxsize=64)
def _roi_rank(cols: int, rows: int, cell_rois: int) -> np.ndarray:
    """(rows * cols,) int64: the budget's order of each RoI's cell (:func:`_cell_rank` of the
    cell holding RoI ``row * cols + col``). Read-only: shared between calls."""
    cell_cols = -(-cols // cell_rois)
    rank = _cell_rank(cell_cols * (-(-rows // cell_rois)))
    row, col = np.divmod(np.arange(rows * cols, dtype=np.int64), cols)
    out = rank[(row // cell_rois) * cell_cols + col // cell_rois]
    out.flags.writeable = False
    return out


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


def _cells_within_torch(roi: Tensor, keep: Tensor, budget: int, roi_rank: Tensor) -> Tensor:
    """(N,) bool: the events whose RoI's cell the budget takes (any device; the first-fit
    pass over the cells' counts runs on the CPU)."""
    rank = roi_rank[roi]
    counts = torch.bincount(rank[keep], minlength=roi_rank.shape[0]).cpu().numpy()
    taken = np.zeros(counts.shape[0], np.bool_)  # first fit, in the cells' order
    used = 0
    for r in np.flatnonzero(counts).tolist():
        if used + counts[r] <= budget:
            used += int(counts[r])
            taken[r] = True
    return torch.from_numpy(taken).to(roi.device)[rank]


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
    return (count <= per_window) | (hash32(seq) * count < per_window * HASH_RANGE)


@njit
def _roi_lookup(rows, cols, roi_size):
    """``(row_base, col_of)``: per pixel row the first RoI index of its RoI row
    (``(y // roi_size) * cols``), per pixel column its RoI column (``x // roi_size``)."""
    row_base = np.empty(rows * roi_size, np.int64)
    for v in range(rows * roi_size):
        row_base[v] = (v // roi_size) * cols
    col_of = np.empty(cols * roi_size, np.int64)
    for v in range(cols * roi_size):
        col_of[v] = v // roi_size
    return row_base, col_of


@njit
def _window_sample(x, y, t, first_seq, window_us, row_base, col_of, n_roi, per_window,
                   with_budget, roi, keep, by_rank, roi_rank):
    """The per-window test into ``keep`` (events of windows of at most ``per_window`` events,
    else those of hash below ``per_window / count * 2^32``): the RoI of each event by the
    lookup tables (into ``roi`` with a budget) and its window by the time-sorted order (a
    division only where a window starts), then the test, counting the kept events per cell
    rank into ``by_rank`` (with a budget). Returns the kept events' count."""
    n = t.shape[0]
    w0 = t[0] // window_us
    key = np.empty(n, np.int64)
    count = np.zeros((t[n - 1] // window_us - w0 + 1) * n_roi, np.int64)
    base = np.int64(0)
    next_start = (w0 + 1) * window_us
    for i in range(n):
        if t[i] >= next_start:
            w = t[i] // window_us
            base = (w - w0) * n_roi
            next_start = (w + 1) * window_us
        r = row_base[y[i]] + col_of[x[i]]
        if with_budget:
            roi[i] = r
        key[i] = base + r
        count[base + r] += 1
    bound = np.int64(per_window) << 32
    total = 0
    for i in range(n):
        c = count[key[i]]
        kept = (c <= per_window) | (hash32_kernel(first_seq + i) * c < bound)
        keep[i] = kept
        if with_budget:  # branch-free in the event: the sample is random
            by_rank[roi_rank[roi[i]]] += kept
            total += kept
    return total


@njit
def _cut_to_budget(keep, roi, by_rank, roi_rank, budget):
    """First fit in the cells' order (``by_rank``: kept events per cell rank, below the RoIs'
    count): the cells whose events still fit in ``budget`` are taken, the events of the
    others dropped from ``keep``."""
    taken = np.zeros(by_rank.shape[0], np.bool_)
    used = 0
    for r in range(by_rank.shape[0]):
        if by_rank[r] and used + by_rank[r] <= budget:
            used += by_rank[r]
            taken[r] = True
    taken_roi = np.empty(roi_rank.shape[0], np.bool_)
    for r in range(roi_rank.shape[0]):
        taken_roi[r] = taken[roi_rank[r]]
    for i in range(keep.shape[0]):
        keep[i] = keep[i] & taken_roi[roi[i]]


@njit
def _sample_compiled(x, y, t, first_seq, roi_size, window_us, cols, rows, per_window, budget,
                     roi_rank):
    """:func:`sampled_search` in passes over NumPy arrays: the per-window test with the
    budget's counts per cell (:func:`_window_sample`), then, over budget, the first fit and
    the cut (:func:`_cut_to_budget`)."""
    n = t.shape[0]
    row_base, col_of = _roi_lookup(rows, cols, roi_size)
    with_budget = budget > 0
    roi = np.empty(n if with_budget else 0, np.int64)
    keep = np.ones(n, np.bool_)
    by_rank = np.zeros(roi_rank.shape[0] if with_budget else 0, np.int64)
    total = 0
    if per_window > 0:
        total = _window_sample(x, y, t, first_seq, window_us, row_base, col_of, rows * cols,
                               per_window, with_budget, roi, keep, by_rank, roi_rank)
    elif with_budget:
        for i in range(n):
            r = row_base[y[i]] + col_of[x[i]]
            roi[i] = r
            by_rank[roi_rank[r]] += 1
        total = n
    if with_budget and total > budget:
        _cut_to_budget(keep, roi, by_rank, roi_rank, budget)
    return keep
