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
  :func:`~evtrack.flow.config.dt_bounds_us`.
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

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.candidates import NEVER_US, Candidates
from evtrack.flow.config import US_PER_S, FlowConfig, dt_bounds_us, search_offsets

try:  # numba is optional: without it the torch backend runs everywhere
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

__all__ = ["available", "CompiledSearch"]

NEVER = NEVER_US  # a module global: numba freezes it as a compile-time constant
_prange = numba.prange if numba is not None else range


def available() -> bool:
    """Whether numba is installed (the compiled kernels can run)."""
    return numba is not None


def _njit(**kwargs):
    def wrap(fn):
        return numba.njit(cache=True, nogil=True, **kwargs)(fn) if numba is not None else fn
    return wrap


@_njit()
def _search_kernel(x, y, t, p, start, seq0, width, height, off_x, off_y, dt_lo, dt_hi, hi_j,
                   num_x, num_y, history, refractory, tol_abs, permille, last, hist, hist_s,
                   o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow, n_out):
    """Process events ``start..`` until done or until the output might overflow.

    ``last[pixel] = (t, p)`` of the pixel's latest event; ``hist[cell] = (n, t_0..t_{K-1})``:
    the cell's ``n <= K`` latest onsets, newest first (one short row: one cache line per
    lookup); ``hist_s[cell]``: their stream indices (read only for a candidate). Returns
    ``(next event index, rows written)``; the state is updated for every processed event
    only, so a call can resume where the previous one stopped.
    """
    n = x.shape[0]
    n_off = off_x.shape[0]
    capacity = o_event.shape[0]
    worst = n_off * history * history
    pixels = width * height
    k = start
    while k < n:
        if n_out + worst > capacity:
            return k, n_out
        xk, yk, tk, pk = x[k], y[k], t[k], p[k]
        seq = seq0 + k
        pix = yk * width + xk
        prev_t, prev_p = last[pix, 0], last[pix, 1]
        last[pix, 0] = tk
        last[pix, 1] = pk
        k += 1
        if refractory > 0 and prev_t != NEVER and prev_p == pk and tk - prev_t <= refractory:
            continue  # inside a burst: neither searched nor stored
        plane = 0 if pk > 0 else pixels
        for o in range(n_off):
            dx, dy = off_x[o], off_y[o]
            xi, yi = xk - 2 * dx, yk - 2 * dy
            if xi < 0 or xi >= width or yi < 0 or yi >= height:
                continue
            cj = plane + (yk - dy) * width + (xk - dx)
            nj = hist[cj, 0]
            if nj == 0:
                continue
            ci = plane + yi * width + xi
            ni = hist[ci, 0]
            if ni == 0:
                continue
            lo, hi, top_j = dt_lo[o], dt_hi[o], hi_j[o]
            for aj in range(nj):
                tj = hist[cj, 1 + aj]
                dkj = tk - tj
                if dkj < 1:
                    continue
                if dkj >= top_j:
                    break  # older e_j are older still: no t_k - t_i can complete them
                for ai in range(ni):
                    ti = hist[ci, 1 + ai]
                    dki = tk - ti
                    if dki > hi:
                        break  # older e_i are older still
                    dji = tj - ti
                    if dji < 1 or dki < lo:
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
        # store e_k: newest first, the oldest of a full cell drops out
        c = plane + pix
        m = hist[c, 0]
        if m < history:
            hist[c, 0] = m + 1
        else:
            m = history - 1
        for a in range(m, 0, -1):
            hist[c, 1 + a] = hist[c, a]
            hist_s[c, a] = hist_s[c, a - 1]
        hist[c, 1] = tk
        hist_s[c, 0] = seq
    return k, n_out


class CompiledSearch:
    """The candidate search as one compiled event loop (CPU only; see the module docstring).

    Same interface and results as :class:`~evtrack.flow.candidates.CandidateSearch`:
    ``search(x, y, t, p) -> Candidates`` on consecutive batches of one stream, ``reset()``,
    ``next_seq``.

    Args:
        config: the flow parameters (sensor size must be set).
        device: must be CPU.
    """

    def __init__(self, config: FlowConfig, device: str | torch.device = "cpu") -> None:
        if numba is None:
            raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
        if config.sensor_size is None:
            raise ValueError("CompiledSearch needs config.sensor_size")
        self.device = torch.device(device)
        if self.device.type != "cpu":
            raise ValueError(f"the compiled flow backend runs on CPU, not {self.device}")
        self.config = config
        self.width, self.height = config.sensor_size
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
        pixels = self.width * self.height
        k = self.config.history
        self.last = np.zeros((pixels, 2), dtype=np.int64)  # (t, p) of each pixel's latest
        self.last[:, 0] = NEVER_US
        self.hist = np.zeros((2 * pixels, 1 + k), dtype=np.int64)  # (n, times)
        self.hist_s = np.zeros((2 * pixels, k), dtype=np.int64)  # stream indices
        self.next_seq = 0

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
        arrays = [np.ascontiguousarray(a.detach().cpu().numpy(), dtype=np.int64)
                  for a in (x, y, t, p)]
        cfg = self.config
        capacity = max(4 * n + self._worst, 1024)
        parts = []
        start = 0
        while start < n:
            out = [np.empty(capacity, np.int64) for _ in range(7)]
            flow = np.empty((capacity, 2), np.float32)
            start, rows = _search_kernel(
                *arrays, start, self.next_seq, self.width, self.height, self._off_x,
                self._off_y, self._lo, self._hi, self._hi_j, self._num_x, self._num_y,
                cfg.history, cfg.refractory_us, cfg.tolerance_us * 1000,
                cfg.tolerance_permille, self.last, self.hist, self.hist_s, *out, flow, 0)
            parts.append(Candidates(*(torch.from_numpy(a[:rows]) for a in out),
                                    flow=torch.from_numpy(flow[:rows])))
            capacity *= 2
        self.next_seq += n
        return Candidates.cat(parts)


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
