"""Per-pixel, per-polarity ring buffer of recent events (:class:`EventHistory`).

Each (polarity, y, x) cell keeps its ``history + pass_repeats`` most recent events as int64
*keys* ``(t - t_base) << SEQ_BITS | (seq - seq_base)``: the timestamp relative to a base
(µs) in the high bits and the event's index in the stream relative to another base in the
low bits. Within a pixel, key order is stream order, so "was written before event k" is the
single comparison ``key < key_k`` even between events with equal timestamps.

The batched search (:mod:`evtrack.flow.candidates`) writes a whole *pass* of events (at most
``pass_repeats`` events per cell) before evaluating that pass's lookups;
:meth:`EventHistory.lookup` then recovers, for each query, exactly the last ``history``
events of the cell that precede the querying event in the stream: it counts the cell's
entries with a key at or after the query's (only events of the current pass can be) and
skips that many of the newest slots.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["EventHistory", "SEQ_BITS", "EMPTY_KEY", "T_LIMIT", "SEQ_LIMIT", "MAX_SPAN_US"]

SEQ_BITS = 33
"""Low bits of a key holding the relative stream index."""
SEQ_MASK = (1 << SEQ_BITS) - 1
T_LIMIT = 1 << 29
"""Relative timestamps stay below this (µs); the base moves forward before they reach it."""
SEQ_LIMIT = 1 << SEQ_BITS
"""Relative stream indices stay below this; the base moves forward before they reach it."""
T_KEEP = 1 << 28
"""After a rebase, entries at most this old (µs) keep their value (older ones are emptied:
they are beyond any speed bound, see ``FlowConfig``)."""
MAX_SPAN_US = 1 << 27
"""Longest time span (µs) of the events of one chunk (the search splits longer chunks)."""
SEQ_KEEP = 1 << 32
"""After a rebase, entries at most this many events old keep their stream index."""
EMPTY_KEY = -(1 << 62)
"""Key of a slot never written; its timestamp ``EMPTY_KEY >> SEQ_BITS`` is ``-T_LIMIT``."""


class EventHistory:
    """Ring buffers of the most recent event keys of every pixel and polarity.

    Args:
        sensor_size: ``(width, height)`` in pixels.
        history: K, the number of events a lookup returns per cell.
        pass_repeats: L, the most events of one cell a pass may write before its lookups.
        device: torch device of the buffers.

    Attributes:
        ring: (2 * H * W * S,) int64 keys, cell-major, with ``S = history + pass_repeats``.
        head: (2 * H * W,) int64, the slot the cell's next event is written to.
        t_base, seq_base: the bases (µs, stream index) keys are relative to.
    """

    def __init__(self, sensor_size: tuple[int, int], history: int, pass_repeats: int,
                 device: str | torch.device = "cpu") -> None:
        self.width, self.height = (int(v) for v in sensor_size)
        self.history = int(history)
        self.pass_repeats = int(pass_repeats)
        self.slots = self.history + self.pass_repeats
        self.cells = 2 * self.width * self.height
        self.device = torch.device(device)
        self.ring = torch.full((self.cells * self.slots,), EMPTY_KEY, dtype=torch.int64,
                               device=self.device)
        self.head = torch.zeros(self.cells, dtype=torch.int64, device=self.device)
        self.t_base: int | None = None
        self.seq_base = 0
        self._ages = torch.arange(self.history, device=self.device)

    # ------------------------------------------------------------------ keys
    def cell_index(self, x: Tensor, y: Tensor, polarity: Tensor) -> Tensor:
        """Cell id ``(c * H + y) * W + x`` with ``c = 0`` for ON (+1), 1 for OFF (-1)."""
        channel = (polarity < 0).to(torch.int64)
        return (channel * self.height + y.to(torch.int64)) * self.width + x.to(torch.int64)

    def make_keys(self, t: Tensor, seq: Tensor) -> Tensor:
        """Keys of events with absolute timestamps ``t`` (µs) and stream indices ``seq``.

        Moves the bases forward first when needed (:meth:`ensure_range`).
        """
        if t.numel():
            self.ensure_range(int(t[0]), int(t[-1]), int(seq[-1]))
        return ((t - self.t_base) << SEQ_BITS) | (seq - self.seq_base)

    def key_time(self, keys: Tensor) -> Tensor:
        """Relative timestamps (µs) of keys; ``-T_LIMIT`` for empty slots."""
        return keys >> SEQ_BITS

    def key_seq(self, keys: Tensor) -> Tensor:
        """Absolute stream indices of (non-empty) keys."""
        return (keys & SEQ_MASK) + self.seq_base

    def ensure_range(self, t_first: int, t_last: int, seq_last: int) -> None:
        """Move the bases so that keys of events in ``[t_first, t_last]`` fit their bit fields.

        The events written together must span less than ``MAX_SPAN_US``.
        """
        if t_last - t_first >= MAX_SPAN_US:
            raise ValueError(f"events written together span {t_last - t_first} µs, more than "
                             f"{MAX_SPAN_US}")
        if self.t_base is None:
            self.t_base = t_first
        shift_t = max(0, t_last - self.t_base - (T_LIMIT - 1))
        shift_s = max(0, seq_last - self.seq_base - (SEQ_LIMIT - 1))
        if shift_t:
            shift_t = t_last - self.t_base - T_KEEP
        if shift_s:
            shift_s = seq_last - self.seq_base - SEQ_KEEP
        if shift_t < 0 or shift_s < 0:
            raise ValueError("events must be given in stream order")
        if shift_t or shift_s:
            self._rebase(shift_t, shift_s)

    def _rebase(self, shift_t: int, shift_s: int) -> None:
        full = self.ring != EMPTY_KEY
        t_rel = (self.ring >> SEQ_BITS) - shift_t
        s_rel = (self.ring & SEQ_MASK) - shift_s
        keep = full & (t_rel >= 0)
        s_rel = s_rel.clamp_min(0)  # only order matters for entries this old
        self.ring = torch.where(keep, (t_rel << SEQ_BITS) | s_rel,
                                torch.full_like(self.ring, EMPTY_KEY))
        self.t_base += shift_t
        self.seq_base += shift_s

    # ------------------------------------------------------------------ write / read
    def write(self, cell: Tensor, slot: Tensor, keys: Tensor, last: Tensor,
              next_head: Tensor) -> None:
        """Store ``keys`` at ``(cell, slot)`` and move the heads of the cells written.

        Args:
            cell, slot, keys: (n,) int64; the (cell, slot) pairs are distinct.
            last: (n,) bool, True for the last event of its cell in this pass.
            next_head: (n,) int64, the cell's head after this event (read where ``last``).
        """
        self.ring.index_put_((cell * self.slots + slot,), keys)
        self.head.index_put_((cell[last],), next_head[last])

    def lookup(self, cell: Tensor, query_key: Tensor) -> Tensor:
        """The last ``history`` keys of each cell that precede each query, newest first.

        Args:
            cell: (M,) int64 cell ids.
            query_key: (M,) int64 keys of the querying events; every event of the current pass
                is already written.

        Returns:
            (M, history) int64 keys, ``EMPTY_KEY`` where the cell holds fewer events.
        """
        rows = self.ring.view(self.cells, self.slots).index_select(0, cell)
        later = (rows >= query_key[:, None]).to(torch.uint8).sum(1, dtype=torch.uint8)
        newest = self.head.index_select(0, cell) - 1 - later.to(torch.int64)
        slot = torch.remainder(newest[:, None] - self._ages, self.slots)
        return rows.gather(1, slot)

    def state_dict(self) -> dict:
        """Buffers and bases, for checkpointing or moving devices."""
        return {"ring": self.ring, "head": self.head, "t_base": self.t_base,
                "seq_base": self.seq_base}
