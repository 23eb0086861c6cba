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

__all__ = ["NO_OBJECT", "ObjectMask", "assign_events", "event_claims", "owners"]

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


def event_claims(x: np.ndarray, y: np.ndarray, masks: Sequence[ObjectMask], margin: float,
                 size: tuple[int, int]) -> np.ndarray:
    """Which objects' silhouettes, grown by ``margin``, contain each event's pixel.

    Args:
        x, y: (N,) integer pixel coordinates of the events.
        masks: one per object.
        margin: pixels added around every silhouette.
        size: the image's ``(W, H)``.

    Returns:
        (K, N) bool, row ``k`` for ``masks[k]`` (all False for a mask without a polygon or
        depth).
    """
    x = np.asarray(x)
    y = np.asarray(y)
    claims = np.zeros((len(masks), len(x)), bool)
    for k, mask in enumerate(masks):
        if mask.polygon is not None and np.isfinite(mask.depth) and len(x):
            claims[k] = mask.polygon.contains_pixels(x, y, margin, size)
    return claims


def owners(claims: np.ndarray, masks: Sequence[ObjectMask]) -> np.ndarray:
    """The owner of each event among the objects that claim it (:func:`event_claims`): the
    nearest; equal depths go to the lower index.

    Returns:
        (N,) int64 object index, :data:`NO_OBJECT` where no object claims the event.
    """
    if not len(masks):
        return np.full(claims.shape[1], NO_OBJECT, np.int64)
    order = np.asarray(sorted(range(len(masks)), key=lambda k: (masks[k].depth, k)))
    owner = order[np.argmax(claims[order], axis=0)]
    return np.where(claims.any(axis=0), owner, NO_OBJECT).astype(np.int64)


def assign_events(x: np.ndarray, y: np.ndarray, masks: Sequence[ObjectMask], margin: float,
                  size: tuple[int, int]) -> np.ndarray:
    """The owner of each event: the nearest object whose silhouette, grown by ``margin``,
    contains the event's pixel (:func:`owners` of :func:`event_claims`).

    Returns:
        (N,) int64 object index, :data:`NO_OBJECT` where no silhouette contains the pixel.
        Equal depths go to the lower index.
    """
    return owners(event_claims(x, y, masks, margin, size), masks)
