"""The flow's pending RoI windows (:class:`Pending`): the candidates and group tallies of the
windows not yet complete, how a searched batch joins them (:func:`add_batch`) and what stays
pending once the closed windows are registered (:func:`keep_open`).

A group is a (RoI, time window) pair with key ``window * n_roi + roi`` (:class:`WindowGrid`).
On the CPU with numba the bookkeeping of a batch runs in one compiled pass
(:func:`_ingest_kernel`) and the dense-table helpers in NumPy; elsewhere it is tensor code
(the same int64 values; the tests run every form, see :data:`NUMPY_ON_CPU`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.candidates import Candidates
from evtrack.flow.hashing import hash32
from evtrack.flow.registration_tensor import select_smallest
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["Pending", "WindowGrid", "add_batch", "keep_open", "compiled_bookkeeping",
           "positions", "unique_inverse", "NUMPY_ON_CPU", "DENSE_SLACK", "DENSE_FLOOR"]

DENSE_SLACK = 8
DENSE_FLOOR = 65_536
"""Group keys spanning at most ``DENSE_SLACK`` times their count plus ``DENSE_FLOOR`` are
indexed through a dense table instead of sorting / binary search: a batch's keys cover a few
windows' RoIs."""

NUMPY_ON_CPU = True
"""The dense-table helpers work in NumPy on CPU tensors, and the events' and candidates'
group keys in compiled loops (in NumPy without numba); False: torch everywhere, as on CUDA
(the tests run every form)."""


@dataclass
class Pending:
    """Candidates and group tallies of RoI windows not yet complete.

    Attributes:
        gkey: (M,) int64 group key of each candidate (in stream order).
        seq: (M,) int64 stream index of its event.
        ordinal: (M,) int64 candidate ordinal within its event.
        flow: (M, 2) float32 candidate flow, px/s.
        g_keys: (G,) int64 sorted keys of the groups seen.
        g_events: (G,) int64 events per group.
        g_support: (G,) int64 events with a candidate per group.
        ev_gkey: (E,) int64 group key of each pending event (per-event flows only).
    """

    gkey: Tensor
    seq: Tensor
    ordinal: Tensor
    flow: Tensor
    g_keys: Tensor
    g_events: Tensor
    g_support: Tensor
    ev_gkey: Tensor

    @classmethod
    def empty(cls, device: torch.device) -> Pending:
        """No pending window."""
        z = torch.zeros(0, dtype=torch.int64, device=device)
        return cls(z, z, z, torch.zeros(0, 2, device=device), z, z, z, z)

    def to(self, device: torch.device) -> Pending:
        """A copy on ``device``."""
        return Pending(*(getattr(self, f.name).to(device) for f in fields(self)))


@dataclass(frozen=True)
class WindowGrid:
    """The groups' RoI grid and time windows.

    Attributes:
        sensor: ``(width, height)`` in pixels.
        roi_size: RoI side in pixels (the last row / column of RoIs is cut by the border).
        window_us: window length in µs (window ``w`` covers ``[w, w + 1) * window_us``).
    """

    sensor: tuple[int, int]
    roi_size: int
    window_us: int

    @property
    def cols(self) -> int:
        """RoI columns."""
        return math.ceil(self.sensor[0] / self.roi_size)

    @property
    def rows(self) -> int:
        """RoI rows."""
        return math.ceil(self.sensor[1] / self.roi_size)

    @property
    def n_roi(self) -> int:
        """RoIs per window, ``cols * rows``."""
        return self.cols * self.rows

    @functools.cached_property
    def roi_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """(W,) RoI column of each pixel column and (H,) first RoI index of each pixel row's
        RoI row, int64."""
        w, h = self.sensor
        return (np.arange(w, dtype=np.int64) // self.roi_size,
                np.arange(h, dtype=np.int64) // self.roi_size * self.cols)

    def group_keys(self, x: Tensor, y: Tensor, t: Tensor) -> Tensor:
        """(N,) int64 group key of each event (pixels ``x, y``, µs ``t``), by tensor ops."""
        s = self.roi_size
        window = torch.div(t, self.window_us, rounding_mode="floor")
        roi = (torch.div(y, s, rounding_mode="floor") * self.cols
               + torch.div(x, s, rounding_mode="floor"))
        return window * self.n_roi + roi


def compiled_bookkeeping(device: torch.device) -> bool:
    """Whether the bookkeeping on ``device`` runs in compiled passes (CPU, numba,
    :data:`NUMPY_ON_CPU`)."""
    return device.type == "cpu" and NUMPY_ON_CPU and jit_available()


def add_batch(pending: Pending, grid: WindowGrid, x: Tensor, y: Tensor, t: Tensor,
              cands: Candidates, seq0: int, history: int, with_events: bool) -> Pending:
    """``pending`` with a searched batch added: its events (pixels ``x, y``, µs ``t``, stream
    indices from ``seq0``) counted in their groups, its candidates appended with their group
    key and ordinal ``(offset * history + age_j) * history + age_i``; ``with_events``: keep
    each event's group key too (per-event flows)."""
    if compiled_bookkeeping(t.device):
        return _ingest(pending, grid, x, y, t, cands, seq0, history, with_events)
    gkey = grid.group_keys(x, y, t)
    c_g, ordinal, supported = _candidate_groups(gkey, cands, seq0, history)
    keys, g_events, g_support = _merged_counts(pending, gkey, supported)
    p = pending
    return Pending(
        gkey=torch.cat([p.gkey, c_g]), seq=torch.cat([p.seq, cands.event]),
        ordinal=torch.cat([p.ordinal, ordinal]), flow=torch.cat([p.flow, cands.flow]),
        g_keys=keys, g_events=g_events, g_support=g_support,
        ev_gkey=torch.cat([p.ev_gkey, gkey]) if with_events else p.ev_gkey)


def _ingest(p: Pending, grid: WindowGrid, x: Tensor, y: Tensor, t: Tensor, cands: Candidates,
            seq0: int, history: int, with_events: bool) -> Pending:
    """:func:`add_batch` on CPU with numba: the group keys, the candidates' bookkeeping and
    the pending arrays in one compiled pass (:func:`_ingest_kernel`), then the group counts
    (:func:`merge_group_counts`)."""
    roi_of_x, roi_of_y = grid.roi_tables
    ev_key, gkey, seq, ordinal, flow, supported = _ingest_kernel(
        x.numpy(), y.numpy(), t.numpy(), grid.window_us, roi_of_x, roi_of_y, grid.n_roi,
        cands.event.numpy(), cands.offset.numpy(), cands.age_j.numpy(), cands.age_i.numpy(),
        cands.flow.numpy(), seq0, history, p.gkey.numpy(), p.seq.numpy(), p.ordinal.numpy(),
        p.flow.numpy())
    merged = merge_group_counts(p.g_keys.numpy(), p.g_events.numpy(), p.g_support.numpy(),
                                ev_key, supported, DENSE_SLACK, DENSE_FLOOR)
    if merged is None:  # keys too spread for a table: the sort-based merge
        keys, g_events, g_support = _merged_counts(p, torch.from_numpy(ev_key),
                                                   torch.from_numpy(supported))
    else:
        keys, g_events, g_support = (torch.from_numpy(a) for a in merged)
    return Pending(
        gkey=torch.from_numpy(gkey), seq=torch.from_numpy(seq),
        ordinal=torch.from_numpy(ordinal), flow=torch.from_numpy(flow), g_keys=keys,
        g_events=g_events, g_support=g_support,
        ev_gkey=(torch.cat([p.ev_gkey, torch.from_numpy(ev_key)]) if with_events
                 else p.ev_gkey))


def _candidate_groups(gkey: Tensor, cands: Candidates, seq0: int, history: int
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """(M,) group key and (M,) ordinal of each candidate, and the group of each event that
    has candidates (its first candidate's); in NumPy on the CPU (the same int64 values).
    Without numba only: with it, :func:`_ingest_kernel`."""
    k = history
    if gkey.device.type == "cpu" and NUMPY_ON_CPU:
        event = cands.event.numpy()
        c_g_np = gkey.numpy()[event - seq0]
        ordinal_np = (cands.offset.numpy() * k + cands.age_j.numpy()) * k \
            + cands.age_i.numpy()
        first_np = np.ones(len(event), np.bool_)
        np.not_equal(event[1:], event[:-1], out=first_np[1:])
        return (torch.from_numpy(c_g_np), torch.from_numpy(ordinal_np),
                torch.from_numpy(c_g_np[first_np]))
    c_g = gkey[cands.event - seq0]
    ordinal = (cands.offset * k + cands.age_j) * k + cands.age_i
    first_of_event = torch.ones(len(cands), dtype=torch.bool, device=gkey.device)
    if len(cands) > 1:
        first_of_event[1:] = cands.event[1:] != cands.event[:-1]
    return c_g, ordinal, c_g[first_of_event]


def _merged_counts(p: Pending, gkey: Tensor, supported: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The pending groups' keys and counts after adding events with keys ``gkey`` (those
    with candidates: ``supported``), by sorting."""
    keys, inv = unique_inverse(torch.cat([p.g_keys, gkey, supported]))
    n_old, n_new = p.g_keys.numel(), gkey.numel()
    # per group: the pending counts, + 1 per new event, + 1 per new event with candidates
    g_events = torch.zeros_like(keys).index_add_(0, inv[:n_old], p.g_events)
    g_events.index_add_(0, inv[n_old:n_old + n_new], torch.ones_like(gkey))
    g_support = torch.zeros_like(keys).index_add_(0, inv[:n_old], p.g_support)
    g_support.index_add_(0, inv[n_old + n_new:], torch.ones_like(supported))
    return keys, g_events, g_support


def keep_open(p: Pending, n_c: int, n_g: int, n_done_events: int, max_events: int,
              prune_above: int | None) -> Pending:
    """What stays pending once the first ``n_g`` groups (their ``n_c`` candidates and
    ``n_done_events`` events) are registered.

    With ``prune_above``, open windows holding more candidates than that are pruned to the
    events the registration can ever use (the same hash selection as the registration's
    cap of ``max_events``, so pruning now or later, or not at all, gives the same flow;
    pruning only large ones bounds the memory and spares small calls the work).
    """
    g, s = p.gkey[n_c:], p.seq[n_c:]
    if prune_above is not None and g.numel() > prune_above:
        first = torch.ones_like(s, dtype=torch.bool)
        first[1:] = s[1:] != s[:-1]
        run = torch.cumsum(first.to(torch.int64), 0) - 1
        open_keys = p.g_keys[n_g:]  # sorted, and every open candidate's key is one
        run_keep = select_smallest(positions(open_keys, g[first]), hash32(s[first]),
                                   max_events, n_groups=open_keys.numel())
        keep = run_keep[run]
        sel = slice(n_c, None) if bool(keep.all()) else n_c + torch.nonzero(keep).reshape(-1)
    else:
        sel = slice(n_c, None)
    return Pending(
        gkey=p.gkey[sel], seq=p.seq[sel], ordinal=p.ordinal[sel], flow=p.flow[sel],
        g_keys=p.g_keys[n_g:], g_events=p.g_events[n_g:], g_support=p.g_support[n_g:],
        ev_gkey=p.ev_gkey[n_done_events:])


@njit
def event_group_keys(x: np.ndarray, y: np.ndarray, t: np.ndarray, window_us: int,
                     roi_of_x: np.ndarray, roi_of_y: np.ndarray, n_roi: int, out: np.ndarray
                    ) -> None:
    """``out[i]``: event ``i``'s group key ``window * n_roi + roi``, ``window`` the floor of
    ``t / window_us``, ``roi = roi_of_y[y] + roi_of_x[x]`` (tables of the RoI column
    ``x // roi_size`` and the row offset ``(y // roi_size) * cols``).

    Without a division per event: the window is divided out only when an event leaves the
    previous event's window (every event in a time-sorted batch of a few windows; any order
    gives the same keys)."""
    lo = hi = np.int64(0)
    w = np.int64(0)
    for i in range(t.shape[0]):
        ti = t[i]
        if i == 0 or ti < lo or ti >= hi:
            w = ti // window_us
            lo = w * window_us
            hi = lo + window_us
        out[i] = w * n_roi + roi_of_y[y[i]] + roi_of_x[x[i]]


@njit
def candidate_group_keys(event: np.ndarray, offset: np.ndarray, age_j: np.ndarray,
                         age_i: np.ndarray, seq0: int, gkey: np.ndarray, history: int,
                         c_g: np.ndarray, ordinal: np.ndarray, supported: np.ndarray) -> int:
    """Per candidate its event's group key and its ordinal; ``supported``: the group key of
    each event with candidates (its first candidate's), in order. Returns their count."""
    n_sup = 0
    for c in range(event.shape[0]):
        g = gkey[event[c] - seq0]
        c_g[c] = g
        ordinal[c] = (offset[c] * history + age_j[c]) * history + age_i[c]
        if c == 0 or event[c] != event[c - 1]:
            supported[n_sup] = g
            n_sup += 1
    return n_sup


@njit
def _ingest_kernel(x, y, t, window_us, roi_of_x, roi_of_y, n_roi, c_event, c_offset, c_age_j,
            c_age_i, c_flow, seq0, history, old_gkey, old_seq, old_ordinal, old_flow):
    """The CPU bookkeeping of a searched batch in one pass: each event's group key (as
    :func:`event_group_keys`), each candidate's group key and ordinal (as
    :func:`candidate_group_keys`) appended to the pending candidates' ``gkey, seq,
    ordinal, flow``, and the groups of the events with candidates.

    Returns ``(event keys (n,), gkey, seq, ordinal, flow (old + new), supported keys)``."""
    n, m, m_old = t.shape[0], c_event.shape[0], old_gkey.shape[0]
    ev_key = np.empty(n, np.int64)
    event_group_keys(x, y, t, window_us, roi_of_x, roi_of_y, n_roi, ev_key)
    gkey = np.empty(m_old + m, np.int64)
    seq = np.empty(m_old + m, np.int64)
    ordinal = np.empty(m_old + m, np.int64)
    flow = np.empty((m_old + m, 2), np.float32)
    for i in range(m_old):
        gkey[i], seq[i], ordinal[i] = old_gkey[i], old_seq[i], old_ordinal[i]
        flow[i, 0], flow[i, 1] = old_flow[i, 0], old_flow[i, 1]
    supported = np.empty(m, np.int64)
    n_sup = candidate_group_keys(c_event, c_offset, c_age_j, c_age_i, seq0, ev_key, history,
                                  gkey[m_old:], ordinal[m_old:], supported)
    for c in range(m):
        seq[m_old + c] = c_event[c]
        flow[m_old + c, 0], flow[m_old + c, 1] = c_flow[c, 0], c_flow[c, 1]
    return ev_key, gkey, seq, ordinal, flow, supported[:n_sup]


@njit
def merge_group_counts(old_keys: np.ndarray, old_events: np.ndarray, old_support: np.ndarray,
                       event_keys: np.ndarray, supported_keys: np.ndarray, slack: int,
                       floor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The pending groups after adding events: the sorted union of ``old_keys`` (sorted,
    distinct) with the new events' keys, with the old counts plus one per new event
    (``events``) and one per new event with candidates (``support``, keys in
    ``supported_keys``). Through a table over the keys' range, as :func:`unique_inverse`;
    ``None`` when that range exceeds ``slack * count + floor`` (the caller sorts then)."""
    n = old_keys.shape[0] + event_keys.shape[0] + supported_keys.shape[0]
    if n == 0:
        return None
    lo, hi = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    for k in old_keys:  # (three loops: the arrays' layouts may differ)
        lo, hi = min(lo, k), max(hi, k)
    for k in event_keys:
        lo, hi = min(lo, k), max(hi, k)
    for k in supported_keys:
        lo, hi = min(lo, k), max(hi, k)
    span = hi - lo + 1
    if span > slack * n + floor:
        return None
    present = np.zeros(span, np.bool_)
    events = np.zeros(span, np.int64)
    support = np.zeros(span, np.int64)
    for i in range(old_keys.shape[0]):
        k = old_keys[i] - lo
        present[k] = True
        events[k] += old_events[i]
        support[k] += old_support[i]
    for k in event_keys:
        present[k - lo] = True
        events[k - lo] += 1
    for k in supported_keys:
        present[k - lo] = True
        support[k - lo] += 1
    m = 0
    for k in range(span):
        m += present[k]
    out_keys = np.empty(m, np.int64)
    out_events = np.empty(m, np.int64)
    out_support = np.empty(m, np.int64)
    j = 0
    for k in range(span):
        if present[k]:
            out_keys[j], out_events[j], out_support[j] = k + lo, events[k], support[k]
            j += 1
    return out_keys, out_events, out_support


def _dense_range(values: Tensor, count: int) -> tuple[int, int] | None:
    """``(lo, span)`` of int64 ``values`` when a dense table over them is small, else None."""
    if values.numel() == 0:
        return None
    lo, hi = torch.stack(torch.aminmax(values)).tolist()  # one pass, one transfer
    span = hi - lo + 1
    return (lo, span) if span <= DENSE_SLACK * count + DENSE_FLOOR else None


def unique_inverse(values: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.unique(values, return_inverse=True)`` (sorted keys), by a presence table when
    the values span a small range (the same result, without sorting; in NumPy on the CPU,
    where its small-array steps cost a third of torch's)."""
    dense = _dense_range(values, values.numel())
    if dense is None:
        return torch.unique(values, return_inverse=True)
    lo, span = dense
    if values.device.type == "cpu" and NUMPY_ON_CPU:
        offset_np = values.numpy() - lo
        present_np = np.zeros(span, np.bool_)
        present_np[offset_np] = True
        rank_np = np.cumsum(present_np, dtype=np.int64) - 1
        return (torch.from_numpy(np.flatnonzero(present_np) + lo),
                torch.from_numpy(rank_np[offset_np]))
    offset = values - lo
    present = torch.zeros(span, dtype=torch.bool, device=values.device)
    present[offset] = True
    rank = torch.cumsum(present.to(torch.int64), 0) - 1
    return torch.nonzero(present).reshape(-1) + lo, rank[offset]


def positions(keys: Tensor, values: Tensor) -> Tensor:
    """``torch.searchsorted(keys, values)`` for ``values`` that all occur in the sorted,
    distinct ``keys``: their positions, by a dense table when the keys span a small range."""
    dense = _dense_range(keys, keys.numel() + values.numel())
    if dense is None or values.numel() < 64:
        return torch.searchsorted(keys, values)
    lo, span = dense
    if keys.device.type == "cpu" and NUMPY_ON_CPU:  # NumPy: as in unique_inverse
        table_np = np.full(span, -1, np.int64)
        table_np[keys.numpy() - lo] = np.arange(keys.numel(), dtype=np.int64)
        return torch.from_numpy(table_np[values.numpy() - lo])
    table = torch.full((span,), -1, dtype=torch.int64, device=keys.device)
    table[keys - lo] = torch.arange(keys.numel(), device=keys.device)
    return table[values - lo]
