"""Batched, causal search of triplet candidates (the per-event step of the flow).

The matching rule is stated in :mod:`evtrack.flow.config`. This module evaluates it for a
chunk of events with tensor operations only, and still lets every event see exactly the
events before it, including earlier events of the same chunk:

0. With ``refractory_us > 0``, only burst onsets take part: an event is skipped (neither
   searched nor stored; its stream index still counts) when the previous event of its pixel
   (kept or not, either polarity) has the same polarity and is at most ``refractory_us``
   older. A moving edge makes each pixel fire a burst of same-polarity events; the onsets
   (first event after a polarity change or a pause) move rigidly with the pattern.
1. The chunk is cut into *passes*: maximal runs of consecutive events in which no
   (pixel, polarity) cell receives more than ``pass_repeats`` events. The cut points come
   from one stable sort by cell (the ``pass_repeats``-th previous event of each event's cell)
   and a reverse cumulative minimum; only the few cut points are followed in Python.
2. A pass writes all its events into the ring buffer first (``history + pass_repeats``
   slots per cell, so nothing a lookup of this pass needs is overwritten), then evaluates the
   lookups of its events in blocks of ``block_size`` events. A lookup skips the cell's entries
   that come after the querying event (keys carry the stream index), which leaves exactly the
   ``history`` events that a sequential, event-by-event ring buffer would hold.
   With ``FlowConfig.lookup == "sorted"`` (the CUDA default) steps 1-2 are replaced by one
   pass per chunk: :class:`~evtrack.flow.history.SortedChunk` sorts the chunk by cell and
   answers the same lookups by binary search, then updates the rings once.
3. For each event, displacement and pair of visible entries, the triplet tests run on a dense
   ``(block, D, K, K)`` tensor; the surviving positions are the candidates, in the order
   (event, displacement, age of e_j, age of e_i).

Peak tensor sizes are bounded by ``block_size`` (and the sort by ``chunk_size``), never by
the event rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.config import FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.constants import MAX_SPAN_US, US_PER_S
from evtrack.flow.history import EventHistory, SortedChunk

__all__ = ["Candidates", "CandidateSearch", "pass_bounds", "pass_starts", "NEVER_US"]

NEVER_US = -(1 << 62)
"""Timestamp (µs) of the previous event of a cell that has none."""
_TABLE_MAX = 1 << 22
"""Largest ``hi_max`` (µs) for which the tolerance interval is tabulated (2 x 16 MiB)."""


@dataclass
class Candidates:
    """Candidate flows of a batch of events, one row per matching triplet.

    Attributes:
        event: (M,) int64 stream index of ``e_k`` (position of the event in the whole
            stream since the last reset).
        offset: (M,) int64 index of the displacement ``d`` in :func:`search_offsets`.
        age_j: (M,) int64 age of ``e_j`` in its cell's history (0 = newest).
        age_i: (M,) int64 age of ``e_i``.
        seq_j: (M,) int64 stream index of ``e_j``.
        seq_i: (M,) int64 stream index of ``e_i``.
        dt_us: (M,) int64 ``t_k - t_i`` in µs.
        flow: (M, 2) float32 candidate flow ``2 d / (t_k - t_i)`` in px/s.
    """

    event: Tensor
    offset: Tensor
    age_j: Tensor
    age_i: Tensor
    seq_j: Tensor
    seq_i: Tensor
    dt_us: Tensor
    flow: Tensor

    def __len__(self) -> int:
        return int(self.event.shape[0])

    @classmethod
    def empty(cls, device: str | torch.device = "cpu") -> Candidates:
        z = torch.zeros(0, dtype=torch.int64, device=device)
        return cls(z, z, z, z, z, z, z, torch.zeros(0, 2, dtype=torch.float32, device=device))

    @staticmethod
    def cat(parts: list[Candidates]) -> Candidates:
        """Concatenate in order (an empty list gives empty CPU candidates)."""
        if not parts:
            return Candidates.empty()
        if len(parts) == 1:
            return parts[0]
        return Candidates(*(torch.cat([getattr(p, f) for p in parts])
                            for f in ("event", "offset", "age_j", "age_i", "seq_j", "seq_i",
                                      "dt_us", "flow")))

    def select(self, index: Tensor) -> Candidates:
        """Rows ``index`` (bool mask or int64 indices)."""
        return Candidates(*(getattr(self, f)[index]
                            for f in ("event", "offset", "age_j", "age_i", "seq_j", "seq_i",
                                      "dt_us", "flow")))


def pass_starts(cell: Tensor, repeats: int) -> Tensor:
    """For every start ``s``, where a pass beginning at ``s`` must end.

    Args:
        cell: (n,) int64 cell id of each event, in stream order.
        repeats: L, the most events of one cell a pass may hold.

    Returns:
        (rank, next_end): ``rank`` (n,) int64 is each event's rank among the chunk's events of
        its cell (0 for the first); ``next_end`` (n,) int64 is, for each start ``s``, the
        smallest ``m > s`` whose cell already has ``L`` events in ``[s, m)`` (``n`` if none).
    """
    n = cell.shape[0]
    device = cell.device
    if n == 0:
        z = torch.zeros(0, dtype=torch.int64, device=device)
        return z, z
    sorted_cell, order = torch.sort(cell, stable=True)
    pos = torch.arange(n, device=device)
    new_group = torch.ones(n, dtype=torch.bool, device=device)
    new_group[1:] = sorted_cell[1:] != sorted_cell[:-1]
    group_start = torch.cummax(torch.where(new_group, pos, torch.zeros_like(pos)), 0).values
    rank_sorted = pos - group_start
    rank = torch.empty_like(rank_sorted)
    rank[order] = rank_sorted
    # The L-th previous event of the same cell (in the chunk), as a stream position.
    has_prev = rank_sorted >= repeats
    prev_pos = order[(pos - repeats).clamp_min(0)]
    first_conflict = torch.full((n,), n, dtype=torch.int64, device=device)
    src = order[has_prev]
    first_conflict.scatter_reduce_(0, prev_pos[has_prev], src, reduce="amin")
    next_end = torch.flip(torch.cummin(torch.flip(first_conflict, (0,)), 0).values, (0,))
    return rank, next_end


def pass_bounds(next_end: Tensor) -> list[tuple[int, int]]:
    """Follow :func:`pass_starts`' ``next_end`` from 0: the greedy, maximal passes."""
    ends = next_end.cpu().numpy()
    n = ends.shape[0]
    bounds = []
    start = 0
    while start < n:
        stop = int(ends[start])
        bounds.append((start, stop))
        start = stop
    return bounds


class CandidateSearch:
    """The batched candidate search over a persistent :class:`EventHistory` (the torch
    backend's search; any device).

    Args:
        config: the flow parameters (sensor size must be set).
        device: torch device.
    """

    runs_ahead: bool = False
    """The search holds the GIL: a caller gains nothing by searching the next batch in a
    worker thread (see :class:`~evtrack.flow.backends.CandidateSearchBackend`)."""

    def __init__(self, config: FlowConfig, device: str | torch.device = "cpu") -> None:
        if config.sensor_size is None:
            raise ValueError("CandidateSearch needs config.sensor_size")
        self.config = config
        self.device = torch.device(device)
        self.width, self.height = config.sensor_size
        self.block_size = config.resolved_block_size(self.device.type)
        self.lookup = config.resolved_lookup(self.device.type)
        offsets = search_offsets(config.radius)
        dev = self.device
        self.offsets = torch.as_tensor(offsets, device=dev)
        self.reset()
        # cell-id offsets of the e_j (x - d) and e_i (x - 2d) pixels on the padded grid
        self.j_cell = self.offsets[:, 1] * self.history.row + self.offsets[:, 0]
        self.i_cell = 2 * self.j_cell
        bounds = dt_bounds_us(offsets, config.min_speed, config.max_speed, config.max_span_us)
        self.dt_lo32 = torch.as_tensor(bounds[:, 0], dtype=torch.int32, device=dev)
        self.dt_hi32 = torch.as_tensor(bounds[:, 1], dtype=torch.int32, device=dev)
        # 2 d * 1e6, the numerator of the candidate flow (px * µs / s).
        self.flow_num = (2.0 * US_PER_S) * self.offsets.to(torch.float32)
        self.tol_abs = int(config.tolerance_us) * 1000
        self.tol_rel = config.tolerance_permille
        # stage 1 keeps an e_j only if some t_k - t_i can complete it: t_k - t_j < hi_d
        # (e_j precedes e_i) and, by the tolerance test (see _dt_ki_bounds), c >= a + 1 with
        # c (1000 + r) >= 2000 a - A, c <= hi_d: a <= (hi_d (1000 + r) + A) / 2000.
        # Exclusive bound of a = t_k - t_j per displacement:
        a_max = (bounds[:, 1] * (1000 + self.tol_rel) + self.tol_abs) // 2000
        self.dt_hi_j32 = torch.as_tensor(np.minimum(bounds[:, 1], a_max + 1), dtype=torch.int32,
                                         device=dev)
        self.dt_hi_j = self.dt_hi_j32[None, :, None]
        self.hi_max = int(bounds[:, 1].max()) if len(bounds) else 0
        self._tol_tables = self._tolerance_tables() if self.hi_max < _TABLE_MAX else None
        # both ends of the tabulated interval in one 8-byte word per entry (one gather)
        self._tol_words = (torch.stack(self._tol_tables, 1).view(torch.int64).reshape(-1)
                           if self._tol_tables is not None else None)

    def reset(self) -> None:
        """Forget every event seen."""
        cfg = self.config
        # padding 2r: the e_i pixel x - 2d of every event is a cell (empty outside the sensor)
        self.history = EventHistory(cfg.sensor_size, cfg.history, cfg.pass_repeats,
                                    pad=2 * cfg.radius, device=self.device)
        self._consumed = (torch.zeros(self.history.cells, dtype=torch.int64, device=self.device)
                          if cfg.pass_repeats > 1 else None)
        pixels = self.width * self.height
        self.last_t = torch.full((pixels,), NEVER_US, dtype=torch.int64, device=self.device)
        self.last_p = torch.zeros(pixels, dtype=torch.int8, device=self.device)
        self.next_seq = 0

    def continue_bursts(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor) -> None:
        """Make each given event the continuation of a burst: its pixel's latest event
        becomes one of the same polarity 1 µs before it (see :meth:`TripletFlow.continue_bursts
        <evtrack.flow.TripletFlow.continue_bursts>`).

        Args:
            x, y: (n,) integer pixel coordinates, one event per pixel.
            t: (n,) int64 timestamps in µs, not before the events seen.
            p: (n,) polarity (+1 / -1).
        """
        pix = (y.long() * self.width + x.long()).to(self.device)
        self.last_t.index_copy_(0, pix, t.to(device=self.device, dtype=torch.int64) - 1)
        self.last_p.index_copy_(0, pix, p.to(device=self.device, dtype=torch.int8))

    def moved(self, config: FlowConfig, device: torch.device) -> CandidateSearch:
        """This search with its history on ``device`` (``config``: the flow's parameters
        there); this search is left as it was."""
        new = CandidateSearch(config, device)
        new.history.load_state_dict(self.history.state_dict())
        new.next_seq = self.next_seq
        new.last_t = self.last_t.to(device)
        new.last_p = self.last_p.to(device)
        return new

    # ------------------------------------------------------------------ driver
    def __call__(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor,
                 search: Tensor | None = None) -> Candidates:
        """Search the candidates of the next events of the stream and add them to the history.

        Args:
            x, y: (n,) integer pixel coordinates (inside the sensor; not checked here).
            t: (n,) int64 timestamps in µs, non-decreasing and not before earlier calls.
            p: (n,) polarity (+1 / -1).
            search: optional (n,) bool: the events whose candidates are searched (default
                all). The others still pass the burst filter and enter the history, so later
                events form the same triplets with them; they only get no candidates of
                their own. (Here the candidates are found for all and those rows dropped;
                the compiled search skips the lookups.)

        Returns:
            The candidates, with stream indices continuing those of earlier calls.
        """
        n = int(t.shape[0])
        if n == 0:
            return Candidates.empty(self.device)
        if search is not None:
            seq0 = self.next_seq
            found = self(x, y, t, p)
            searched = search.to(found.event.device, torch.bool)
            return found.select(searched[found.event - seq0])
        dev = self.device
        x = x.to(dev, torch.int64)
        y = y.to(dev, torch.int64)
        t = t.to(dev, torch.int64)
        p = p.to(dev)
        parts = []
        for start, stop in self._chunks(t):
            parts.append(self._chunk(x[start:stop], y[start:stop], t[start:stop],
                                     p[start:stop]))
        return Candidates.cat(parts)

    def _chunks(self, t: Tensor) -> list[tuple[int, int]]:
        """Chunk bounds: at most ``chunk_size`` events spanning less than ``MAX_SPAN_US``."""
        n = int(t.shape[0])
        size = self.config.chunk_size
        out = []
        start = 0
        while start < n:
            stop = min(n, start + size)
            if int(t[stop - 1]) - int(t[start]) >= MAX_SPAN_US:
                limit = torch.tensor([int(t[start]) + MAX_SPAN_US], device=t.device)
                stop = int(torch.searchsorted(t[start:stop], limit)) + start
            out.append((start, stop))
            start = stop
        return out

    def _chunk(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor) -> Candidates:
        n = int(t.shape[0])
        hist = self.history
        dev = self.device
        seq = torch.arange(self.next_seq, self.next_seq + n, device=dev)
        if self.config.refractory_us > 0:
            onset = torch.nonzero(self._onsets(x, y, t, p)).reshape(-1)  # one sync on CUDA
            x, y, t, p, seq = (torch.index_select(v, 0, onset) for v in (x, y, t, p, seq))
        self.next_seq += n
        m = int(t.numel())
        if m == 0:
            return Candidates.empty(dev)
        cell = hist.cell_index(x, y, p)
        t_rel = hist.relative_times(t)
        pos = torch.arange(m, dtype=torch.int32, device=dev)
        if self.lookup == "sorted":
            chunk = SortedChunk(hist, cell, t_rel, seq)
            parts = [self._block(pos[b0:b0 + self.block_size], cell[b0:b0 + self.block_size],
                                 t_rel, seq, chunk)
                     for b0 in range(0, m, self.block_size)]
            chunk.close()
            return Candidates.cat(parts)
        rank, next_end = pass_starts(cell, self.config.pass_repeats)
        next_same = self._next_same_cell(cell)
        parts = []
        for start, stop in pass_bounds(next_end):
            sl = slice(start, stop)
            if self._consumed is None:
                in_rank = torch.zeros_like(rank[sl])
            else:  # rank among the pass's events of the cell
                in_rank = rank[sl] - self._consumed[cell[sl]]
            newest = next_same[sl] >= stop
            hist.open_pass(cell[sl], in_rank, pos[sl], t_rel, seq)
            block = self._block_slots if self.config.pass_repeats == 1 else self._block
            for b0 in range(start, stop, self.block_size):
                b1 = min(stop, b0 + self.block_size)
                parts.append(block(pos[b0:b1], cell[b0:b1], t_rel, seq))
            hist.close_pass(cell[sl], in_rank, t_rel, seq, newest)
            if self._consumed is not None:
                self._consumed.index_put_((cell[sl][newest],), rank[sl][newest] + 1)
        if self._consumed is not None:
            self._consumed.index_fill_(0, cell, 0)
        return Candidates.cat(parts)

    def _onsets(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor) -> Tensor:
        """Which events start a burst (see the module docstring, step 0).

        An event is an onset unless the previous event of the same pixel (kept or not, either
        polarity) has the same polarity and is at most ``refractory_us`` older. ``last_t`` and
        ``last_p`` carry each pixel's latest event across chunks.
        """
        n = t.shape[0]
        pixel = y * self.width + x
        sorted_pix, order = torch.sort(pixel, stable=True)
        t_sorted = t.index_select(0, order)
        p_sorted = p.index_select(0, order).to(torch.int8)
        prev_t = self.last_t.index_select(0, sorted_pix)
        prev_p = self.last_p.index_select(0, sorted_pix)
        same = sorted_pix[1:] == sorted_pix[:-1]
        prev_t[1:] = torch.where(same, t_sorted[:-1], prev_t[1:])
        prev_p[1:] = torch.where(same, p_sorted[:-1], prev_p[1:])
        onset_sorted = (prev_p != p_sorted) | ((t_sorted - prev_t) > self.config.refractory_us)
        onset = torch.empty(n, dtype=torch.bool, device=t.device)
        onset.index_copy_(0, order, onset_sorted)
        last_idx = torch.nonzero(torch.cat([~same, same.new_ones(1)])).reshape(-1)
        last_pix = sorted_pix.index_select(0, last_idx)  # distinct pixels: no write conflicts
        self.last_t.index_copy_(0, last_pix, t_sorted.index_select(0, last_idx))
        self.last_p.index_copy_(0, last_pix, p_sorted.index_select(0, last_idx))
        return onset

    @staticmethod
    def _next_same_cell(cell: Tensor) -> Tensor:
        """(n,) stream position of the next event of the same cell in the chunk (n if none)."""
        n = cell.shape[0]
        sorted_cell, order = torch.sort(cell, stable=True)
        nxt_sorted = torch.full((n,), n, dtype=torch.int64, device=cell.device)
        same = sorted_cell[1:] == sorted_cell[:-1]
        nxt_sorted[:-1] = torch.where(same, order[1:], torch.full_like(order[1:], n))
        out = torch.empty_like(nxt_sorted)
        out[order] = nxt_sorted
        return out

    # ------------------------------------------------------------------ one block
    def _block(self, pos: Tensor, cell: Tensor, t_rel: Tensor, seq: Tensor,
               lookups: EventHistory | SortedChunk | None = None) -> Candidates:
        """Candidates of the chunk's events at positions ``pos`` (all in the open pass).

        Args:
            pos: (b,) int32 chunk positions; cell: (b,) int64 their cells.
            t_rel: (n_chunk,) int32 relative times; seq: (n_chunk,) int64 stream indices.
            lookups: what answers the lookups: the history with its open pass (default), or
                the :class:`SortedChunk` of the chunk (``lookup == "sorted"``).
        """
        hist = self.history if lookups is None else lookups
        b = pos.shape[0]
        d = self.offsets.shape[0]
        k = self.config.history
        t_k = t_rel[pos]
        # stage 1, e_j: lookups at x - d for every displacement, (b * D, K)
        j_cell = (cell[:, None] - self.j_cell).reshape(-1)
        seen_j = hist.lookup_times(j_cell, pos[:, None].expand(b, d).reshape(-1), t_rel)
        dt_kj = t_k[:, None, None] - seen_j.view(b, d, k)
        ok_j = ((dt_kj >= 1) & (dt_kj < self.dt_hi_j)).view(b * d, k)
        dt_kj = dt_kj.view(b * d, k)
        rows = ok_j.any(1).nonzero().reshape(-1)
        if rows.numel() == 0:
            return Candidates.empty(self.device)
        ev = torch.div(rows, d, rounding_mode="floor")
        off = rows - ev * d
        # the e_i test as an interval of t_k - t_i per (row, e_j), see _dt_ki_bounds
        lo, hi = self._dt_ki_bounds(dt_kj.index_select(0, rows), ok_j.index_select(0, rows), off)
        # stage 2, e_i: lookups at x - 2d for the surviving (event, displacement) rows only
        ev_pos = pos[ev]
        t_i = hist.lookup_times(cell[ev] - self.i_cell[off], ev_pos, t_rel)
        dt_ki = t_k[ev][:, None] - t_i  # (R, K) over the ages of e_i
        ok = (dt_ki[:, None, :] >= lo[:, :, None]) & (dt_ki[:, None, :] <= hi[:, :, None])
        row, aj, ai = ok.nonzero(as_tuple=True)
        ev_c, off_c = ev[row], off[row]
        dt = dt_ki.view(-1)[row * k + ai].to(torch.int64)
        flow = self.flow_num[off_c] / dt.to(torch.float32)[:, None]
        c_pos = ev_pos[row]
        c_cell = cell[ev_c]
        return Candidates(event=seq[c_pos], offset=off_c, age_j=aj, age_i=ai,
                          seq_j=hist.lookup_seq(c_cell - self.j_cell[off_c], c_pos, aj, seq),
                          seq_i=hist.lookup_seq(c_cell - self.i_cell[off_c], c_pos, ai, seq),
                          dt_us=dt, flow=flow)

    def _block_slots(self, pos: Tensor, cell: Tensor, t_rel: Tensor, seq: Tensor) -> Candidates:
        """:meth:`_block` for ``pass_repeats == 1``, on the K + 1 slots of each cell.

        Every lookup is one gather of a cell's slot row (see :mod:`evtrack.flow.history`);
        the tests then run on one (queries,) vector per slot or pair of slots, which avoids
        where-selections and broadcasts over tiny trailing dimensions. Slot ``s`` of a query
        has age ``s - 1 + visible``, increasing with ``s``, so the order of the candidates
        (event, displacement, age of e_j, age of e_i) is that of (row, slot of e_j, slot of
        e_i) and equals :meth:`_block`'s.

        Args:
            pos: (b,) int32 chunk positions; cell: (b,) int64 their cells.
            t_rel: (n_chunk,) int32 relative times; seq: (n_chunk,) int64 stream indices.
        """
        hist = self.history
        b = pos.shape[0]
        d = self.offsets.shape[0]
        n_slots = self.config.history + 1
        take = torch.index_select
        t_k = take(t_rel, 0, pos)
        # stage 1, e_j: the slot rows at x - d for every displacement, viewed as (b, D); the
        # test 1 <= t_k - t_j < hi_j (see __init__) as t_k - hi_j < t_j <= t_k - 1
        j_cell = (cell[:, None] - self.j_cell).reshape(-1)
        rows_j = hist.gather_slots(j_cell)
        upper = (t_k - 1)[:, None]
        lower = t_k[:, None] - self.dt_hi_j32
        vis_j = rows_j[:, 0].view(b, d) < pos[:, None]
        ok = None
        for s in range(n_slots):
            t_s = rows_j[:, 1 + s].view(b, d)
            ok_s = torch.gt(t_s, lower)
            ok_s &= t_s <= upper
            if s == n_slots - 1:
                ok_s &= ~vis_j
            ok = ok_s if ok is None else ok.logical_or_(ok_s)
        rows = ok.view(-1).nonzero().reshape(-1)
        r = rows.numel()
        if r == 0:
            return Candidates.empty(self.device)
        ev = torch.div(rows, d, rounding_mode="floor")
        off = rows - ev * d
        vis_j = take(vis_j.view(-1), 0, rows)
        t_kr = take(t_k, 0, ev)
        # the e_i test as an interval of t_k - t_i per (row, slot of e_j)
        lo_d = take(self.dt_lo32, 0, off)
        hi_d = take(self.dt_hi32, 0, off)
        bounds = []
        for s in range(n_slots):
            a = t_kr - take(rows_j[:, 1 + s], 0, rows)
            if s == n_slots - 1:  # the oldest slot is hidden behind a visible pass event
                a.masked_fill_(vis_j, 0)
            lo, hi = self._interval(a)
            bounds.append((torch.maximum(lo, lo_d), torch.minimum(hi, hi_d)))
        # stage 2, e_i: the slot rows at x - 2d for the surviving (event, displacement) rows
        ev_pos = take(pos, 0, ev)
        i_cell = take(cell, 0, ev) - take(self.i_cell, 0, off)
        rows_i = hist.gather_slots(i_cell)
        dt_ki = torch.stack([t_kr - rows_i[:, 1 + s] for s in range(n_slots)])  # (S, R)
        hide_i = rows_i[:, 0] < ev_pos  # visible pass event: the oldest slot is hidden
        n_pairs = n_slots * n_slots
        ok = torch.empty(r, n_pairs, dtype=torch.bool, device=self.device)
        for sj, (lo, hi) in enumerate(bounds):
            for si in range(n_slots):
                out = ok[:, sj * n_slots + si]
                torch.ge(dt_ki[si], lo, out=out)
                out &= dt_ki[si] <= hi
                if si == n_slots - 1:
                    out &= ~hide_i
        flat = ok.view(-1).nonzero().reshape(-1)
        row = torch.div(flat, n_pairs, rounding_mode="floor")
        pair = flat - row * n_pairs
        sj = torch.div(pair, n_slots, rounding_mode="floor")
        si = pair - sj * n_slots
        ev_c, off_c = take(ev, 0, row), take(off, 0, row)
        dt = take(dt_ki.view(-1), 0, si * r + row).to(torch.int64)
        flow = take(self.flow_num, 0, off_c) / dt.to(torch.float32)[:, None]
        c_pos = take(ev_pos, 0, row)
        j_cell_c = take(cell, 0, ev_c) - take(self.j_cell, 0, off_c)
        return Candidates(event=take(seq, 0, c_pos), offset=off_c,
                          age_j=sj + take(vis_j, 0, row) - 1,
                          age_i=si + take(hide_i, 0, row) - 1,
                          seq_j=hist.slot_seq(j_cell_c, sj),
                          seq_i=hist.slot_seq(take(i_cell, 0, row), si),
                          dt_us=dt, flow=flow)

    def _interval(self, a: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`_dt_ki_bounds`' tolerance interval of ``t_k - t_i`` for ``a = t_k - t_j``
        (int32, any value): (lo, hi) int32, empty (``lo > hi``) where ``a < 1``. Where
        ``a >= hi_d`` it is empty too once intersected with the displacement's speed bounds
        (``lo >= a + 1``)."""
        a = a.clamp(0, self.hi_max)
        if self._tol_tables is not None:  # entry 0 is empty
            both = self._tol_words.index_select(0, a).view(torch.int32).view(-1, 2)
            return both[:, 0], both[:, 1]
        lo, hi = self._tolerance_interval(a.to(torch.int64))
        lo = torch.where(a >= 1, lo, hi + 1)
        return lo.to(torch.int32), hi.to(torch.int32)

    def _tolerance_tables(self) -> tuple[Tensor, Tensor]:
        """:meth:`_dt_ki_bounds`' interval for every ``t_k - t_j`` in ``[0, hi_max]``
        (int32, capped at ``hi_max + 1``; empty at 0), so that a block looks it up instead of
        dividing."""
        a = torch.arange(self.hi_max + 1, dtype=torch.int64, device=self.device)
        lo, hi = self._tolerance_interval(a)
        cap = self.hi_max + 1
        lo[0], hi[0] = cap, 0  # a = 0 never completes a triplet (t_k - t_j >= 1)
        return lo.clamp_max(cap).to(torch.int32), hi.clamp_max(cap).to(torch.int32)

    def _tolerance_interval(self, a: Tensor) -> tuple[Tensor, Tensor]:
        """int64 ``[max(ceil((2000 a - A) / (1000 + r)), a + 1), floor((2000 a + A) /
        (1000 - r))]`` (see :meth:`_dt_ki_bounds`); the upper end is ``hi_max + 1`` when
        ``r >= 1000`` (the relative tolerance then bounds nothing from above)."""
        lo = -torch.div(self.tol_abs - 2000 * a, 1000 + self.tol_rel, rounding_mode="floor")
        lo = torch.maximum(lo, a + 1)
        if self.tol_rel < 1000:
            hi = torch.div(2000 * a + self.tol_abs, 1000 - self.tol_rel, rounding_mode="floor")
        else:
            hi = torch.full_like(a, self.hi_max + 1)
        return lo, hi

    def _dt_ki_bounds(self, dt_kj: Tensor, ok_j: Tensor, off: Tensor) -> tuple[Tensor, Tensor]:
        """The ``t_k - t_i`` that complete a triplet, as an interval per (row, age of e_j).

        With ``a = t_k - t_j`` and ``c = t_k - t_i`` (µs), the rule of
        :mod:`evtrack.flow.config` asks ``c >= a + 1`` (``t_j - t_i >= 1``), the speed bounds
        ``lo_d <= c <= hi_d`` and ``1000 |2a - c| <= A + r c`` (``A = 1000 tolerance_us``,
        ``r`` the per-mille tolerance). As ``1000 + r > 0`` and ``1000 - r >= 0``, the last is
        exactly ``c (1000 + r) >= 2000 a - A`` and ``c (1000 - r) <= 2000 a + A``, i.e.
        ``ceil((2000 a - A) / (1000 + r)) <= c <= floor((2000 a + A) / (1000 - r))``.

        Args:
            dt_kj: (R, K) int32 ``t_k - t_j``; ok_j: (R, K) bool, e_j usable (then
                ``1 <= a < hi_d <= hi_max``); off: (R,) displacement index.

        Returns:
            ``(lo, hi)``: (R, K) int32 bounds; ``lo > hi`` where e_j is unusable.
        """
        if self._tol_tables is not None:
            a = dt_kj.clamp(0, self.hi_max).to(torch.int64)
            lo_tab, hi_tab = self._tol_tables
            lo_tol, hi_tol = lo_tab[a], hi_tab[a]
        else:
            lo_tol, hi_tol = self._tolerance_interval(dt_kj.clamp(0, self.hi_max)
                                                      .to(torch.int64))
        lo = torch.maximum(lo_tol, self.dt_lo32[off][:, None])
        hi = torch.minimum(hi_tol, self.dt_hi32[off][:, None])
        lo = torch.where(ok_j, lo, hi + 1)
        return lo.to(torch.int32), hi.to(torch.int32)
