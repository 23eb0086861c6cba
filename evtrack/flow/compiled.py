"""The compiled CPU candidate search (numba): :class:`CompiledSearch`, the compiled backend's
search.

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
  :class:`CompiledSearch`), with the same candidates in the same order.

The kernels are in :mod:`evtrack.flow.search_kernels`. ``FlowConfig.backend`` chooses
(:func:`evtrack.flow.backends.resolve`): ``"auto"`` (default) uses this search on CPU when
numba is installed, ``"torch"`` never, ``"compiled"`` always (an error without numba). The
tests check both searches against the same sequential reference and against each other.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.candidates import Candidates
from evtrack.flow.config import FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.constants import EMPTY_T, MAX_SPAN_US, NO_EVENT, T_KEEP, T_LIMIT, US_PER_S
from evtrack.flow.numba_support import available, thread_limit, torch_thread_count
from evtrack.flow.search_kernels import (
    merge_strips,
    search_kernel,
    search_strips,
    search_strips_merged,
    strip_cuts,
)

__all__ = ["CompiledSearch"]


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
    runs_ahead: bool = True
    """The kernels release the GIL: a caller may search the next batch in a worker thread
    while it registers this one (see :class:`~evtrack.flow.backends.CandidateSearchBackend`)."""

    def __init__(self, config: FlowConfig, device: str | torch.device = "cpu",
                 strips: int | None = None) -> None:
        if not available():
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
        strips = self.strips if self.strips is not None else thread_limit()
        self._allocate(strips if strips > 1 else 0)
        self.next_seq = 0
        self.t_base: int | None = None
        """The base (µs) of the state's relative times; ``None`` before the first event."""

    def continue_bursts(self, x: Tensor | np.ndarray, y: Tensor | np.ndarray,
                        t: Tensor | np.ndarray, p: Tensor | np.ndarray) -> None:
        """Make each given event the continuation of a burst: its pixel's latest event
        becomes one of the same polarity 1 µs before it, so that the burst filter skips it
        when it is searched next (see :meth:`TripletFlow.continue_bursts
        <evtrack.flow.TripletFlow.continue_bursts>`).

        Args:
            x, y: (n,) integer pixel coordinates, one event per pixel (tensors or arrays).
            t: (n,) int64 timestamps in µs, time-sorted, not before the events seen.
            p: (n,) polarity (+1 / -1).
        """
        x, y, t, p = (v.detach().cpu().numpy() if isinstance(v, Tensor) else np.asarray(v)
                      for v in (x, y, t, p))
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

    def moved(self, config: FlowConfig, device: torch.device) -> None:
        """None: the compiled state stays on the CPU (the caller makes a fresh search for
        ``device``, or refuses the move once events were searched)."""
        return None

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
            1 if n < self.parallel_min_events else thread_limit())
        count = max(1, min(count, self.height))
        if count == 1:
            return (np.zeros(1, np.int64), np.full(1, self.height, np.int64),
                    np.full(1, n, np.int64))
        return strip_cuts(y, self.height, count)

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
            start, rows = search_kernel(*arrays, start, self.next_seq, *self._params(), *out,
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
                d_dt, d_flow = search_strips_merged(
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
                search_strips(*arrays, starts, self.next_seq, *self._params(), *out, flow,
                               n_outs, capacity, lo_s, hi_s, self._r2, pixels, 2 * pixels)
                rounds.append((out, flow, n_outs, capacity))
                if bool((starts >= n).all()):
                    break
            seg_start, seg_len, src, src_flow = _strip_segments(rounds, count)
            total = int(seg_len.sum())
            dst = [np.empty(total, np.int64) for _ in range(7)]
            dst_flow = np.empty((total, 2), np.float32)
            merge_strips(n, self.next_seq, seg_start, seg_len, *src, src_flow, *dst, dst_flow)
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
