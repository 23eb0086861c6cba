"""``TripletFlow``: event optical flow by triplet matching and RoI registration.

Section III-A of the method paper, after Shiba et al. 2022: per-event triplet candidates
(:mod:`evtrack.flow.candidates`) registered into one flow per region of interest and time
window (:mod:`evtrack.flow.registration`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import Tensor, nn

from evtrack.configs import checked_device
from evtrack.errors import EventsError, EvtrackError
from evtrack.events import Events
from evtrack.flow.backends import (
    CandidateSearchBackend,
    FlowBackend,
    RegistrationBackend,
    resolve,
)
from evtrack.flow.candidates import Candidates
from evtrack.flow.config import FlowConfig, search_offsets
from evtrack.flow.constants import COST_SCALE
from evtrack.flow.line_rules import line_report, one_line_normal
from evtrack.flow.pending import (
    Pending,
    WindowGrid,
    add_batch,
    compiled_bookkeeping,
    keep_open,
    positions,
)
from evtrack.flow.registration import Registration, register_groups
from evtrack.flow.result import FlowResult

__all__ = ["TripletFlow"]

_ORD_BITS = 20
_INT64_MAX = torch.iinfo(torch.int64).max


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
        self._pending = Pending.empty(self.device)

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
        index = torch.from_numpy(first).to(events.t.device)
        self._search.continue_bursts(*(v.index_select(0, index) for v in (
            events.x, events.y, events.t, events.p)))

    def to(self, device: str | torch.device) -> TripletFlow:  # type: ignore[override]
        """Move the state to ``device`` (the history is kept)."""
        device = torch.device(device)
        if device == self.device:
            return self
        config = self.config.replace(device=str(device))
        old_search = self._search
        moved = old_search.moved(config, device) if old_search is not None else None
        if old_search is not None and moved is None and old_search.next_seq > 0:
            raise EvtrackError("TripletFlow.to(): the compiled CPU backend cannot carry its "
                               "history to another device; move the flow before its first "
                               "events, or use FlowConfig(backend='torch')")
        self.config = config
        self.device = device
        if old_search is not None:
            self._search = moved if moved is not None else self._new_search()
        self._pending = self._pending.to(device)
        return self

    def _backend(self) -> FlowBackend:
        """The backend of the flow's config and device (:func:`~evtrack.flow.backends.resolve`;
        raises :class:`~evtrack.errors.ConfigError` where it cannot run)."""
        return resolve(self.config, self.device)

    def _new_search(self) -> CandidateSearchBackend:
        return self._backend().search(self.config, self.device)

    @property
    def num_rois(self) -> tuple[int, int]:
        """RoI grid size ``(columns, rows)``."""
        grid = self._window_grid()
        return grid.cols, grid.rows

    def _window_grid(self) -> WindowGrid:
        """The groups' RoI grid and windows (kept between calls; made again when the sensor,
        the RoI size or the window changed)."""
        if self._sensor is None:
            raise EventsError("the sensor size is not known yet (no events seen, none set)")
        key = (tuple(self._sensor), self.config.roi_size, self.config.window_us)
        grid = getattr(self, "_grid", None)
        if grid is None or (grid.sensor, grid.roi_size, grid.window_us) != key:
            self._grid = grid = WindowGrid(*key)
        return grid

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

    def _searched(self, pieces: list[tuple[Events, Tensor | None]]):
        """The searched pieces, in order. With the compiled search and several pieces, the
        search of piece ``k + 1`` runs in a worker thread (the kernel releases the GIL) while
        the caller registers piece ``k``: the search is sequential by nature and the
        registration does not touch its history, so the two overlap without changing a bit
        of the result."""
        if len(pieces) < 2 or not self._search.runs_ahead:
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
        self._pending = add_batch(self._pending, self._window_grid(), x, y, t, cands, seq0,
                                  self.config.history, self.return_event_flow)
        if not finalise:
            return FlowResult.empty(self.device, event_start=self._emitted,
                                    with_events=self.return_event_flow)
        cols, rows = self.num_rois
        w_open = int(torch.div(t[-1], self.config.window_us, rounding_mode="floor"))
        return self._finalise(w_open * cols * rows)

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
        registration = self._backend().registration
        if (registration.reports_rows and cfg.refine and compiled_bookkeeping(self.device)
                and n_c):
            # registered and reported in one compiled call (the refined flow of the NumPy
            # bookkeeping's groups is what its rows reproduce)
            result, reported, full_flow, c_local = self._register_compiled(
                registration, keys, p.gkey[:n_c], p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c],
                support, p.g_events[:n_g])
        else:
            c_local = positions(keys, p.gkey[:n_c])
            reg = register_groups(c_local, p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c],
                                  keys.numel(), cfg.max_events_per_roi, cfg.max_hypotheses,
                                  cfg.aperture_ratio, cfg.pair_budget, cfg.refine,
                                  cfg.line_gate, cfg.refine_iters, n_ordinals=self._n_ordinals,
                                  backend=registration, fit_min_lines=cfg.fit_min_lines)
            agree = reg.inliers.to(torch.float64) >= (float(cfg.min_inlier_fraction)
                                                      * reg.used_events.to(torch.float64))
            passing = (support >= cfg.min_support) & ~torch.isnan(reg.full_flow[:, 0]) & agree
            cols, rows = self.num_rois
            reported, strict = line_report(torch.div(keys, cols * rows, rounding_mode="floor"),
                                           passing, reg.lines, cfg.min_lines,
                                           cfg.max_lineless_share)
            reg = one_line_normal(reg, strict & (reg.lines == 1))
            result = self._rows(keys, reported, reg, support, p.g_events[:n_g])
            full_flow = reg.full_flow
        if self.return_event_flow:
            result.event_flow = self._event_flows(
                c_local, p.seq[:n_c], p.ordinal[:n_c], p.flow[:n_c],
                torch.where(reported[:, None], full_flow, torch.nan), n_done_events)
        result.event_start = self._emitted
        self._emitted += n_done_events
        self._pending = keep_open(p, n_c, n_g, n_done_events, cfg.max_events_per_roi,
                                  None if self.return_event_flow else 4 * cfg.chunk_size)
        return result

    def _register_compiled(self, registration: RegistrationBackend, keys: Tensor,
                           gkey: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor,
                           support: Tensor, n_events: Tensor
                           ) -> tuple[FlowResult, Tensor, Tensor, Tensor]:
        """The registration of the closed groups ``keys`` and their reported rows in one
        compiled call (``registration.register_closed``, see
        :meth:`~evtrack.flow.registration_compiled.CompiledRegistration.register_closed`):
        the same rows as :func:`register_groups` (compiled) and :meth:`_rows`, without their
        two dozen small tensor operations. Returns the rows, ``reported`` (G,),
        ``full_flow`` (G, 2) and each candidate's group position (M,)."""
        cfg = self.config
        cols, rows = self.num_rois
        out = registration.register_closed(
            keys.numpy(), gkey.numpy(), seq.numpy(), ordinal.numpy(), flow.numpy(),
            support.numpy(), n_events.numpy(), self._device_centres().numpy(), cols * rows,
            cfg.window_us, cfg.max_events_per_roi, cfg.max_hypotheses, self._n_ordinals,
            cfg.line_gate, cfg.refine_iters, cfg.aperture_ratio, cfg.min_support,
            cfg.min_inlier_fraction, cfg.min_lines, cfg.fit_min_lines, cfg.max_lineless_share)
        position, reported, full, *columns = (torch.from_numpy(a) for a in out)
        names = ("xy", "t", "flow", "support", "cost", "normal", "normal_dir", "full_flow",
                 "n_events", "roi", "window")
        result = FlowResult(**dict(zip(names, columns, strict=True)))
        return result, reported, full, position

    def _rows(self, keys: Tensor, reported: Tensor, reg: Registration, support: Tensor,
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
