"""``TripletFlow``: event optical flow by triplet matching and RoI registration.

Section III-A of the method paper, after Shiba et al. 2022: per-event triplet candidates
(:mod:`evtrack.flow.candidates`) registered into one flow per region of interest and time
window (:mod:`evtrack.flow.registration`).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from evtrack.config_values import checked_device
from evtrack.errors import EventsError, EvtrackError
from evtrack.events import Events
from evtrack.flow.candidates import Candidates, CandidateSearch
from evtrack.flow.compiled import CompiledSearch
from evtrack.flow.config import FlowConfig, search_offsets
from evtrack.flow.registration import (
    COST_SCALE,
    hash32,
    register_groups,
    select_smallest,
)
from evtrack.flow.registration_compiled import register_closed_groups
from evtrack.flow.result import FlowResult
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["TripletFlow"]

_ORD_BITS = 20
_INT64_MAX = torch.iinfo(torch.int64).max


@dataclass
class _Pending:
    """Candidates and group tallies of RoI windows not yet complete."""

    gkey: Tensor  # (M,) group key of each candidate
    seq: Tensor  # (M,) stream index of its event
    ordinal: Tensor  # (M,) candidate ordinal within its event
    flow: Tensor  # (M, 2)
    g_keys: Tensor  # (G,) groups seen
    g_events: Tensor  # (G,) events per group
    g_support: Tensor  # (G,) events with a candidate per group
    ev_gkey: Tensor  # (E,) group key of each pending event (per-event mode only)


_DENSE_SLACK = 8
"""Group keys spanning at most this many times their count (plus 64k) are indexed through a
dense table instead of sorting / binary search: a batch's keys cover a few windows' RoIs."""


_NUMPY_ON_CPU = True
"""The dense-table helpers below work in NumPy on CPU tensors, and the events' and
candidates' group keys in the compiled loops below (in NumPy without numba); False: torch
everywhere, as on CUDA (the tests run every form)."""


@njit
def _event_group_keys(x, y, t, window_us, roi_of_x, roi_of_y, n_roi, out):
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
def _candidate_group_keys(event, offset, age_j, age_i, seq0, gkey, history, c_g, ordinal,
                          supported):
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
def _ingest(x, y, t, window_us, roi_of_x, roi_of_y, n_roi, c_event, c_offset, c_age_j,
            c_age_i, c_flow, seq0, history, old_gkey, old_seq, old_ordinal, old_flow):
    """The CPU bookkeeping of a searched batch in one pass: each event's group key (as
    :func:`_event_group_keys`), each candidate's group key and ordinal (as
    :func:`_candidate_group_keys`) appended to the pending candidates' ``gkey, seq,
    ordinal, flow``, and the groups of the events with candidates.

    Returns ``(event keys (n,), gkey, seq, ordinal, flow (old + new), supported keys)``."""
    n, m, m_old = t.shape[0], c_event.shape[0], old_gkey.shape[0]
    ev_key = np.empty(n, np.int64)
    _event_group_keys(x, y, t, window_us, roi_of_x, roi_of_y, n_roi, ev_key)
    gkey = np.empty(m_old + m, np.int64)
    seq = np.empty(m_old + m, np.int64)
    ordinal = np.empty(m_old + m, np.int64)
    flow = np.empty((m_old + m, 2), np.float32)
    for i in range(m_old):
        gkey[i], seq[i], ordinal[i] = old_gkey[i], old_seq[i], old_ordinal[i]
        flow[i, 0], flow[i, 1] = old_flow[i, 0], old_flow[i, 1]
    supported = np.empty(m, np.int64)
    n_sup = _candidate_group_keys(c_event, c_offset, c_age_j, c_age_i, seq0, ev_key, history,
                                  gkey[m_old:], ordinal[m_old:], supported)
    for c in range(m):
        seq[m_old + c] = c_event[c]
        flow[m_old + c, 0], flow[m_old + c, 1] = c_flow[c, 0], c_flow[c, 1]
    return ev_key, gkey, seq, ordinal, flow, supported[:n_sup]


@njit
def _merge_group_counts(old_keys, old_events, old_support, event_keys, supported_keys, slack,
                        floor):
    """The pending groups after adding events: the sorted union of ``old_keys`` (sorted,
    distinct) with the new events' keys, with the old counts plus one per new event
    (``events``) and one per new event with candidates (``support``, keys in
    ``supported_keys``). Through a table over the keys' range, as :func:`_unique_inverse`;
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
    return (lo, span) if span <= _DENSE_SLACK * count + 65_536 else None


def _unique_inverse(values: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.unique(values, return_inverse=True)`` (sorted keys), by a presence table when
    the values span a small range (the same result, without sorting; in NumPy on the CPU,
    where its small-array steps cost a third of torch's)."""
    dense = _dense_range(values, values.numel())
    if dense is None:
        return torch.unique(values, return_inverse=True)
    lo, span = dense
    if values.device.type == "cpu" and _NUMPY_ON_CPU:
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


def _positions(keys: Tensor, values: Tensor) -> Tensor:
    """``torch.searchsorted(keys, values)`` for ``values`` that all occur in the sorted,
    distinct ``keys``: their positions, by a dense table when the keys span a small range."""
    dense = _dense_range(keys, keys.numel() + values.numel())
    if dense is None or values.numel() < 64:
        return torch.searchsorted(keys, values)
    lo, span = dense
    if keys.device.type == "cpu" and _NUMPY_ON_CPU:  # NumPy: as in _unique_inverse
        table_np = np.full(span, -1, np.int64)
        table_np[keys.numpy() - lo] = np.arange(keys.numel(), dtype=np.int64)
        return torch.from_numpy(table_np[values.numpy() - lo])
    table = torch.full((span,), -1, dtype=torch.int64, device=keys.device)
    table[keys - lo] = torch.arange(keys.numel(), device=keys.device)
    return table[values - lo]


class TripletFlow(nn.Module):
    """Event optical flow: triplet candidates registered per RoI and time window.

    Args:
        config: a :class:`FlowConfig`; keyword arguments override its fields.
        return_event_flow: also return a flow per event (its candidate nearest to its RoI's
            registered flow). Candidates of open windows are then kept in full until the
            window closes (memory grows with the events of one window).
        **overrides: :class:`FlowConfig` fields.

    Use ``flow(events)`` on a whole recording (it resets first and flushes at the end), or
    ``update(events)`` repeatedly on consecutive batches of a stream plus a final
    ``flush()``: the concatenated results equal one call on the concatenated events.

    Example:
        >>> from evtrack.flow.scenes import translating_texture
        >>> ev, _ = translating_texture((64, 48), velocity=(500.0, 0.0), duration_us=40_000)
        >>> res = TripletFlow(roi_size=32, window_us=10_000)(ev)
        >>> res.flow.shape[1]
        2
    """

    def __init__(self, config: FlowConfig | None = None, *, return_event_flow: bool = False,
                 **overrides: object) -> None:
        super().__init__()
        config = config if config is not None else FlowConfig()
        if overrides:
            config = config.replace(**overrides)
        self.config = config
        self.return_event_flow = bool(return_event_flow)
        self.device = checked_device(config.device, "flow config field 'device'")
        # candidate ordinals (offset * K + age_j) * K + age_i lie below this, for every call
        self._n_ordinals = len(search_offsets(config.radius)) * config.history ** 2
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the history, the pending windows and the stream position."""
        self._sensor = self.config.sensor_size
        self._search = self._new_search() if self._sensor is not None else None
        self._last_t: int | None = None
        self._emitted = 0
        self._pending = self._empty_pending()

    def continue_bursts(self, events: Events) -> None:
        """Take the first event of each pixel in ``events`` as the continuation of a burst:
        the burst filter (``refractory_us``) skips it when :meth:`update` gets it, as if the
        pixel's previous event, of the same polarity, had just been seen.

        For a stream from which a stretch of events was taken out (an event burst the
        tracker dropped): each pixel's first event after the gap would otherwise start a
        burst even in the middle of an edge's, and such onsets, nearly simultaneous along
        the edge, pair into triplets of spurious fast flows. Nothing changes with
        ``refractory_us = 0``.

        Args:
            events: the next events of the stream, before they are given to :meth:`update`
                (time-sorted, not before the events seen).

        Raises:
            EventsError: as :meth:`update` for the same events.
        """
        if not isinstance(events, Events):
            self._check(events)  # raises
        if self.config.refractory_us == 0 or not len(events):
            return
        last_t = self._last_t
        self._check(events)
        self._last_t = last_t  # update() gets these events next
        pixel = (events.y.long() * self._sensor[0] + events.x.long()).cpu().numpy()
        first = np.sort(np.unique(pixel, return_index=True)[1])  # each pixel's first, in order
        if isinstance(self._search, CompiledSearch):
            self._search.continue_bursts(events.x.numpy()[first], events.y.numpy()[first],
                                         events.t.numpy()[first], events.p.numpy()[first])
        else:
            index = torch.from_numpy(first)
            self._search.continue_bursts(*(v.index_select(0, index) for v in (
                events.x, events.y, events.t, events.p)))

    def to(self, device: str | torch.device) -> TripletFlow:  # type: ignore[override]
        """Move the state to ``device`` (the history is kept)."""
        device = torch.device(device)
        if device == self.device:
            return self
        old_search = self._search
        if isinstance(old_search, CompiledSearch) and old_search.next_seq > 0:
            raise EvtrackError("TripletFlow.to(): the compiled CPU backend cannot carry its "
                               "history to another device; move the flow before its first "
                               "events, or use FlowConfig(backend='torch')")
        self.config = self.config.replace(device=str(device))
        self.device = device
        if isinstance(old_search, CompiledSearch):
            old_search = None
            self._search = self._new_search()
        if old_search is not None:
            new = CandidateSearch(self.config, device)
            new.history.load_state_dict(old_search.history.state_dict())
            new.next_seq = old_search.next_seq
            new.last_t = old_search.last_t.to(device)
            new.last_p = old_search.last_p.to(device)
            self._search = new
        p = self._pending
        self._pending = _Pending(*(getattr(p, f).to(device) for f in _Pending.__annotations__))
        return self

    def _new_search(self) -> CandidateSearch | CompiledSearch:
        self.config.use_triton(self.device.type)  # a backend that cannot run fails here
        if self.config.use_compiled(self.device.type):
            return CompiledSearch(self.config, self.device)
        return CandidateSearch(self.config, self.device)

    def _empty_pending(self) -> _Pending:
        z = torch.zeros(0, dtype=torch.int64, device=self.device)
        return _Pending(z, z, z, torch.zeros(0, 2, device=self.device), z, z, z, z)

    @property
    def num_rois(self) -> tuple[int, int]:
        """RoI grid size ``(columns, rows)``."""
        if self._sensor is None:
            raise EventsError("the sensor size is not known yet (no events seen, none set)")
        s = self.config.roi_size
        return math.ceil(self._sensor[0] / s), math.ceil(self._sensor[1] / s)

    def roi_centres(self) -> Tensor:
        """(num_rois, 2) float32 centres in px of every RoI (row-major), clipped RoIs too."""
        return self._roi_centres()

    def _roi_centres(self) -> Tensor:
        cols, rows = self.num_rois
        s = self.config.roi_size
        w, h = self._sensor
        rx = torch.arange(cols, dtype=torch.float32)
        ry = torch.arange(rows, dtype=torch.float32)
        cx = (rx * s + torch.clamp(rx * s + s, max=w) - 1) / 2
        cy = (ry * s + torch.clamp(ry * s + s, max=h) - 1) / 2
        gy, gx = torch.meshgrid(cy, cx, indexing="ij")
        return torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)

    # ------------------------------------------------------------------ public calls
    def forward(self, events: Events) -> FlowResult:
        """Flow of a complete stream: ``reset()``, ``update(events)``, ``flush()``."""
        self.reset()
        first = self.update(events)
        return FlowResult.cat([first, self.flush()])

    @property
    def events_seen(self) -> int:
        """Events given since the last reset: the stream index of the next event."""
        return self._search.next_seq if self._search is not None else 0

    def update(self, events: Events, until_us: int | None = None,
               search: Tensor | None = None) -> FlowResult:
        """Add the next events of the stream; return the RoI windows they complete.

        Args:
            events: the next events (time-sorted, not before earlier ones).
            until_us: optional promise that no later event is earlier than this time (µs),
                e.g. a live source's clock or the end of a batch of time: the windows that
                end at or before it are complete and are reported now, in the same
                registration as those the events close. A later event before it raises
                :class:`EventsError`. The results equal those without the promise, only
                sooner.
            search: optional (N,) bool, which of ``events`` are searched for candidates
                (default all). The others enter the history as usual, so the triplets of
                later events are those of the whole stream; they get no candidates (nor a
                per-event flow) and add nothing to a RoI window's data term or support.
                Used to spend the search on a sample of dense windows' events (see
                :func:`evtrack.flow.sampling.sampled_search`).

        Raises:
            EventsError: unsorted events, events before the previous batch (or before an
                earlier ``until_us``), events after ``until_us``, events outside the sensor,
                or bad polarity.
        """
        if until_us is not None:  # checked before anything changes
            until_us = int(until_us)
            if isinstance(events, Events) and len(events) and until_us < events.t_end:
                raise EventsError(f"flow input: until_us={until_us} µs is before the last "
                                  f"event (t={events.t_end} µs)")
        if search is not None:  # checked before anything changes, as until_us
            search = torch.as_tensor(search)
            n = len(events) if isinstance(events, Events) else -1
            if search.dtype != torch.bool or search.shape != (n,):
                raise ValueError(f"flow input: search must be a ({n},) bool tensor, "
                                 f"got {tuple(search.shape)} {search.dtype}")
        self._check(events)
        parts = [FlowResult.empty(self.device, self._emitted, self.return_event_flow)]
        size = self.config.chunk_size
        pieces = [(events[start:start + size],
                   None if search is None else search[start:start + size])
                  for start in range(0, len(events), size)]
        for i, piece in enumerate(self._searched(pieces)):
            last = i == len(pieces) - 1 and until_us is not None
            parts.append(self._register_piece(*piece, finalise=not last))
        if until_us is not None and self._search is not None:
            self._last_t = max(self._last_t if self._last_t is not None else until_us,
                               until_us)
            cols, rows = self.num_rois
            parts.append(self._finalise(until_us // self.config.window_us * cols * rows))
        return FlowResult.cat(parts)

    def flush(self) -> FlowResult:
        """Report every pending RoI window (call at the end of the stream)."""
        if self._search is None:
            return FlowResult.empty(self.device, self._emitted, self.return_event_flow)
        return self._finalise(_INT64_MAX)

    # ------------------------------------------------------------------ internals
    def _check(self, events: Events) -> None:
        if not isinstance(events, Events):
            raise EventsError(f"TripletFlow expects an Events container, got "
                              f"{type(events).__name__}")
        size = events.sensor_size
        if self._sensor is None:
            if size is None:
                raise EventsError("the sensor size is unknown: set FlowConfig.sensor_size or "
                                  "give events with sensor_size")
            self._sensor = tuple(size)
            self.config = self.config.replace(sensor_size=self._sensor)
            self._search = self._new_search()
        elif size is not None and tuple(size) != tuple(self._sensor):
            raise EventsError(f"events of sensor size {tuple(size)} given to a flow set up "
                              f"for {tuple(self._sensor)}")
        if not len(events):
            return
        report = events.validate(self._sensor)
        if not report.ok:
            raise EventsError(f"flow input: {report}")
        if self._last_t is not None and events.t_start < self._last_t:
            raise EventsError(f"flow input: events start at t={events.t_start} µs, before the "
                              f"last event of the previous batch (t={self._last_t} µs)")
        self._last_t = events.t_end

    def _group_keys(self, x: Tensor, y: Tensor, t: Tensor) -> Tensor:
        """(N,) group key of each event, by tensor ops (CUDA, or CPU without numba; on CPU
        with numba :func:`_ingest` computes them)."""
        cols, rows = self.num_rois
        s = self.config.roi_size
        window = torch.div(t, self.config.window_us, rounding_mode="floor")
        roi = torch.div(y, s, rounding_mode="floor") * cols + torch.div(x, s,
                                                                       rounding_mode="floor")
        return window * (cols * rows) + roi

    def _roi_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """(W,) RoI column of each pixel column and (H,) first RoI index of each pixel row's
        RoI row, int64 (kept between calls; made again when the sensor or RoI size changed)."""
        key = (self._sensor, self.config.roi_size)
        cached = getattr(self, "_roi_lut", None)
        if cached is None or cached[0] != key:
            s = self.config.roi_size
            cols, _ = self.num_rois
            w, h = self._sensor
            self._roi_lut = (key, np.arange(w, dtype=np.int64) // s,
                             np.arange(h, dtype=np.int64) // s * cols)
        return self._roi_lut[1], self._roi_lut[2]

    def _searched(self, pieces: list[tuple[Events, Tensor | None]]):
        """The searched pieces, in order. With the compiled search and several pieces, the
        search of piece ``k + 1`` runs in a worker thread (the kernel releases the GIL) while
        the caller registers piece ``k``: the search is sequential by nature and the
        registration does not touch its history, so the two overlap without changing a bit
        of the result."""
        if len(pieces) < 2 or not isinstance(self._search, CompiledSearch):
            for piece in pieces:
                yield self._search_piece(piece)
            return
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="evtrack-flow") as pool:
            ahead = pool.submit(self._search_piece, pieces[0])
            for k in range(len(pieces)):
                done = ahead.result()
                if k + 1 < len(pieces):
                    ahead = pool.submit(self._search_piece, pieces[k + 1])
                yield done

    def _search_piece(self, piece: tuple[Events, Tensor | None]
                      ) -> tuple[Tensor, Tensor, Tensor, Candidates, int]:
        """The candidates of the next events (advances the search's history)."""
        ev, search = piece
        dev = self.device
        x = ev.x.to(dev, torch.int64)
        y = ev.y.to(dev, torch.int64)
        t = ev.t.to(dev, torch.int64)
        seq0 = self._search.next_seq
        if search is None:
            return x, y, t, self._search(x, y, t, ev.p.to(dev)), seq0
        return x, y, t, self._search(x, y, t, ev.p.to(dev), search.to(dev)), seq0

    def _register_piece(self, x: Tensor, y: Tensor, t: Tensor, cands: Candidates,
                        seq0: int, finalise: bool = True) -> FlowResult:
        """Add searched events to the pending windows; register the windows they close
        (unless ``finalise`` is false: the caller registers them)."""
        if t.device.type == "cpu" and _NUMPY_ON_CPU and jit_available():
            self._ingest(x, y, t, cands, seq0)
        else:
            self._add_pending(self._group_keys(x, y, t), cands, seq0)
        if not finalise:
            return FlowResult.empty(self.device, event_start=self._emitted,
                                    with_events=self.return_event_flow)
        cols, rows = self.num_rois
        w_open = int(torch.div(t[-1], self.config.window_us, rounding_mode="floor"))
        return self._finalise(w_open * cols * rows)

    def _candidate_groups(self, gkey: Tensor, cands: Candidates, seq0: int
                          ) -> tuple[Tensor, Tensor, Tensor]:
        """(M,) group key and (M,) ordinal of each candidate, and the group of each event
        that has candidates (its first candidate's); in NumPy on the CPU (as the table
        helpers: the same int64 values). Without numba only: with it, :func:`_ingest`."""
        k = self.config.history
        if self.device.type == "cpu" and _NUMPY_ON_CPU:
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
        first_of_event = torch.ones(len(cands), dtype=torch.bool, device=self.device)
        if len(cands) > 1:
            first_of_event[1:] = cands.event[1:] != cands.event[:-1]
        return c_g, ordinal, c_g[first_of_event]

    def _ingest(self, x: Tensor, y: Tensor, t: Tensor, cands: Candidates, seq0: int) -> None:
        """:meth:`_add_pending` of a batch's events and candidates on CPU with numba: the
        group keys, the candidates' bookkeeping and the pending arrays in one compiled pass
        (:func:`_ingest`), then the group counts (:func:`_merge_group_counts`)."""
        p = self._pending
        cols, rows = self.num_rois
        roi_of_x, roi_of_y = self._roi_tables()
        ev_key, gkey, seq, ordinal, flow, supported = _ingest(
            x.numpy(), y.numpy(), t.numpy(), self.config.window_us, roi_of_x, roi_of_y,
            cols * rows, cands.event.numpy(), cands.offset.numpy(), cands.age_j.numpy(),
            cands.age_i.numpy(), cands.flow.numpy(), seq0, self.config.history,
            p.gkey.numpy(), p.seq.numpy(), p.ordinal.numpy(), p.flow.numpy())
        merged = _merge_group_counts(p.g_keys.numpy(), p.g_events.numpy(), p.g_support.numpy(),
                                     ev_key, supported, _DENSE_SLACK, 65_536)
        if merged is None:  # keys too spread for a table: the sort-based merge
            keys, g_events, g_support = self._merged_counts(torch.from_numpy(ev_key),
                                                            torch.from_numpy(supported))
        else:
            keys, g_events, g_support = (torch.from_numpy(a) for a in merged)
        self._pending = _Pending(
            gkey=torch.from_numpy(gkey), seq=torch.from_numpy(seq),
            ordinal=torch.from_numpy(ordinal), flow=torch.from_numpy(flow), g_keys=keys,
            g_events=g_events, g_support=g_support,
            ev_gkey=(torch.cat([p.ev_gkey, torch.from_numpy(ev_key)])
                     if self.return_event_flow else p.ev_gkey))

    def _merged_counts(self, gkey: Tensor, supported: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The pending groups' keys and counts after adding events with keys ``gkey`` (those
        with candidates: ``supported``), by sorting."""
        p = self._pending
        keys, inv = _unique_inverse(torch.cat([p.g_keys, gkey, supported]))
        n_old, n_new = p.g_keys.numel(), gkey.numel()
        # per group: the pending counts, + 1 per new event, + 1 per new event with candidates
        g_events = torch.zeros_like(keys).index_add_(0, inv[:n_old], p.g_events)
        g_events.index_add_(0, inv[n_old:n_old + n_new], torch.ones_like(gkey))
        g_support = torch.zeros_like(keys).index_add_(0, inv[:n_old], p.g_support)
        g_support.index_add_(0, inv[n_old + n_new:], torch.ones_like(supported))
        return keys, g_events, g_support

    def _add_pending(self, gkey: Tensor, cands: Candidates, seq0: int) -> None:
        """:meth:`_ingest` by tensor and NumPy operations (CUDA, or CPU without numba)."""
        p = self._pending
        c_g, ordinal, supported = self._candidate_groups(gkey, cands, seq0)
        keys, g_events, g_support = self._merged_counts(gkey, supported)
        self._pending = _Pending(
            gkey=torch.cat([p.gkey, c_g]), seq=torch.cat([p.seq, cands.event]),
            ordinal=torch.cat([p.ordinal, ordinal]), flow=torch.cat([p.flow, cands.flow]),
            g_keys=keys, g_events=g_events, g_support=g_support,
            ev_gkey=torch.cat([p.ev_gkey, gkey]) if self.return_event_flow else p.ev_gkey)

    def _finalise(self, open_key: int) -> FlowResult:
        """Register the pending groups with key < ``open_key`` and keep the rest pending."""
        cfg = self.config
        p = self._pending
        if (p.g_keys.numel() == 0 or int(p.g_keys[0]) >= open_key) and (
                self.return_event_flow or p.gkey.numel() <= 4 * cfg.chunk_size):
            # no window closes (keys are sorted) and the open ones are small: nothing to do
            # now (their pruning below waits for a later call; it gives the same selection)
            return FlowResult.empty(self.device, event_start=self._emitted,
                                    with_events=self.return_event_flow)
        # pending candidates are in stream order, so their windows never decrease and the
        # closed ones (key < open_key <=> window < the open window) are a prefix; g_keys are
        # sorted, so the closed groups are a prefix too
        if self.device.type == "cpu":  # (bisection finds the prefix's end too)
            n_g = int(np.searchsorted(p.g_keys.numpy(), open_key))
            n_c = int(np.searchsorted(p.gkey.numpy(), open_key))
        else:
            n_g = int(torch.searchsorted(p.g_keys, open_key))
            n_c = int((p.gkey < open_key).sum())
        keys = p.g_keys[:n_g]
        n_done_events = int((p.ev_gkey < open_key).sum()) if self.return_event_flow else 0
        support = p.g_support[:n_g]
        if self._compiled_report() and n_c:
            result, reported, full_flow, c_local = self._register_compiled(
                keys, p.gkey[:n_c], p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c], support,
                p.g_events[:n_g])
        else:
            c_local = _positions(keys, p.gkey[:n_c])
            reg = register_groups(c_local, p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c],
                                  keys.numel(), cfg.max_events_per_roi, cfg.max_hypotheses,
                                  cfg.aperture_ratio, cfg.pair_budget, cfg.refine,
                                  cfg.line_gate, cfg.refine_iters,
                                  compiled=cfg.use_compiled(self.device.type),
                                  n_ordinals=self._n_ordinals,
                                  triton=cfg.use_triton(self.device.type))
            agree = reg.inliers.to(torch.float64) >= (float(cfg.min_inlier_fraction)
                                                      * reg.used_events.to(torch.float64))
            reported = (support >= cfg.min_support) & ~torch.isnan(reg.full_flow[:, 0]) & agree
            result = self._rows(keys, reported, reg, support, p.g_events[:n_g])
            full_flow = reg.full_flow
        if self.return_event_flow:
            result.event_flow = self._event_flows(
                c_local, p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c],
                torch.where(reported[:, None], full_flow, torch.nan), n_done_events)
        result.event_start = self._emitted
        self._emitted += n_done_events
        g, s = p.gkey[n_c:], p.seq[n_c:]
        if not self.return_event_flow and g.numel() > 4 * cfg.chunk_size:
            # prune the open windows to the events the registration can ever use (the same
            # hash selection as the registration's cap, so pruning now or later, or not at
            # all, gives the same flow; pruning only large ones bounds the memory and spares
            # small calls the work)
            first = torch.ones_like(s, dtype=torch.bool)
            first[1:] = s[1:] != s[:-1]
            run = torch.cumsum(first.to(torch.int64), 0) - 1
            open_keys = p.g_keys[n_g:]  # sorted, and every open candidate's key is one
            run_keep = select_smallest(_positions(open_keys, g[first]), hash32(s[first]),
                                       cfg.max_events_per_roi, n_groups=open_keys.numel())
            keep = run_keep[run]
            sel = slice(n_c, None) if bool(keep.all()) else n_c + torch.nonzero(keep).reshape(-1)
        else:
            sel = slice(n_c, None)
        self._pending = _Pending(
            gkey=p.gkey[sel], seq=p.seq[sel], ordinal=p.ordinal[sel], flow=p.flow[sel],
            g_keys=p.g_keys[n_g:], g_events=p.g_events[n_g:], g_support=p.g_support[n_g:],
            ev_gkey=p.ev_gkey[n_done_events:])
        return result

    def _compiled_report(self) -> bool:
        """Whether ``_finalise`` registers and reports in compiled form
        (:meth:`_register_compiled`): CPU, the compiled backend, numba, the NumPy bookkeeping
        and the refined flow (the form that :func:`_report_rows` reproduces)."""
        return (self.device.type == "cpu" and _NUMPY_ON_CPU and jit_available()
                and self.config.refine and self.config.use_compiled("cpu"))

    def _register_compiled(self, keys: Tensor, gkey: Tensor, seq: Tensor, ordinal: Tensor,
                           flow: Tensor, support: Tensor, n_events: Tensor
                           ) -> tuple[FlowResult, Tensor, Tensor, Tensor]:
        """The registration of the closed groups ``keys`` and their reported rows in one
        compiled call (:func:`~evtrack.flow.registration_compiled.register_closed_groups`):
        the same rows as :func:`register_groups` (compiled) and :meth:`_rows`, without their
        two dozen small tensor operations. Returns the rows, ``reported`` (G,),
        ``full_flow`` (G, 2) and each candidate's group position (M,)."""
        cfg = self.config
        cols, rows = self.num_rois
        out = register_closed_groups(
            keys.numpy(), gkey.numpy(), seq.numpy(), ordinal.numpy(), flow.numpy(),
            support.numpy(), n_events.numpy(), self._device_centres().numpy(), cols * rows,
            cfg.window_us, cfg.max_events_per_roi, cfg.max_hypotheses, self._n_ordinals,
            cfg.line_gate, cfg.refine_iters, cfg.aperture_ratio, cfg.min_support,
            cfg.min_inlier_fraction)
        position, reported, full, *columns = (torch.from_numpy(a) for a in out)
        names = ("xy", "t", "flow", "support", "cost", "normal", "normal_dir", "full_flow",
                 "n_events", "roi", "window")
        result = FlowResult(**dict(zip(names, columns, strict=True)))
        return result, reported, full, position

    def _rows(self, keys: Tensor, reported: Tensor, reg, support: Tensor,
              n_events: Tensor) -> FlowResult:
        cols, rows = self.num_rois
        n_roi = cols * rows
        idx = torch.nonzero(reported).reshape(-1)  # one mask -> index (a sync on CUDA)

        def pick(v: Tensor) -> Tensor:
            return torch.index_select(v, 0, idx)

        k = pick(keys)
        window = torch.div(k, n_roi, rounding_mode="floor")
        roi = k - window * n_roi
        centres = self._device_centres()
        w_us = self.config.window_us
        return FlowResult(
            xy=torch.index_select(centres, 0, roi), t=window * w_us + w_us // 2,
            flow=pick(reg.flow), support=pick(support), cost=pick(reg.cost),
            normal=pick(reg.normal), normal_dir=pick(reg.normal_dir),
            full_flow=pick(reg.full_flow), n_events=pick(n_events), roi=roi, window=window)

    def _device_centres(self) -> Tensor:
        """:meth:`roi_centres` on the flow's device, kept between calls (computed again when
        the sensor, the RoI size or the device changed; not to be changed in place)."""
        key = (self._sensor, self.config.roi_size, self.device)
        cached = getattr(self, "_centres", None)
        if cached is None or cached[0] != key:
            self._centres = (key, self._roi_centres().to(self.device))
        return self._centres[1]

    def _event_flows(self, c_local: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor,
                     group_flow: Tensor, n_events: int) -> Tensor:
        out = torch.full((n_events, 2), float("nan"), dtype=torch.float32, device=self.device)
        if seq.numel() == 0:
            return out
        target = group_flow[c_local]
        valid = ~torch.isnan(target[:, 0])
        dist = (flow - target).norm(dim=1)
        q = torch.round(torch.nan_to_num(dist, nan=0.0).to(torch.float64) * COST_SCALE)
        combo = (q.to(torch.int64) << _ORD_BITS) | ordinal
        slot = seq - self._emitted
        best = torch.full((n_events,), _INT64_MAX, dtype=torch.int64, device=self.device)
        best.scatter_reduce_(0, slot[valid], combo[valid], "amin")
        chosen = valid & (combo == best[slot])
        out[slot[chosen]] = flow[chosen]
        return out

    def extra_repr(self) -> str:
        return str(self.config)
