"""Sensor noise removal from event streams: background activity and hot pixels.

Real event cameras emit events that no change of brightness caused:

* **background activity**: isolated events at a low rate on every pixel (0.1 to a few Hz, more
  in the dark and when warm). An event with no recent event of its neighbourhood is likely such
  noise. ``DenoiseConfig.method`` picks one of the spatio-temporal filters of iniVation's
  `dv-processing <https://dv-processing.inivation.com>`_ (``dv.noise``), each streaming, its
  memory kept from one call to the next:

  - ``background_activity`` (``BackgroundActivityNoiseFilter``): an event is kept when one of
    its 8 neighbours had an event within ``window_us``;
  - ``knoise`` (``KNoiseFilter``, Khodamoradi's filter): a neighbourhood test on one
    timestamp per row and per column (less memory; on the real samples measured it removed
    far more than ``background_activity``);
  - ``fast_decay`` (``FastDecayNoiseFilter``): an event is kept when the decaying event count
    (half-life ``window_us``) of its cell of ``fast_decay_subdivision`` pixels square exceeds
    ``fast_decay_threshold``.

* **hot pixels**: pixels that fire at hundreds of Hz or more whatever the scene, which a
  neighbourhood test keeps in part (and whose events support their neighbours' noise). The
  events are counted per pixel in windows of ``hot_window_us`` aligned on absolute time; when
  a window closes, a pixel whose count exceeds ``hot_factor`` times the ``hot_percentile``
  percentile of the counts of the pixels that fired in it (and at least ``hot_min_rate_hz``
  over the window) is hot, and its events are dropped until the next window closes (a window
  without any event: none is hot); a hot pixel's every event goes, signal too. The events of
  the first window pass: the rule learns on the stream itself, online. A scene's busiest
  pixels (an edge moving to and fro) share their rate with many others, which lifts the
  percentile; a hot pixel stands alone far above it.

Hot pixels are removed first, so they support no neighbour's noise. Everything is streaming:
calls on consecutive windows of a stream give the events (and the counts) of one call on the
whole stream, in the same order; nothing is reordered. Time: µs (int64), as in
:class:`~evtrack.events.Events`.

dv-processing takes its events as a ``dv.EventStore``, which has no constructor from arrays
(2.0): the events go in one by one from Python (``EventStore.push_back`` mapped over the
columns, ~3-4 M events/s) and come back as a structured array (``EventStore.numpy()``, fast).
That copy, not the filter, bounds the throughput (``benchmarks/bench_denoise.py``).

Example:
    >>> cfg = DenoiseConfig(method="background_activity", hot_pixels=True)
    >>> denoiser = EventDenoiser(cfg, sensor_size=(240, 180))
    >>> t0 = 5_000_000  # µs
    >>> ev = Events(x=[10, 11, 200], y=[5, 5, 100], t=[t0, t0 + 100, t0 + 150], p=[1, 1, -1])
    >>> len(denoiser(ev)), denoiser.counts.removed_noise   # the first event has no support yet
    (1, 2)
"""

from __future__ import annotations

import dataclasses
import datetime
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from evtrack.configs import Config, setting
from evtrack.errors import EventsError
from evtrack.events import Events

__all__ = ["DenoiseConfig", "DenoiseCounts", "EventDenoiser", "denoise_events",
           "hot_pixel_mask", "make_noise_filter", "to_event_store"]

METHODS = ("none", "background_activity", "knoise", "fast_decay")
"""The values of ``DenoiseConfig.method``."""


@dataclass
class DenoiseConfig(Config):
    """What :class:`EventDenoiser` removes. Off by default (``method: none``, no hot pixels).

    Attributes:
        method: the background-activity filter: ``"none"``, ``"background_activity"``,
            ``"knoise"`` or ``"fast_decay"`` (see :mod:`evtrack.denoise`).
        window_us: the filter's time constant, µs: the support window of
            ``background_activity`` and ``knoise``, the half-life of ``fast_decay``. 5 ms, not
            dv-processing's 2 ms: on a sparse simulated stream (128x96, no noise)
            ``background_activity`` took 17 % of the events at 2 ms and 3 % at 5 ms; on the ECD
            DAVIS240C rotation cuts 18-40 % and 5-18 % (``benchmarks/bench_denoise.py``).
        fast_decay_subdivision: ``fast_decay``'s cells are this many pixels square.
        fast_decay_threshold: ``fast_decay`` keeps an event when its cell's decayed count
            exceeds this.
        hot_pixels: drop the events of hot pixels, learned on the stream.
        hot_window_us: hot pixels are found on event counts over windows of this length, µs.
        hot_percentile: the percentile (0-100] of the counts of a window's active pixels that
            measures the scene's busiest pixels.
        hot_factor: a pixel is hot when its count exceeds this many times that percentile...
        hot_min_rate_hz: ...and this rate (events per second over the window).
    """

    method: Literal["none", "background_activity", "knoise", "fast_decay"] = "none"
    window_us: int = setting(5000, ge=1, unit="µs")
    fast_decay_subdivision: int = setting(4, ge=1, unit="px")
    fast_decay_threshold: float = setting(6.0, gt=0)
    hot_pixels: bool = False
    hot_window_us: int = setting(100_000, ge=1, unit="µs")
    hot_percentile: float = setting(99.0, gt=0, le=100)
    hot_factor: float = setting(10.0, ge=1)
    hot_min_rate_hz: float = setting(100.0, ge=0, unit="Hz")

    @property
    def enabled(self) -> bool:
        """Whether anything is removed (a filter or hot pixels)."""
        return self.method != "none" or self.hot_pixels


@dataclass
class DenoiseCounts:
    """What an :class:`EventDenoiser` did since its last reset.

    Attributes:
        events_in: events given to it; events_out: events it returned.
        removed_noise: events removed by the background-activity filter.
        removed_hot: events removed on hot pixels.
        hot_pixels: pixels hot now (found on the last closed window).
        hot_pixels_found: distinct pixels found hot at least once.
    """

    events_in: int = 0
    events_out: int = 0
    removed_noise: int = 0
    removed_hot: int = 0
    hot_pixels: int = 0
    hot_pixels_found: int = 0

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


def hot_pixel_mask(counts: np.ndarray, window_us: int, percentile: float = 99.0,
                   factor: float = 10.0, min_rate_hz: float = 100.0) -> np.ndarray:
    """The hot pixels of one window's per-pixel event counts.

    Args:
        counts: (P,) or (H, W) events per pixel over the window.
        window_us: the window's length, µs.
        percentile: of the counts of the pixels with at least one event, in (0, 100].
        factor: a hot pixel's count exceeds ``factor`` times that percentile...
        min_rate_hz: ...and ``min_rate_hz * window_us * 1e-6`` events.

    Returns:
        A bool array of ``counts``' shape, True on the hot pixels.

    Example:
        >>> counts = np.array([3, 4, 2, 0, 5, 3, 400])
        >>> hot_pixel_mask(counts, 1_000_000, percentile=50, factor=10, min_rate_hz=10)
        array([False, False, False, False, False, False,  True])
    """
    counts = np.asarray(counts)
    active = counts[counts > 0]
    if not active.size:
        return np.zeros(counts.shape, bool)
    level = float(np.percentile(active, percentile))
    return counts > max(factor * level, min_rate_hz * window_us * 1e-6)


def make_noise_filter(cfg: DenoiseConfig, sensor_size: tuple[int, int]) -> Any:
    """The dv-processing filter of ``cfg.method`` for a ``(width, height)`` sensor, or
    ``None`` for ``"none"``."""
    if cfg.method == "none":
        return None
    import dv_processing as dv

    span = datetime.timedelta(microseconds=cfg.window_us)
    if cfg.method == "background_activity":
        return dv.noise.BackgroundActivityNoiseFilter(sensor_size, span)
    if cfg.method == "knoise":
        return dv.noise.KNoiseFilter(sensor_size, span)
    return dv.noise.FastDecayNoiseFilter(sensor_size, span, cfg.fast_decay_subdivision,
                                         cfg.fast_decay_threshold)


def to_event_store(t: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray) -> Any:
    """A ``dv.EventStore`` of the events ``t`` (N,) µs, ``x``, ``y`` (N,) px and ``on`` (N,)
    bool (ON polarity), in their order: the fastest way found (dv-processing 2.0 has no
    constructor from arrays), ``push_back`` of ``(t, x, y, on)`` tuples mapped in C."""
    import dv_processing as dv

    store = dv.EventStore()
    deque(map(store.push_back, zip(t.tolist(), x.tolist(), y.tolist(), on.tolist(),
                                   strict=True)), maxlen=0)
    return store


class EventDenoiser:
    """Removes background activity and hot pixels from a stream of events, window by window.

    Args:
        config: what to remove (default: :class:`DenoiseConfig`, i.e. nothing).
        sensor_size: ``(width, height)`` px of the sensor; events carrying another size are
            refused.

    Attributes:
        counts: :class:`DenoiseCounts` since the last :meth:`reset`.

    Calls take consecutive windows of one stream, in time order (see :meth:`__call__`).
    dv-processing's filters start with every pixel last seen at t = 0: in a stream whose clock
    starts at 0, the events of its first ``window_us`` all find support.
    """

    def __init__(self, config: DenoiseConfig | None = None, *,
                 sensor_size: tuple[int, int]) -> None:
        self.config = config if config is not None else DenoiseConfig()
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        if min(self.sensor_size) < 1:
            raise ValueError(f"EventDenoiser: sensor_size must be positive, got {sensor_size}")
        self.reset()

    def reset(self) -> None:
        """Start a new stream: the filter's memory, the hot pixels and the counts cleared."""
        w, h = self.sensor_size
        self._filter = make_noise_filter(self.config, self.sensor_size)
        self._last_t: int | None = None
        self._window: int | None = None  # index of the hot-pixel window being counted
        self._counts = np.zeros(w * h, np.int64)
        self._hot = np.zeros(w * h, bool)
        self._ever_hot = np.zeros(w * h, bool)
        self.counts = DenoiseCounts()

    @property
    def hot_mask(self) -> np.ndarray:
        """(H, W) bool: the pixels whose events are dropped now."""
        w, h = self.sensor_size
        return self._hot.reshape(h, w).copy()

    def __call__(self, events: Events) -> Events:
        """The events of this window of the stream that are not noise, in their order.

        Args:
            events: the next events of the stream: sorted by time, not before the previous
                call's, inside the sensor, polarity ±1; on the CPU. An empty window is
                returned as it is (it moves no state).

        Returns:
            The kept events, with the sensor size (its dtypes those of ``events``).

        Raises:
            EventsError: not an :class:`Events`, another sensor size, events unsorted,
                before the previous call's, outside the sensor or of another polarity.
        """
        self._check(events)
        if not len(events):
            return events
        n = len(events)
        t = events.t.numpy()
        keep = self._hot_pixels_kept(events) if self.config.hot_pixels else None
        kept = events if keep is None or keep.all() else events[torch.from_numpy(keep)]
        n_kept = len(kept)
        if self._filter is not None and n_kept:
            kept = self._filtered(kept)
        self._last_t = int(t[-1])
        c = self.counts
        c.events_in += n
        c.events_out += len(kept)
        c.removed_hot += n - n_kept
        c.removed_noise += n_kept - len(kept)
        if kept.sensor_size is None:
            kept = Events(kept.x, kept.y, kept.t, kept.p, self.sensor_size)
        return kept

    def _check(self, events: Events) -> None:
        if not isinstance(events, Events):
            raise EventsError(f"EventDenoiser expects an Events container, got "
                              f"{type(events).__name__}")
        if events.sensor_size is not None and tuple(events.sensor_size) != self.sensor_size:
            raise EventsError(f"EventDenoiser: events of sensor size {tuple(events.sensor_size)}"
                              f" given to a denoiser of a {self.sensor_size} sensor")
        if events.device.type != "cpu":
            raise EventsError(f"EventDenoiser: events on {events.device}; it runs on the CPU "
                              "(events.to('cpu'))")
        if not len(events):
            return
        report = events.validate(self.sensor_size)
        if not report.ok:
            raise EventsError(f"EventDenoiser: {report}")
        if self._last_t is not None and events.t_start < self._last_t:
            raise EventsError(f"EventDenoiser: events from t={events.t_start} µs after events "
                              f"up to t={self._last_t} µs (a stream goes forward in time)")

    def _hot_pixels_kept(self, events: Events) -> np.ndarray:
        """(N,) bool: the events not on a hot pixel; counts them per pixel and closes the
        hot-pixel windows they pass."""
        cfg = self.config
        width = self.sensor_size[0]
        pixel = events.y.numpy().astype(np.int64) * width + events.x.numpy()
        window = events.t.numpy() // cfg.hot_window_us
        keep = np.empty(len(pixel), bool)
        starts = np.concatenate([[0], np.flatnonzero(np.diff(window)) + 1, [len(pixel)]])
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            w = int(window[a])
            if self._window is None:
                self._window = w
            elif w != self._window:
                self._close_window(w)
            keep[a:b] = ~self._hot[pixel[a:b]]
            np.add.at(self._counts, pixel[a:b], 1)
        return keep

    def _close_window(self, window: int) -> None:
        """The counting window ends, ``window`` starts: the hot pixels become those of the
        window just closed (none if a window without events lay between)."""
        cfg = self.config
        if window == self._window + 1:
            self._hot = hot_pixel_mask(self._counts, cfg.hot_window_us, cfg.hot_percentile,
                                       cfg.hot_factor, cfg.hot_min_rate_hz)
        else:
            self._hot = np.zeros_like(self._hot)
        self._ever_hot |= self._hot
        self.counts.hot_pixels = int(self._hot.sum())
        self.counts.hot_pixels_found = int(self._ever_hot.sum())
        self._counts[:] = 0
        self._window = window

    def _filtered(self, events: Events) -> Events:
        """``events`` through the dv-processing filter (its memory carried on)."""
        store = to_event_store(events.t.numpy(), events.x.numpy(), events.y.numpy(),
                               events.p.numpy() > 0)
        self._filter.accept(store)
        out = self._filter.generateEvents().numpy()
        on = out["polarity"].astype(bool)
        return Events(torch.from_numpy(out["x"].astype(events.x.numpy().dtype)),
                      torch.from_numpy(out["y"].astype(events.y.numpy().dtype)),
                      torch.from_numpy(out["timestamp"].astype(np.int64)),
                      torch.from_numpy(np.where(on, 1, -1).astype(np.int8)), self.sensor_size)


def denoise_events(events: Events, config: DenoiseConfig | None = None,
                   sensor_size: tuple[int, int] | None = None) -> Events:
    """:class:`EventDenoiser` on one whole stream (a fresh state).

    Args:
        events: sorted events (see :meth:`EventDenoiser.__call__`).
        config: what to remove; default :class:`DenoiseConfig` (nothing).
        sensor_size: ``(width, height)``; default ``events.sensor_size``.

    Raises:
        EventsError: as :meth:`EventDenoiser.__call__`; neither size known.
    """
    size = sensor_size if sensor_size is not None else events.sensor_size
    if size is None:
        raise EventsError("denoise_events: the events carry no sensor size: pass sensor_size")
    return EventDenoiser(config, sensor_size=size)(events)
