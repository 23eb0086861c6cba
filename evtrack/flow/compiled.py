"""Compiled CPU kernels of the flow (numba): the candidate search and the Eq. 3 costs.

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
* :func:`hypothesis_costs` evaluates the exact integer Eq. 3 cost of every hypothesis of
  :func:`~evtrack.flow.registration.register_groups` (float32 squared distances with separate
  IEEE operations, the per-event minimum, the exact rounded distance of
  :func:`~evtrack.flow.registration.rounded_distance`, summed in int64), in parallel over the
  hypotheses.

``FlowConfig.backend`` chooses: ``"auto"`` (default) uses these kernels on CPU when numba is
installed, ``"torch"`` never, ``"compiled"`` always (an error without numba or on CUDA). The
tests check both backends against the same sequential reference.
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

__all__ = ["available", "CompiledSearch", "hypothesis_costs"]

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
def _search_kernel(x, y, t, p, start, seq0, width, height, off_x, off_y, dt_lo, dt_hi, num_x,
                   num_y, history, refractory, tol_abs, permille, last_t, last_p, hist_t,
                   hist_s, hist_n, o_event, o_off, o_aj, o_ai, o_sj, o_si, o_dt, o_flow, n_out):
    """Process events ``start..`` until done or until the output might overflow.

    Returns ``(next event index, rows written)``; the state arrays are updated for every
    processed event only, so a call can resume where the previous one stopped.
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
        prev_t, prev_p = last_t[pix], last_p[pix]
        last_t[pix] = tk
        last_p[pix] = pk
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
            ci = plane + yi * width + xi
            nj, ni = hist_n[cj], hist_n[ci]
            lo, hi = dt_lo[o], dt_hi[o]
            for aj in range(nj):
                tj = hist_t[cj, aj]
                dkj = tk - tj
                if dkj < 1:
                    continue
                for ai in range(ni):
                    ti = hist_t[ci, ai]
                    dji = tj - ti
                    dki = tk - ti
                    if dji < 1 or dki < lo or dki > hi:
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
        m = hist_n[c]
        if m < history:
            hist_n[c] = m + 1
        else:
            m = history - 1
        for a in range(m, 0, -1):
            hist_t[c, a] = hist_t[c, a - 1]
            hist_s[c, a] = hist_s[c, a - 1]
        hist_t[c, 0] = tk
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
        # the candidate flow's numerator 2 d * 1e6 in float32, as the torch search has it
        self._num_x = (np.float32(2.0 * US_PER_S) * self._off_x.astype(np.float32))
        self._num_y = (np.float32(2.0 * US_PER_S) * self._off_y.astype(np.float32))
        self._worst = len(offsets) * config.history * config.history
        self.reset()

    def reset(self) -> None:
        """Forget every event seen."""
        pixels = self.width * self.height
        k = self.config.history
        self.last_t = np.full(pixels, NEVER_US, dtype=np.int64)
        self.last_p = np.zeros(pixels, dtype=np.int64)
        self.hist_t = np.zeros((2 * pixels, k), dtype=np.int64)
        self.hist_s = np.zeros((2 * pixels, k), dtype=np.int64)
        self.hist_n = np.zeros(2 * pixels, dtype=np.int64)
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
                self._off_y, self._lo, self._hi, self._num_x, self._num_y, cfg.history,
                cfg.refractory_us, cfg.tolerance_us * 1000, cfg.tolerance_permille,
                self.last_t, self.last_p, self.hist_t, self.hist_s, self.hist_n, *out, flow, 0)
            parts.append(Candidates(*(torch.from_numpy(a[:rows]) for a in out),
                                    flow=torch.from_numpy(flow[:rows])))
            capacity *= 2
        self.next_seq += n
        return Candidates.cat(parts)


@_njit(parallel=True)
def _costs_kernel(h_cand, h_group, c_x, c_y, c_start, counts, c_event, ev_per_group,
                  cost_scale, q_max):
    n_h = h_cand.shape[0]
    cost = np.zeros(n_h, dtype=np.int64)
    for h in _prange(n_h):
        g = h_group[h]
        hx, hy = c_x[h_cand[h]], c_y[h_cand[h]]
        mins = np.full(ev_per_group[g], np.inf, dtype=np.float32)
        for c in range(c_start[g], c_start[g] + counts[g]):
            dx = hx - c_x[c]
            dy = hy - c_y[c]
            d2 = dx * dx
            d2 = d2 + dy * dy
            e = c_event[c]
            if d2 < mins[e]:
                mins[e] = d2
        total = 0
        for e in range(mins.shape[0]):
            total += _rounded_distance(mins[e], cost_scale, q_max)
        cost[h] = total
    return cost


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


def hypothesis_costs(h_idx: Tensor, h_group: Tensor, c_flow: Tensor, counts: Tensor,
                     c_start: Tensor, c_event: Tensor, ev_per_group: Tensor,
                     cost_scale: float, q_max: int) -> Tensor:
    """The exact int64 Eq. 3 cost of every hypothesis (see
    :func:`evtrack.flow.registration._hypothesis_costs`, which it equals bit for bit).

    Args:
        h_idx: (H,) candidate index of each hypothesis; h_group: (H,) its group.
        c_flow: (M, 2) float32 candidate flows, grouped by group, events contiguous.
        counts, c_start: (G,) candidates per group and the first of each.
        c_event: (M,) index of each candidate's event among its group's kept events.
        ev_per_group: (G,) kept events per group.
        cost_scale: distances are rounded to ``1 / cost_scale`` px/s (a power of two).
        q_max: cap of a rounded distance.
    """
    if numba is None:
        raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
    if h_idx.numel() == 0:
        return torch.zeros(0, dtype=torch.int64)
    flow = c_flow.detach().cpu().numpy().astype(np.float32, copy=False)
    as64 = [np.ascontiguousarray(a.detach().cpu().numpy(), dtype=np.int64)
            for a in (h_idx, h_group, c_start, counts, c_event, ev_per_group)]
    cost = _costs_kernel(as64[0], as64[1], np.ascontiguousarray(flow[:, 0]),
                         np.ascontiguousarray(flow[:, 1]), as64[2], as64[3], as64[4], as64[5],
                         float(cost_scale), float(q_max))
    return torch.from_numpy(cost)
