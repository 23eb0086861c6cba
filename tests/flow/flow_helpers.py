"""Helpers shared by the flow tests: random event streams and the reference's rows."""

from __future__ import annotations

import numpy as np
import torch
from flow_reference import reference_candidates


def random_stream(rng: np.random.Generator, n: int, size: tuple[int, int], max_gap: int):
    """(x, y, t, p) int64 tensors of ``n`` random events on a ``size`` sensor, time steps of
    0 to ``max_gap`` µs."""
    t = torch.as_tensor(np.cumsum(rng.integers(0, max_gap + 1, n)))
    x = torch.as_tensor(rng.integers(0, size[0], n))
    y = torch.as_tensor(rng.integers(0, size[1], n))
    p = torch.as_tensor(rng.choice([-1, 1], n))
    return x, y, t, p


def reference_rows(x, y, t, p, cfg, search=None) -> list[tuple]:
    """The sequential reference's candidate rows for a :class:`~evtrack.flow.FlowConfig`
    (``(k, offset, age_j, age_i, seq_j, seq_i, dt_ki, flow_x, flow_y)``)."""
    rows, _ = reference_candidates(
        x.tolist(), y.tolist(), t.tolist(), p.tolist(), cfg.sensor_size, radius=cfg.radius,
        history=cfg.history, refractory_us=cfg.refractory_us, tolerance_us=cfg.tolerance_us,
        tolerance_permille=cfg.tolerance_permille, min_speed=cfg.min_speed,
        max_speed=cfg.max_speed, max_span_us=cfg.max_span_us,
        search=None if search is None else search.tolist())
    return rows
