"""Motion blur as the mean of sub-frames, exposure windows, sRGB, sensor and depth noise."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.sim.config import FrameConfig
from evtrack.sim.frames import (
    ExposureAccumulator,
    add_depth_noise,
    add_rgb_noise,
    exposure_windows,
    linear_to_srgb,
    srgb_to_linear,
    stereo_shadow_mask,
)


def test_blurred_frame_is_the_mean_of_its_subframes() -> None:
    rng = np.random.default_rng(0)
    subframes = rng.random((9, 12, 16, 3)).astype(np.float32)
    acc = ExposureAccumulator()
    for f in subframes:
        acc.add(f[::1, :, :])
    np.testing.assert_allclose(acc.mean(), subframes.mean(axis=0), rtol=1e-6, atol=1e-7)
    acc.reset()
    with pytest.raises(ValueError, match="no render"):
        acc.mean()
    acc.add(subframes[0])
    with pytest.raises(ValueError, match="differs"):
        acc.add(subframes[0, :5])


def test_exposure_windows() -> None:
    times = np.arange(0, 1_000_001, 2000)  # 500 FPS for 1 s
    wins = exposure_windows(times, 60.0, 1.0, 1_000_000)
    assert len(wins) == 60
    firsts = [w.first for w in wins]
    lasts = [w.last for w in wins]
    assert firsts[0] == 0 and all(b == a + 1 for a, b in zip(lasts[:-1], firsts[1:], strict=True))
    counts = np.array(lasts) - np.array(firsts) + 1
    assert set(counts.tolist()) <= {8, 9} and counts.sum() == 500
    for w in wins:
        start = round(w.index * 1e6 / 60)
        assert start <= times[w.first] and times[w.last] < start + 1e6 / 60
        assert w.t_us == round(times[w.first:w.last + 1].mean())
    half = exposure_windows(times, 60.0, 0.5, 1_000_000)
    assert all(w.last - w.first + 1 in (4, 5) for w in half)


def test_srgb_round_trip() -> None:
    v = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(linear_to_srgb(srgb_to_linear(v)), v)
    assert srgb_to_linear(np.array([255], np.uint8))[0] == 1.0
    assert linear_to_srgb(np.array([2.0, -1.0])).tolist() == [255, 0]


def test_rgb_noise_statistics() -> None:
    cfg = FrameConfig(read_noise=0.01, shot_noise=0.05)
    img = np.full((200, 200, 3), 0.4, np.float32)
    out = add_rgb_noise(img, np.random.default_rng(0), cfg)
    assert abs(out.mean() - 0.4) < 1e-3
    assert abs(out.std() - np.sqrt(0.01 ** 2 + 0.05 ** 2 * 0.4)) < 1e-3
    assert np.array_equal(add_rgb_noise(img, np.random.default_rng(0), FrameConfig.noiseless()),
                          img)


def test_stereo_shadow_left_of_a_near_object() -> None:
    depth = np.full((4, 100), 2.0, np.float32)
    depth[:, 50:70] = 0.5  # a near object
    fx, b = 600.0, 0.05
    shadow = stereo_shadow_mask(depth, fx, b)
    width = fx * b * (1 / 0.5 - 1 / 2.0)  # disparity difference: 45 px
    cols = np.nonzero(shadow[0])[0]
    assert cols.max() == 49 and cols.min() == 50 - int(np.floor(width))
    assert not shadow[:, 50:].any()


def test_depth_noise() -> None:
    depth = np.full((300, 300), 1.0, np.float32)
    depth[:5] = 0.0  # nothing seen
    depth[5:10] = 12.0  # out of range
    cfg = FrameConfig(depth_noise=0.003, depth_dropout=0.1, depth_shadow_baseline=0.0)
    out = add_depth_noise(depth, np.random.default_rng(0), cfg, 600.0)
    assert (out[:10] == 0).all()
    valid = out[10:] > 0
    assert abs(1 - valid.mean() - 0.1) < 0.01
    assert abs(out[10:][valid].std() - 0.003) < 2e-4
    clean = add_depth_noise(depth, np.random.default_rng(0), FrameConfig.noiseless(), 600.0)
    np.testing.assert_array_equal(clean[10:], depth[10:])
