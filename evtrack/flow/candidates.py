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
3. For each event, displacement and pair of visible entries, the triplet tests run on a dense
   ``(block, D, K, K)`` tensor; the surviving positions are the candidates, in the order
   (event, displacement, age of e_j, age of e_i).

Peak tensor sizes are bounded by ``block_size`` (and the sort by ``chunk_size``), never by
the event rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evtrack.flow.config import US_PER_S, FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.history import MAX_SPAN_US, EventHistory

__all__ = ["Candidates", "CandidateSearch", "pass_bounds", "pass_starts", "NEVER_US"]

NEVER_US = -(1 << 62)
"""Timestamp (µs) of the previous event of a cell that has none."""


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
    """The batched candidate search over a persistent :class:`EventHistory`.

    Args:
        config: the flow parameters (sensor size must be set).
        device: torch device.
    """

    def __init__(self, config: FlowConfig, device: str | torch.device = "cpu") -> None:
        if config.sensor_size is None:
            raise ValueError("CandidateSearch needs config.sensor_size")
        self.config = config
        self.device = torch.device(device)
        self.width, self.height = config.sensor_size
        self.history = EventHistory(config.sensor_size, config.history, config.pass_repeats,
                                    self.device)
        self.block_size = config.resolved_block_size(self.device.type)
        offsets = search_offsets(config.radius)
        dev = self.device
        self.offsets = torch.as_tensor(offsets, device=dev)
        # cell-id offsets of the e_j (x - d) and e_i (x - 2d) pixels
        self.j_cell = self.offsets[:, 1] * self.width + self.offsets[:, 0]
        self.i_cell = 2 * self.j_cell
        bounds = dt_bounds_us(offsets, config.min_speed, config.max_speed)
        self.dt_lo32 = torch.as_tensor(bounds[:, 0], dtype=torch.int32, device=dev)
        self.dt_hi32 = torch.as_tensor(bounds[:, 1], dtype=torch.int32, device=dev)
        # e_j precedes e_i's match: t_k - t_j < t_k - t_i <= hi
        self.dt_hi_j = self.dt_hi32[None, :, None]
        self.hi_max = int(bounds[:, 1].max()) if len(bounds) else 0
        self.err_cap = self.hi_max + 1
        largest = max(1000 * self.err_cap, int(config.tolerance_us) * 1000
                      + config.tolerance_permille * self.hi_max)
        self.tol_dtype = torch.int32 if largest < (1 << 31) - 1 else torch.int64
        # 2 d * 1e6, the numerator of the candidate flow (px * µs / s).
        self.flow_num = (2.0 * US_PER_S) * self.offsets.to(torch.float32)
        self.tol_abs = int(config.tolerance_us) * 1000
        self.tol_rel = config.tolerance_permille
        self.reset()

    def reset(self) -> None:
        """Forget every event seen."""
        self.history = EventHistory(self.config.sensor_size, self.config.history,
                                    self.config.pass_repeats, self.device)
        pixels = self.width * self.height
        self.last_t = torch.full((pixels,), NEVER_US, dtype=torch.int64, device=self.device)
        self.last_p = torch.zeros(pixels, dtype=torch.int8, device=self.device)
        self.next_seq = 0

    # ------------------------------------------------------------------ driver
    def __call__(self, x: Tensor, y: Tensor, t: Tensor, p: Tensor) -> Candidates:
        """Search the candidates of the next events of the stream and add them to the history.

        Args:
            x, y: (n,) integer pixel coordinates (inside the sensor; not checked here).
            t: (n,) int64 timestamps in µs, non-decreasing and not before earlier calls.
            p: (n,) polarity (+1 / -1).

        Returns:
            The candidates, with stream indices continuing those of earlier calls.
        """
        n = int(t.shape[0])
        if n == 0:
            return Candidates.empty(self.device)
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
        seq = torch.arange(self.next_seq, self.next_seq + n, device=self.device)
        cell = hist.cell_index(x, y, p)
        if self.config.refractory_us > 0:
            onset = self._onsets(x, y, t, p)
            x, y, t, seq, cell = x[onset], y[onset], t[onset], seq[onset], cell[onset]
        self.next_seq += n
        if t.numel() == 0:
            return Candidates.empty(self.device)
        keys = hist.make_keys(t, seq)
        rank, next_end = pass_starts(cell, self.config.pass_repeats)
        head0 = hist.head.index_select(0, cell)
        slot = torch.remainder(head0 + rank, hist.slots)
        # Is the event the last of its cell in the chunk up to the end of its pass? Decided
        # per pass from the next event of the same cell.
        next_same = self._next_same_cell(cell)
        parts = []
        for start, stop in pass_bounds(next_end):
            sl = slice(start, stop)
            last = next_same[sl] >= stop
            hist.write(cell[sl], slot[sl], keys[sl], last,
                       torch.remainder(slot[sl] + 1, hist.slots))
            for b0 in range(start, stop, self.block_size):
                b1 = min(stop, b0 + self.block_size)
                parts.append(self._block(x[b0:b1], y[b0:b1], cell[b0:b1], keys[b0:b1],
                                         seq[b0:b1]))
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
        t_sorted = t[order]
        p_sorted = p[order].to(torch.int8)
        prev_t = self.last_t.index_select(0, sorted_pix)
        prev_p = self.last_p.index_select(0, sorted_pix)
        same = sorted_pix[1:] == sorted_pix[:-1]
        prev_t[1:] = torch.where(same, t_sorted[:-1], prev_t[1:])
        prev_p[1:] = torch.where(same, p_sorted[:-1], prev_p[1:])
        burst = (prev_p == p_sorted) & ((t_sorted - prev_t) <= self.config.refractory_us)
        onset = torch.empty(n, dtype=torch.bool, device=t.device)
        onset[order] = ~burst
        last = torch.ones(n, dtype=torch.bool, device=t.device)
        last[:-1] = ~same
        self.last_t.index_put_((sorted_pix[last],), t_sorted[last])
        self.last_p.index_put_((sorted_pix[last],), p_sorted[last])
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
    def _block(self, x: Tensor, y: Tensor, cell: Tensor, keys: Tensor, seq: Tensor
               ) -> Candidates:
        hist = self.history
        b = x.shape[0]
        d = self.offsets.shape[0]
        # the e_i pixel x - 2d must be inside (then so is the e_j pixel x - d)
        ix = x[:, None] - 2 * self.offsets[:, 0]
        iy = y[:, None] - 2 * self.offsets[:, 1]
        inside = (ix >= 0) & (ix < self.width) & (iy >= 0) & (iy < self.height)
        # stage 1, e_j: lookups at x - d for every displacement, (b, D, K)
        j_cell = torch.where(inside, cell[:, None] - self.j_cell, cell[:, None])
        seen_j = hist.lookup(j_cell.reshape(-1), keys[:, None].expand(b, d).reshape(-1))
        seen_j = seen_j.view(b, d, -1)
        # relative times fit int32: |t| < T_LIMIT = 2^29, empty slots at -2^29
        t_k = hist.key_time(keys).to(torch.int32)
        dt_kj = t_k[:, None, None] - hist.key_time(seen_j).to(torch.int32)
        ok_j = (dt_kj >= 1) & (dt_kj < self.dt_hi_j) & inside[:, :, None]
        ev, off = ok_j.any(2).nonzero(as_tuple=True)
        if ev.numel() == 0:
            return Candidates.empty(self.device)
        # stage 2, e_i: lookups at x - 2d for the surviving (event, displacement) rows only
        seen_i = hist.lookup(cell[ev] - self.i_cell[off], keys[ev])
        t_i = hist.key_time(seen_i).to(torch.int32)[:, None, :]
        dt_kj = dt_kj[ev, off][:, :, None]
        t_j = t_k[ev][:, None, None] - dt_kj
        dt_ki = t_k[ev][:, None, None] - t_i
        dt_ji = t_j - t_i
        lo = self.dt_lo32[off][:, None, None]
        hi = self.dt_hi32[off][:, None, None]
        ok = ok_j[ev, off][:, :, None] & (dt_ji >= 1) & (dt_ki >= lo) & (dt_ki <= hi)
        # exact integer tolerance test; operands are clamped so that the products fit
        dt_c = dt_ki.clamp(0, self.hi_max).to(self.tol_dtype)
        err = (dt_kj - dt_ji).abs().clamp_max(self.err_cap).to(self.tol_dtype)
        ok &= err * 1000 <= self.tol_abs + self.tol_rel * dt_c
        row, aj, ai = ok.nonzero(as_tuple=True)
        ev_c, off_c = ev[row], off[row]
        dt = dt_ki[row, 0, ai].to(torch.int64)
        k_j = seen_j[ev_c, off_c, aj]
        k_i = seen_i[row, ai]
        flow = self.flow_num[off_c] / dt.to(torch.float32)[:, None]
        return Candidates(event=seq[ev_c], offset=off_c, age_j=aj, age_i=ai,
                          seq_j=hist.key_seq(k_j), seq_i=hist.key_seq(k_i), dt_us=dt,
                          flow=flow)
