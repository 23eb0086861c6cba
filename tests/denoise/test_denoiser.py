"""The event denoiser (evtrack.denoise): noise, a hot pixel and signal of a synthetic stream,
streaming in windows against one call, bad input, the hot-pixel rule and the config."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from denoise_scenes import HOT_PIXEL, SIZE, T0_US, kinds_kept, noisy_stream

from evtrack.denoise import (
    DenoiseConfig,
    DenoiseCounts,
    EventDenoiser,
    denoise_events,
    hot_pixel_mask,
)
from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events
from evtrack.tracking.config import TrackerConfig

SIGNAL, NOISE, HOT = 0, 1, 2


@pytest.fixture(scope="module")
def scene():
    return noisy_stream(seed=0)


def _kept_shares(scene, out: Events) -> list[float]:
    kept = kinds_kept(scene, out)
    return [float(kept[scene.kind == k].mean()) for k in (SIGNAL, NOISE, HOT)]


def test_background_activity_and_hot_pixel_removed_signal_kept(scene) -> None:
    cfg = DenoiseConfig(method="background_activity", window_us=2000, hot_pixels=True)
    denoiser = EventDenoiser(cfg, sensor_size=SIZE)
    out = denoiser(scene.events)
    signal, noise, hot = _kept_shares(scene, out)
    assert signal > 0.98 and noise < 0.3 and hot < 0.25, (signal, noise, hot)
    c = denoiser.counts
    assert c.events_in == len(scene.events) and c.events_out == len(out)
    assert c.removed_noise + c.removed_hot == c.events_in - c.events_out
    # the hot pixel is found at the first window's end (100 ms of the 500) and nothing else
    assert c.hot_pixels == c.hot_pixels_found == 1
    mask = denoiser.hot_mask
    assert mask.shape == (SIZE[1], SIZE[0]) and mask[HOT_PIXEL[1], HOT_PIXEL[0]]
    hot_events = int((scene.kind == HOT).sum())
    assert 0.7 * hot_events <= c.removed_hot <= hot_events


def test_hot_pixels_alone_touch_no_other_pixel(scene) -> None:
    out = EventDenoiser(DenoiseConfig(hot_pixels=True), sensor_size=SIZE)(scene.events)
    kept = kinds_kept(scene, out)
    ev = scene.events
    on_hot = (ev.x.numpy() == HOT_PIXEL[0]) & (ev.y.numpy() == HOT_PIXEL[1])
    assert kept[~on_hot].all()
    assert kept[on_hot & (ev.t.numpy() < T0_US + 100_000)].all()  # the first window: learning
    assert not kept[on_hot & (ev.t.numpy() >= T0_US + 100_000)].any()


@pytest.mark.parametrize("method", ["knoise", "fast_decay"])
def test_other_filters_remove_most_noise(scene, method: str) -> None:
    out = denoise_events(scene.events, DenoiseConfig(method=method, window_us=2000))
    signal, noise, _ = _kept_shares(scene, out)
    assert noise < 0.2 and signal > 0.3, (signal, noise)


def test_off_returns_the_events_themselves(scene) -> None:
    denoiser = EventDenoiser(sensor_size=SIZE)
    assert denoiser(scene.events) is scene.events
    assert denoiser.counts == DenoiseCounts(events_in=len(scene.events),
                                            events_out=len(scene.events))


@pytest.mark.parametrize("method", ["background_activity", "knoise", "fast_decay"])
def test_windows_equal_one_call(scene, method: str) -> None:
    cfg = DenoiseConfig(method=method, hot_pixels=True, hot_window_us=50_000)
    whole = EventDenoiser(cfg, sensor_size=SIZE)
    one = whole(scene.events)
    rng = np.random.default_rng(4)
    cuts = np.sort(rng.integers(0, len(scene.events), 40))
    cuts = np.concatenate([[0], cuts, cuts[5:7], [len(scene.events)]])  # some empty windows
    cuts.sort()
    streamed = EventDenoiser(cfg, sensor_size=SIZE)
    parts = [streamed(scene.events[int(a):int(b)]) for a, b in zip(cuts[:-1], cuts[1:],
                                                                    strict=True)]
    got = Events(*(torch.cat([getattr(p, k) for p in parts]) for k in "xytp"), SIZE)
    assert got == one
    assert streamed.counts == whole.counts
    assert np.array_equal(streamed.hot_mask, whole.hot_mask)


def test_reset_starts_a_new_stream(scene) -> None:
    denoiser = EventDenoiser(DenoiseConfig(method="background_activity", hot_pixels=True),
                             sensor_size=SIZE)
    first = denoiser(scene.events)
    denoiser.reset()
    assert denoiser.counts == DenoiseCounts() and not denoiser.hot_mask.any()
    assert denoiser(scene.events) == first  # earlier times accepted again


def test_bad_input_raises_clear_errors() -> None:
    denoiser = EventDenoiser(DenoiseConfig(method="background_activity"), sensor_size=SIZE)
    with pytest.raises(EventsError, match="outside"):
        denoiser(Events([64], [0], [T0_US], [1]))
    with pytest.raises(EventsError, match="backwards"):
        denoiser(Events([1, 2], [0, 0], [T0_US + 10, T0_US], [1, 1]))
    with pytest.raises(EventsError, match="sensor size"):
        denoiser(Events([1], [0], [T0_US], [1], sensor_size=(128, 96)))
    with pytest.raises(EventsError, match="Events container"):
        denoiser(np.zeros(3))
    out = denoiser(Events([1, 2], [0, 0], [T0_US, T0_US + 5], [1, -1]))
    assert out.sensor_size == SIZE
    with pytest.raises(EventsError, match="forward in time"):
        denoiser(Events([1], [0], [T0_US + 4], [1]))
    empty = Events.empty(SIZE)
    counts = DenoiseCounts(**denoiser.counts.to_dict())
    assert denoiser(empty) is empty and denoiser.counts == counts  # passed through, no state
    with pytest.raises(EventsError, match="sensor size"):
        denoise_events(Events([1], [0], [T0_US], [1]))


def test_hot_pixel_rule() -> None:
    counts = np.ones((40, 40), np.int64)
    counts[:, 20:] = 0  # pixels without events do not count in the percentile
    counts[2, 3] = 40  # > 10 x the 99th percentile (1) and > 100 Hz over 0.1 s
    counts[5, 5] = 9  # not > 10 x 1
    hot = hot_pixel_mask(counts, 100_000)
    assert hot.shape == counts.shape and hot.sum() == 1 and hot[2, 3]
    assert not hot_pixel_mask(counts, 1_000_000).any()  # 40 events in 1 s: below 100 Hz
    assert not hot_pixel_mask(np.zeros(5, np.int64), 100_000).any()


def test_hot_pixels_forgotten_after_a_window_without_events() -> None:
    cfg = DenoiseConfig(hot_pixels=True, hot_window_us=10_000, hot_percentile=50.0,
                        hot_min_rate_hz=0.0)
    denoiser = EventDenoiser(cfg, sensor_size=SIZE)
    x = np.r_[np.zeros(50, int), np.arange(1, 21)]
    t = T0_US + np.sort(np.r_[np.linspace(0, 9_000, 50), np.linspace(0, 9_000, 20)])
    t = t.astype(np.int64)
    denoiser(Events(x[np.argsort(t, kind="stable")], np.zeros(70, int), t, np.ones(70, int)))
    assert denoiser.counts.hot_pixels == 0  # the window is still open
    out = denoiser(Events([0, 0], [0, 0], [T0_US + 10_000, T0_US + 10_001], [1, 1]))
    assert len(out) == 0 and denoiser.counts.hot_pixels == 1  # pixel (0, 0): 50 vs 1
    out = denoiser(Events([0], [0], [T0_US + 35_000], [1]))  # a window without events between
    assert len(out) == 1 and denoiser.counts.hot_pixels == 0
    assert denoiser.counts.hot_pixels_found == 1


def test_config_section_names_the_field() -> None:
    with pytest.raises(ConfigError) as info:
        TrackerConfig.from_dict({"denoise": {"method": "median"}})
    message = str(info.value)
    assert "denoise.method" in message and "background_activity" in message
    assert "\n" not in message
    with pytest.raises(ConfigError, match=r"denoise\.window_us"):
        TrackerConfig.from_dict({"denoise": {"window_us": 0}})
    with pytest.raises(ConfigError, match=r"denoise\.hot_percentile"):
        TrackerConfig.from_dict({"denoise": {"hot_percentile": 0}})
    cfg = TrackerConfig.from_dict({"denoise": {"method": "knoise", "hot_pixels": True}})
    assert cfg.denoise.enabled and cfg.denoise.window_us == 5000
    assert not TrackerConfig().denoise.enabled
