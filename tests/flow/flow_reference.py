"""A plain, sequential, event-by-event reference of the triplet candidate search.

Written from the rule stated in ``evtrack.flow.config`` with Python loops, dicts and deques
only (no tensors), so that the batched search can be checked against it bit for bit.
"""

from __future__ import annotations

import math
from collections import deque


def reference_offsets(radius: int) -> list[tuple[int, int]]:
    """Offsets on the square rings 1..r, ordered by ring, then dy, then dx."""
    out = []
    for ring in range(1, radius + 1):
        for dy in range(-ring, ring + 1):
            for dx in range(-ring, ring + 1):
                if max(abs(dx), abs(dy)) == ring:
                    out.append((dx, dy))
    return out


def reference_candidates(x, y, t, p, sensor_size, *, radius, history, refractory_us,
                         tolerance_us, tolerance_permille, min_speed, max_speed, max_span_us=0,
                         state=None, search=None):
    """Candidates of every event, sequentially.

    ``search`` (optional, one bool per event): events marked False are not searched, but
    stored like any other.

    Returns ``(rows, state)``; each row is ``(k, offset, age_j, age_i, seq_j, seq_i, dt_ki,
    flow_x, flow_y)`` with ``k`` the stream index of e_k. ``state`` (the per-pixel deques and
    the next stream index) lets a later call continue the same stream.
    """
    width, height = sensor_size
    offsets = reference_offsets(radius)
    if state is None:
        state = {"cells": {}, "last": {}, "next": 0}
    cells = state["cells"]
    last = state["last"]
    rows = []
    wanted = [True] * len(list(t)) if search is None else [bool(s) for s in search]
    for xk, yk, tk, pk, searched in zip(list(x), list(y), list(t), list(p), wanted,
                                        strict=True):
        xk, yk, tk, pk = int(xk), int(yk), int(tk), int(pk)
        k = state["next"]
        state["next"] = k + 1
        c = 0 if pk > 0 else 1
        previous = last.get((yk, xk))  # previous event of the pixel, either polarity
        last[(yk, xk)] = (tk, pk)
        if (refractory_us > 0 and previous is not None and previous[1] == pk
                and tk - previous[0] <= refractory_us):
            continue  # inside the burst of an earlier event: skipped, not stored
        for oi, (dx, dy) in enumerate(offsets if searched else ()):
            xj, yj, xi, yi = xk - dx, yk - dy, xk - 2 * dx, yk - 2 * dy
            if not (0 <= xi < width and 0 <= yi < height):
                continue
            hist_j = list(reversed(cells.get((c, yj, xj), ())))
            hist_i = list(reversed(cells.get((c, yi, xi), ())))
            for aj, (tj, sj) in enumerate(hist_j):
                for ai, (ti, si) in enumerate(hist_i):
                    dkj, dji, dki = tk - tj, tj - ti, tk - ti
                    if dkj < 1 or dji < 1:
                        continue
                    if abs(dkj - dji) * 1000 > tolerance_us * 1000 + tolerance_permille * dki:
                        continue
                    if max_span_us > 0 and dki > max_span_us:
                        continue
                    speed = math.hypot(2 * dx, 2 * dy) * 1e6 / dki
                    if not (min_speed <= speed <= max_speed):
                        continue
                    rows.append((k, oi, aj, ai, sj, si, dki,
                                 2 * dx * 1e6 / dki, 2 * dy * 1e6 / dki))
        cells.setdefault((c, yk, xk), deque(maxlen=history)).append((tk, k))
    return rows, state
