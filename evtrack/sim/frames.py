"""The RGB-D camera model: exposure averaging (motion blur), sensor noise and depth noise.

Renders are linear RGB (1 = white). A 60 FPS frame is the mean of the renders whose times lie
in its exposure window, plus sensor noise, then encoded to 8-bit sRGB. Depth frames come
from a single render (the one nearest the RGB frame's timestamp), with RealSense-like noise:
axial noise growing with z², random dropout, and the occlusion shadow of a stereo pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evtrack.sim.config import FrameConfig

__all__ = [
    "srgb_to_linear",
    "linear_to_srgb",
    "ExposureAccumulator",
    "exposure_windows",
    "add_rgb_noise",
    "stereo_shadow_mask",
    "add_depth_noise",
    "luminance",
]

#: Rec. 709 luminance weights of linear RGB.
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """8-bit sRGB (any shape, uint8) -> linear float32 in [0, 1] (IEC 61966-2-1)."""
    x = np.asarray(c, np.float32) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


_LUT_SIZE = 65536
_SRGB_LUT = _srgb_encode(np.linspace(0.0, 1.0, _LUT_SIZE))


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear RGB (any shape) -> 8-bit sRGB uint8; values are clipped to [0, 1] first.

    Through a 65536-entry table (the encoding rounded at ``x`` quantised to 1/65535): it
    agrees with the exact formula except within 0.03 of a code boundary, and is exact on
    every decoded 8-bit value.
    """
    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    idx = (x * np.float32(_LUT_SIZE - 1) + np.float32(0.5)).astype(np.uint16)
    return _SRGB_LUT[idx]


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> (...) linear luminance (Rec. 709 weights)."""
    w = np.asarray(LUMA_WEIGHTS, np.float32)
    return np.asarray(rgb, np.float32) @ w


@dataclass(frozen=True)
class ExposureWindow:
    """One RGB frame's exposure: the renders ``[first, last]`` (indices on the base grid)."""

    index: int
    first: int
    last: int
    t_us: int  # the mean time of the averaged renders


def exposure_windows(render_times_us: np.ndarray, rgb_hz: float, exposure: float,
                     duration_us: int) -> list[ExposureWindow]:
    """Which base-grid renders make up each RGB frame.

    Frame ``j`` starts at ``round(j * 1e6 / rgb_hz)`` µs and averages the renders with
    ``start <= t < start + exposure * 1e6 / rgb_hz``. Only frames whose window ends within
    ``duration_us`` are made. Its timestamp is the mean time of its renders (rounded).

    Args:
        render_times_us: (K,) int64 increasing times of the base-grid renders.

    Returns:
        the windows, in time order (frames with no render inside are skipped).
    """
    period = 1e6 / rgb_hz
    out = []
    j = 0
    while True:
        start = round(j * period)
        end = start + exposure * period
        if end > duration_us + 1e-6:
            break
        lo = int(np.searchsorted(render_times_us, start, side="left"))
        hi = int(np.searchsorted(render_times_us, end, side="left")) - 1
        if hi >= lo:
            t = int(round(float(np.mean(render_times_us[lo:hi + 1]))))
            out.append(ExposureWindow(len(out), lo, hi, t))
        j += 1
    return out


class ExposureAccumulator:
    """Running mean of the renders within one exposure (float32 sum, no stored sub-frames).

    Example:
        >>> acc = ExposureAccumulator()
        >>> acc.add(np.zeros((2, 2, 3), np.float32)); acc.add(np.ones((2, 2, 3), np.float32))
        >>> float(acc.mean()[0, 0, 0])
        0.5
    """

    def __init__(self) -> None:
        self._sum: np.ndarray | None = None
        self.count = 0

    def add(self, frame: np.ndarray) -> None:
        """Add one linear render (H, W, C), e.g. RGB, or RGBA with an ignored channel (a
        contiguous RGBA buffer adds ~25x faster than its strided RGB view)."""
        if self._sum is None:
            self._sum = np.zeros(frame.shape, np.float32)
        elif frame.shape != self._sum.shape:
            raise ValueError(f"render shape {frame.shape} differs from {self._sum.shape}")
        self._sum += frame
        self.count += 1

    def mean(self) -> np.ndarray:
        """(H, W, C) float32 mean of the renders added so far."""
        if self._sum is None:
            raise ValueError("no render was added to this exposure")
        return self._sum / np.float32(self.count)

    def reset(self) -> None:
        self._sum = None
        self.count = 0


def add_rgb_noise(linear: np.ndarray, rng: np.random.Generator, config: FrameConfig
                  ) -> np.ndarray:
    """Sensor noise on a linear image: ``I + N(0, read² + shot²·I)`` (clipped at 0).

    Args:
        linear: (H, W, 3) float32 linear RGB.
        rng: generator for the noise.

    Returns:
        a new (H, W, 3) float32 image (the input is not modified).
    """
    if config.read_noise == 0 and config.shot_noise == 0:
        return linear.copy()
    var = config.read_noise ** 2 + config.shot_noise ** 2 * np.clip(linear, 0.0, None)
    noise = rng.standard_normal(linear.shape, dtype=np.float32) * np.sqrt(var).astype(np.float32)
    return np.clip(linear + noise, 0.0, None).astype(np.float32)


def stereo_shadow_mask(depth: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """Pixels that the second imager of a stereo pair cannot see (occlusion shadow).

    The second imager sits ``baseline`` metres along ``+x``: a point at column ``u`` and depth
    ``z`` appears there at ``s = u - fx·baseline/z``. A pixel is shadowed when a pixel to its
    right lands at ``s`` no greater than its own (a nearer surface covers it).

    Args:
        depth: (H, W) metres, 0 or NaN where nothing was seen.
        fx: focal length, pixels.

    Returns:
        (H, W) bool.
    """
    h, w = depth.shape
    valid = depth > 0
    z = np.where(valid, depth, np.float32(np.inf)).astype(np.float32)
    s = np.arange(w, dtype=np.float32)[None, :] - np.float32(fx * baseline) / z
    s[~valid] = np.inf
    # min over columns strictly to the right, computed right to left
    right_min = np.minimum.accumulate(s[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf, np.float32)], axis=1)
    return valid & (right_min <= s)


def add_depth_noise(depth: np.ndarray, rng: np.random.Generator, config: FrameConfig,
                    fx: float) -> np.ndarray:
    """RealSense-like depth: axial noise ``σ = c·z²``, stereo shadow, dropout, range limits.

    Args:
        depth: (H, W) float32 metres, 0 where nothing was rendered.
        rng: generator for the noise.
        fx: focal length in pixels (for the stereo shadow).

    Returns:
        (H, W) float32 metres with 0 where depth is missing (a new array).
    """
    out = depth.astype(np.float32).copy()
    missing = ~(out > 0)
    if config.depth_shadow_baseline > 0:
        missing |= stereo_shadow_mask(out, fx, config.depth_shadow_baseline)
    if config.depth_noise > 0:
        out += (rng.standard_normal(out.shape, dtype=np.float32)
                * np.float32(config.depth_noise) * out * out)
    if config.depth_dropout > 0:
        missing |= rng.random(out.shape, dtype=np.float32) < config.depth_dropout
    lo, hi = config.depth_range
    missing |= (out < lo) | (out > hi)
    out[missing] = 0.0
    return out
