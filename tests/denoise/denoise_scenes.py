"""A synthetic event stream with known sensor noise, for the denoiser's tests: a bar's two
edges sweeping to and fro across a small sensor (signal), uniform background activity and one
hot pixel, each event labelled."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evtrack.events import Events

SIZE = (64, 48)
HOT_PIXEL = (20, 30)  # (x, y)
T0_US = 1_000_000  # the stream starts here (dv's filters remember every pixel at t = 0)


@dataclass
class Scene:
    events: Events
    kind: np.ndarray  # (N,) 0 signal, 1 background activity, 2 hot pixel


def noisy_stream(seed: int = 0, duration_s: float = 0.5, speed_px_s: float = 640.0,
                 noise_hz: float = 5.0, hot_hz: float = 2000.0) -> Scene:
    """``duration_s`` of the scene: edges at ``speed_px_s``, background activity at
    ``noise_hz`` per pixel, the hot pixel at ``hot_hz``; time-sorted (stable: equal times keep
    signal, noise, hot order)."""
    rng = np.random.default_rng(seed)
    w, h = SIZE
    parts = []
    sweep_us = w / speed_px_s * 1e6
    n_sweeps = int(duration_s * 1e6 // sweep_us)
    for s in range(n_sweeps):
        cols = np.arange(w) if s % 2 == 0 else np.arange(w)[::-1]
        for polarity, lag_px in ((1, 0.0), (-1, 6.0)):
            t_col = T0_US + s * sweep_us + (np.arange(w) + lag_px) / speed_px_s * 1e6
            xs, ys = np.meshgrid(cols, np.arange(h), indexing="ij")
            t = np.repeat(t_col, h) + rng.normal(0.0, 60.0, w * h)
            keep = t < T0_US + (s + 1) * sweep_us
            parts.append((t[keep], xs.ravel()[keep], ys.ravel()[keep],
                          np.full(int(keep.sum()), polarity * (1 - 2 * (s % 2))),
                          np.full(int(keep.sum()), 0)))
    n_noise = rng.poisson(noise_hz * duration_s * w * h)
    parts.append((T0_US + rng.uniform(0, duration_s * 1e6, n_noise), rng.integers(0, w, n_noise),
                  rng.integers(0, h, n_noise), rng.choice([-1, 1], n_noise),
                  np.full(n_noise, 1)))
    n_hot = int(hot_hz * duration_s)
    parts.append((T0_US + np.sort(rng.uniform(0, duration_s * 1e6, n_hot)),
                  np.full(n_hot, HOT_PIXEL[0]), np.full(n_hot, HOT_PIXEL[1]),
                  np.ones(n_hot, int), np.full(n_hot, 2)))
    t, x, y, p, kind = (np.concatenate(c) for c in zip(*parts, strict=True))
    t = np.round(t).astype(np.int64)
    order = np.argsort(t, kind="stable")
    ev = Events(x[order].astype(np.int16), y[order].astype(np.int16), t[order],
                p[order].astype(np.int8), SIZE)
    return Scene(ev, kind[order])


def kinds_kept(scene: Scene, out: Events) -> np.ndarray:
    """Which of ``scene``'s events are in ``out`` (a subsequence of them, in order), (N,) bool:
    matched in one pass over both."""
    def rows(ev: Events) -> list[tuple[int, ...]]:
        return list(zip(*(getattr(ev, k).tolist() for k in ("t", "x", "y", "p")), strict=True))

    src, dst = rows(scene.events), rows(out)
    kept = np.zeros(len(src), bool)
    j = 0
    for i, row in enumerate(src):
        if j < len(dst) and row == dst[j]:
            kept[i] = True
            j += 1
    assert j == len(dst), "the output is not a subsequence of the input, in order"
    return kept
