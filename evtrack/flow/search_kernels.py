"""Compiled kernels of the candidate search (numba; driven by
:class:`~evtrack.flow.compiled.CompiledSearch`).

:func:`search_kernel` is the event loop of the matching rule of :mod:`evtrack.flow.config`
over the compact state described there; the others run it on horizontal strips of the
sensor in parallel (:func:`search_strips`, :func:`search_strips_merged`), copy the rows
around each strip (:func:`copy_halos`), cut the strips (:func:`strip_cuts`) and merge their
rows back into stream order (:func:`merge_strips`). Arrays are NumPy; times are int32-range
µs relative to the search's base.
"""

from __future__ import annotations

import numpy as np

from evtrack.flow.constants import EMPTY_T, NO_EVENT
from evtrack.flow.numba_support import filled, kernel, prange

__all__ = ["search_kernel", "search_strips", "search_strips_merged", "copy_halos",
           "merge_strips", "strip_cuts"]

_NO_EVENT = np.int32(NO_EVENT)  # the int32 state's value


@kernel()
def _pixel_index(yy, xx, lo, hi, r2, width, halo_pix):
    """Index into ``last`` of pixel ``(xx, yy)``: the shared rows ``[lo, hi)`` of the strip's
    own part of the sensor, or the strip's private copy of the ``r2`` rows above / below."""
    if yy >= lo and yy < hi:
        return yy * width + xx
    row = yy - lo + r2 if yy < lo else r2 + yy - hi
    return halo_pix + row * width + xx


@kernel()
def _cell_index(plane, yy, xx, lo, hi, r2, width, pixels, halo_cell):
    """Index into ``hist`` / ``hist_s`` of the (pixel, polarity) cell (``plane`` 0: positive,
    1: negative), shared or private as :func:`_pixel_index`."""
    if yy >= lo and yy < hi:
        return plane * pixels + yy * width + xx
    row = yy - lo + r2 if yy < lo else r2 + yy - hi
    return halo_cell + (plane * 2 * r2 + row) * width + xx


@kernel()
def _in_burst(prev, tk, positive, refractory):
    """Whether an event at ``tk`` of polarity ``positive`` (1: positive) continues the burst of
    its pixel's previous event ``prev`` (``last`` form, ``NO_EVENT``: none): same polarity and
    at most ``refractory`` µs older (0: no burst filter)."""
    return (refractory > 0 and prev != _NO_EVENT and (prev & 1) == positive
            and tk - (prev >> 1) <= refractory)


@kernel()
def _pair_cells(inner, cell_k, step, dx, dy, xk, yk, plane, lo, hi, r2, width, height,
                halo_cell):
    """The cells of ``e_j`` (``x - d``) and ``e_i`` (``x - 2d``) for the displacement
    ``d = (dx, dy)`` (flat step ``step`` within a plane) of an event at ``(xk, yk)`` whose cell
    is ``cell_k``; ``(-1, -1)`` where ``x - 2d`` lies outside the sensor. ``inner``: every
    cell read lies in the strip's own rows and inside the sensor (a flat step suffices).
    Scalars only: the kernel calls it per displacement."""
    if inner:
        return cell_k - step, cell_k - 2 * step
    xi, yi = xk - 2 * dx, yk - 2 * dy
    if xi < 0 or xi >= width or yi < 0 or yi >= height:
        return -1, -1
    pixels = width * height
    cj = _cell_index(plane, yk - dy, xk - dx, lo, hi, r2, width, pixels, halo_cell)
    return cj, _cell_index(plane, yi, xi, lo, hi, r2, width, pixels, halo_cell)


@kernel()
def _is_triplet(dkj, dji, dki, lo_dt, tol_abs, permille):
    """The triplet test of :mod:`evtrack.flow.config` for ``t_k - t_j = dkj``, ``t_j - t_i =
    dji`` and ``t_k - t_i = dki`` (µs; ``dkj >= 1`` and ``dki`` at most the displacement's
    upper bound already hold): time increases, the lower speed bound ``lo_dt`` and the
    constant-velocity tolerance (``tol_abs`` in µs / 1000, ``permille`` per mille)."""
    return dji >= 1 and dki >= lo_dt and abs(dkj - dji) * 1000 <= tol_abs + permille * dki


@kernel()
def _store(hist, hist_s, c, history, tk, seq):
    """Store an onset ``(tk, seq)`` in cell ``c``: newest first, the oldest (or an empty slot)
    drops out."""
    for a in range(history - 1, 0, -1):
        hist[c, a] = hist[c, a - 1]
        hist_s[c, a] = hist_s[c, a - 1]
    hist[c, 0] = tk
    hist_s[c, 0] = seq


@kernel()
def search_kernel(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, srch: np.ndarray,
                  start: int, seq0: int, width: int, height: int, off_x: np.ndarray,
                  off_y: np.ndarray, dt_lo: np.ndarray, dt_hi: np.ndarray, hi_j: np.ndarray,
                  num_x: np.ndarray, num_y: np.ndarray, history: int, refractory: int,
                  tol_abs: int, permille: int, last: np.ndarray, hist: np.ndarray,
                  hist_s: np.ndarray, o_event: np.ndarray, o_off: np.ndarray, o_aj: np.ndarray,
                  o_ai: np.ndarray, o_sj: np.ndarray, o_si: np.ndarray, o_dt: np.ndarray,
                  o_flow: np.ndarray, n_out: int, lo: int, hi: int, r2: int, halo_pix: int,
                  halo_cell: int) -> tuple[int, int]:
    """Process events ``start..`` until done or until the output might overflow.

    Times ``t`` and the state's are int32-range µs relative to the search's base.
    ``last[pixel] = 2 * t + (p > 0)`` of the pixel's latest event (``NO_EVENT``: none);
    ``hist[cell] = (t_0..t_{K-1})``: the cell's latest onsets, newest first, ``EMPTY_T``
    where it holds fewer (``t - EMPTY_T`` exceeds every speed bound, so the loops stop
    there); ``hist_s[cell]``: their stream indices (read only for a candidate). Returns
    ``(next event index, rows written)``; the state is updated for every processed event
    only, so a call can resume where the previous one stopped.

    Strips: only events of rows ``[lo, hi)`` are searched. The events of the ``r2`` rows
    above and below (``r2 = 2 * radius``: the rows a search can read) are stored into the
    strip's private copy of those rows (at ``halo_pix`` in ``last``, ``halo_cell`` in
    ``hist`` and ``hist_s``), so that a search sees exactly the state the sequential loop
    would; other events are skipped. ``lo = 0, hi = height``: the whole sensor, sequentially.
    """
    n = x.shape[0]
    capacity = o_event.shape[0]
    worst = off_x.shape[0] * history * history
    pixels = width * height
    step = off_y * width + off_x  # flat index of a displacement within a plane
    k = start
    while k < n:
        if n_out + worst > capacity:
            return k, n_out
        yk = y[k]
        own = yk >= lo and yk < hi
        if not own and (yk < lo - r2 or yk >= hi + r2):
            k += 1
            continue  # neither searched nor read by this strip
        xk, tk, pk = x[k], t[k], p[k]
        seq = seq0 + k
        pix = _pixel_index(yk, xk, lo, hi, r2, width, halo_pix)
        positive = 1 if pk > 0 else 0
        prev = last[pix]
        last[pix] = 2 * tk + positive
        k += 1
        if _in_burst(prev, tk, positive, refractory):
            continue  # inside a burst: neither searched nor stored
        plane = 1 - positive
        if own and srch[k - 1]:
            inner = yk - r2 >= lo and yk + r2 < hi and xk >= r2 and xk < width - r2
            cell_k = plane * pixels + yk * width + xk
            for o in range(off_x.shape[0]):
                cj, ci = _pair_cells(inner, cell_k, step[o], off_x[o], off_y[o], xk, yk, plane,
                                     lo, hi, r2, width, height, halo_cell)
                if ci < 0 or hist[cj, 0] == EMPTY_T or hist[ci, 0] == EMPTY_T:
                    continue
                lo_dt, hi_dt, top_j = dt_lo[o], dt_hi[o], hi_j[o]
                for aj in range(history):
                    tj = np.int64(hist[cj, aj])
                    dkj = tk - tj
                    if dkj < 1:
                        continue
                    if dkj >= top_j:
                        break  # older (or empty) e_j: no t_k - t_i can complete them
                    for ai in range(history):
                        ti = np.int64(hist[ci, ai])
                        dki = tk - ti
                        if dki > hi_dt:
                            break  # older e_i are older still (an empty slot: the oldest)
                        if not _is_triplet(dkj, tj - ti, dki, lo_dt, tol_abs, permille):
                            continue
                        o_event[n_out] = seq
                        o_off[n_out] = o
                        o_aj[n_out] = aj
                        o_ai[n_out] = ai
                        o_sj[n_out] = hist_s[cj, aj]
                        o_si[n_out] = hist_s[ci, ai]
                        o_dt[n_out] = dki
                        dt32 = np.float32(dki)
                        o_flow[n_out, 0] = num_x[o] / dt32
                        o_flow[n_out, 1] = num_y[o] / dt32
                        n_out += 1
        _store(hist, hist_s, _cell_index(plane, yk, xk, lo, hi, r2, width, pixels, halo_cell),
               history, tk, seq)
    return k, n_out


@kernel()
def copy_halos(lo_s: np.ndarray, hi_s: np.ndarray, r2: int, width: int, height: int, x_min: int,
               x_max: int, last: np.ndarray, hist: np.ndarray, hist_s: np.ndarray, halo_pix0: int,
               halo_cell0: int) -> None:
    """Copy, for every strip, the ``r2`` rows above and below it from the shared state into
    its private rows (run before any strip searches: the copies are the state at the start
    of the batch). Only columns ``x_min - r2 .. x_max + r2`` (the batch's events' columns and
    the cells their searches read): the batch reads no other private cell, and the next batch
    copies its own columns afresh."""
    pixels = width * height
    strip_pix = 2 * r2 * width
    x0, x1 = max(0, x_min - r2), min(width, x_max + r2 + 1)
    for s in range(lo_s.shape[0]):
        for row in range(2 * r2):
            yy = lo_s[s] - r2 + row if row < r2 else hi_s[s] + row - r2
            if yy < 0 or yy >= height:
                continue  # never read: no event lies there and searches stay inside
            for xx in range(x0, x1):
                src = yy * width + xx
                dst = halo_pix0 + s * strip_pix + row * width + xx
                last[dst] = last[src]
                for plane in range(2):
                    cs = plane * pixels + src
                    cd = halo_cell0 + s * 2 * strip_pix + (plane * 2 * r2 + row) * width + xx
                    for a in range(hist.shape[1]):
                        hist[cd, a] = hist[cs, a]
                    for a in range(hist_s.shape[1]):
                        hist_s[cd, a] = hist_s[cs, a]


@kernel(parallel=True)
def search_strips(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, srch: np.ndarray,
                  starts: np.ndarray, seq0: int, width: int, height: int, off_x: np.ndarray,
                  off_y: np.ndarray, dt_lo: np.ndarray, dt_hi: np.ndarray, hi_j: np.ndarray,
                  num_x: np.ndarray, num_y: np.ndarray, history: int, refractory: int,
                  tol_abs: int, permille: int, last: np.ndarray, hist: np.ndarray,
                  hist_s: np.ndarray, o_event: np.ndarray, o_off: np.ndarray, o_aj: np.ndarray,
                  o_ai: np.ndarray, o_sj: np.ndarray, o_si: np.ndarray, o_dt: np.ndarray,
                  o_flow: np.ndarray, n_outs: np.ndarray, cap: int, lo_s: np.ndarray,
                  hi_s: np.ndarray, r2: int, halo_pix0: int, halo_cell0: int) -> None:
    """:func:`search_kernel` on every strip in parallel; strip ``s`` writes its rows at
    ``[s * cap, (s + 1) * cap)`` of the outputs and resumes from ``starts[s]``."""
    strip_pix = 2 * r2 * width
    for s in prange(lo_s.shape[0]):
        if starts[s] >= x.shape[0]:
            continue
        a, b = s * cap, (s + 1) * cap
        k, m = search_kernel(
            x, y, t, p, srch, starts[s], seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
            num_x, num_y, history, refractory, tol_abs, permille, last, hist, hist_s,
            o_event[a:b], o_off[a:b], o_aj[a:b], o_ai[a:b], o_sj[a:b], o_si[a:b], o_dt[a:b],
            o_flow[a:b], n_outs[s], lo_s[s], hi_s[s], r2, halo_pix0 + s * strip_pix,
            halo_cell0 + s * 2 * strip_pix)
        starts[s] = k
        n_outs[s] = m


@kernel()
def merge_strips(n: int, seq0: int, seg_start: np.ndarray, seg_len: np.ndarray,
                 i_event: np.ndarray, i_off: np.ndarray, i_aj: np.ndarray, i_ai: np.ndarray,
                 i_sj: np.ndarray, i_si: np.ndarray, i_dt: np.ndarray, i_flow: np.ndarray,
                 o_event: np.ndarray, o_off: np.ndarray, o_aj: np.ndarray, o_ai: np.ndarray,
                 o_sj: np.ndarray, o_si: np.ndarray, o_dt: np.ndarray, o_flow: np.ndarray) -> None:
    """Interleave the strips' rows (each in stream order, events disjoint) into stream order:
    an event's rows go where the sequential loop would have written them."""
    first_row = filled(n + 1, 0, np.int64)
    for s in range(seg_start.shape[0]):
        for j in range(seg_start[s], seg_start[s] + seg_len[s]):
            first_row[i_event[j] - seq0 + 1] += 1
    for e in range(n):
        first_row[e + 1] += first_row[e]
    for s in range(seg_start.shape[0]):
        prev = -1
        pos = 0
        for j in range(seg_start[s], seg_start[s] + seg_len[s]):
            e = i_event[j] - seq0
            if e != prev:
                prev = e
                pos = first_row[e]
            o_event[pos] = i_event[j]
            o_off[pos] = i_off[j]
            o_aj[pos] = i_aj[j]
            o_ai[pos] = i_ai[j]
            o_sj[pos] = i_sj[j]
            o_si[pos] = i_si[j]
            o_dt[pos] = i_dt[j]
            o_flow[pos, 0] = i_flow[j, 0]
            o_flow[pos, 1] = i_flow[j, 1]
            pos += 1


@kernel()
def strip_cuts(y: np.ndarray, height: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` strips of consecutive rows with about ``len(y) / count`` of the events
    each: ``(first rows, end rows, events per strip)``. Each cut is the row boundary nearest
    to its share of the cumulative row counts; cuts that fall together merge (fewer strips,
    none empty of rows)."""
    n = y.shape[0]
    cum = filled(height, 0, np.int64)
    for i in range(n):
        cum[y[i]] += 1
    for r in range(1, height):
        cum[r] += cum[r - 1]
    cuts = np.empty(count, np.int64)
    for k in range(1, count):
        target = k * (n / count)
        row = np.searchsorted(cum, target)  # first row whose cumulative count reaches it
        below = cum[row - 1] if row > 0 else 0
        cut = row if target - below < cum[row] - target else row + 1  # the nearer boundary
        cuts[k - 1] = min(max(cut, 1), height)
    cuts[count - 1] = height
    cuts.sort()
    m = 0
    for k in range(count):
        if m == 0 or cuts[k] != cuts[m - 1]:
            cuts[m] = cuts[k]
            m += 1
    ends = cuts[:m].copy()
    lo = np.empty(m, np.int64)
    own = np.empty(m, np.int64)
    for k in range(m):
        lo[k] = ends[k - 1] if k else 0
        own[k] = cum[ends[k] - 1] - (cum[lo[k] - 1] if lo[k] else 0)
    return lo, ends, own


@kernel(parallel=True)
def search_strips_merged(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                         srch: np.ndarray, seq0: int, width: int, height: int, off_x: np.ndarray,
                         off_y: np.ndarray, dt_lo: np.ndarray, dt_hi: np.ndarray, hi_j: np.ndarray,
                         num_x: np.ndarray, num_y: np.ndarray, history: int, refractory: int,
                         tol_abs: int, permille: int, last: np.ndarray, hist: np.ndarray,
                         hist_s: np.ndarray, lo_s: np.ndarray, hi_s: np.ndarray, r2: int,
                         halo_pix0: int, halo_cell0: int, cap: int) -> tuple:
    """The first pass of a batch in strips, in one call: the private rows' copy
    (:func:`copy_halos`), every strip's search in parallel into outputs of ``cap`` rows each
    (:func:`search_strips`) and, when no strip stopped early, the merge into stream order
    (:func:`merge_strips`).

    Returns ``(complete, starts, n_outs, strip outputs (8), merged outputs (8))``; without
    ``complete`` the merged outputs are empty and the caller goes on from ``starts``."""
    n = x.shape[0]
    count = lo_s.shape[0]
    x_min, x_max = width, -1
    for i in range(n):
        x_min = min(x_min, x[i])
        x_max = max(x_max, x[i])
    copy_halos(lo_s, hi_s, r2, width, height, x_min, x_max, last, hist, hist_s, halo_pix0,
                halo_cell0)
    rows = count * cap
    o_event, o_off, o_aj, o_ai = (np.empty(rows, np.int64), np.empty(rows, np.int64),
                                  np.empty(rows, np.int64), np.empty(rows, np.int64))
    o_sj, o_si, o_dt = np.empty(rows, np.int64), np.empty(rows, np.int64), np.empty(rows, np.int64)
    o_flow = np.empty((rows, 2), np.float32)
    starts = filled(count, 0, np.int64)
    n_outs = filled(count, 0, np.int64)
    strip_pix = 2 * r2 * width
    for s in prange(count):
        a, b = s * cap, (s + 1) * cap
        k, m = search_kernel(
            x, y, t, p, srch, 0, seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j, num_x,
            num_y, history, refractory, tol_abs, permille, last, hist, hist_s, o_event[a:b],
            o_off[a:b], o_aj[a:b], o_ai[a:b], o_sj[a:b], o_si[a:b], o_dt[a:b], o_flow[a:b],
            0, lo_s[s], hi_s[s], r2, halo_pix0 + s * strip_pix, halo_cell0 + s * 2 * strip_pix)
        starts[s] = k
        n_outs[s] = m
    complete = True
    total = 0
    for s in range(count):
        complete = complete and starts[s] >= n
        total += n_outs[s]
    if not complete:
        total = 0
    d_event, d_off, d_aj, d_ai = (np.empty(total, np.int64), np.empty(total, np.int64),
                                  np.empty(total, np.int64), np.empty(total, np.int64))
    d_sj, d_si, d_dt = (np.empty(total, np.int64), np.empty(total, np.int64),
                        np.empty(total, np.int64))
    d_flow = np.empty((total, 2), np.float32)
    if complete:
        seg_start = np.empty(count, np.int64)
        for s in range(count):
            seg_start[s] = s * cap
        merge_strips(n, seq0, seg_start, n_outs, o_event, o_off, o_aj, o_ai, o_sj, o_si,
                      o_dt, o_flow, d_event, d_off, d_aj, d_ai, d_sj, d_si, d_dt, d_flow)
    return (complete, starts, n_outs, o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow,
            d_event, d_off, d_aj, d_ai, d_sj, d_si, d_dt, d_flow)
