"""Compiled CPU kernels of the flow (numba): the candidate search and the rounded distance.

The batched tensor search of :mod:`evtrack.flow.candidates` runs on CPU and CUDA, but on a
CPU most of its time goes to the passes it needs for causality: on a fast object at
640x480 a quarter of the events are burst onsets and a (pixel, polarity) cell repeats every
~1,500 onsets, so a 100k-event chunk needs ~25 passes of small tensor operations. The rule
itself is sequential and cheap per event (at most ``D * K * K`` timing tests), so on CPU a
compiled event-by-event loop is the faster form of the *same* rule:

* :class:`CompiledSearch` is a drop-in for :class:`~evtrack.flow.candidates.CandidateSearch`
  (same candidates, bit for bit, in the same order; same stream indices; state carried
  across calls). It keeps ``history`` entries per cell, newest first, like the sequential
  reference of the tests, and tests the speed bounds as the integer ``t_k - t_i`` bounds of
  :func:`~evtrack.flow.config.dt_bounds_us`. The search is bound by the latency of its
  lookups (up to ``2 * D`` cells around each event), so its state is compact: int32 times
  relative to a base that moves forward as the stream goes on (as
  :class:`~evtrack.flow.history.EventHistory`'s), an empty slot marked by a time too old for
  any triplet, and a pixel's latest time and polarity packed in one int32;
* large batches are searched in horizontal strips of the sensor in parallel (one per
  thread, each with private copies of the ``2 * radius`` rows around it; see
  :class:`CompiledSearch`), with the same candidates in the same order;
* :mod:`evtrack.flow.registration_compiled` is the compiled form of the registration; it
  uses ``_rounded_distance`` here (the exact rounded distance of
  :func:`~evtrack.flow.registration.rounded_distance`, for one float32 value).

``FlowConfig.backend`` chooses: ``"auto"`` (default) uses these kernels on CPU when numba is
installed, ``"torch"`` never, ``"compiled"`` always (an error without numba or on CUDA). The
tests check both backends against the same sequential reference and against each other.

The first use compiles the kernels (about 3 s); numba caches them on disk (``__pycache__``
beside this file, or ``NUMBA_CACHE_DIR``), so later processes start in a fraction of a second.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.candidates import Candidates
from evtrack.flow.config import US_PER_S, FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.history import EMPTY_T, MAX_SPAN_US, T_KEEP, T_LIMIT

try:  # numba is optional: without it the torch backend runs everywhere
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

__all__ = ["available", "CompiledSearch"]

NO_EVENT = np.int32(-(1 << 31))
"""``last`` of a pixel without an event (``last = 2 * t + (p > 0)`` otherwise)."""
_prange = numba.prange if numba is not None else range


def available() -> bool:
    """Whether numba is installed (the compiled kernels can run)."""
    return numba is not None


@contextmanager
def torch_thread_count():
    """Run numba's parallel kernels inside on as many threads as torch may use, and leave
    torch's count as it was: numba's OpenMP layer resets the process's OpenMP thread count
    (torch's) when it starts."""
    threads = torch.get_num_threads()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def _njit(**kwargs):
    def wrap(fn):
        return numba.njit(cache=True, nogil=True, **kwargs)(fn) if numba is not None else fn
    return wrap


@_njit()
def _filled(shape, value, dtype):
    """``np.full(shape, value, dtype)`` compiled on its own. Written inside a
    ``parallel=True`` kernel, an array constructor (``np.zeros``, ``np.full``, a copy) becomes
    a parallel loop of its own, one thread-pool launch per array, which costs more than
    filling the few thousand entries of a tracker's call; through this helper it stays a
    plain loop."""
    return np.full(shape, value, dtype)


@_njit()
def _pixel_index(yy, xx, lo, hi, r2, width, halo_pix):
    """Index into ``last`` of pixel ``(xx, yy)``: the shared rows ``[lo, hi)`` of the strip's
    own part of the sensor, or the strip's private copy of the ``r2`` rows above / below."""
    if yy >= lo and yy < hi:
        return yy * width + xx
    row = yy - lo + r2 if yy < lo else r2 + yy - hi
    return halo_pix + row * width + xx


@_njit()
def _cell_index(plane, yy, xx, lo, hi, r2, width, pixels, halo_cell):
    """Index into ``hist`` / ``hist_s`` of the (pixel, polarity) cell (``plane`` 0: positive,
    1: negative), shared or private as :func:`_pixel_index`."""
    if yy >= lo and yy < hi:
        return plane * pixels + yy * width + xx
    row = yy - lo + r2 if yy < lo else r2 + yy - hi
    return halo_cell + (plane * 2 * r2 + row) * width + xx


@_njit()
def _search_kernel(x, y, t, p, srch, start, seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
                   num_x, num_y, history, refractory, tol_abs, permille, last, hist, hist_s,
                   o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow, n_out,
                   lo, hi, r2, halo_pix, halo_cell):
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
    n_off = off_x.shape[0]
    capacity = o_event.shape[0]
    worst = n_off * history * history
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
        if (refractory > 0 and prev != NO_EVENT and (prev & 1) == positive
                and tk - (prev >> 1) <= refractory):
            continue  # inside a burst: neither searched nor stored
        plane = 1 - positive
        if own and srch[k - 1]:
            # inner: every cell read lies in the strip's own rows and inside the sensor
            inner = yk - r2 >= lo and yk + r2 < hi and xk >= r2 and xk < width - r2
            cell_k = plane * pixels + yk * width + xk
            for o in range(n_off):
                if inner:
                    cj = cell_k - step[o]
                    ci = cj - step[o]
                else:
                    dx, dy = off_x[o], off_y[o]
                    xi, yi = xk - 2 * dx, yk - 2 * dy
                    if xi < 0 or xi >= width or yi < 0 or yi >= height:
                        continue
                    cj = _cell_index(plane, yk - dy, xk - dx, lo, hi, r2, width, pixels,
                                     halo_cell)
                    ci = _cell_index(plane, yi, xi, lo, hi, r2, width, pixels, halo_cell)
                if hist[cj, 0] == EMPTY_T or hist[ci, 0] == EMPTY_T:
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
                        dji = tj - ti
                        if dji < 1 or dki < lo_dt:
                            continue
                        if abs(dkj - dji) * 1000 > tol_abs + permille * dki:
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
        # store e_k: newest first, the oldest (or an empty slot) drops out
        c = _cell_index(plane, yk, xk, lo, hi, r2, width, pixels, halo_cell)
        for a in range(history - 1, 0, -1):
            hist[c, a] = hist[c, a - 1]
            hist_s[c, a] = hist_s[c, a - 1]
        hist[c, 0] = tk
        hist_s[c, 0] = seq
    return k, n_out


@_njit()
def _copy_halos(lo_s, hi_s, r2, width, height, x_min, x_max, last, hist, hist_s, halo_pix0,
                halo_cell0):
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


@_njit(parallel=True)
def _search_strips(x, y, t, p, srch, starts, seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
                   num_x, num_y, history, refractory, tol_abs, permille, last, hist, hist_s,
                   o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow, n_outs, cap,
                   lo_s, hi_s, r2, halo_pix0, halo_cell0):
    """:func:`_search_kernel` on every strip in parallel; strip ``s`` writes its rows at
    ``[s * cap, (s + 1) * cap)`` of the outputs and resumes from ``starts[s]``."""
    strip_pix = 2 * r2 * width
    for s in _prange(lo_s.shape[0]):
        if starts[s] >= x.shape[0]:
            continue
        a, b = s * cap, (s + 1) * cap
        k, m = _search_kernel(
            x, y, t, p, srch, starts[s], seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
            num_x, num_y, history, refractory, tol_abs, permille, last, hist, hist_s,
            o_event[a:b], o_off[a:b], o_aj[a:b], o_ai[a:b], o_sj[a:b], o_si[a:b], o_dt[a:b],
            o_flow[a:b], n_outs[s], lo_s[s], hi_s[s], r2, halo_pix0 + s * strip_pix,
            halo_cell0 + s * 2 * strip_pix)
        starts[s] = k
        n_outs[s] = m


@_njit()
def _merge_strips(n, seq0, seg_start, seg_len, i_event, i_off, i_aj, i_ai, i_sj, i_si, i_dt,
                  i_flow, o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow):
    """Interleave the strips' rows (each in stream order, events disjoint) into stream order:
    an event's rows go where the sequential loop would have written them."""
    first_row = _filled(n + 1, 0, np.int64)
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


@_njit()
def _strip_cuts(y, height, count):
    """``count`` strips of consecutive rows with about ``len(y) / count`` of the events
    each: ``(first rows, end rows, events per strip)``. Each cut is the row boundary nearest
    to its share of the cumulative row counts; cuts that fall together merge (fewer strips,
    none empty of rows)."""
    n = y.shape[0]
    cum = _filled(height, 0, np.int64)
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


@_njit(parallel=True)
def _search_strips_merged(x, y, t, p, srch, seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
                          num_x, num_y, history, refractory, tol_abs, permille, last, hist,
                          hist_s, lo_s, hi_s, r2, halo_pix0, halo_cell0, cap):
    """The first pass of a batch in strips, in one call: the private rows' copy
    (:func:`_copy_halos`), every strip's search in parallel into outputs of ``cap`` rows each
    (:func:`_search_strips`) and, when no strip stopped early, the merge into stream order
    (:func:`_merge_strips`).

    Returns ``(complete, starts, n_outs, strip outputs (8), merged outputs (8))``; without
    ``complete`` the merged outputs are empty and the caller goes on from ``starts``."""
    n = x.shape[0]
    count = lo_s.shape[0]
    x_min, x_max = width, -1
    for i in range(n):
        x_min = min(x_min, x[i])
        x_max = max(x_max, x[i])
    _copy_halos(lo_s, hi_s, r2, width, height, x_min, x_max, last, hist, hist_s, halo_pix0,
                halo_cell0)
    rows = count * cap
    o_event, o_off, o_aj, o_ai = (np.empty(rows, np.int64), np.empty(rows, np.int64),
                                  np.empty(rows, np.int64), np.empty(rows, np.int64))
    o_sj, o_si, o_dt = np.empty(rows, np.int64), np.empty(rows, np.int64), np.empty(rows, np.int64)
    o_flow = np.empty((rows, 2), np.float32)
    starts = _filled(count, 0, np.int64)
    n_outs = _filled(count, 0, np.int64)
    strip_pix = 2 * r2 * width
    for s in _prange(count):
        a, b = s * cap, (s + 1) * cap
        k, m = _search_kernel(
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
        _merge_strips(n, seq0, seg_start, n_outs, o_event, o_off, o_aj, o_ai, o_sj, o_si,
                      o_dt, o_flow, d_event, d_off, d_aj, d_ai, d_sj, d_si, d_dt, d_flow)
    return (complete, starts, n_outs, o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow,
            d_event, d_off, d_aj, d_ai, d_sj, d_si, d_dt, d_flow)


class CompiledSearch:
    """The candidate search as one compiled event loop (CPU only; see the module docstring).

    Same interface and results as :class:`~evtrack.flow.candidates.CandidateSearch`:
    ``search(x, y, t, p) -> Candidates`` on consecutive batches of one stream, ``reset()``,
    ``next_seq``.

    **Strips in parallel.** The rule is sequential in time but local in space: an event reads
    the cells of rows at most ``2 * radius`` away. A batch of at least
    ``parallel_min_events`` events is therefore split into horizontal strips of the sensor
    (as many as ``torch.get_num_threads()``, with equal numbers of the batch's events), each
    searched by one thread in stream order. A strip searches and stores its own events in the
    shared state, and also stores the events of the ``2 * radius`` rows above and below it
    into a private copy of those rows taken at the start of the batch: every search sees the
    state the sequential loop would, so the candidates are the same bit for bit. The strips'
    rows are then interleaved back into stream order.

    Args:
        config: the flow parameters (sensor size must be set).
        device: must be CPU.
        strips: force this many strips for every batch (``None``: as described above).
    """

    parallel_min_events: int = 7000
    """Smaller batches are searched in one strip: the private rows' copy, the parallel
    launch and the merge cost more than the second thread saves. Measured on the mustard
    `faster` scene (2 threads, search alone): one strip 2.64 / 2.28 M ev/s against two
    strips' 2.33 / 2.16 in 5k / 6k-event batches; two strips 2.76 / 2.68 against 2.44 / 2.42
    in 8k / 10k ones."""
    rows_per_event: int = 4
    """Output rows first allocated per event (plus one event's worst case); a loop that
    might overflow stops and goes on in an output twice as large."""
    min_rows: int = 1024
    """Smallest output allocation, rows."""

    def __init__(self, config: FlowConfig, device: str | torch.device = "cpu",
                 strips: int | None = None) -> None:
        if numba is None:
            raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
        if config.sensor_size is None:
            raise ValueError("CompiledSearch needs config.sensor_size")
        if strips is not None and int(strips) < 1:
            raise ValueError(f"CompiledSearch: strips must be >= 1, got {strips}")
        self.device = torch.device(device)
        if self.device.type != "cpu":
            raise ValueError(f"the compiled flow backend runs on CPU, not {self.device}")
        self.config = config
        self.strips = None if strips is None else int(strips)
        self.width, self.height = config.sensor_size
        self._r2 = 2 * config.radius  # the rows a search reads on either side of its event
        offsets = search_offsets(config.radius)
        bounds = dt_bounds_us(offsets, config.min_speed, config.max_speed, config.max_span_us)
        self._off_x = np.ascontiguousarray(offsets[:, 0], dtype=np.int64)
        self._off_y = np.ascontiguousarray(offsets[:, 1], dtype=np.int64)
        self._lo = np.ascontiguousarray(bounds[:, 0], dtype=np.int64)
        self._hi = np.ascontiguousarray(bounds[:, 1], dtype=np.int64)
        # e_j with t_k - t_j >= hi_j complete no triplet (as CandidateSearch's stage 1)
        a_max = (self._hi * (1000 + config.tolerance_permille)
                 + config.tolerance_us * 1000) // 2000
        self._hi_j = np.minimum(self._hi, a_max + 1)
        # the candidate flow's numerator 2 d * 1e6 in float32, as the torch search has it
        self._num_x = (np.float32(2.0 * US_PER_S) * self._off_x.astype(np.float32))
        self._num_y = (np.float32(2.0 * US_PER_S) * self._off_y.astype(np.float32))
        self._worst = len(offsets) * config.history * config.history
        self.reset()

    def reset(self) -> None:
        """Forget every event seen."""
        # private rows for the strips the thread count allows now (more are added when
        # needed): growing them later copies the whole state
        strips = self.strips if self.strips is not None else min(
            torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
        self._allocate(strips if strips > 1 else 0)
        self.next_seq = 0
        self.t_base: int | None = None
        """The base (µs) of the state's relative times; ``None`` before the first event."""

    def continue_bursts(self, x: np.ndarray, y: np.ndarray, t: np.ndarray,
                        p: np.ndarray) -> None:
        """Make each given event the continuation of a burst: its pixel's latest event
        becomes one of the same polarity 1 µs before it, so that the burst filter skips it
        when it is searched next (see :meth:`TripletFlow.continue_bursts
        <evtrack.flow.TripletFlow.continue_bursts>`). One event per pixel, time-sorted, not
        before the events seen."""
        if not len(t):
            return
        t = np.asarray(t, np.int64)
        first = int(t[0]) - 1
        if self.t_base is not None:
            # an event at the base's own µs (the stream's first): its previous event lies
            # 1 µs before the base, relative time -1, which the int32 state holds
            first = max(first, self.t_base)
        self._ensure_range(first, int(t[-1]))
        pix = np.asarray(y, np.int64) * self.width + np.asarray(x, np.int64)
        positive = (np.asarray(p) > 0).astype(np.int64)
        self.last[pix] = (2 * (t - 1 - self.t_base) + positive).astype(np.int32)

    def _allocate(self, strips: int) -> None:
        """Fresh state with private rows for ``strips`` strips after the shared ones."""
        pixels = self.width * self.height
        extra = strips * 2 * self._r2 * self.width  # pixels of private rows
        k = self.config.history
        self.last = np.full(pixels + extra, NO_EVENT, dtype=np.int32)  # 2 t + (p > 0)
        self.hist = np.full((2 * (pixels + extra), k), EMPTY_T, dtype=np.int32)  # times
        self.hist_s = np.zeros((2 * (pixels + extra), k), dtype=np.int64)  # stream indices
        self._room = strips

    def _make_room(self, strips: int) -> None:
        """Grow the private rows to ``strips`` strips, keeping the shared state."""
        if strips <= self._room:
            return
        pixels = self.width * self.height
        last, hist, hist_s = self.last, self.hist, self.hist_s
        self._allocate(strips)
        self.last[:pixels] = last[:pixels]
        self.hist[:2 * pixels] = hist[:2 * pixels]
        self.hist_s[:2 * pixels] = hist_s[:2 * pixels]

    def _strip_rows(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First and end row of each strip (consecutive rows with about equal event counts)
        and the number of the batch's events in each."""
        n = y.shape[0]
        count = self.strips if self.strips is not None else (
            1 if n < self.parallel_min_events else
            min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
        count = max(1, min(count, self.height))
        if count == 1:
            return (np.zeros(1, np.int64), np.full(1, self.height, np.int64),
                    np.full(1, n, np.int64))
        return _strip_cuts(y, self.height, count)

    def __call__(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor,
                 search: Tensor | None = None) -> Candidates:
        """Search the candidates of the next events of the stream and add them to the history.

        Args:
            x, y: (n,) integer pixel coordinates (inside the sensor; not checked here).
            t: (n,) int64 timestamps in µs, non-decreasing and not before earlier calls.
            p: (n,) polarity (+1 / -1).
            search: optional (n,) bool: the events whose candidates are searched (default
                all); the others enter the history all the same (see
                :meth:`~evtrack.flow.candidates.CandidateSearch.__call__`).

        Returns:
            The candidates, with stream indices continuing those of earlier calls.
        """
        n = int(t.shape[0])
        if n == 0:
            return Candidates.empty(self.device)
        x, y, t, p = (np.ascontiguousarray(a.detach().cpu().numpy(), dtype=np.int64)
                      for a in (x, y, t, p))
        srch = (np.ones(n, np.uint8) if search is None else
                np.ascontiguousarray(search.detach().cpu().numpy(), dtype=np.uint8))
        parts = []
        start = 0
        while start < n:  # pieces spanning less than MAX_SPAN_US, as the torch search
            stop = int(np.searchsorted(t, t[start] + MAX_SPAN_US, side="left"))
            self._ensure_range(int(t[start]), int(t[stop - 1]))
            arrays = [x[start:stop], y[start:stop], t[start:stop] - self.t_base,
                      p[start:stop], srch[start:stop]]
            lo_s, hi_s, own = self._strip_rows(arrays[1])
            if lo_s.shape[0] == 1:
                parts += self._search_whole(arrays, stop - start)
            else:
                parts += self._search_in_strips(arrays, stop - start, lo_s, hi_s, own)
            self.next_seq += stop - start
            start = stop
        return Candidates.cat(parts)

    def _ensure_range(self, t_first: int, t_last: int) -> None:
        """Move the base so that ``[t_first, t_last]`` (spanning less than ``MAX_SPAN_US``)
        maps into ``[0, T_LIMIT)``; entries older than ``T_KEEP`` before ``t_last`` are
        emptied (beyond any speed bound, see ``FlowConfig``)."""
        if self.t_base is None:
            self.t_base = t_first
        if t_first < self.t_base:
            raise ValueError(f"events must be given in stream order: t={t_first} µs is before "
                             f"the search's time base ({self.t_base} µs)")
        if t_last - self.t_base < T_LIMIT:
            return
        shift = t_last - self.t_base - T_KEEP
        pixels = self.width * self.height
        hist = self.hist[:2 * pixels].astype(np.int64) - shift
        self.hist[:2 * pixels] = np.where((hist >= 0) & (self.hist[:2 * pixels] != EMPTY_T),
                                          hist, EMPTY_T)
        last = self.last[:pixels].astype(np.int64)
        moved = (last >> 1) - shift
        self.last[:pixels] = np.where((last != NO_EVENT) & (moved >= 0),
                                      2 * moved + (last & 1), NO_EVENT)
        self.t_base += shift

    def _capacity(self, n: int) -> int:
        return max(self.rows_per_event * n + self._worst, self.min_rows)

    def _params(self) -> tuple:
        cfg = self.config
        return (self.width, self.height, self._off_x, self._off_y, self._lo, self._hi,
                self._hi_j, self._num_x, self._num_y, cfg.history, cfg.refractory_us,
                cfg.tolerance_us * 1000, cfg.tolerance_permille, self.last, self.hist,
                self.hist_s)

    def _search_whole(self, arrays: list[np.ndarray], n: int) -> list[Candidates]:
        """One sequential loop over the batch (whole sensor)."""
        capacity = self._capacity(n)
        parts = []
        start = 0
        while start < n:
            out = [np.empty(capacity, np.int64) for _ in range(7)]
            flow = np.empty((capacity, 2), np.float32)
            start, rows = _search_kernel(*arrays, start, self.next_seq, *self._params(), *out,
                                         flow, 0, 0, self.height, self._r2, 0, 0)
            parts.append(Candidates(*(torch.from_numpy(a[:rows]) for a in out),
                                    flow=torch.from_numpy(flow[:rows])))
            capacity *= 2
        return parts

    def _search_in_strips(self, arrays: list[np.ndarray], n: int, lo_s: np.ndarray,
                          hi_s: np.ndarray, own: np.ndarray) -> list[Candidates]:
        """The strips in parallel (see the class docstring), merged into stream order."""
        count = lo_s.shape[0]
        self._make_room(count)
        pixels = self.width * self.height
        with torch_thread_count():
            capacity = self._capacity(int(own.max()))
            complete, starts, n_outs, *out, flow, d_event, d_off, d_aj, d_ai, d_sj, d_si, \
                d_dt, d_flow = _search_strips_merged(
                    *arrays, self.next_seq, *self._params(), lo_s, hi_s, self._r2, pixels,
                    2 * pixels, capacity)
            if complete:  # the usual case: one pass, merged in the same call
                return [Candidates(*(torch.from_numpy(a) for a in (
                    d_event, d_off, d_aj, d_ai, d_sj, d_si, d_dt)),
                    flow=torch.from_numpy(d_flow))]
            rounds = [(out, flow, n_outs, capacity)]  # (outputs, rows per strip) of each pass
            while True:
                capacity *= 2  # a strip's output was nearly full: it goes on in a larger one
                out = [np.empty(count * capacity, np.int64) for _ in range(7)]
                flow = np.empty((count * capacity, 2), np.float32)
                n_outs = np.zeros(count, np.int64)
                _search_strips(*arrays, starts, self.next_seq, *self._params(), *out, flow,
                               n_outs, capacity, lo_s, hi_s, self._r2, pixels, 2 * pixels)
                rounds.append((out, flow, n_outs, capacity))
                if bool((starts >= n).all()):
                    break
            seg_start, seg_len, src, src_flow = _strip_segments(rounds, count)
            total = int(seg_len.sum())
            dst = [np.empty(total, np.int64) for _ in range(7)]
            dst_flow = np.empty((total, 2), np.float32)
            _merge_strips(n, self.next_seq, seg_start, seg_len, *src, src_flow, *dst, dst_flow)
        return [Candidates(*(torch.from_numpy(a) for a in dst), flow=torch.from_numpy(dst_flow))]


def _strip_segments(rounds: list, count: int
                    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Each strip's rows as one segment of flat arrays, its passes in order.

    With one pass the output buffers are used as they are (strip ``s`` at ``s * capacity``);
    after an overflow the passes' rows are gathered strip by strip."""
    if len(rounds) == 1:
        out, flow, n_outs, capacity = rounds[0]
        return np.arange(count, dtype=np.int64) * capacity, n_outs, out, flow
    pieces = [[] for _ in range(8)]
    seg_len = np.zeros(count, np.int64)
    for s in range(count):
        for out, flow, n_outs, capacity in rounds:
            a, b = s * capacity, s * capacity + int(n_outs[s])
            for f in range(7):
                pieces[f].append(out[f][a:b])
            pieces[7].append(flow[a:b])
            seg_len[s] += b - a
    seg_start = np.concatenate([[0], np.cumsum(seg_len)[:-1]]).astype(np.int64)
    src = [np.concatenate(pieces[f]) for f in range(7)]
    return seg_start, seg_len, src, np.concatenate(pieces[7])


@_njit()
def _rounded_distance(d2, cost_scale, q_max):
    """:func:`evtrack.flow.registration.rounded_distance` of one float32 ``d2``."""
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
