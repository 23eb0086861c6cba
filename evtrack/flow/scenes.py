"""Synthetic event streams with known optical flow, for tests and benchmarks.

An ideal event camera watches a log-intensity pattern ``L(x, y, t)``: each pixel (at integer
coordinates) emits an event whenever ``L`` moves ``contrast`` away from the level of its last
event, with the crossing time interpolated linearly between simulation steps (as ESIM does).

Two patterns translate rigidly at a constant velocity, so the true flow of every signal event
is that velocity:

* :func:`translating_texture`: a 2-D texture (sum of random plane waves) — the full flow is
  observable.
* :func:`moving_stripes`: a 1-D texture (plane waves along one normal) — only the normal flow
  is observable (the aperture problem); the true flow is the stripes' normal velocity.

Both return the events and an (N, 2) float32 ground-truth flow in px/s (NaN for noise events).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from evtrack.events import Events
from evtrack.flow.constants import US_PER_S

__all__ = ["render_events", "translating_texture", "moving_stripes", "texture_waves"]

LogIntensity = Callable[[Tensor, Tensor, float], Tensor]
"""``f(x, y, t_s) -> log intensity`` on pixel grids (float64 tensors)."""

MAX_STEP_PX = 0.05
"""Largest motion (px) of the pattern between two simulation steps."""


def render_events(log_intensity: LogIntensity, sensor_size: tuple[int, int],
                  duration_us: int, speed_px_s: float, contrast: float = 0.2,
                  noise_rate_hz: float = 0.0, t0_us: int = 0, seed: int = 0
                  ) -> tuple[Events, Tensor]:
    """Simulate an ideal event camera over ``[t0_us, t0_us + duration_us)``.

    Args:
        log_intensity: the pattern, evaluated on the pixel grid at a time in seconds
            (relative to ``t0_us``).
        sensor_size: ``(width, height)`` in pixels.
        duration_us: simulated time in µs.
        speed_px_s: the largest image speed of the pattern (sets the simulation step so that
            it moves at most ``MAX_STEP_PX`` per step).
        contrast: log-intensity change per event.
        noise_rate_hz: mean rate of uniformly random noise events per pixel (Hz).
        t0_us: timestamp of the start.
        seed: seed of the noise events (the signal is deterministic).

    Returns:
        ``(events, is_signal)``: time-sorted events (ties in pixel order) and an (N,) bool
        tensor, False for noise events.
    """
    width, height = sensor_size
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64),
                            torch.arange(width, dtype=torch.float64), indexing="ij")
    step_us = max(1.0, min(1000.0, MAX_STEP_PX / max(speed_px_s, 1e-9) * US_PER_S))
    n_steps = int(math.ceil(duration_us / step_us))
    level = log_intensity(xs, ys, 0.0)
    previous = level.clone()
    out_t: list[Tensor] = []
    out_pix: list[Tensor] = []
    out_pol: list[Tensor] = []
    for n in range(1, n_steps + 1):
        t_prev = (n - 1) * step_us
        t_cur = min(n * step_us, float(duration_us))
        current = log_intensity(xs, ys, t_cur / US_PER_S)
        delta = current - level
        count = torch.floor(delta.abs() / contrast).to(torch.int64)
        active = count > 0
        if active.any():
            idx = torch.nonzero(active.reshape(-1)).reshape(-1)
            cnt = count.reshape(-1)[idx]
            sign = torch.sign(delta.reshape(-1)[idx])
            lv = level.reshape(-1)[idx]
            lp = previous.reshape(-1)[idx]
            lc = current.reshape(-1)[idx]
            reps = torch.repeat_interleave(torch.arange(idx.numel()), cnt)
            m = torch.arange(reps.numel()) - torch.repeat_interleave(
                torch.cumsum(cnt, 0) - cnt, cnt) + 1
            cross = lv[reps] + sign[reps] * m * contrast
            frac = ((cross - lp[reps]) / (lc[reps] - lp[reps])).clamp(0.0, 1.0)
            out_t.append(t_prev + frac * (t_cur - t_prev))
            out_pix.append(idx[reps])
            out_pol.append(sign[reps].to(torch.int8))
            flat = level.reshape(-1)
            flat[idx] = lv + sign * cnt * contrast
        previous = current
    t = torch.cat(out_t) if out_t else torch.zeros(0, dtype=torch.float64)
    pix = torch.cat(out_pix) if out_pix else torch.zeros(0, dtype=torch.int64)
    pol = torch.cat(out_pol) if out_pol else torch.zeros(0, dtype=torch.int8)
    t_int = torch.floor(t).to(torch.int64) + int(t0_us)
    signal = torch.ones(t_int.numel(), dtype=torch.bool)
    if noise_rate_hz > 0:
        rng = np.random.default_rng(seed)
        n_noise = rng.poisson(noise_rate_hz * width * height * duration_us / US_PER_S)
        t_int = torch.cat([t_int, torch.as_tensor(
            rng.integers(t0_us, t0_us + duration_us, n_noise), dtype=torch.int64)])
        pix = torch.cat([pix, torch.as_tensor(rng.integers(0, width * height, n_noise),
                                              dtype=torch.int64)])
        pol = torch.cat([pol, torch.as_tensor(rng.choice([-1, 1], n_noise), dtype=torch.int8)])
        signal = torch.cat([signal, torch.zeros(n_noise, dtype=torch.bool)])
    order = np.lexsort((pix.numpy(), t_int.numpy()))
    order_t = torch.as_tensor(order)
    pix = pix[order_t]
    ev = Events(x=(pix % width).to(torch.int32), y=(pix // width).to(torch.int32),
                t=t_int[order_t], p=pol[order_t], sensor_size=(width, height))
    return ev, signal[order_t]


def texture_waves(n_waves: int, wavelength_px: tuple[float, float], seed: int,
                  angles: np.ndarray | None = None) -> np.ndarray:
    """Random plane waves ``(kx, ky, phase, amplitude)`` (rad/px, rad, -) of a texture.

    Args:
        n_waves: number of waves.
        wavelength_px: (shortest, longest) wavelength in pixels.
        seed: random seed.
        angles: optional fixed wave-vector angles (rad), e.g. one angle for stripes.
    """
    rng = np.random.default_rng(seed)
    lam = rng.uniform(*wavelength_px, n_waves)
    ang = rng.uniform(0, math.pi, n_waves) if angles is None else np.resize(angles, n_waves)
    k = 2 * math.pi / lam
    phase = rng.uniform(0, 2 * math.pi, n_waves)
    amp = rng.uniform(0.5, 1.0, n_waves)
    amp *= 0.4 / amp.sum()
    return np.stack([k * np.cos(ang), k * np.sin(ang), phase, amp], axis=1)


def _moving_pattern(waves: np.ndarray, velocity: tuple[float, float],
                    sharpness: float) -> LogIntensity:
    """``log(0.5 + 0.4 tanh(sharpness * f))`` with ``f`` the normalised wave sum, translating.

    Large ``sharpness`` turns the smooth random field into patches with sharp edges (edge
    width about ``1 / (sharpness * |grad f|)`` px), the kind of texture an event camera sees.
    """
    w = torch.as_tensor(waves, dtype=torch.float64)
    vx, vy = (float(v) for v in velocity)
    norm = float(np.sqrt(0.5 * np.sum(waves[:, 3] ** 2)))

    def log_intensity(x: Tensor, y: Tensor, t_s: float) -> Tensor:
        u = x - vx * t_s
        v = y - vy * t_s
        field = torch.zeros_like(x)
        for kx, ky, ph, a in w.tolist():
            field += a * torch.sin(kx * u + ky * v + ph)
        return torch.log(0.5 + 0.4 * torch.tanh(sharpness * field / norm))

    return log_intensity


def translating_texture(sensor_size: tuple[int, int] = (96, 72),
                        velocity: tuple[float, float] = (800.0, 300.0),
                        duration_us: int = 100_000, contrast: float = 0.15,
                        wavelength_px: tuple[float, float] = (12.0, 40.0), n_waves: int = 12,
                        sharpness: float = 3.0, noise_rate_hz: float = 0.0, t0_us: int = 0,
                        seed: int = 0) -> tuple[Events, Tensor]:
    """A 2-D random texture (patches with sharp edges) translating at ``velocity`` (px/s).

    Returns:
        ``(events, flow)``: events and their (N, 2) float32 true flow in px/s (NaN for noise).
    """
    waves = texture_waves(n_waves, wavelength_px, seed)
    speed = math.hypot(*velocity)
    ev, signal = render_events(_moving_pattern(waves, velocity, sharpness), sensor_size,
                               duration_us, speed, contrast, noise_rate_hz, t0_us, seed + 1)
    return ev, _flow_of(signal, velocity)


def moving_stripes(sensor_size: tuple[int, int] = (96, 72), normal_angle: float = 0.3,
                   speed: float = 600.0, duration_us: int = 100_000, contrast: float = 0.15,
                   wavelength_px: tuple[float, float] = (12.0, 40.0), n_waves: int = 4,
                   sharpness: float = 3.0, noise_rate_hz: float = 0.0, t0_us: int = 0,
                   seed: int = 0) -> tuple[Events, Tensor]:
    """Stripes (a 1-D texture) moving at ``speed`` px/s along their normal.

    Args:
        normal_angle: direction of the stripes' normal, radians from the +x axis.

    Returns:
        ``(events, flow)``: the true (= normal) flow ``speed * n`` of every signal event.
    """
    waves = texture_waves(n_waves, wavelength_px, seed, angles=np.array([normal_angle]))
    velocity = (speed * math.cos(normal_angle), speed * math.sin(normal_angle))
    ev, signal = render_events(_moving_pattern(waves, velocity, sharpness), sensor_size,
                               duration_us, speed, contrast, noise_rate_hz, t0_us, seed + 1)
    return ev, _flow_of(signal, velocity)


def _flow_of(signal: Tensor, velocity: tuple[float, float]) -> Tensor:
    flow = torch.full((signal.numel(), 2), float("nan"), dtype=torch.float32)
    flow[signal] = torch.tensor(velocity, dtype=torch.float32)
    return flow
