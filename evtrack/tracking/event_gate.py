"""The event gate: which of a step group's events reach the motion source.

* **Sensor noise** (``TrackerConfig.denoise``, off by default): as each packet is pushed,
  background activity and hot pixels are removed (:class:`~evtrack.denoise.EventDenoiser`),
  before anything else sees the events.
* **Silhouette mask**: events within ``mask_margin_px`` of the object's silhouette swept over
  the group (the silhouette at the group's start and the one predicted at its end).
* **Event bursts**: a step whose events outside the mask exceed ``burst_rate_hz`` per pixel
  over the image outside it, and ``burst_factor`` times the median of that rate over the
  steps of the last ``burst_baseline_ms`` (this one included), is an event burst (flicker, a
  sensor glitch): none of its events is used, and the step's end starts a
  re-synchronisation of the flow's burst filter. A burst is a sudden rise over the stream's
  own background activity: a static camera's background is quiet (the median near the
  sensor's noise, so the absolute rate decides), while a moving camera's textured background
  fires all the time, its median rises with it within half the baseline window, and only a
  rise well above it is a burst (a burst longer than half the window then counts as the
  background). ``burst_baseline_ms: 0`` keeps the absolute test alone. The test needs at least
  ``BURST_MIN_OUTSIDE`` of the image outside the mask.
* **Thinning**: at most ``load.max_events_per_step`` events per step (on average over a group)
  enter the flow. Above it the group's events are thinned by cells of 2 x 2 RoIs (squares of
  ``2 * flow.roi_size`` pixels), deterministically and independently of how the events were
  chunked. The cells are taken in one fixed pseudo-random order (a hash of the cell's index):
  the first ``int(n_cells * 0.75**level)``, all their events kept, the other events counted.
  The level rises as far as the budget needs and falls only when the lower level fits in 80 %
  of the budget, so the kept cells change seldom. A kept cell keeps whole edges' event trails,
  so its triplets and RoI flows are those of the unthinned stream, and its pixels' histories
  stay whole from one group to the next. Thinning single events instead leaves every trail
  with gaps, and the triplet search matches the survivors to unrelated older events: on the
  cracker box (`faster`, 8.6 M events/s) a budget of 4000 events per step gave 34.5 cm / 58°
  by single events, 9.2 cm / 13.8° by cells, against 4.35 cm / 6.5° unthinned.

Sampled search (``load.search_per_roi_window``): of a RoI window with more events than that, the
flow searches only a hash sample of about that many for candidates
(:func:`evtrack.flow.sampled_search`). Every event still enters the search's history,
so a searched event forms the triplets it would form in the whole stream, and the sample is
drawn by the hash that also picks the registration's data term (at most
``flow.max_events_per_roi`` events): a window whose sample still holds that many
candidate-bearing events registers the same flow as unsampled. The candidate search is most of
the flow's cost and grows with the events, while the data term does not. On the densely
textured cracker box `faster` (8.6 M events/s, the default 12 px RoIs, oracle poses) the default
64 left 41 % of the flow's events unsearched and cut the flow's time from 4.6 to 2.9 s of the
2 s sequence, at 3.90 cm / 4.98 deg against 3.88 / 4.86 (32: 66 %, 2.2 s, 4.30 / 5.04). On the
four YCB objects' benchmark set (4 kHz, oracle poses) the full method's RMSE moved by at most
0.11 deg (64); 32 made the ablation rows worse (``faster`` without the normal-flow constraint
6.28 -> 10.12 cm), 64 did not (6.45 cm).

Search budget (``load.max_searched_per_step``): of the events so chosen, at most that many per
velocity step (over a step group) are searched, by whole RoIs visited in a fixed hash order and
taken while they fit (``budget`` of :func:`~evtrack.flow.sampling.sampled_search`). Unlike
thinning (above), the left-out RoIs' events still enter the history: a taken RoI's flow is the
one it would have without the budget however the taken RoIs change from group to group, and
only the left-out RoIs give no flow. It bounds the search and the registration per step
whatever the event rate. On the cracker box `faster` (~5k sampled events per ms) the default
2500 took the flow from ~2.9 s to ~1.8 s of the 2 s sequence, at 3.90 cm / 4.74 deg against
3.90 / 4.98; the other YCB benchmark sequences do not reach it after their first pose.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.denoise import EventDenoiser
from evtrack.events import Events
from evtrack.filters.scalar_lie import rotation_matrix, se3_exp
from evtrack.flow import sampled_search
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.stats import TrackerStats

__all__ = ["EventGate", "moved_pose"]

BURST_MIN_OUTSIDE = 0.1
"""The burst test needs at least this share of the image outside the object's silhouette."""

THIN_CELL_ROIS = 2
"""Event thinning keeps or drops cells of this many RoIs square: a kept RoI then has kept
neighbours on most sides, whose events its border events' triplets need (with cells of one
RoI the kept RoIs' flows were twice as far off on a translating texture)."""

THIN_RATIO = 0.75
"""Each event-thinning level keeps this share of the previous level's RoI cells."""

HASH_MULTIPLIER = np.uint64(0x9E3779B97F4A7C15)
"""Fibonacci hashing of RoI cell indices (thinning keeps the cells of smallest hash first)."""

THIN_HEADROOM = 0.8
"""Event thinning goes back a level (more cells) only when that level's events fit in this
share of the budget (hysteresis: the kept cells change seldom)."""


def moved_pose(T: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """:func:`evtrack.geometry.integrate_twist` for one (4, 4) float64 pose and (6,) twist
    ``[v_o, ω]`` (camera frame) over ``dt`` seconds, on Python floats
    (:func:`evtrack.filters.scalar_lie.se3_exp`): microseconds instead of a millisecond of
    tensor dispatch, for the tracker's per-group and per-query poses."""
    xi = [float(v) * dt for v in twist]
    q, p = se3_exp((xi[0], xi[1], xi[2]), (xi[3], xi[4], xi[5]))
    step = np.eye(4)
    step[:3, :3] = rotation_matrix(q)
    step[:3, 3] = p
    return step @ np.asarray(T, np.float64)


class EventGate:
    """Masks, burst tests and thins a step group's events (see the module docstring).

    Args:
        camera: the event camera.
        silhouette: the object's silhouette in it.
        mask_margin_px: margin around the silhouette (px).
        burst_rate_hz: events per pixel and second outside the mask that make a burst (0: no
            test).
        burst_baseline_us: the window of the background rate's running median (µs; 0: the
            absolute test alone).
        burst_factor: a burst step's rate is also above this times that median.
        roi_size: the flow's RoI size (px); thinning cells are ``THIN_CELL_ROIS`` RoIs square.
        denoiser: removes sensor noise from the pushed events (:meth:`denoised`); ``None``:
            none is removed.

    Attributes:
        stats: the counters it adds to (``events_on_object``, ``burst_steps``,
            ``events_in_bursts``, ``events_thinned``, ``events_unsearched``) or sets
            (``events_denoised``, ``events_on_hot_pixels``, ``hot_pixels``).
        burst_ends: ends (µs) of the bursts found in the last group masked.
        thin_level: thinning keeps ``THIN_RATIO ** thin_level`` of the cells.
    """

    def __init__(self, camera: PinholeCamera, silhouette: Silhouette, mask_margin_px: float,
                 burst_rate_hz: float, roi_size: int,
                 denoiser: EventDenoiser | None = None, *, burst_baseline_us: int = 0,
                 burst_factor: float = 1.0) -> None:
        self.camera = camera
        self.denoiser = denoiser
        self.silhouette = silhouette
        self.mask_margin_px = mask_margin_px
        self.burst_rate_hz = burst_rate_hz
        self.burst_baseline_us = int(burst_baseline_us)
        self.burst_factor = float(burst_factor)
        self.roi_size = roi_size
        self._cell_order: np.ndarray | None = None
        self.stats = TrackerStats()
        self.reset()

    def reset(self) -> None:
        """Forget the thinning level, the bursts and the denoiser's stream."""
        self.thin_level = 0
        self.burst_ends: list[int] = []
        # the outside rates (events/px/s) of the last burst_baseline_us of steps, and their
        # steps' start times (µs)
        self._rate_t = np.zeros(0, np.int64)
        self._rate = np.zeros(0, np.float64)
        if self.denoiser is not None:
            self.denoiser.reset()

    def denoised(self, ev: Events) -> Events:
        """A pushed packet ``ev`` (checked: sorted, inside the sensor, after the previous one)
        without its sensor noise, in its order (itself without a denoiser); counts what went."""
        if self.denoiser is None or not len(ev):
            return ev
        kept = self.denoiser(ev)
        counts, st = self.denoiser.counts, self.stats
        st.events_denoised = counts.removed_noise
        st.events_on_hot_pixels = counts.removed_hot
        st.hot_pixels = counts.hot_pixels_found
        return kept

    def on_object(self, ev: Events, t0: int, t_end: int, step_us: int, pose: np.ndarray,
                  poly: SilhouettePolygon, twist: Callable[[], np.ndarray]) -> Events:
        """The events of the group ``[t0, t_end)`` within the mask swept from ``poly`` (at
        ``pose``) with ``twist()`` (6,), without those of burst steps; counts them."""
        if not len(ev):
            return ev
        mask = self.swept_mask(poly, pose, t_end - t0, twist())
        keep = mask.contains_pixels(ev.x.numpy(), ev.y.numpy(), self.mask_margin_px,
                                    self.camera.size)
        self.stats.events_on_object += int(keep.sum())
        if self.burst_rate_hz > 0:
            keep &= ~self.in_burst(ev.t.numpy(), keep, mask, t0, t_end, step_us)
        return ev[torch.from_numpy(keep)]

    def swept_mask(self, poly: SilhouettePolygon, pose: np.ndarray, span_us: int,
                   twist: np.ndarray) -> SilhouettePolygon:
        """The polygon that masks a step group's events: the convex hull of the silhouette
        at the group's start (``poly`` at ``pose``) and the one predicted ``span_us`` later
        with ``twist`` (6,), so that the object's events stay inside the mask while it
        moves through the group (a group of 40 ms at 1,000 px/s moves it 40 px, more than
        the mask's margin). The start's silhouette alone where the prediction is not finite
        or the object would not be in front of the camera."""
        if not (np.isfinite(twist).all() and np.any(twist)):
            return poly
        end = moved_pose(pose, twist, span_us * 1e-6)
        end_poly = self.silhouette.polygon(end) if np.isfinite(end).all() else None
        return poly if end_poly is None else self.silhouette.hull([poly, end_poly])

    def in_burst(self, t: np.ndarray, on_object: np.ndarray, poly: SilhouettePolygon, t0: int,
                 t_end: int, step_us: int) -> np.ndarray:
        """(N,) bool: the events of the steps of ``[t0, t_end)`` that are event bursts;
        counts them and adds each run of burst steps' end to :attr:`burst_ends`."""
        w, h = self.camera.size
        outside = w * h - min(self._mask_area(poly), w * h)
        none = np.zeros(len(t), bool)
        if outside < BURST_MIN_OUTSIDE * w * h or not len(t):
            return none
        steps = (t_end - t0) // step_us
        # the events are time-sorted: each step's are one slice (the first also takes any
        # before t0, the last any from t_end on), counted without a pass over every event
        cuts = [0, *np.searchsorted(t, t0 + step_us * np.arange(1, steps), side="left").tolist(),
                len(t)]
        off = np.array([(b - a) - np.count_nonzero(on_object[a:b])
                        for a, b in zip(cuts[:-1], cuts[1:], strict=True)], np.float64)
        rate = off / (outside * step_us * 1e-6)
        burst = rate > self.burst_rate_hz
        if self.burst_baseline_us > 0:
            burst = self._above_background(rate, t0 + step_us * np.arange(steps), burst)
        if not burst.any():
            return none
        hit = np.repeat(burst, np.diff(cuts))
        # the end of each run of burst steps starts a re-synchronisation of the flow
        ends = np.flatnonzero(burst & ~np.append(burst[1:], False)) + 1
        self.burst_ends += (t0 + step_us * ends).tolist()
        self.stats.burst_steps += int(burst.sum())
        self.stats.events_in_bursts += int((hit & on_object).sum())
        return hit

    def _above_background(self, rate: np.ndarray, start: np.ndarray, over: np.ndarray
                          ) -> np.ndarray:
        """``over`` (steps above the absolute rate) where the rate is also above
        ``burst_factor`` times the median rate of the steps starting in the last
        ``burst_baseline_us`` (this one included); records the steps' rates."""
        rates = np.concatenate([self._rate, rate])
        times = np.concatenate([self._rate_t, start])
        seen = len(self._rate)
        burst = over.copy()
        for i in np.flatnonzero(over):
            lo = np.searchsorted(times, start[i] - self.burst_baseline_us, side="right")
            burst[i] = rate[i] > self.burst_factor * np.median(rates[lo:seen + i + 1])
        keep = times > start[-1] - self.burst_baseline_us
        self._rate, self._rate_t = rates[keep], times[keep]
        return burst

    def _mask_area(self, poly: SilhouettePolygon) -> float:
        """Area (px²) of the mask in the image: the silhouette grown by the margin (Steiner's
        formula), times its visible fraction."""
        margin = self.mask_margin_px
        v = poly.vertices
        area = 0.5 * abs(float(np.dot(v[:, 0], np.roll(v[:, 1], -1))
                               - np.dot(v[:, 1], np.roll(v[:, 0], -1))))
        perimeter = float(np.linalg.norm(v - np.roll(v, -1, 0), axis=1).sum())
        return poly.visible_fraction * (area + perimeter * margin + np.pi * margin ** 2)

    def thin(self, ev: Events, budget: int) -> Events:
        """At most ``budget`` events of a step group, by cells of RoIs: the first
        ``int(n_cells * THIN_RATIO ** level)`` cells of the fixed hash order, at the thinning
        level of the last group unless the budget forces a higher one or the next lower one
        fits in ``THIN_HEADROOM`` of the budget; the other cells' events are counted.
        ``budget`` 0: no cap (the level goes back to 0, nothing thinned)."""
        if not budget:
            self.thin_level = 0
            return ev
        if len(ev) <= budget and not self.thin_level:
            return ev
        s = THIN_CELL_ROIS * self.roi_size
        cols = -(-self.camera.width // s)
        n_cells = cols * -(-self.camera.height // s)
        order = self._cell_order
        if order is None or len(order) != n_cells:
            with np.errstate(over="ignore"):
                hashed = np.arange(n_cells, dtype=np.uint64) * HASH_MULTIPLIER
            order = self._cell_order = np.argsort(hashed, kind="stable")
        cell = (ev.y.numpy().astype(np.int64) // s) * cols + ev.x.numpy().astype(np.int64) // s
        kept = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=n_cells)[order])])

        def taken_at(level: int) -> int:
            return int(n_cells * THIN_RATIO ** level)

        def events_at(level: int) -> int:
            return int(kept[taken_at(level)])

        level = self.thin_level
        while level and events_at(level - 1) <= THIN_HEADROOM * budget:
            level -= 1
        while events_at(level) > budget:  # ends: no cell at all at the last level
            level += 1
        self.thin_level = level
        if level == 0:
            return ev
        taken = np.zeros(n_cells, bool)
        taken[order[:taken_at(level)]] = True
        keep = taken[cell]
        self.stats.events_thinned += int(len(ev) - keep.sum())
        return ev[torch.from_numpy(keep)]

    def search_sample(self, ev: Events, events_seen: Tensor, per_window: int,
                      budget: int, window_us: int) -> Tensor | None:
        """(N,) bool: the events of ``ev`` to search for candidates (``None``: all), a hash
        sample of at most ``per_window`` per RoI window (0: all) within ``budget`` per group
        (0: none); counts the others."""
        if not ((per_window or budget) and len(ev)):
            return None
        search = sampled_search(ev.x, ev.y, ev.t, events_seen, roi_size=self.roi_size,
                                window_us=window_us, sensor_width=self.camera.width,
                                per_window=per_window, budget=budget)
        self.stats.events_unsearched += int(len(search) - np.count_nonzero(search.numpy()))
        return search
