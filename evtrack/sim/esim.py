"""Event-camera model on log intensity, batched over pixels in torch (CPU or CUDA).

Model (per pixel):
    * The simulator works on ``L = log(luminance + eps)`` sampled at render times. Between two
      renders ``L`` is taken to vary linearly in time.
    * Each pixel keeps a reference level ``ref``. Whenever ``L - ref`` reaches ``+C_on`` an ON
      event is emitted and ``ref += C_on``; at ``-C_off`` an OFF event and ``ref -= C_off``.
      A large change gives several events in one interval, at the times (linear interpolation)
      where each level is crossed.
    * ``C_on``/``C_off`` differ per pixel: ``C · (1 + σ·N(0, 1))`` (seeded, clipped below).
    * Refractory period: a crossing less than ``refractory_us`` after the pixel's previous
      event is not reported; the reference still moves past it (like a DVS pixel, whose reset
      after the refractory period discards the change seen meanwhile).
    * Leak noise (optional): ``ref`` drifts down at ``leak_hz · C_on`` per second (per-pixel
      rate with mismatch), so a static pixel emits ON events at about ``leak_hz``. With leak,
      the initial reference is lowered by a random fraction of ``C_on`` so pixels are not in
      phase.
    * Shot noise (optional): independent ON/OFF events, Poisson with ``shot_hz`` per pixel,
      uniform in time; they do not change ``ref`` or the refractory state.

Output order: events of one render interval are sorted by timestamp, ties broken by pixel
index ``y · W + x``, then by crossing order within a pixel, and model events before shot
noise; intervals follow each other, so the whole stream is non-decreasing in time.
Timestamps are ``round(t_prev + f · (t_cur - t_prev))`` µs with ``f`` the crossing fraction.

The same seed gives the same events on the same device (CPU and CUDA draw different random
numbers, so threshold mismatch and noise differ between devices).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.events import Events
from evtrack.sim.config import EventConfig
from evtrack.sim.frames import LUMA_WEIGHTS

__all__ = ["EventSimulator", "log_intensity", "simulate_reference"]


def log_intensity(rgb: Tensor, eps: float) -> Tensor:
    """(..., 3) linear RGB -> (...) ``log(luminance + eps)`` (Rec. 709 luminance)."""
    w = torch.tensor(LUMA_WEIGHTS, dtype=rgb.dtype, device=rgb.device)
    return torch.log(rgb @ w + eps)


class EventSimulator:
    """Turn a stream of log-intensity frames into events (see the module docstring).

    Args:
        width, height: sensor size in pixels.
        config: thresholds, refractory period, noise, device.
        seed: seeds threshold mismatch, leak rates and noise.
        device: overrides ``config.device``.

    Example:
        >>> sim = EventSimulator(4, 3, EventConfig(threshold_mismatch=0.0, refractory_us=0))
        >>> sim.reset(torch.zeros(3, 4), 0)
        >>> ev = sim.step(torch.full((3, 4), 0.45), 1000)   # +2.25 thresholds
        >>> len(ev), ev.t[:2].tolist()
        (24, [444, 444])
    """

    def __init__(self, width: int, height: int, config: EventConfig | None = None,
                 seed: int = 0, device: str | torch.device | None = None) -> None:
        self.config = cfg = config or EventConfig()
        self.width, self.height = int(width), int(height)
        self.device = torch.device(device if device is not None else cfg.device)
        self.dtype = torch.float64
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(int(seed))
        n = self.width * self.height
        self.c_on = self._mismatch(cfg.threshold_on, cfg.threshold_mismatch, n).clamp(
            min=cfg.min_threshold)
        self.c_off = self._mismatch(cfg.threshold_off, cfg.threshold_mismatch, n).clamp(
            min=cfg.min_threshold)
        self.leak_rate = None
        if cfg.leak_noise_hz > 0:
            self.leak_rate = self._mismatch(cfg.leak_noise_hz, cfg.leak_mismatch, n).clamp(min=0)
        self.ref: Tensor | None = None
        self.prev: Tensor | None = None
        self.t_prev: int | None = None
        self.last_event = torch.full((n,), -np.inf, dtype=self.dtype, device=self.device)
        self._coord_dtype = torch.int16 if max(self.width, self.height) < 2 ** 15 else torch.int32

    def _mismatch(self, nominal: float, sigma: float, n: int) -> Tensor:
        noise = torch.randn(n, generator=self.generator, device=self.device, dtype=self.dtype)
        return nominal * (1.0 + sigma * noise)

    def _flat(self, frame: Tensor) -> Tensor:
        if tuple(frame.shape) != (self.height, self.width):
            raise ValueError(f"frame must be ({self.height}, {self.width}), got "
                             f"{tuple(frame.shape)}")
        return frame.to(device=self.device, dtype=self.dtype).reshape(-1)

    def reset(self, log_frame: Tensor, t_us: int) -> None:
        """Start at ``t_us`` with reference levels equal to ``log_frame`` (H, W)."""
        cur = self._flat(log_frame)
        self.ref = cur.clone()
        if self.leak_rate is not None:
            u = torch.rand(cur.shape, generator=self.generator, device=self.device,
                           dtype=self.dtype)
            self.ref -= u * self.c_on
        self.prev = cur
        self.t_prev = int(t_us)
        self.last_event.fill_(-np.inf)

    def step(self, log_frame: Tensor, t_us: int) -> Events:
        """Advance to the frame ``log_frame`` (H, W) at ``t_us``; events in ``(t_prev, t_us]``.

        Returns:
            :class:`~evtrack.Events` on the simulator's device, sorted (see module docstring).
        """
        if self.ref is None:
            raise RuntimeError("EventSimulator.step before reset")
        t_us = int(t_us)
        if t_us <= self.t_prev:
            raise ValueError(f"frame time {t_us} µs is not after the previous {self.t_prev} µs")
        cfg = self.config
        cur = self._flat(log_frame)
        dt_us = t_us - self.t_prev
        ref_end = self.ref
        if self.leak_rate is not None:
            ref_end = self.ref - self.leak_rate * self.c_on * (dt_us * 1e-6)
        d1 = cur - ref_end
        # only pixels beyond a threshold emit: work on those alone
        idx = torch.nonzero((d1 >= self.c_on) | (d1 <= -self.c_off)).squeeze(1)
        d1_i = d1[idx]
        c_on_i, c_off_i = self.c_on[idx], self.c_off[idx]
        n_on = torch.floor(d1_i / c_on_i).clamp(min=0)
        n_off = torch.floor(-d1_i / c_off_i).clamp(min=0)
        d0_i = self.prev[idx] - self.ref[idx]
        events = self._crossings(idx, d0_i, d1_i, n_on, n_off, c_on_i, c_off_i, dt_us,
                                 cfg.refractory_us)
        if self.leak_rate is not None:
            self.ref = ref_end
        self.ref[idx] = ref_end[idx] + n_on * c_on_i - n_off * c_off_i
        if cfg.shot_noise_hz > 0:
            events = self._merge(events, self._shot_noise(dt_us))
        pix, t_rel, pol = self._sorted(*events)
        self.prev = cur
        t = t_rel + self.t_prev
        self.t_prev = t_us
        return Events((pix % self.width).to(self._coord_dtype),
                      (pix // self.width).to(self._coord_dtype), t, pol.to(torch.int8),
                      (self.width, self.height))

    def _crossings(self, idx, a, b, n_on, n_off, c_on, c_off, dt_us: int, refractory: float):
        """Threshold crossings of the pixels ``idx`` with the refractory rule, in closed form.

        ``a``/``b`` are ``L - ref`` at the interval's start and end. Within one interval the
        crossings of a pixel are evenly spaced in time (``Δ``), so the accepted ones are
        ``i0, i0 + m, i0 + 2m, ...`` with ``i0`` the first crossing at least ``refractory``
        after the last event and ``m = ceil(refractory / Δ)``.
        """
        if idx.numel() == 0:
            empty = torch.zeros(0, dtype=torch.int64, device=self.device)
            return empty, empty.clone(), empty.to(torch.int8)
        n = n_on + n_off
        on = n_on > 0
        c = torch.where(on, c_on, c_off)
        sign = torch.where(on, 1.0, -1.0).to(self.dtype)
        dd = b - a
        safe = torch.where(dd == 0, torch.ones_like(dd), dd)
        f1 = torch.where(dd == 0, torch.ones_like(dd), (sign * c - a) / safe)
        step = torch.where(dd == 0, torch.zeros_like(dd), c / safe.abs())
        tau1 = f1 * dt_us  # µs after t_prev
        delta = step * dt_us
        last = self.last_event[idx] - self.t_prev
        if refractory > 0:
            wait = torch.where(delta > 0, (last + refractory - tau1) / delta.clamp(min=1e-300),
                               torch.where(last + refractory > tau1, np.inf, 0.0))
            i0 = 1 + torch.ceil(wait).clamp(min=0, max=float(2 ** 62))
            m = torch.where(delta > 0, torch.ceil(refractory / delta.clamp(min=1e-300)),
                            torch.full_like(delta, np.inf)).clamp(min=1, max=float(2 ** 62))
        else:
            i0 = torch.ones_like(n)
            m = torch.ones_like(n)
        k = torch.where(i0 > n, torch.zeros_like(n), 1 + torch.floor((n - i0) / m))
        k = k.to(torch.int64)
        has = k > 0
        last_i = i0 + (k - 1).to(self.dtype) * m
        self.last_event[idx[has]] = self.t_prev + (tau1 + (last_i - 1) * delta)[has]
        group = torch.repeat_interleave(torch.arange(idx.numel(), device=self.device), k)
        if group.numel() == 0:
            empty = torch.zeros(0, dtype=torch.int64, device=self.device)
            return empty, empty.clone(), empty.to(torch.int8)
        starts = torch.cumsum(k, 0) - k
        j = torch.arange(group.numel(), device=self.device) - starts[group]
        i = i0[group] + j.to(self.dtype) * m[group]
        tau = (tau1[group] + (i - 1) * delta[group]).clamp(0.0, float(dt_us))
        t_rel = torch.round(tau).to(torch.int64)
        pol = torch.where(on[group], 1, -1).to(torch.int8)
        return idx[group], t_rel, pol

    def _shot_noise(self, dt_us: int):
        n_pix = self.width * self.height
        lam = torch.tensor([self.config.shot_noise_hz * n_pix * dt_us * 1e-6],
                           dtype=torch.float64, device=self.device)
        count = int(torch.poisson(lam, generator=self.generator).item())
        g = self.generator
        pix = torch.randint(0, n_pix, (count,), generator=g, device=self.device)
        t_rel = torch.randint(1, dt_us + 1, (count,), generator=g, device=self.device)
        pol = (torch.randint(0, 2, (count,), generator=g, device=self.device) * 2 - 1).to(
            torch.int8)
        return pix, t_rel, pol

    @staticmethod
    def _merge(a, b):
        return tuple(torch.cat([x, y]) for x, y in zip(a, b, strict=True))

    def _sorted(self, pix: Tensor, t_rel: Tensor, pol: Tensor):
        if pix.numel() == 0:
            return pix, t_rel, pol
        key = t_rel * (self.width * self.height) + pix
        order = torch.sort(key, stable=True).indices
        return pix[order], t_rel[order], pol[order]


def simulate_reference(
    log_frames: np.ndarray,
    times_us: np.ndarray,
    c_on: np.ndarray,
    c_off: np.ndarray,
    refractory_us: float = 0.0,
) -> dict[str, np.ndarray]:
    """A plain per-pixel, per-crossing loop of the same model (no noise), for checking.

    Args:
        log_frames: (K, H, W) log intensities.
        times_us: (K,) int increasing render times.
        c_on, c_off: (H, W) thresholds.
        refractory_us: refractory period in µs.

    Returns:
        dict of ``x, y, t, p`` arrays sorted like :class:`EventSimulator`'s output.
    """
    k_frames, h, w = log_frames.shape
    rows = []
    for y in range(h):
        for x in range(w):
            ref = float(log_frames[0, y, x])
            last = -np.inf
            con, coff = float(c_on[y, x]), float(c_off[y, x])
            for k in range(1, k_frames):
                t0, t1 = int(times_us[k - 1]), int(times_us[k])
                a = float(log_frames[k - 1, y, x]) - ref
                b = float(log_frames[k, y, x]) - ref
                level, crossing = 0.0, 0
                while True:
                    if b - level >= con:
                        level += con
                        pol = 1
                    elif level - b >= coff:
                        level -= coff
                        pol = -1
                    else:
                        break
                    crossing += 1
                    frac = (level - a) / (b - a) if b != a else 1.0
                    tau = min(max(frac, 0.0), 1.0) * (t1 - t0)
                    if t0 + tau - last >= refractory_us:
                        last = t0 + tau
                        rows.append((k, int(round(tau)) + t0, y * w + x, crossing, pol))
                ref += level
    if not rows:
        z = np.zeros(0, np.int64)
        return {"x": z, "y": z, "t": z, "p": z.astype(np.int8)}
    arr = np.array(rows, np.int64)
    order = np.lexsort((arr[:, 3], arr[:, 2], arr[:, 1], arr[:, 0]))
    arr = arr[order]
    return {"x": arr[:, 2] % w, "y": arr[:, 2] // w, "t": arr[:, 1], "p": arr[:, 4].astype(np.int8)}
