"""Per-pixel, per-polarity history of recent events (:class:`EventHistory`).

Each (polarity, y, x) *cell* keeps its ``history`` (K) most recent events, newest first: their
timestamps as int32 µs relative to a base ``t_base`` (``ring_t``) and their stream indices
(``ring_s``). The grid is padded by ``pad`` empty cells on every side, so that a neighbour
``x - d`` of any pixel is a valid cell id (padding cells are never written and read as empty):
lookups need no bounds test.

The batched search (:mod:`evtrack.flow.candidates`) handles a *pass* of events (at most
``pass_repeats`` (L) events per cell) at once:

1. :meth:`EventHistory.open_pass` records, per cell, the chunk positions of the pass's events
   (``pass_pos``, oldest first, ``UNUSED`` elsewhere) without touching the rings (with
   ``pass_repeats == 1`` also the event's time and stream index, see *slots* below);
2. :meth:`EventHistory.lookup_times` then returns, for each query (a cell and the chunk
   position of the querying event), the K newest events of the cell that precede the query in
   the stream: the cell's pass events before it (newest first), then its ring;
3. :meth:`EventHistory.close_pass` shifts the pass's events into the rings.

So every event sees exactly the events before it, as a sequential ring buffer would.

Storage and *slots* (``pass_repeats == 1``, the default). One int32 row per cell,
``slot_t[cell] = [pass_pos, pass_t, ring_t[0], ..., ring_t[K - 1]]`` (padded to a multiple of
four), is fetched by a single gather of 16-byte words (:meth:`EventHistory.gather_slots`). The
K + 1 *slots* of a cell are its pass event (slot 0, time ``pass_t``: ``NO_PASS_T`` when the cell
has none, which is after every event) and its ring (slots 1..K). A query at chunk position
``q`` sees the pass event when ``pass_pos < q`` (*visible*); it then sees slots 0..K-1, else
slots 1..K: the age of slot ``s`` is ``s - 1 + visible``. A pass event that is not visible has
``pass_t >= t_q`` (it is later in the stream, or absent), so any test that needs the entry to
be strictly older than the query rejects slot 0 by itself; only slot K needs the visibility
mask. ``slot_s`` holds the stream indices the same way (``[pass_seq, ring_s...]``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.flow.constants import EMPTY_T, MAX_SPAN_US, T_KEEP, T_LIMIT

__all__ = ["EventHistory", "SortedChunk", "UNUSED", "NO_PASS_T"]

UNUSED = (1 << 31) - 1
"""``pass_pos`` of a slot without a pass event: after every chunk position."""
NO_PASS_T = (1 << 31) - 1
"""``pass_t`` of a cell without a pass event: after every relative time (``t - NO_PASS_T < 0``
without overflow for ``0 <= t < T_LIMIT``)."""


class EventHistory:
    """The K most recent events of every pixel and polarity, on a padded grid.

    Args:
        sensor_size: ``(width, height)`` in pixels.
        history: K, the number of events a lookup returns per cell.
        pass_repeats: L, the most events of one cell a pass may hold.
        pad: empty cells around the sensor on every side (>= the largest lookup offset).
        device: torch device of the buffers.

    Attributes:
        slot_t: (cells, W) int32 storage of ``pass_pos``, ``pass_t`` and ``ring_t`` (in that
            column order; W is ``L + 1 + K`` rounded up to a multiple of 4).
        slot_s: (cells, 1 + K) int64 storage of the pass event's stream index (L = 1 only)
            and ``ring_s``.
        ring_t: (cells, K) int32 view, relative timestamps (µs), newest first; ``EMPTY_T`` if
            unused.
        ring_s: (cells, K) int64 view, stream indices, newest first; -1 if unused.
        pass_pos: (cells, L) int32 view, chunk positions of the open pass's events, oldest
            first; ``UNUSED`` (larger than any position) elsewhere.
        pass_t: (cells,) int32 view, relative time of the open pass's event of the cell
            (L = 1 only; ``NO_PASS_T`` without one).
        t_base: the base (µs) of the relative timestamps, ``None`` before the first event.
        row: cell-id stride of one row (the padded width).
    """

    def __init__(self, sensor_size: tuple[int, int], history: int, pass_repeats: int,
                 pad: int = 0, device: str | torch.device = "cpu") -> None:
        self.width, self.height = (int(v) for v in sensor_size)
        self.history = int(history)
        self.pass_repeats = int(pass_repeats)
        self.pad = int(pad)
        self.row = self.width + 2 * self.pad
        self.rows = self.height + 2 * self.pad
        self.cells = 2 * self.row * self.rows
        self.device = torch.device(device)
        dev = self.device
        k, n_pass = self.history, self.pass_repeats
        width = -(-(n_pass + 1 + k) // 4) * 4  # whole 16-byte words per row
        self.slot_t = torch.full((self.cells, width), EMPTY_T, dtype=torch.int32, device=dev)
        self.slot_t[:, :n_pass] = UNUSED
        self.slot_t[:, n_pass] = NO_PASS_T
        self.slot_s = torch.full((self.cells, 1 + k), -1, dtype=torch.int64, device=dev)
        self.pass_pos = self.slot_t[:, :n_pass]
        self.pass_t = self.slot_t[:, n_pass]
        self.ring_t = self.slot_t[:, n_pass + 1:n_pass + 1 + k]
        self.ring_s = self.slot_s[:, 1:]
        self._words = self.slot_t.view(torch.complex128)  # (cells, W / 4): one 16-byte word
        self.t_base: int | None = None
        self._ages = torch.arange(self.history, device=dev)

    # ------------------------------------------------------------------ cells and times
    def cell_index(self, x: Tensor, y: Tensor, polarity: Tensor) -> Tensor:
        """Cell id ``(c * Hp + y + pad) * Wp + x + pad`` (int64), ``c = 0`` ON, 1 OFF."""
        channel = (polarity < 0).to(torch.int64)
        return ((channel * self.rows + y.to(torch.int64) + self.pad) * self.row
                + x.to(torch.int64) + self.pad)

    def relative_times(self, t: Tensor) -> Tensor:
        """Int32 timestamps relative to the base, moving the base forward first if needed.

        Args:
            t: (n,) int64 absolute µs, non-decreasing, spanning less than ``MAX_SPAN_US``.
        """
        if t.numel():
            self.ensure_range(int(t[0]), int(t[-1]))
        return (t - self.t_base).to(torch.int32)

    def ensure_range(self, t_first: int, t_last: int) -> None:
        """Move the base so that ``[t_first, t_last]`` maps into ``[0, T_LIMIT)``."""
        if t_last - t_first >= MAX_SPAN_US:
            raise ValueError(f"events written together span {t_last - t_first} µs, more than "
                             f"{MAX_SPAN_US}")
        if self.t_base is None:
            self.t_base = t_first
        if t_first < self.t_base:
            raise ValueError("events must be given in stream order")
        if t_last - self.t_base >= T_LIMIT:
            shift = t_last - self.t_base - T_KEEP
            moved = self.ring_t.to(torch.int64) - shift
            kept = (self.ring_t != EMPTY_T) & (moved >= 0)
            self.ring_t.copy_(torch.where(kept, moved, EMPTY_T))
            self.ring_s.copy_(torch.where(kept, self.ring_s, -1))
            self.t_base += shift

    # ------------------------------------------------------------------ passes
    def open_pass(self, cell: Tensor, rank: Tensor, pos: Tensor, t: Tensor,
                  seq: Tensor) -> None:
        """Register the events of a pass (their cells, ranks within the pass, chunk positions).

        Args:
            cell: (m,) int64 cell ids; each cell appears at most L times.
            rank: (m,) int64 rank of the event among the pass's events of its cell (0 oldest).
            pos: (m,) int32 chunk positions, increasing.
            t: (n_chunk,) int32 relative timestamps of the chunk's events (by chunk position).
            seq: (n_chunk,) int64 stream indices of the chunk's events.
        """
        if self.pass_repeats == 1:
            rows = self.slot_t.index_select(0, cell)
            rows[:, 0] = pos
            rows[:, 1] = t[pos]
            self.slot_t.index_copy_(0, cell, rows)
            self.slot_s[:, 0].index_put_((cell,), seq[pos])
            return
        self.pass_pos.index_put_((cell, rank), pos.to(torch.int32))

    def close_pass(self, cell: Tensor, rank: Tensor, t: Tensor, seq: Tensor,
                   newest: Tensor) -> None:
        """Shift the events of the open pass into the rings and clear the pass.

        Args:
            cell, rank: as given to :meth:`open_pass`.
            t: (n_chunk,) int32 relative timestamps of the chunk's events (by chunk position).
            seq: (n_chunk,) int64 stream indices of the chunk's events.
            newest: (m,) bool, True for the newest pass event of its cell (one per cell).
        """
        if self.pass_repeats == 1:  # every cell once: its slots 0..K-1 become its ring
            k = self.history
            rows = self.slot_t.index_select(0, cell)
            rows[:, 2:2 + k] = rows[:, 1:1 + k].clone()
            rows[:, 0] = UNUSED
            rows[:, 1] = NO_PASS_T
            self.slot_t.index_copy_(0, cell, rows)
            s_rows = self.slot_s.index_select(0, cell)
            s_rows[:, 1:] = s_rows[:, :k].clone()
            self.slot_s.index_copy_(0, cell, s_rows)
            return
        cells = cell[newest]
        count = rank[newest] + 1
        t_new, s_new = self._newest_first(cells, count, self._ages.expand(cells.numel(), -1),
                                          t, seq)
        self.ring_t.index_put_((cells,), t_new)
        self.ring_s.index_put_((cells,), s_new)
        self.pass_pos.index_put_((cell, rank), torch.full_like(rank, UNUSED, dtype=torch.int32))

    def _newest_first(self, cell: Tensor, count: Tensor, idx: Tensor, t: Tensor | None,
                      seq: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
        """Entries ``idx`` (Q, A) of the newest-first sequence ``[pass events of the cell
        (``count`` of them), ring]`` of cells ``cell`` (Q,): (Q, A) int32 relative times (if
        ``t`` is given) and int64 stream indices (if ``seq`` is given).
        """
        count = count[:, None]
        from_pass = idx < count
        ring_slot = (idx - count).clamp(0, self.history - 1)
        pass_slot = (count - 1 - idx).clamp(0, self.pass_repeats - 1)
        pos = self.pass_pos[cell].gather(1, pass_slot)
        pos = torch.where(from_pass, pos, 0).to(torch.int64)
        times = indices = None
        if t is not None:
            times = torch.where(from_pass, t[pos], self.ring_t[cell].gather(1, ring_slot))
        if seq is not None:
            indices = torch.where(from_pass, seq[pos], self.ring_s[cell].gather(1, ring_slot))
        return times, indices

    # ------------------------------------------------------------------ lookups
    def lookup_times(self, cell: Tensor, pos: Tensor, t: Tensor) -> Tensor:
        """Times of the last K events of each cell that precede each query, newest first.

        Args:
            cell: (Q,) int64 cell ids.
            pos: (Q,) int32 chunk positions of the querying events (in the open pass).
            t: (n_chunk,) int32 relative timestamps of the chunk's events.

        Returns:
            (Q, K) int32 relative times, ``EMPTY_T`` where the cell holds fewer events.
        """
        pp = self.pass_pos[cell]
        count = (pp != UNUSED).sum(1)
        skip = count - (pp < pos[:, None]).sum(1)
        times, _ = self._newest_first(cell, count, skip[:, None] + self._ages, t, None)
        return times

    def lookup_seq(self, cell: Tensor, pos: Tensor, age: Tensor, seq: Tensor) -> Tensor:
        """Stream index of the entry ``age`` (newest first) each query of
        :meth:`lookup_times` saw.

        Args:
            cell, pos: (M,) as in :meth:`lookup_times`.
            age: (M,) int64 age of the entry (0 = newest visible).
            seq: (n_chunk,) int64 stream indices of the chunk's events.
        """
        pp = self.pass_pos[cell]
        count = (pp != UNUSED).sum(1)
        skip = count - (pp < pos[:, None]).sum(1)
        _, indices = self._newest_first(cell, count, (skip + age)[:, None], None, seq)
        return indices[:, 0]

    def gather_slots(self, cell: Tensor) -> Tensor:
        """The rows of ``slot_t`` of cells ``cell`` (Q,): (Q, W) int32, one gather of 16-byte
        words. With L = 1, column 0 is ``pass_pos`` and column ``1 + s`` the time of slot
        ``s`` (see the module docstring)."""
        return torch.view_as_real(self._words.index_select(0, cell)).view(torch.int32) \
            .view(cell.shape[0], -1)

    def slot_seq(self, cell: Tensor, slot: Tensor) -> Tensor:
        """(M,) int64 stream indices of slots ``slot`` (0 = pass event, 1 + a = ring entry a)
        of cells ``cell`` (L = 1)."""
        return self.slot_s.view(-1).index_select(0, cell * (self.history + 1) + slot)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Buffers and base, for checkpointing or moving devices."""
        return {"ring_t": self.ring_t, "ring_s": self.ring_s, "t_base": self.t_base}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (tensors moved to this history's device)."""
        self.ring_t.copy_(state["ring_t"].to(self.device, torch.int32))
        self.ring_s.copy_(state["ring_s"].to(self.device, torch.int64))
        self.t_base = state["t_base"]


class SortedChunk:
    """A whole chunk as one pass: lookups by binary search in the chunk sorted by cell.

    The alternative to :meth:`EventHistory.open_pass` / :meth:`EventHistory.close_pass` for
    ``FlowConfig.lookup == "sorted"``. The chunk's events are ordered by the key
    ``cell * m + position`` (``m`` events, so keys are unique and a cell's events stay in
    stream order). The events of cell ``c`` before chunk position ``q`` are then the sorted
    entries ``[searchsorted(c * m), searchsorted(c * m + q))``; a lookup takes the newest of
    those first and continues in the cell's ring, as a sequential ring buffer would. Nothing
    is sequential in the number of events per cell, so a chunk needs no passes.

    Args:
        history: the :class:`EventHistory` whose rings hold the events before the chunk.
        cell: (m,) int64 cell ids of the chunk's events, in stream order.
        t: (m,) int32 relative timestamps of the chunk's events.
        seq: (m,) int64 stream indices of the chunk's events.
    """

    def __init__(self, history: EventHistory, cell: Tensor, t: Tensor, seq: Tensor) -> None:
        self.history = history
        self.m = int(cell.shape[0])
        pos = torch.arange(self.m, dtype=torch.int64, device=cell.device)
        self.keys, order = torch.sort(cell * self.m + pos)
        self.t_sorted = t.index_select(0, order)
        self.s_sorted = seq.index_select(0, order)
        self.cells = torch.unique_consecutive(torch.div(self.keys, self.m,
                                                        rounding_mode="floor"))
        self._ages = torch.arange(history.history, device=cell.device)

    def _visible(self, cell: Tensor, pos: Tensor) -> tuple[Tensor, Tensor]:
        """(end, count): sorted index after the last event of ``cell`` before ``pos``, and
        how many of the cell's chunk events precede ``pos`` (both (Q,) int64)."""
        base = cell * self.m
        end = torch.searchsorted(self.keys, base + pos.to(torch.int64))
        start = torch.searchsorted(self.keys, base)
        return end, end - start

    def _entries(self, cell: Tensor, end: Tensor, count: Tensor, age: Tensor,
                 chunk_values: Tensor, ring: Tensor) -> Tensor:
        """Entry ``age`` (Q, A) of the newest-first sequence [chunk events, ring]."""
        from_chunk = age < count[:, None]
        idx = (end[:, None] - 1 - age).clamp_min(0)
        ring_age = (age - count[:, None]).clamp(0, self.history.history - 1)
        return torch.where(from_chunk, chunk_values[idx], ring[cell].gather(1, ring_age))

    def lookup_times(self, cell: Tensor, pos: Tensor, t: Tensor | None = None) -> Tensor:
        """:meth:`EventHistory.lookup_times` for the chunk (``t`` is not needed): (Q, K)
        int32 times of the last K events of each cell before each query, newest first."""
        end, count = self._visible(cell, pos)
        return self._entries(cell, end, count, self._ages.expand(cell.shape[0], -1),
                             self.t_sorted, self.history.ring_t)

    def lookup_seq(self, cell: Tensor, pos: Tensor, age: Tensor,
                   seq: Tensor | None = None) -> Tensor:
        """:meth:`EventHistory.lookup_seq` for the chunk: (M,) int64 stream index of entry
        ``age`` of each query."""
        end, count = self._visible(cell, pos)
        return self._entries(cell, end, count, age[:, None], self.s_sorted,
                             self.history.ring_s)[:, 0]

    def close(self) -> None:
        """Move each touched cell's K newest events (chunk, then ring) into its ring."""
        cells = self.cells
        end, count = self._visible(cells, torch.full_like(cells, self.m))
        ages = self._ages.expand(cells.shape[0], -1)
        ring_t = self._entries(cells, end, count, ages, self.t_sorted, self.history.ring_t)
        ring_s = self._entries(cells, end, count, ages, self.s_sorted, self.history.ring_s)
        self.history.ring_t.index_put_((cells,), ring_t)
        self.history.ring_s.index_put_((cells,), ring_s)
