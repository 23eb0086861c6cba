"""Which object each event belongs to, when one stream shows several tracked objects.

Each object has a predicted silhouette (a convex polygon, grown by a margin) and a depth (its
origin's camera ``z``). An event inside one object's polygon is that object's; inside several,
the nearest object's (it occludes the others there); inside none, nobody's. The rule is
applied per pixel, so it is the same however the events are split into packets.

The nearer object also keeps the pixels in its margin that lie inside a farther object's
silhouette: its edge events land there whenever its prediction is a few pixels off. Giving
such pixels to the farther object instead (the nearest object whose silhouette itself holds
the pixel) gave the occluded object twice its own events in a simulated crossing (a can
passing in front of a turning box, 160x120, oracle poses), but ten times as many of the
can's (6.0k against 0.6k): 86 % of the assigned events went to their object, against 94 %
with this rule.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from evtrack.tracking.silhouette import SilhouettePolygon

__all__ = ["NO_OBJECT", "ObjectMask", "assign_events", "assign_events_reference"]

NO_OBJECT = -1
"""The owner index of an event on no object."""


@dataclass(frozen=True)
class ObjectMask:
    """Where one object is predicted to be.

    Attributes:
        polygon: its silhouette (swept over the window), or ``None`` when it has no pose (the
            object then owns no event).
        depth: camera ``z`` of its origin, metres; the smaller owns an overlap.
    """

    polygon: SilhouettePolygon | None
    depth: float


def assign_events(x: np.ndarray, y: np.ndarray, masks: Sequence[ObjectMask], margin: float,
                  size: tuple[int, int]) -> np.ndarray:
    """The owner of each event: the nearest object whose silhouette, grown by ``margin``,
    contains the event's pixel.

    Args:
        x, y: (N,) integer pixel coordinates of the events.
        masks: one per object (index = owner).
        margin: pixels added around every silhouette.
        size: the image's ``(W, H)``.

    Returns:
        (N,) int64 object index, :data:`NO_OBJECT` where no silhouette contains the pixel.
        Equal depths go to the lower index.
    """
    x = np.asarray(x)
    y = np.asarray(y)
    owner = np.full(len(x), NO_OBJECT, np.int64)
    order = sorted(range(len(masks)), key=lambda k: (masks[k].depth, k))
    for k in order:  # nearest first: a pixel keeps the first object that claims it
        mask = masks[k]
        if mask.polygon is None or not np.isfinite(mask.depth):
            continue
        free = owner == NO_OBJECT
        if not free.any():
            break
        idx = np.flatnonzero(free)
        inside = mask.polygon.contains_pixels(x[idx], y[idx], margin, size)
        owner[idx[inside]] = k
    return owner


def assign_events_reference(x: np.ndarray, y: np.ndarray, masks: Sequence[ObjectMask],
                            margin: float) -> np.ndarray:
    """:func:`assign_events` one event at a time, each object's silhouette tested by its
    distance to the polygon (a plain reference for the tests)."""
    owner = np.full(len(x), NO_OBJECT, np.int64)
    for i in range(len(x)):
        best, best_depth = NO_OBJECT, np.inf
        for k, mask in enumerate(masks):
            if mask.polygon is None or not np.isfinite(mask.depth):
                continue
            if _distance_to_convex(mask.polygon.vertices, float(x[i]), float(y[i])) > margin:
                continue
            if mask.depth < best_depth:
                best, best_depth = k, mask.depth
        owner[i] = best
    return owner


def _distance_to_convex(poly: np.ndarray, px: float, py: float) -> float:
    """Largest signed distance of ``(px, py)`` outside a convex polygon's edge lines (the
    tracker's mask test: <= margin means within the grown polygon)."""
    n = len(poly)
    if n < 3:
        lo, hi = poly.min(0), poly.max(0)
        return max(lo[0] - px, px - hi[0], lo[1] - py, py - hi[1])
    area2 = sum(poly[i, 0] * poly[(i + 1) % n, 1] - poly[(i + 1) % n, 0] * poly[i, 1]
                for i in range(n))
    sign = 1.0 if area2 > 0 else -1.0
    worst = -np.inf
    for i in range(n):
        ax, ay = poly[i]
        bx, by = poly[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        length = (ex * ex + ey * ey) ** 0.5
        if length == 0:
            continue
        nx, ny = sign * ey / length, -sign * ex / length
        worst = max(worst, nx * (px - ax) + ny * (py - ay))
    return worst
